"""Evaluating segmenters over sessions and exported datasets (the paper's section 3).

Pipeline: ``collect_jobs(target)`` turns a session, a data root full of sessions, or an
exported dataset (``HIL/<Satellite>/b<N>/e<N>/<light>_<k>.png``) into one ``FrameJob``
per image (paths and metadata only, no pixels); ``evaluate_jobs`` runs ``evaluate_job``
on each, on Dask (``m2s2hil.analysis.parallel``); ``write_evaluation`` writes the
Table-2-shaped report (``table2``), the per-image CSV, the charts (``charts``) and a
``summary.json``.

Per image (``evaluate_job``):

- cube: the stored cube (sha256 checked against the journal), or the raw mosaic run
  through ``processing.FrameProcessor`` (the session's dark and method, or ``reprocess=``);
  exported datasets are processed from their PNG mosaic (``HIL16`` when present), without
  dark subtraction;
- ground truth: the simulator's label map the engine stored with the frame
  (``extra`` role ``truth_labels``, sensor resolution), reduced to the cube's grid by the
  majority label of each n×n cell (``labels_to_cube``); images without it get mTC only;
- every segmenter of ``EvalOptions.segmenters`` runs once (timed: ``time_s`` is the
  segmentation only), its clusters are matched to classes (oracle Hungarian matching,
  ``score_clusters``, label set = ground-truth classes, 0/0 = 0) and scored (macro P, R,
  Dice, micro-IoU);
- mTC (K = 8 seeded shifts, ``analysis.mtc``) of the multispectral segmenter (or every
  segmenter, ``mtc="all"``). ``mtc_mode="labels"`` (default): the segmenter's full label
  map, each shifted prediction aligned to the base one (Hungarian, 0 ↔ 0).
  ``mtc_mode="binary"``: the paper's HIL setting, bands 5, 9, 10 segmented one by one and
  fused as foreground/background (RGB segmenters: their prediction's foreground). With a
  pixel-wise segmenter (``spectral``) binary mTC is exactly 1.0 (a shift is undone
  exactly), which is why it is not the default.

Modules: ``jobs`` (finding the images: ``FrameJob``, ``collect_jobs``), ``loading`` (cubes,
raws and labels from the store, reprocessing, ``labels_to_cube``), ``options``
(``EvalOptions``, segmenter names, mTC predictors), ``aggregates`` (per-image rows, speed
against accuracy), ``study`` (simulated sessions, the failure study). This module is the
driver and re-exports their public names, so ``from m2s2hil.analysis.evaluate import ...``
keeps working.
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from m2s2hil.analysis.aggregates import machine, per_image_rows, speed_accuracy
from m2s2hil.analysis.jobs import (
    TRUTH_ROLE,
    EvaluationError,
    FileRef,
    FrameJob,
    collect_jobs,
    dataset_jobs,
    session_jobs,
)
from m2s2hil.analysis.loading import labels_to_cube, load_cube, load_truth
from m2s2hil.analysis.metrics import score_clusters
from m2s2hil.analysis.mtc import mtc
from m2s2hil.analysis.options import (
    RGB_COUNTERPART,
    EvalOptions,
    MtcFor,
    MtcMode,
    cached_segmenter,
    check_segmenters,
    is_rgb,
    make_segmenter,
    mtc_predictor,
)
from m2s2hil.analysis.study import SCENARIOS, simulate_session, stability_markdown, stability_study
from m2s2hil.store.frame_files import decode_tiff

log = logging.getLogger(__name__)



# ----------------------------------------------------------------------------- one image
def evaluate_job(job: FrameJob, options: EvalOptions) -> dict[str, Any]:
    """Scores of every segmenter on one image; errors are returned in the record, not raised."""
    rec: dict[str, Any] = {
        "image_id": job.image_id,
        "source": job.source,
        "satellite": job.satellite,
        "build": job.build,
        "classes": job.n_classes,
        "elevation": job.elevation,
        "lighting": job.lighting,
        "azimuth_deg": job.azimuth_deg,
        "has_truth": False,
        "error": None,
        "results": {},
    }
    try:
        t0 = time.perf_counter()
        cube = load_cube(job, options.reprocess)
        gt = load_truth(job, cube.shape[1:])
        rec["load_s"] = time.perf_counter() - t0
        rec["has_truth"] = gt is not None
        rec["cube_shape"] = list(cube.shape)
        bands_nm = job.camera.get("bands_nm") or ()
        for name in options.segmenters:
            seg = cached_segmenter(name, options, bands_nm)
            t1 = time.perf_counter()
            pred = seg.segment(cube)
            res: dict[str, Any] = {
                "time_s": time.perf_counter() - t1,
                "n_segments": len(np.unique(pred[pred > 0])),
            }
            if gt is not None:
                s, _ = score_clusters(gt, pred)
                res.update(
                    precision=s.macro_precision,
                    recall=s.macro_recall,
                    dice=s.macro_dice,
                    micro_iou=s.micro_iou,
                )
            if options.mtc_for == "all" or (options.mtc_for == "multi" and name == options.multi):
                predict, align = mtc_predictor(seg, name, options.mtc_mode, cube.shape[0])
                t2 = time.perf_counter()
                r = mtc(predict, cube, align=align)
                res.update(mtc=r.score, mtc_time_s=time.perf_counter() - t2)
            rec["results"][name] = res
    except Exception as exc:  # one bad image must not end a 16,000-image run; it is reported
        log.warning("evaluation of %s failed: %s", job.image_id, exc)
        rec["error"] = f"{type(exc).__name__}: {exc}"
    return rec


# ----------------------------------------------------------------------------- running
@dataclass
class EvaluationResult:
    records: list[dict[str, Any]]
    options: EvalOptions
    sources: list[str]
    elapsed_s: float
    compute: dict[str, Any]

    @property
    def has_truth(self) -> bool:
        return any(r["has_truth"] for r in self.records)

    @property
    def errors(self) -> list[dict[str, Any]]:
        return [r for r in self.records if r.get("error")]


def evaluate_jobs(
    jobs: Sequence[FrameJob],
    options: EvalOptions,
    *,
    scheduler: str | None = None,
    workers: int | None = None,
    processes: bool = True,
    sources: Sequence[str] = (),
    progress: Callable[[int, int], None] | None = None,
) -> EvaluationResult:
    """Run ``evaluate_job`` over ``jobs`` on Dask (``workers=0``: in this process)."""
    from m2s2hil.analysis.parallel import dask_client, describe, map_ordered

    if not jobs:
        raise EvaluationError("nothing to evaluate: no images found")
    check_segmenters(options)
    total = len(jobs)

    def on_result(done: int, _rec: Any) -> None:
        if progress is not None:
            progress(done, total)

    t0 = time.perf_counter()
    if workers == 0 and not scheduler:
        records = map_ordered(evaluate_job, list(jobs), client=None, on_result=on_result, options=options)
        compute = describe(None)
    else:
        with dask_client(scheduler, workers=workers, processes=processes) as client:
            compute = describe(client)
            records = map_ordered(
                evaluate_job, list(jobs), client=client, on_result=on_result, options=options
            )
    return EvaluationResult(records, options, list(sources), time.perf_counter() - t0, compute)


# ----------------------------------------------------------------------------- writing
def write_evaluation(result: EvaluationResult, out: str | Path) -> dict[str, Path]:
    """Write table2.csv/.md, per_image.csv, significance.md, the charts and summary.json into ``out``."""
    from m2s2hil.analysis import charts, table2
    from m2s2hil.store.atomic import write_text_atomic

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    opts = result.options
    rows = table2.build_rows(result.records, multi=opts.multi, rgb=opts.rgb_name, rho=opts.rho)
    written: dict[str, Path] = {}
    notes = table2.notes(result, rows)
    write_text_atomic(out / "table2.csv", table2.to_csv(rows))
    write_text_atomic(out / "table2.md", table2.to_markdown(rows, notes=notes))
    written["table2.csv"], written["table2.md"] = out / "table2.csv", out / "table2.md"
    write_text_atomic(out / "per_image.csv", table2.rows_csv(per_image_rows(result.records)))
    written["per_image.csv"] = out / "per_image.csv"
    by_light = table2.by_lighting(result.records, segmenters=opts.segmenters)
    write_text_atomic(out / "by_lighting.csv", table2.rows_csv(by_light))
    written["by_lighting.csv"] = out / "by_lighting.csv"
    if result.has_truth:
        write_text_atomic(
            out / "significance.md",
            table2.significance_markdown(result.records, rows, multi=opts.multi, rgb=opts.rgb_name),
        )
        written["significance.md"] = out / "significance.md"
    speed = speed_accuracy(result.records)
    written.update(charts.write_evaluation_charts(out, rows, speed, has_truth=result.has_truth))
    summary = {
        "written": datetime.now(UTC).isoformat(timespec="seconds"),
        "sources": result.sources,
        "images": len(result.records),
        "images_with_truth": sum(r["has_truth"] for r in result.records),
        "errors": [{"image_id": r["image_id"], "error": r["error"]} for r in result.errors],
        "options": {**asdict(opts), "segmenters": list(opts.segmenters), "rgb": opts.rgb_name},
        "elapsed_s": result.elapsed_s,
        "compute": result.compute,
        "machine": machine(),
        "speed_accuracy": speed,
        "notes": notes,
    }
    write_text_atomic(out / "summary.json", json.dumps(summary, indent=2, sort_keys=True, default=str) + "\n")
    written["summary.json"] = out / "summary.json"
    return written


__all__ = [
    "RGB_COUNTERPART",
    "SCENARIOS",
    "TRUTH_ROLE",
    "EvalOptions",
    "EvaluationError",
    "EvaluationResult",
    "FileRef",
    "FrameJob",
    "MtcFor",
    "MtcMode",
    "check_segmenters",
    "collect_jobs",
    "dataset_jobs",
    "decode_tiff",
    "evaluate_job",
    "evaluate_jobs",
    "is_rgb",
    "labels_to_cube",
    "load_cube",
    "load_truth",
    "machine",
    "make_segmenter",
    "mtc_predictor",
    "per_image_rows",
    "session_jobs",
    "simulate_session",
    "speed_accuracy",
    "stability_markdown",
    "stability_study",
    "write_evaluation",
]
