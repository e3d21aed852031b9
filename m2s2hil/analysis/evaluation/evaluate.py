"""Evaluating segmenters over sessions and exported datasets (the paper's section 3).

Pipeline: ``collect_jobs(target)`` turns a session, a data root full of sessions, or an
exported dataset (``HIL/<Satellite>/b<N>/e<N>/<light>_<k>.png``) into one ``FrameJob``
per image (paths and metadata only, no pixels); ``evaluate_jobs`` runs ``evaluate_job``
on each, on Dask (``evaluation.parallel``); ``report.evaluation_files.write_evaluation`` writes the
Table-2-shaped report (``table2``), the per-image CSV, the charts (``report.charts``) and a
``summary.json``.

Per image (``evaluate_job``):

- cube: the stored cube (sha256 checked against the journal), or the raw mosaic run
  through ``processing.FrameProcessor`` (the session's dark and method, or ``reprocess=``);
  exported datasets are processed from their PNG mosaic (``HIL16`` when present), without
  dark subtraction;
- clipping mask (``EvalOptions.clip_masks``, on by default): which bands of each pixel hold a
  clipped raw value, from the raw frame (``loading.clipping_mask``; its ``any`` over bands is the
  processor's mask, also for a stored cube, which does not keep it). Segmenters that take it
  (``segmenters.masks``) get it, and label mTC shifts it with the cube; ``clipped_fraction`` in the
  per-image rows is the share of the image with a band clipped;
- bracket (``EvalOptions.bracket``, on by default): a pose the sweep bracketed
  (``Sweep.bracket``) is one image, its frames merged per band and pixel where each did not clip
  (``loading.load_frame``, ``processing.bracket``) on its own frame's scale; ``bracket_frames`` in
  the per-image rows counts them, ``bracket_error`` says why a pose's were not merged;
- ground truth: the simulator's label map the engine stored with the frame
  (``extra`` role ``truth_labels``, sensor resolution), reduced to the cube's grid by the
  majority label of each n×n cell (``labels_to_cube``); images without it get mTC only;
- every segmenter of ``EvalOptions.segmenters`` runs once (timed: ``time_s`` is the
  segmentation only), its clusters are matched to classes (oracle Hungarian matching,
  ``score_clusters``, label set = ground-truth classes, 0/0 = 0) and scored (macro P, R,
  Dice, micro-IoU);
- mTC (K = 8 seeded shifts, ``analysis.metrics.mtc``) of the multispectral segmenter (or every
  segmenter, ``mtc="all"``). ``mtc_mode="labels"`` (default): the segmenter's full label
  map, each shifted prediction aligned to the base one (Hungarian, 0 ↔ 0).
  ``mtc_mode="binary"``: the paper's HIL setting, bands 5, 9, 10 segmented one by one and
  fused as foreground/background (RGB segmenters: their prediction's foreground). With a
  pixel-wise segmenter (``spectral``) binary mTC is exactly 1.0 (a shift is undone
  exactly), which is why it is not the default.

Modules of ``m2s2hil.analysis.evaluation``: ``jobs`` (finding the images: ``FrameJob``,
``collect_jobs``), ``loading`` (cubes, raws and labels from the store, reprocessing,
``labels_to_cube``), ``options`` (``EvalOptions``, segmenter names, mTC predictors),
``aggregates`` (per-image rows, speed against accuracy), ``table2`` (the paper's table),
``parallel`` (Dask). This module is the driver; the report folder is written by
``m2s2hil.analysis.report.evaluation_files.write_evaluation``.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from m2s2hil.analysis.bands import PAPER_BANDS, select_bands_pca
from m2s2hil.analysis.evaluation.jobs import EvaluationError, FrameJob
from m2s2hil.analysis.evaluation.loading import load_frame, load_projected, load_truth
from m2s2hil.analysis.evaluation.options import (
    EvalOptions,
    cached_segmenter,
    check_segmenters,
    is_pose,
    is_sweep,
    mtc_predictor,
)
from m2s2hil.analysis.evaluation.parallel import dask_client, describe, map_ordered
from m2s2hil.analysis.evaluation.poses import attach_pose_references
from m2s2hil.analysis.evaluation.sweeps import fit_sweeps, sweep_cube
from m2s2hil.analysis.metrics.band_stability import band_stability
from m2s2hil.analysis.metrics.mtc import mtc
from m2s2hil.analysis.metrics.scores import score_clusters
from m2s2hil.analysis.segmenters.masks import segment_masked, takes_saturated
from m2s2hil.analysis.segmenters.pose import PoseReference
from m2s2hil.analysis.segmenters.spectral import foreground_mask

log = logging.getLogger(__name__)
PCA_SAMPLE_PIXELS = 200  # foreground spectra per image pooled for PCA band selection (8 kB per image)


# ----------------------------------------------------------------------------- one image
def _error(exc: BaseException) -> str:
    return f"{type(exc).__name__}: {exc}"


def _segmenter_result(
    name: str, cube: np.ndarray, gt: np.ndarray | None, job: FrameJob, options: EvalOptions, bands_nm: Any,
    projected: np.ndarray | None = None, saturated: np.ndarray | None = None,
) -> dict[str, Any]:
    """One segmenter on one image. Each step (segmentation, scores, mTC) fails on its own: its error
    is recorded under ``errors`` and the other steps' values are kept. ``saturated``: the image's
    clipping mask, given to a segmenter that takes it (``segmenters.masks``)."""
    res: dict[str, Any] = {}
    errors: dict[str, str] = {}
    try:
        seg = cached_segmenter(name, options, bands_nm)
        pred = None
        if is_pose(name):  # labelled from the pose's diffuse frame (evaluation.poses)
            ref = job.pose_ref
            if not isinstance(ref, PoseReference):
                raise EvaluationError(ref or f"{name}: no pose reference was looked for")
            seg.use(ref)  # type: ignore[attr-defined]
            res["pose_reference"] = ref.image_id
            if ref.image_id == job.image_id:  # a diffuse frame is its own reference
                pred = ref.labels.astype(np.int64)
                res["time_s"] = ref.time_s
        if is_sweep(name):  # label with the mixture fitted on this image's sweep (evaluation.sweeps)
            model = dict(job.sweep).get(name)
            if model is None or isinstance(model, str):
                raise EvaluationError(model or f"{name}: no model fitted for this image's sweep")
            seg.use(model)  # type: ignore[attr-defined]
            cube = sweep_cube(cube, job)  # at the exposure the sweep was fitted at
        if pred is None:
            t1 = time.perf_counter()
            pred = segment_masked(seg, cube, saturated)
            res["time_s"] = time.perf_counter() - t1
            last = getattr(seg, "last", None) if is_pose(name) else None
            if last is not None:  # how far the reference was moved to meet this frame
                res["pose_shift_rows"], res["pose_shift_cols"] = last.shift
        res["n_segments"] = len(np.unique(pred[pred > 0]))
    except Exception as exc:  # reported per segmenter; the image's other segmenters still run
        log.warning("%s on %s failed: %s", name, job.image_id, exc)
        return {"errors": {"segment": _error(exc)}}
    return _scored(res, errors, name, pred, cube, gt, job, options, seg, projected, saturated)


def _scored(res: dict[str, Any], errors: dict[str, str], name: str, pred: np.ndarray, cube: np.ndarray,
            gt: np.ndarray | None, job: FrameJob, options: EvalOptions, seg: Any,
            projected: np.ndarray | None, saturated: np.ndarray | None) -> dict[str, Any]:
    """``res`` with the scores of ``pred`` and the segmenter's mTC."""
    if gt is not None:
        try:
            s, _ = score_clusters(gt, pred)
            res.update(precision=s.macro_precision, recall=s.macro_recall, dice=s.macro_dice,
                       micro_iou=s.micro_iou)
        except Exception as exc:
            errors["scores"] = _error(exc)
    if projected is not None:  # a HIL frame against the twin's projected labels (no truth there)
        try:
            s, _ = score_clusters(projected, pred)
            res.update(hil_precision=s.macro_precision, hil_recall=s.macro_recall, hil_dice=s.macro_dice)
        except Exception as exc:
            errors["hil_scores"] = _error(exc)
    if options.mtc_for == "all" or (options.mtc_for == "multi" and name == options.multi):
        try:
            predict, align = mtc_predictor(
                seg, name, options.mtc_mode, cube.shape[0], n_classes=job.n_classes, bands=options.mtc_bands
            )
            # the mask moves with each shift; the binary setting segments bands one by one, without it
            masked = options.mtc_mode == "labels" and takes_saturated(seg.segment)
            t2 = time.perf_counter()
            r = mtc(predict, cube, align=align, saturated=saturated if masked else None)
            res.update(mtc=r.score, mtc_time_s=time.perf_counter() - t2)
        except Exception as exc:
            log.warning("mTC of %s on %s failed: %s", name, job.image_id, exc)
            errors["mtc"] = _error(exc)
    if errors:
        res["errors"] = errors
    return res


