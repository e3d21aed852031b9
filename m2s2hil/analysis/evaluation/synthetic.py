"""Table 2's synthetic columns as the paper computed them, and the sim-to-real comparison.

**Synthetic columns** (paper, sections 2.4.1 and 3): on each synthetic view (a session of
kind ``synthetic``, m2s2hil.twin.synth) the same segmenter runs on

- *RGB*: the RGB render (its three channels as a 3-band cube, 0..1);
- *Multi*: each of the band renders of the paper's PCA bands 5, 9 and 10 (1-based,
  ``analysis.bands.PAPER_BANDS``) segmented one by one, the label maps fused by a pixel-wise
  majority vote, non-background favoured on ties (``compositing.majority_vote``, maps aligned
  to the first);

and both are scored against the view's mask (oracle Hungarian matching of segments to
materials, then macro precision, recall and Dice: ``metrics.scores.score_clusters``). One row
per (satellite, build, elevation), E3 included: the mean of each metric over the row's views
and the paired t-test of Multi against RGB (``metrics.significance.paired_t_test``, ρ = 0.9
as the paper assumes).

**Sim to real**: for every pose that has both a synthetic view and a HIL frame (paired by
``twin.synth.pose_key``: elevation and nominal azimuth), the same segmenter on the synthetic
Multi input and on the HIL frame's cube, each scored against its own truth (the view's
mask; the HIL frame's simulator truth or, failing that, its projected labels); the gap is
synthetic − HIL per metric. HIL frames without any truth are skipped (counted).
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from m2s2hil.analysis.bands import PAPER_BANDS
from m2s2hil.analysis.errors import AnalysisInputError
from m2s2hil.analysis.metrics.scores import score_clusters
from m2s2hil.analysis.metrics.significance import DEFAULT_RHO, paired_t_test
from m2s2hil.analysis.segmenters.compositing import majority_vote
from m2s2hil.analysis.segmenters.registry import Segmenter, run_segmenter
from m2s2hil.store.frame_files import decode_image
from m2s2hil.store.session import SessionStore
from m2s2hil.twin.synth import band_images, pose_key

METRICS = ("precision", "recall", "dice")
HIL_TRUTH_ROLES = ("truth_labels", "projected_labels")  # the simulator's truth first


@dataclass(frozen=True)
class ViewScores:
    """One synthetic view scored with the RGB and the fused band inputs."""

    satellite: str
    build: str
    elevation: str
    azimuth_deg: float
    event_id: str
    rgb: dict[str, float]
    multi: dict[str, float]


def _cube(img: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8 → (3, H, W) float32 in 0..1."""
    return np.ascontiguousarray(np.moveaxis(img, -1, 0), dtype=np.float32) / np.float32(255.0)


def _scores(truth: np.ndarray, labels: np.ndarray) -> dict[str, float]:
    s, _ = score_clusters(truth, labels)
    return {"precision": s.macro_precision, "recall": s.macro_recall, "dice": s.macro_dice}


def fused_bands(segmenter: Segmenter, bands: np.ndarray, picks: Sequence[int] = PAPER_BANDS) -> np.ndarray:
    """The paper's multispectral prediction: bands ``picks`` (1-based) of ``bands`` (n, H, W, 3)
    segmented one by one, fused by majority vote."""
    if any(not 1 <= b <= len(bands) for b in picks):
        raise AnalysisInputError("bands", f"picks {list(picks)} outside 1..{len(bands)}")
    return majority_vote([run_segmenter(segmenter, _cube(bands[b - 1])) for b in picks])


def score_views(store: SessionStore, segmenter: Segmenter, progress: Callable[[int, int], None] | None = None,
                limit: int | None = None) -> list[ViewScores]:
    """Every view (the first ``limit``) of a synthetic session, RGB and Multi scored against its mask."""
    if store.kind != "synthetic":
        raise AnalysisInputError("session", f"{store.session_id} is a {store.kind} session, not synthetic")
    frames = store.frames()[:limit]
    out = []
    for i, fr in enumerate(frames):
        rgb, bands, mask = band_images(store, fr.event_id)
        key = pose_key(fr.meta, fr.event_id)
        out.append(ViewScores(
            satellite=store.sweep.satellite, build=store.sweep.build, elevation=key[0] if key else "",
            azimuth_deg=float(fr.meta.get("nominal_azimuth_deg", 0.0)), event_id=fr.event_id,
            rgb=_scores(mask, run_segmenter(segmenter, _cube(rgb))),
            multi=_scores(mask, fused_bands(segmenter, bands)),
        ))
        if progress is not None:
            progress(i + 1, len(frames))
    return out


