"""The paper's Table 2 from per-image evaluation records, as CSV and Markdown.

One row per (satellite, build, elevation); "Classes" is the build's materials + 1
(background), as the paper counts (Voyager B1 = 2). The build is shown as well because
two builds can have the same class count (Hubble B2 and B3 both have 4 materials).

- Macro precision, recall and Dice: mean over the row's images with ground truth, for
  the RGB baseline and the multispectral segmenter, on the same images.
- Significance: per row and metric, ``paired_t_test(multi, rgb, rho)`` over the images
  (ρ = 0.9 by default, the paper's assumption; ``significance.md`` sweeps ρ). The
  better of the two values is marked when the two-sided p is below α:

  ============ ======================== ======================
  α            Markdown                 CSV ``*_mark``
  ============ ======================== ======================
  p < 0.05     ``**0.9614**\\*``          ``*``
  p < 0.01     ``***0.9614***\\*\\*``      ``**``
  ============ ======================== ======================

  The paper typesets α = 0.05 in bold and α = 0.01 in italics; here p < 0.01 is bold
  *and* italic (it also passes α = 0.05), and the stars make the level explicit in
  plain text. Fewer than 2 paired images: no test ("–").
- The assumption beside the data: each metric has a column "ρ̂" with the observed Pearson
  correlation of the row's paired scores and the marks the test gives at that ρ (which is
  ``scipy.stats.ttest_rel``; M/R: multi/RGB better, ns: not significant). Where those marks
  differ from the ones at the assumed ρ the column carries a †, and a note under the table
  names the cell with both p-values.
- mTC per lighting condition (Dir / Weak / Strong): mean mTC of the multispectral
  segmenter over the row's images under that condition (images without ground truth
  count too: mTC needs none).
- HIL Macro Precision / Recall / Dice: the multispectral segmenter on the row's HIL frames
  against the twin's projected labels (``evaluate``'s ``hil_*`` scores; frames stored with
  ``projected_labels``), mean over those frames; the columns appear when any row has them.
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from m2s2hil.analysis.metrics.significance import (
    SENSITIVITY_RHOS,
    AssumedVsObserved,
    PairedTest,
    assumed_and_observed,
    paired_t_test,
    rho_sensitivity,
)
from m2s2hil.catalog import load_catalog

if TYPE_CHECKING:  # a type only (the driver's result)
    from m2s2hil.analysis.evaluation.evaluate import EvaluationResult

METRICS = ("precision", "recall", "dice")
METRIC_TITLES = {"precision": "Macro Precision", "recall": "Macro Recall", "dice": "Dice"}
LIGHTINGS = ("directional", "weak", "strong")
LIGHTING_TITLES = {"directional": "Dir", "weak": "Weak", "strong": "Strong"}


@dataclass(frozen=True)
class MetricCell:
    """RGB and multispectral means of one metric over the row's paired images, and their test."""

    rgb: float
    multi: float
    n: int
    test: PairedTest | None  # at the assumed ρ
    observed: PairedTest | None = None  # the same pairs at their observed correlation

    @property
    def stars(self) -> str:
        return self.test.stars if self.test is not None else ""

    @property
    def winner(self) -> str | None:
        """ "multi" or "rgb" when the difference is significant at α = 0.05, else None."""
        return self._winner(self.stars)

    @property
    def stars_observed(self) -> str:
        return self.observed.stars if self.observed is not None else ""

    @property
    def winner_observed(self) -> str | None:
        return self._winner(self.stars_observed)

    @property
    def rho_observed(self) -> float:
        return self.observed.rho_observed if self.observed is not None else math.nan

    @property
    def agrees(self) -> bool:
        """The marks at the assumed and at the observed ρ agree (True without a test)."""
        if self.test is None or self.observed is None:
            return True
        return AssumedVsObserved(self.test, self.observed).agree

    def _winner(self, stars: str) -> str | None:
        if not stars or self.multi == self.rgb:
            return None
        return "multi" if self.multi > self.rgb else "rgb"


@dataclass(frozen=True)
class Table2Row:
    satellite: str  # catalog key
    satellite_name: str
    build: str
    classes: int
    elevation: str
    n_images: int
    n_truth: int
    cells: dict[str, MetricCell] = field(default_factory=dict)
    mtc: dict[str, tuple[float, int]] = field(default_factory=dict)  # lighting -> (mean, images)
    # HIL frames against the twin's projected labels: metric -> (the multispectral segmenter's mean, images)
    hil: dict[str, tuple[float, int]] = field(default_factory=dict)


