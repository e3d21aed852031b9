"""Table 2 from per-image records: means, paired tests, marks, mTC per lighting — checked by hand."""

from __future__ import annotations

import csv
import io
import math

import numpy as np
import pytest
from scipy import stats

from m2s2hil.analysis.errors import AnalysisInputError
from m2s2hil.analysis.evaluation import table2
from m2s2hil.analysis.evaluation.aggregates import speed_accuracy
from m2s2hil.analysis.evaluation.evaluate import EvaluationResult
from m2s2hil.analysis.evaluation.loading import labels_to_cube
from m2s2hil.analysis.evaluation.options import EvalOptions
from m2s2hil.errors import UsageError


def rec(i, sat="voyager", build="B2", elev="E0", light="weak", multi=None, rgb=None, mtc=None, truth=True):
    res = {"spectral": {"time_s": 0.1 * (i + 1)}, "rgb": {"time_s": 0.05 * (i + 1)}}
    if truth:
        res["spectral"].update(multi)
        res["rgb"].update(rgb)
    if mtc is not None:
        res["spectral"]["mtc"] = mtc
    return {
        "image_id": f"{sat}/{build}/{elev}/{light}/{i}",
        "source": "s",
        "satellite": sat,
        "build": build,
        "classes": 5,
        "elevation": elev,
        "lighting": light,
        "azimuth_deg": 10.0 * i,
        "has_truth": truth,
        "error": None,
        "results": res,
    }


def scores(p, r, d):
    return {"precision": p, "recall": r, "dice": d, "micro_iou": d}


def hand_p(a, b, rho):
    a, b = np.asarray(a), np.asarray(b)
    sa, sb = a.std(ddof=1), b.std(ddof=1)
    sd = math.sqrt(sa**2 + sb**2 - 2 * rho * sa * sb)
    t = (a - b).mean() / (sd / math.sqrt(a.size))
    return t, 2 * stats.t.sf(abs(t), a.size - 1)


# Dice: multi clearly better (p < 0.01 at ρ = 0.9); recall: rgb better only at α = 0.05; precision: equal-ish.
MULTI_DICE = [0.80, 0.70, 0.90, 0.75]
RGB_DICE = [0.60, 0.52, 0.69, 0.57]
MULTI_REC = [0.60, 0.61, 0.58, 0.62]
RGB_REC = [0.66, 0.62, 0.64, 0.70]
MULTI_PREC = [0.5, 0.6, 0.7, 0.8]
RGB_PREC = [0.8, 0.7, 0.6, 0.5]


def records():
    out = []
    lights = ["weak", "weak", "directional", "directional"]
    mtcs = [0.99, 0.97, 0.95, 0.93]
    for i in range(4):
        out.append(
            rec(
                i,
                light=lights[i],
                mtc=mtcs[i],
                multi=scores(MULTI_PREC[i], MULTI_REC[i], MULTI_DICE[i]),
                rgb=scores(RGB_PREC[i], RGB_REC[i], RGB_DICE[i]),
            )
        )
    # Hubble B2 and B3 have the same class count: they must stay separate rows
    out.append(rec(0, sat="hubble", build="B3", mtc=0.9, multi=scores(1, 1, 1), rgb=scores(1, 1, 1)))
    out.append(rec(1, sat="hubble", build="B2", mtc=0.8, multi=scores(1, 1, 1), rgb=scores(1, 1, 1)))
    # an image that failed is left out; an image without truth counts for mTC only
    bad = rec(9, multi=scores(0, 0, 0), rgb=scores(1, 1, 1))
    bad["error"] = "OSError: gone"
    out.append(bad)
    out.append(rec(5, light="strong", mtc=0.5, truth=False))
    return out


def test_rows_means_tests_and_mtc_by_hand():
    rows = table2.build_rows(records(), multi="spectral", rgb="rgb", rho=0.9)
    assert [(r.satellite_name, r.build) for r in rows] == [
        ("Voyager", "B2"),
        ("Hubble", "B2"),
        ("Hubble", "B3"),
    ]
    v = rows[0]
    assert v.n_images == 5 and v.n_truth == 4 and v.classes == 5
    dice = v.cells["dice"]
    assert dice.multi == pytest.approx(np.mean(MULTI_DICE)) and dice.rgb == pytest.approx(np.mean(RGB_DICE))
    t, p = hand_p(MULTI_DICE, RGB_DICE, 0.9)
    assert dice.test.t == pytest.approx(t) and dice.test.p == pytest.approx(p)
    assert p < 0.01 and dice.stars == "**" and dice.winner == "multi"
    t, p = hand_p(MULTI_REC, RGB_REC, 0.9)
    assert v.cells["recall"].test.p == pytest.approx(p)
    assert 0.01 <= p < 0.05 and v.cells["recall"].winner == "rgb" and v.cells["recall"].stars == "*"
    assert v.cells["precision"].winner is None  # mean difference 0
    assert v.mtc == {
        "weak": (pytest.approx(0.98), 2),
        "directional": (pytest.approx(0.94), 2),
        "strong": (0.5, 1),
    }