@dataclass(frozen=True)
class SyntheticRow:
    satellite: str
    build: str
    classes: int
    elevation: str
    n: int
    rgb: dict[str, float]
    multi: dict[str, float]
    p: dict[str, float]  # two-sided p of Multi vs RGB (NaN: fewer than 2 views)


def synthetic_rows(views: Sequence[ViewScores], class_counts: dict[tuple[str, str], int],
                   rho: float = DEFAULT_RHO) -> list[SyntheticRow]:
    """Table 2's synthetic columns: one row per (satellite, build, elevation)."""
    groups: dict[tuple[str, str, str], list[ViewScores]] = {}
    for v in views:
        groups.setdefault((v.satellite, v.build, v.elevation), []).append(v)
    rows = []
    for (sat, build, elev), vs in sorted(groups.items()):
        p = {}
        for m in METRICS:
            a, b = [v.multi[m] for v in vs], [v.rgb[m] for v in vs]
            try:
                p[m] = paired_t_test(a, b, rho).p
            except AnalysisInputError:  # fewer than 2 views, or constant scores
                p[m] = math.nan
        rows.append(SyntheticRow(
            satellite=sat, build=build, classes=class_counts.get((sat, build), 0), elevation=elev, n=len(vs),
            rgb={m: float(np.mean([v.rgb[m] for v in vs])) for m in METRICS},
            multi={m: float(np.mean([v.multi[m] for v in vs])) for m in METRICS}, p=p,
        ))
    return rows


def rows_csv(rows: Sequence[SyntheticRow]) -> str:
    buf = io.StringIO()
    cols = ["satellite", "build", "classes", "elevation", "n"]
    cols += [f"{m}_{k}" for m in METRICS for k in ("rgb", "multi", "p")]
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(cols)
    for r in rows:
        w.writerow([r.satellite, r.build, r.classes, r.elevation, r.n]
                   + [f"{x:.4f}" for m in METRICS for x in (r.rgb[m], r.multi[m], r.p[m])])
    return buf.getvalue()