def _ok(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _order(satellite: str, build: str, elevation: str) -> tuple:
    cat = load_catalog()
    sats = list(cat.satellites)
    elevs = list(cat.elevations)
    return (
        sats.index(satellite) if satellite in sats else len(sats),
        satellite,
        build,
        elevs.index(elevation) if elevation in elevs else len(elevs),
        elevation,
    )


def build_rows(
    records: Sequence[Mapping[str, Any]], *, multi: str, rgb: str, rho: float = 0.9
) -> list[Table2Row]:
    """Group per-image records (``evaluate.evaluate_job``) into Table-2 rows."""
    cat = load_catalog()
    groups: dict[tuple[str, str, str], list[Mapping[str, Any]]] = {}
    for r in records:
        if r.get("error"):
            continue
        groups.setdefault((r["satellite"], r["build"], r["elevation"]), []).append(r)
    rows = []
    for (sat, build, elev), recs in sorted(groups.items(), key=lambda kv: _order(*kv[0])):
        cells: dict[str, MetricCell] = {}
        for metric in METRICS:
            a, b = [], []
            for r in recs:
                res = r.get("results", {})
                va = res.get(multi, {}).get(metric)
                vb = res.get(rgb, {}).get(metric)
                if _ok(va) and _ok(vb):
                    a.append(float(va))
                    b.append(float(vb))
            if a:
                both = assumed_and_observed(a, b, rho) if len(a) >= 2 else None
                cells[metric] = MetricCell(float(np.mean(b)), float(np.mean(a)), len(a),
                                           both.assumed if both else None, both.observed if both else None)
        mtc: dict[str, tuple[float, int]] = {}
        for light in sorted({r["lighting"] for r in recs}, key=lambda x: (x not in LIGHTINGS, x)):
            vals = [
                float(r["results"][multi]["mtc"])
                for r in recs
                if r["lighting"] == light and _ok(r.get("results", {}).get(multi, {}).get("mtc"))
            ]
            if vals:
                mtc[light] = (float(np.mean(vals)), len(vals))
        hil: dict[str, tuple[float, int]] = {}
        for metric in METRICS:
            vals = [float(r["results"][multi][f"hil_{metric}"]) for r in recs
                    if _ok(r.get("results", {}).get(multi, {}).get(f"hil_{metric}"))]
            if vals:
                hil[metric] = (float(np.mean(vals)), len(vals))
        name = cat.satellites[sat].name if sat in cat.satellites else sat
        classes = int(recs[0]["classes"])
        rows.append(
            Table2Row(
                sat,
                name,
                build,
                classes,
                elev,
                len(recs),
                sum(bool(r.get("has_truth")) for r in recs),
                cells,
                mtc,
                hil,
            )
        )
    return rows


# ----------------------------------------------------------------------------- formatting
def _f(v: float | None, digits: int = 4) -> str:
    return "–" if v is None or not math.isfinite(v) else f"{v:.{digits}f}"


def _marked(value: float, cell: MetricCell, side: str) -> str:
    text = _f(value)
    if cell.winner != side:
        return text
    if cell.stars == "**":
        return f"***{text}***\\*\\*"
    return f"**{text}**\\*"


def _escaped(stars: str) -> str:
    return stars.replace("*", "\\*") if stars else "ns"  # ns: not significant at α = 0.05


def _observed(cell: MetricCell) -> str:
    """The ρ̂ column: observed correlation, the marks at it, † when they differ from the assumed ρ's."""
    if cell.observed is None:
        return "–"
    side = {"multi": " M", "rgb": " R"}.get(cell.winner_observed or "", "")
    return f"{_f(cell.rho_observed, 2)} {_escaped(cell.stars_observed)}{side}" + ("" if cell.agrees else " †")


def disagreement_notes(rows: Sequence[Table2Row]) -> list[str]:
    """One note per cell whose marks at the observed ρ differ from those at the assumed ρ."""
    out = []
    for r in rows:
        for m in METRICS:
            cell = r.cells.get(m)
            if cell is None or cell.agrees or cell.test is None or cell.observed is None:
                continue
            both = AssumedVsObserved(cell.test, cell.observed)
            out.append(f"† {r.satellite_name} {r.build} {r.elevation} {METRIC_TITLES[m]}: the verdict "
                       f"depends on ρ ({both.describe()}).")
    return out


def to_markdown(rows: Sequence[Table2Row], *, notes: Sequence[str] = ()) -> str:
    lights = [lt for lt in LIGHTINGS if any(lt in r.mtc for r in rows)]
    lights += sorted({lt for r in rows for lt in r.mtc} - set(lights))
    head = ["Satellite", "Build", "Classes", "Elevation", "Images"]
    for m in METRICS:
        head += [f"{METRIC_TITLES[m]} RGB", f"{METRIC_TITLES[m]} Multi", f"{METRIC_TITLES[m]} ρ̂"]
    head += [f"mTC {LIGHTING_TITLES.get(lt, lt)}" for lt in lights]
    hil = [m for m in METRICS if any(m in r.hil for r in rows)]
    head += [f"HIL {METRIC_TITLES[m]}" for m in hil]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        cols = [r.satellite_name, r.build, str(r.classes), r.elevation, str(r.n_images)]
        for m in METRICS:
            cell = r.cells.get(m)
            if cell is None:
                cols += ["–", "–", "–"]
            else:
                cols += [_marked(cell.rgb, cell, "rgb"), _marked(cell.multi, cell, "multi"), _observed(cell)]
        cols += [_f(r.mtc[lt][0]) if lt in r.mtc else "–" for lt in lights]
        cols += [_f(r.hil[m][0]) if m in r.hil else "–" for m in hil]
        lines.append("| " + " | ".join(cols) + " |")
    out = "\n".join(lines) + "\n"
    all_notes = [*disagreement_notes(rows), *notes]
    if hil:
        all_notes.append("HIL: the multispectral segmenter on the HIL frames against the registered twin's "
                         "projected labels (m2s2hil.twin.labels), not a ground truth: the paper had none.")
    if all_notes:
        out += "\n" + "\n".join(f"- {n}" for n in all_notes) + "\n"
    return out


def table_rows(rows: Sequence[Table2Row]) -> list[dict[str, Any]]:
    """Flat dicts (one per row) for CSV: means, n, p, t, stars and winner per metric; mTC per lighting."""
    out = []
    for r in rows:
        d: dict[str, Any] = {
            "satellite": r.satellite_name,
            "build": r.build,
            "classes": r.classes,
            "elevation": r.elevation,
            "images": r.n_images,
            "images_with_truth": r.n_truth,
        }
        for m in METRICS:
            cell = r.cells.get(m)
            t = cell.test if cell else None
            d.update(
                {
                    f"{m}_rgb": cell.rgb if cell else "",
                    f"{m}_multi": cell.multi if cell else "",
                    f"{m}_n": cell.n if cell else 0,
                    f"{m}_t": t.t if t else "",
                    f"{m}_p": t.p if t else "",
                    f"{m}_mark": cell.stars if cell else "",
                    f"{m}_better": (cell.winner or "") if cell else "",
                    f"{m}_rho_observed": cell.rho_observed if cell else "",
                    f"{m}_p_observed": cell.observed.p if cell and cell.observed else "",
                    f"{m}_mark_observed": cell.stars_observed if cell else "",
                    f"{m}_better_observed": (cell.winner_observed or "") if cell else "",
                    f"{m}_marks_agree": cell.agrees if cell and cell.test else "",
                }
            )
        for lt in LIGHTINGS:
            mean_n = r.mtc.get(lt)
            d[f"mtc_{lt}"] = mean_n[0] if mean_n else ""
            d[f"mtc_{lt}_n"] = mean_n[1] if mean_n else 0
        for m in METRICS:
            mean_n = r.hil.get(m)
            d[f"hil_{m}"] = mean_n[0] if mean_n else ""
            d[f"hil_{m}_n"] = mean_n[1] if mean_n else 0
        out.append(d)
    return out


def rows_csv(rows: Sequence[Mapping[str, Any]]) -> str:
    """CSV with the union of the rows' keys as columns (first-seen order)."""
    cols: list[str] = []
    for r in rows:
        for k in r:
            if k not in cols:
                cols.append(k)
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=cols, lineterminator="\n", extrasaction="ignore")
    w.writeheader()
    for r in rows:
        w.writerow({c: _csv_value(r.get(c, "")) for c in cols})
    return buf.getvalue()