def test_markdown_marks_and_csv_columns():
    rows = table2.build_rows(records(), multi="spectral", rgb="rgb")
    md = table2.to_markdown(rows, notes=["a note"])
    line = next(x for x in md.splitlines() if x.startswith("| Voyager"))
    cells = [c.strip() for c in line.strip("|").split("|")]
    # Sat Build Classes Elev Images | P, R, Dice: rgb, multi, ρ̂ | mTC Dir Weak Strong
    assert cells[:5] == ["Voyager", "B2", "5", "E0", "5"]
    assert cells[5:7] == ["0.6500", "0.6500"]
    assert cells[8] == f"**{np.mean(RGB_REC):.4f}**\\*" and cells[9] == f"{np.mean(MULTI_REC):.4f}"
    assert cells[11] == f"{np.mean(RGB_DICE):.4f}" and cells[12] == f"***{np.mean(MULTI_DICE):.4f}***\\*\\*"
    assert cells[14:] == ["0.9400", "0.9800", "0.5000"]
    assert "- a note" in md
    hub = next(x for x in md.splitlines() if x.startswith("| Hubble | B3"))
    assert "–" in hub  # one image: no test, no mark
    data = list(csv.DictReader(io.StringIO(table2.to_csv(rows))))
    assert data[0]["dice_mark"] == "**" and data[0]["dice_better"] == "multi"
    assert float(data[0]["dice_p"]) == pytest.approx(hand_p(MULTI_DICE, RGB_DICE, 0.9)[1])
    assert data[0]["recall_mark"] == "*" and data[0]["recall_better"] == "rgb"
    assert data[1]["dice_p"] == "" and data[1]["mtc_weak"] == "0.8"


def test_significance_sweep_lists_observed_rho():
    recs = records()
    rows = table2.build_rows(recs, multi="spectral", rgb="rgb")
    md = table2.significance_markdown(recs, rows, multi="spectral", rgb="rgb")
    line = next(x for x in md.splitlines() if "| Dice |" in x and "Voyager" in x)
    cells = [c.strip() for c in line.strip("|").split("|")]
    r_obs = stats.pearsonr(MULTI_DICE, RGB_DICE).statistic
    assert float(cells[-2]) == pytest.approx(r_obs, abs=1e-3)
    assert float(cells[-1]) == pytest.approx(stats.ttest_rel(MULTI_DICE, RGB_DICE).pvalue, rel=1e-2)
    assert float(cells[9]) == pytest.approx(hand_p(MULTI_DICE, RGB_DICE, 0.9)[1], rel=1e-2)
    assert cells[-3] == "\\*\\* / \\*\\*"  # the marks at ρ = 0.9 and at the observed ρ agree


def test_notes_say_when_there_is_no_ground_truth():
    recs = [rec(i, truth=False, mtc=0.9) for i in range(3)]
    res = EvaluationResult(recs, EvalOptions(), ["dataset x"], 1.0, {})
    rows = table2.build_rows(recs, multi="spectral", rgb="rgb")
    assert not rows[0].cells and rows[0].mtc == {"weak": (0.9, 3)}
    text = " ".join(table2.notes(res, rows))
    assert "only the ground-truth-free mTC" in text
    md = table2.to_markdown(rows)
    assert md.splitlines()[2].count("–") == 9  # P, R, Dice: RGB, Multi, ρ̂


def test_speed_accuracy_aggregates_per_segmenter():
    pts = {p["segmenter"]: p for p in speed_accuracy(records())}
    assert pts["spectral"]["images"] == 8  # every image that ran, with or without truth
    assert pts["spectral"]["scored_images"] == 7
    assert pts["rgb"]["time_mean_s"] == pytest.approx(np.mean([0.05, 0.1, 0.15, 0.2, 0.05, 0.1, 0.5, 0.3]))


def test_labels_to_cube_majority_by_hand():
    lab = np.array(
        [
            [1, 1, 2, 2],
            [3, 3, 2, 0],
            [0, 0, 5, 5],
            [0, 4, 5, 4],
        ]
    )
    # 2×2 cells: {1,1,3,3} tie → lowest id 1; {2,2,2,0} → 2; {0,0,0,4} → 0; {5,5,5,4} → 5
    assert labels_to_cube(lab, (2, 2)).tolist() == [[1, 2], [0, 5]]
    assert labels_to_cube(lab, (4, 4)).tolist() == lab.tolist()
    with pytest.raises(AnalysisInputError):
        labels_to_cube(lab, (3, 3))