def rows_markdown(rows: Sequence[SyntheticRow]) -> str:
    """The synthetic half of Table 2; the better value bold where p < 0.05 (paired t-test)."""
    head = ("| Satellite | Build | Classes | Elevation | n | Precision RGB | Precision Multi | Recall RGB "
            "| Recall Multi | Dice RGB | Dice Multi |")
    lines = [head, "|" + "---|" * 11]
    for r in rows:
        cells = []
        for m in METRICS:
            a, b = f"{r.rgb[m]:.4f}", f"{r.multi[m]:.4f}"
            if r.p[m] < 0.05:
                if r.multi[m] > r.rgb[m]:
                    b = f"**{b}**"
                elif r.rgb[m] > r.multi[m]:
                    a = f"**{a}**"
            cells += [a, b]
        lead = f"| {r.satellite} | {r.build} | {r.classes} | {r.elevation} | {r.n} | "
        lines.append(lead + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


@dataclass(frozen=True)
class PosePair:
    """One pose seen in both domains, the same segmenter on each."""

    elevation: str
    azimuth_deg: int
    synthetic_event: str
    hil_event: str
    hil_truth: str  # which HIL label file scored it
    synthetic: dict[str, float]
    hil: dict[str, float]

    @property
    def gap(self) -> dict[str, float]:
        return {m: self.synthetic[m] - self.hil[m] for m in METRICS}


def sim_to_real(synthetic: SessionStore, hil: SessionStore, segmenter: Segmenter,
                lighting: str | None = None) -> tuple[list[PosePair], int]:
    """Every pose of ``synthetic`` that ``hil`` captured (under ``lighting``, default any):
    (pairs, HIL frames of those poses skipped for want of a truth)."""
    if synthetic.kind != "synthetic" or hil.kind != "hil":
        raise AnalysisInputError("sessions", "sim_to_real takes a synthetic session and a HIL session")
    if (synthetic.sweep.satellite, synthetic.sweep.build) != (hil.sweep.satellite, hil.sweep.build):
        raise AnalysisInputError("sessions", f"{synthetic.session_id} and {hil.session_id}: not one build")
    views = {pose_key(f.meta, f.event_id): f for f in synthetic.frames()}
    pairs, skipped = [], 0
    for fr in hil.frames():
        ev = fr.meta.get("event", {})
        key = pose_key(ev, fr.event_id)
        if key is None or key not in views or (lighting and ev.get("lighting") != lighting):
            continue
        role = next((r for r in HIL_TRUTH_ROLES if r in fr.files), None)
        if role is None:
            skipped += 1
            continue
        truth = decode_image(hil.read_file(fr.files[role])).astype(np.int64)
        cube = hil.read_cube(fr.event_id)
        if truth.shape != cube.shape[1:]:  # the truth is the sensor's grid, the cube may be smaller
            from m2s2hil.analysis.evaluation.loading import labels_to_cube  # processing: only here

            truth = labels_to_cube(truth, cube.shape[1:])
        sv = views[key]
        _, bands, mask = band_images(synthetic, sv.event_id)
        pairs.append(PosePair(
            elevation=key[0], azimuth_deg=key[1], synthetic_event=sv.event_id, hil_event=fr.event_id,
            hil_truth=role, synthetic=_scores(mask, fused_bands(segmenter, bands)),
            hil=_scores(truth, run_segmenter(segmenter, cube)),
        ))
    return pairs, skipped


def synthetic_target(target: str, root: str | Path | None) -> SessionStore | None:
    """The synthetic session ``target`` names (a folder, or an id under ``root``), open for
    reading; None when it names anything else (a HIL session, a data root, an export)."""
    from m2s2hil.store.catalogue import default_data_root
    from m2s2hil.store.layout import JOURNAL

    p = Path(target)
    folder = p if (p / JOURNAL).is_file() else Path(root or default_data_root()) / target
    if not (folder / JOURNAL).is_file():
        return None
    store = SessionStore.open_path(folder)
    if store.kind == "synthetic":
        return store
    store.close()
    return None


def evaluate_synthetic(store: SessionStore, segmenter: Segmenter, out: str | Path, *,
                       hil: SessionStore | None = None, limit: int | None = None, rho: float = DEFAULT_RHO,
                       progress: Callable[[int, int], None] | None = None) -> dict[str, Path]:
    """Score ``store``'s views (the first ``limit``), write ``synthetic_table2.{csv,md}`` and, with
    ``hil``, ``sim_to_real.csv`` (one row per pose) under ``out``; returns the files."""
    from m2s2hil.atomic import write_text_atomic
    from m2s2hil.catalog import load_catalog

    views = score_views(store, segmenter, progress, limit)
    cat = load_catalog()
    counts = {(store.sweep.satellite, store.sweep.build):
              len(cat.build(store.sweep.satellite, store.sweep.build).materials) + 1}
    rows = synthetic_rows(views, counts, rho)
    out = Path(out)
    files = {name: out / name for name in ("synthetic_table2.csv", "synthetic_table2.md")}
    write_text_atomic(files["synthetic_table2.csv"], rows_csv(rows))
    write_text_atomic(files["synthetic_table2.md"], rows_markdown(rows))
    if hil is not None:
        pairs, skipped = sim_to_real(store, hil, segmenter)
        buf = io.StringIO()
        w = csv.writer(buf, lineterminator="\n")
        w.writerow(["elevation", "azimuth_deg", "synthetic_event", "hil_event", "hil_truth",
                    *[f"{m}_{d}" for m in METRICS for d in ("synthetic", "hil", "gap")]])
        for pr in pairs:
            w.writerow([pr.elevation, pr.azimuth_deg, pr.synthetic_event, pr.hil_event, pr.hil_truth,
                        *[f"{x:.4f}" for m in METRICS for x in (pr.synthetic[m], pr.hil[m], pr.gap[m])]])
        if skipped:
            w.writerow([f"# {skipped} HIL frame(s) of these poses had no truth and were skipped"])
        files["sim_to_real.csv"] = out / "sim_to_real.csv"
        write_text_atomic(files["sim_to_real.csv"], buf.getvalue())
    return files