def _csv_value(v: Any) -> Any:
    if isinstance(v, float):
        return "" if not math.isfinite(v) else repr(v)
    if isinstance(v, (list, tuple, dict)):
        return str(v)
    return "" if v is None else v


def to_csv(rows: Sequence[Table2Row]) -> str:
    return rows_csv(table_rows(rows))


def by_lighting(records: Sequence[Mapping[str, Any]], *, segmenters: Sequence[str]) -> list[dict[str, Any]]:
    """Mean scores per (satellite, build, elevation, lighting, segmenter)."""
    groups: dict[tuple, list[Mapping[str, Any]]] = {}
    for r in records:
        if r.get("error"):
            continue
        groups.setdefault(
            (r["satellite"], r["build"], r["classes"], r["elevation"], r["lighting"]), []
        ).append(r)
    out = []
    for (sat, build, classes, elev, light), recs in sorted(
        groups.items(), key=lambda kv: (*_order(kv[0][0], kv[0][1], kv[0][3]), kv[0][4])
    ):
        for seg in segmenters:
            res = [r["results"][seg] for r in recs if seg in r.get("results", {})]
            if not res:
                continue
            row: dict[str, Any] = {
                "satellite": sat,
                "build": build,
                "classes": classes,
                "elevation": elev,
                "lighting": light,
                "segmenter": seg,
                "images": len(res),
            }
            for key in ("precision", "recall", "dice", "micro_iou", "mtc", "time_s"):
                vals = [float(x[key]) for x in res if _ok(x.get(key))]
                row[key] = float(np.mean(vals)) if vals else ""
            out.append(row)
    return out