def pca_sample(cube: np.ndarray, n: int = PCA_SAMPLE_PIXELS, seed: int = 0) -> np.ndarray:
    """Up to ``n`` foreground spectra ``(n, bands)`` float32 (Otsu foreground, seeded draw), pooled
    over the evaluated images for PCA band selection."""
    fg, _ = foreground_mask(cube)
    spectra = cube[:, fg].T
    if spectra.shape[0] > n:
        spectra = spectra[np.random.default_rng(seed).choice(spectra.shape[0], n, replace=False)]
    return np.ascontiguousarray(spectra, dtype=np.float32)


def evaluate_job(job: FrameJob, options: EvalOptions) -> dict[str, Any]:
    """Scores of every segmenter on one image; errors are returned in the record, not raised.

    ``error`` is set only when the image itself cannot be read; a segmenter or metric that fails
    records its error in ``results[name]["errors"]`` and keeps the other values.
    """
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
        frame = load_frame(job, options.reprocess, masks=options.clip_masks, bracket=options.bracket)
        cube, saturated = frame.cube, frame.saturated
        gt = load_truth(job, cube.shape[1:])
        rec["load_s"] = time.perf_counter() - t0
        rec["has_truth"] = gt is not None
        rec["cube_shape"] = list(cube.shape)
    except Exception as exc:  # one bad image must not end a 16,000-image run; it is reported
        log.warning("evaluation of %s failed: %s", job.image_id, exc)
        rec["error"] = _error(exc)
        return rec
    if frame.mask_error:
        rec["mask_error"] = frame.mask_error
    rec["bracket_frames"] = frame.bracket_frames
    if frame.bracket_error:
        rec["bracket_error"] = frame.bracket_error
    rec["clipped_fraction"] = frame.clipped_fraction
    bands_nm = job.camera.get("bands_nm") or ()
    projected = None
    try:
        projected = load_projected(job, cube.shape[1:])
    except Exception as exc:  # projected labels are optional: the other scores still count
        rec["projected_error"] = _error(exc)
    rec["has_projected"] = projected is not None
    for name in options.segmenters:
        rec["results"][name] = _segmenter_result(name, cube, gt, job, options, bands_nm, projected, saturated)
    try:
        rec["pca_sample"] = pca_sample(cube)
    except Exception as exc:
        rec["pca_error"] = _error(exc)
    return rec