def test_options_refuse_an_rgb_segmenter_as_the_multispectral_one():
    with pytest.raises(UsageError, match="RGB baseline"):
        EvalOptions(multi="rgb")
    with pytest.raises(UsageError):
        EvalOptions(mtc_for="some")
    assert EvalOptions(multi="spectral-smooth").segmenters == ("spectral-smooth", "rgb-smooth")


# Negatively correlated pairs (observed ρ ≈ −0.75): p = 0.003 at the assumed ρ = 0.9, 0.26 at the observed.
DISAGREE_MULTI = [0.90, 0.70, 0.80, 0.60, 0.85, 0.65, 0.75, 0.72]
DISAGREE_RGB = [0.62, 0.78, 0.58, 0.76, 0.64, 0.72, 0.60, 0.70]


def test_observed_rho_beside_the_assumed_and_a_note_where_they_disagree():
    recs = records() + [
        rec(i, sat="iss", build="B3", multi=scores(0.5, 0.5, m), rgb=scores(0.5, 0.4, r))
        for i, (m, r) in enumerate(zip(DISAGREE_MULTI, DISAGREE_RGB, strict=True))
    ]
    rows = table2.build_rows(recs, multi="spectral", rgb="rgb", rho=0.9)
    iss = next(r for r in rows if r.satellite == "iss")
    dice = iss.cells["dice"]
    assert dice.test.p == pytest.approx(hand_p(DISAGREE_MULTI, DISAGREE_RGB, 0.9)[1]) and dice.stars == "**"
    assert dice.observed.p == pytest.approx(stats.ttest_rel(DISAGREE_MULTI, DISAGREE_RGB).pvalue)
    assert dice.rho_observed == pytest.approx(stats.pearsonr(DISAGREE_MULTI, DISAGREE_RGB).statistic)
    assert dice.stars_observed == "" and dice.winner_observed is None and not dice.agrees
    # Voyager's Dice is significant either way (observed ρ ≈ 1): the marks agree, no dagger.
    vd = rows[0].cells["dice"]
    assert vd.agrees and vd.stars_observed == "**" and vd.winner_observed == "multi"
    md = table2.to_markdown(rows)
    line = next(x for x in md.splitlines() if x.startswith("| ISS"))
    cells = [c.strip() for c in line.strip("|").split("|")]
    assert cells[13] == f"{dice.rho_observed:.2f} ns †"
    vline = next(x for x in md.splitlines() if x.startswith("| Voyager"))
    vcells = [c.strip() for c in vline.strip("|").split("|")]
    assert vcells[13] == f"{vd.rho_observed:.2f} \\*\\* M"
    notes = [x for x in md.splitlines() if x.startswith("- †")]
    assert len(notes) == 1 and "ISS B3 E0 Dice" in notes[0]
    assert "at assumed ρ = 0.9" in notes[0] and f"p = {dice.observed.p:.2g} at observed ρ = -0.75" in notes[0]
    data = {d["satellite"]: d for d in csv.DictReader(io.StringIO(table2.to_csv(rows)))}
    assert data["ISS"]["dice_mark"] == "**" and data["ISS"]["dice_mark_observed"] == ""
    assert data["ISS"]["dice_marks_agree"] == "False" and data["Voyager"]["dice_marks_agree"] == "True"
    assert float(data["ISS"]["dice_p_observed"]) == pytest.approx(dice.observed.p)


def test_band_note_reports_how_stable_the_pca_pick_is():
    from m2s2hil.analysis.evaluation.evaluate import band_report

    rng = np.random.default_rng(5)
    samples = [rng.normal(size=(60, 10)) * np.linspace(1, 3, 10) for _ in range(4)]
    bands = band_report([{"pca_sample": s} for s in samples], EvalOptions())
    st = bands["pca_stability"]
    assert st["n_frames"] == 4 and st["bands"] == bands["pca_bands"]
    assert sum(x["share"] for x in st["set_frequency"]) == pytest.approx(1.0)
    recs = [rec(i, truth=False, mtc=0.9) for i in range(2)]
    res = EvaluationResult(recs, EvalOptions(), ["s"], 1.0, {}, bands)
    text = " ".join(table2.notes(res, table2.build_rows(recs, multi="spectral", rgb="rgb")))
    assert f"recurs in {st['pick_frequency']:.0%} of {st['n_boot']} bootstrap resamples of the images" in text