def significance_markdown(
    records: Sequence[Mapping[str, Any]], rows: Sequence[Table2Row], *, multi: str, rgb: str, rho: float = 0.9
) -> str:
    """ρ sensitivity of every row's tests: p at each assumed ρ and at the observed correlation."""
    head = ["Satellite", "Build", "Elevation", "Metric", "n", "mean(multi − rgb)"]
    head += [f"p (ρ={r:g})" for r in SENSITIVITY_RHOS]
    head += [f"marks ρ={rho:g} / observed", "observed ρ", "p (observed)"]
    lines = [
        f"# Significance: {multi} (multi) vs {rgb} (RGB), paired over images",
        "",
        "SD_diff = sqrt(s_a² + s_b² − 2ρ·s_a·s_b), t = mean(a − b)/(SD_diff/√n), df = n − 1, two-sided "
        "(Cochrane Handbook 16.4.6; `analysis.metrics.significance`). "
        f"Table 2 uses ρ = {rho:g}.",
        "",
        "| " + " | ".join(head) + " |",
        "|" + "---|" * len(head),
    ]
    by_key: dict[tuple, list[Mapping[str, Any]]] = {}
    for r in records:
        if not r.get("error"):
            by_key.setdefault((r["satellite"], r["build"], r["elevation"]), []).append(r)
    for row in rows:
        recs = by_key.get((row.satellite, row.build, row.elevation), [])
        for m in METRICS:
            a = [
                float(r["results"][multi][m])
                for r in recs
                if _ok(r.get("results", {}).get(multi, {}).get(m))
                and _ok(r.get("results", {}).get(rgb, {}).get(m))
            ]
            b = [
                float(r["results"][rgb][m])
                for r in recs
                if _ok(r.get("results", {}).get(multi, {}).get(m))
                and _ok(r.get("results", {}).get(rgb, {}).get(m))
            ]
            if len(a) < 2:
                continue
            sweep = rho_sensitivity(a, b)
            cols = [
                row.satellite_name,
                row.build,
                row.elevation,
                METRIC_TITLES[m],
                str(len(a)),
                f"{np.mean(np.subtract(a, b)):+.4f}",
            ]
            cols += [f"{t.p:.3g}" for t in sweep[:-1]]
            both = AssumedVsObserved(paired_t_test(a, b, rho), sweep[-1])
            marks = f"{_escaped(both.assumed.stars)} / {_escaped(both.observed.stars)}"
            marks += "" if both.agree else " †"
            cols += [marks, _f(sweep[-1].rho_observed, 3), f"{sweep[-1].p:.3g}"]
            lines.append("| " + " | ".join(cols) + " |")
    return "\n".join(lines) + "\n"


def _band_stability_note(st: Mapping[str, Any] | None) -> str:
    """The PCA pick's bootstrap over images (``metrics.band_stability``), for the band note."""
    if not st:
        return ""
    sets = "; ".join(f"{', '.join(map(str, x['bands']))}: {x['share']:.0%}" for x in st["set_frequency"][:3])
    freq = sorted(((int(k), v) for k, v in st["band_frequency"].items() if v > 0), key=lambda kv: -kv[1])
    bands = ", ".join(f"{k}: {v:.0%}" for k, v in freq)
    return (f" Stability: that set recurs in {st['pick_frequency']:.0%} of {st['n_boot']} bootstrap "
            f"resamples of the images (most frequent sets {sets}; each band chosen in {bands}).")