# ----------------------------------------------------------------------------- running
@dataclass
class EvaluationResult:
    records: list[dict[str, Any]]
    options: EvalOptions
    sources: list[str]
    elapsed_s: float
    compute: dict[str, Any]
    bands: dict[str, Any] | None = None  # ``band_report``: PCA's bands beside the paper's and mTC's

    @property
    def metric_errors(self) -> list[dict[str, Any]]:
        """Segmenter or metric failures on images that were otherwise evaluated."""
        out = []
        for r in self.records:
            for name, res in r.get("results", {}).items():
                for step, err in res.get("errors", {}).items():
                    out.append({"image_id": r["image_id"], "segmenter": name, "step": step, "error": err})
        return out

    @property
    def has_truth(self) -> bool:
        return any(r["has_truth"] for r in self.records)

    @property
    def errors(self) -> list[dict[str, Any]]:
        return [r for r in self.records if r.get("error")]


def band_report(records: list[dict[str, Any]], options: EvalOptions, bands_nm: Sequence[float] = ()) -> dict:
    """PCA band selection on the evaluated images (their pooled foreground spectra, taken out of the
    records), beside the paper's bands 5, 9, 10 and the bands the binary mTC used."""
    samples = [r.pop("pca_sample") for r in records if r.get("pca_sample") is not None]
    report: dict[str, Any] = {
        "paper_bands": list(PAPER_BANDS),
        "mtc_bands": list(options.mtc_bands),
        "mtc_used": "paper" if tuple(options.mtc_bands) == PAPER_BANDS else "given",
        "mtc_binary": options.mtc_mode == "binary" and options.mtc_for != "none",
        "pca_bands": None,
        "pca_images": len(samples),
    }
    samples = [s for s in samples if s.shape[0] > 0]
    try:
        pixels = np.concatenate(samples)[:, :, np.newaxis] if samples else None
        if pixels is None:
            raise ValueError("no foreground pixels in the evaluated images")
        sel = select_bands_pca(np.moveaxis(pixels, 0, 1))  # (bands, n, 1): one "cube" of pooled pixels
    except Exception as exc:  # reported, never fatal: PCA is a side result
        report["pca_error"] = _error(exc)
        return report
    if tuple(options.mtc_bands) == sel.bands_1based:
        report["mtc_used"] = "pca"
    report.update(
        pca_bands=sorted(sel.bands_1based),
        pca_pick_order=list(sel.bands_1based),
        pca_explained_variance=[float(v) for v in sel.explained_variance_ratio],
        pca_pixels=sel.n_pixels,
        pca_standardized=sel.standardize,
        loadings_table=sel.loadings_table(list(bands_nm) if len(bands_nm) == sel.loadings.shape[1] else None),
    )
    try:  # how often the pick recurs when the images are resampled (metrics.band_stability)
        report["pca_stability"] = band_stability(samples).as_dict()
    except Exception as exc:  # a side result of a side result: reported, never fatal
        report["pca_stability_error"] = _error(exc)
    return report


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
    if not jobs:
        raise EvaluationError("nothing to evaluate: no images found")
    check_segmenters(options)
    total = len(jobs)

    def on_result(done: int, _rec: Any) -> None:
        if progress is not None:
            progress(done, total)

    t0 = time.perf_counter()
    if workers == 0 and not scheduler:
        fitted = fit_sweeps(jobs, options)  # the sweep segmenters' mixtures first, one task a sweep
        fitted = attach_pose_references(fitted, options)  # then spectral-pose's references
        records = map_ordered(evaluate_job, fitted, client=None, on_result=on_result, options=options)
        compute = describe(None)
    else:
        with dask_client(scheduler, workers=workers, processes=processes) as client:
            compute = describe(client)
            fitted = fit_sweeps(jobs, options, client=client)
            fitted = attach_pose_references(fitted, options, client=client)
            records = map_ordered(evaluate_job, fitted, client=client, on_result=on_result, options=options)
    bands_nm: Sequence[float] = next((j.camera["bands_nm"] for j in jobs if j.camera.get("bands_nm")), ())
    bands = band_report(records, options, bands_nm)
    return EvaluationResult(records, options, list(sources), time.perf_counter() - t0, compute, bands)
