"""Finding each frame's pose reference for ``spectral-pose`` (``segmenters.pose``) before the images
are evaluated.

A pose is one source's satellite, build, elevation and azimuth; a session takes it under each of its
lightings at the same stage position. The pose's reference is its frame under the first lighting of
``POSE_REFERENCE_LIGHTINGS`` the source has there (strong diffuse, else weak diffuse), labelled by
the sweep segmenter (``POSE_REFERENCE_SEGMENTER``) fitted on that lighting's sweep: the model the
evaluation fitted already when it runs that segmenter too, else one fitted here. The references are
labelled as one task each on the evaluation's workers; each frame of the pose then carries its
reference (``FrameJob.pose_ref``: the labels and a log-energy image, about 1.5 bytes a pixel), or why
it has none as a string, which that image reports as the segmenter's error. A reference frame is its
own reference: its ``spectral-pose`` labels are the sweep segmenter's.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import replace
from typing import Any

from m2s2hil.analysis.evaluation.jobs import FrameJob
from m2s2hil.analysis.evaluation.loading import load_frame
from m2s2hil.analysis.evaluation.options import (
    POSE_REFERENCE_SEGMENTER,
    EvalOptions,
    cached_segmenter,
    is_pose,
)
from m2s2hil.analysis.evaluation.parallel import map_ordered
from m2s2hil.analysis.evaluation.sweeps import fit_sweeps, sweep_cube
from m2s2hil.analysis.segmenters.masks import segment_masked
from m2s2hil.analysis.segmenters.pose import POSE_REFERENCE_LIGHTINGS, PoseReference

PoseKey = tuple[str, str, str, str, float]


def pose_key(job: FrameJob) -> PoseKey | None:
    """The pose an image shows; None when its azimuth is unknown (no pose to share)."""
    if job.azimuth_deg is None or not math.isfinite(job.azimuth_deg):
        return None
    return (job.source, job.satellite, job.build, job.elevation, round(float(job.azimuth_deg) % 360.0, 3))


def label_reference(job: FrameJob, options: EvalOptions) -> PoseReference | str:
    """The reference of ``job``'s pose: ``job`` labelled by its sweep's model, or why it cannot be."""
    model = dict(job.sweep).get(POSE_REFERENCE_SEGMENTER)
    if model is None or isinstance(model, str):
        return f"the pose's reference {job.image_id} has no sweep model: {model or 'none was fitted'}"
    try:
        frame = load_frame(job, options.reprocess, masks=options.clip_masks, bracket=options.bracket)
        seg = cached_segmenter(POSE_REFERENCE_SEGMENTER, options, job.camera.get("bands_nm") or ())
        seg.use(model)  # type: ignore[attr-defined]
        t0 = time.perf_counter()
        labels = segment_masked(seg, sweep_cube(frame.cube, job), frame.saturated)
        return PoseReference.of(job.image_id, frame.cube, labels, time.perf_counter() - t0)
    except Exception as exc:  # the pose's images report it
        return f"the pose's reference {job.image_id} could not be labelled: {type(exc).__name__}: {exc}"


def attach_pose_references(jobs: Sequence[FrameJob], options: EvalOptions, *,
                           client: Any = None) -> list[FrameJob]:
    """``jobs`` with each one's pose reference (``FrameJob.pose_ref``) when ``spectral-pose`` is
    evaluated; unchanged otherwise."""
    if not any(is_pose(n) for n in options.segmenters):
        return list(jobs)
    refs: dict[PoseKey, FrameJob] = {}
    rank = POSE_REFERENCE_LIGHTINGS.index
    for job in jobs:
        key = pose_key(job)
        if key is None or job.lighting not in POSE_REFERENCE_LIGHTINGS:
            continue
        held = refs.get(key)
        if held is None or rank(job.lighting) < rank(held.lighting):
            refs[key] = job
    # the reference lightings' sweeps, fitted where the evaluation did not fit them already
    chosen = {j.image_id for j in refs.values()}
    lights = {(j.source, j.satellite, j.build, j.lighting) for j in refs.values()}
    members = [j for j in jobs if (j.source, j.satellite, j.build, j.lighting) in lights]
    if any(POSE_REFERENCE_SEGMENTER not in dict(j.sweep) for j in members):
        members = fit_sweeps(members, options, client=client, names=(POSE_REFERENCE_SEGMENTER,))
    ref_jobs = [j for j in members if j.image_id in chosen]
    labelled = map_ordered(label_reference, ref_jobs, client=client, options=options)
    by_id = {j.image_id: r for j, r in zip(ref_jobs, labelled, strict=True)}
    out = []
    for job in jobs:
        key = pose_key(job)
        ref = refs.get(key) if key is not None else None
        if ref is None:
            why = ("no azimuth recorded: its pose is unknown" if key is None else
                   f"no frame of this pose under {' or '.join(POSE_REFERENCE_LIGHTINGS)} diffuse light in "
                   f"{job.source}")
            out.append(replace(job, pose_ref=why))
        else:
            out.append(replace(job, pose_ref=by_id[ref.image_id]))
    return out