def notes(result: EvaluationResult, rows: Sequence[Table2Row]) -> list[str]:
    """The report's reading notes: what was compared, how, and what is missing."""
    o = result.options
    n = len(result.records)
    n_truth = sum(bool(r.get("has_truth")) for r in result.records)
    out = [
        f"{n} images from {', '.join(result.sources) or 'the given jobs'}; {n_truth} with ground truth "
        "(the simulator's label maps stored with the frames).",
        f"Multi = `{o.multi}` on the 10-band cube; RGB = `{o.rgb_name}` (the same segmenter on "
        + ("the wavelength→RGB rendering with the near-infrared bands clamped into red (Bruton, γ = 0.8): "
           "NOT what an RGB camera sees)." if "nir" in o.rgb_name else
           "the image an RGB camera would see: band responses through the CIE 1931 colour-matching "
           "functions to linear sRGB, behind an IR-cut filter at 700 nm; `analysis.segmenters.rgb`)."),
        "Macro scores average the ground-truth classes of each image (background included, 0/0 = 0) after "
        "oracle Hungarian matching of clusters to classes: an upper bound for a segmenter whose cluster "
        "ids carry no material names.",
        f"Significance: paired t-test over the row's images with an assumed within-image correlation "
        f"ρ = {o.rho:g} (significance.md sweeps ρ). The better value is marked: **bold**\\* p < 0.05, "
        "***bold italic***\\*\\* p < 0.01 (the paper: bold α = 0.05, italic α = 0.01); '–' = fewer than "
        "2 images. Each metric's ρ̂ column gives the observed correlation of the row's paired scores and "
        "the marks at it (M/R: multi/RGB better, ns: not significant; the plain paired t-test), † where "
        "they differ from the marks at the assumed ρ.",
    ]
    if o.mtc_for == "none":
        out.append("mTC was not computed (--mtc none).")
    elif o.mtc_mode == "labels":
        out.append(
            "mTC: K = 8 integer shifts (seed 42, |Δ| ≤ 3), micro-IoU of the multispectral segmenter's "
            "full label map against its shifted-and-unshifted prediction, aligned by Hungarian matching; "
            "mean over the row's images per lighting condition."
        )
    else:
        bands = ", ".join(str(b) for b in o.mtc_bands)
        out.append(
            f"mTC: the paper's binary setting (bands {bands} segmented separately, fused "
            "foreground/background, K = 8 shifts, seed 42; SAM keeps the top k = number of classes masks "
            "per band after de-duplication at IoU 0.9). A pixel-wise segmenter scores exactly 1.0 here."
        )
    b = getattr(result, "bands", None)
    if b:
        used = {"paper": "the paper's", "pca": "PCA's", "given": "the given"}.get(b.get("mtc_used"), "")
        mtc_b = ", ".join(str(x) for x in b.get("mtc_bands", ()))
        if b.get("pca_bands"):
            pca = ", ".join(str(x) for x in b["pca_bands"])
            out.append(
                f"Band selection: PCA on these images ({b.get('pca_images')} images' foreground spectra, "
                f"standardised) picks bands {pca}; the paper's PCA picked 5, 9, 10. The binary mTC "
                f"{'used' if b.get('mtc_binary') else 'would use'} bands {mtc_b} ({used} bands)."
                + _band_stability_note(b.get("pca_stability"))
            )
        else:
            out.append(f"Band selection: PCA could not run ({b.get('pca_error', 'no pixels')}); "
                       f"mTC bands {mtc_b} ({used} bands).")
    metric_errors = getattr(result, "metric_errors", [])
    if metric_errors:
        out.append(f"{len(metric_errors)} segmenter or metric failures on otherwise evaluated images "
                   "(their other metrics are kept; see summary.json, metric_errors).")
    if n_truth == 0:
        out.append(
            "No ground truth in these images (e.g. an exported or real dataset): only the "
            "ground-truth-free mTC is reported; precision, recall and Dice are '–'."
        )
    elif n_truth < n:
        out.append(f"{n - n_truth} images have no ground truth: they count for mTC only.")
    if result.errors:
        out.append(f"{len(result.errors)} images could not be evaluated (see summary.json).")
    return out
