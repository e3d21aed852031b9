"""Fitting the sweep segmenters (``segmenters.sweep``) before the images are evaluated.

A sweep is every frame of one session (or exported dataset) of one satellite and build under one
lighting: the same materials, seen from every azimuth and tilt. Each sweep
segmenter the evaluation runs (``spectral-sweep``, ``rgb-sweep``) is fitted once per sweep, as one
task per sweep on the same workers as the images; the fitted model (a few kB of mixture) then
travels with each of the sweep's ``FrameJob``s, which label their image with it. A sweep whose
model cannot be fitted (no frame could be read, no foreground) carries the reason instead, and each
of its images reports it as that segmenter's error, as any failed segmentation is reported.

The plan gives every frame of a lighting one exposure; where a sweep's frames record different
ones (auto-exposure), each cube is scaled to the first frame's exposure × gain before it is fitted
and labelled (``FrameJob.sweep_scale``), so a material keeps one brightness coordinate across the
sweep: on simulated frames each exposed for its own peak, unscaled, the spotlight at 0° fell
from 76 to 65 % of frames within ±1 (docs/evaluation.md, ninth pass). A sweep where any frame lacks its
exposure is left unscaled.
"""

from __future__ import annotations

import logging
from collections import deque
from collections.abc import Iterator, Sequence
from dataclasses import replace
from typing import Any

import numpy as np

from m2s2hil.analysis.evaluation.jobs import FrameJob
from m2s2hil.analysis.evaluation.loading import load_frame
from m2s2hil.analysis.evaluation.options import EvalOptions, is_sweep, make_segmenter
from m2s2hil.analysis.evaluation.parallel import map_ordered
from m2s2hil.analysis.segmenters.masks import takes_saturated

log = logging.getLogger(__name__)

SweepKey = tuple[str, str, str, str]


def sweep_key(job: FrameJob) -> SweepKey:
    """The sweep an image belongs to: its source, satellite, build and lighting."""
    return (job.source, job.satellite, job.build, job.lighting)


def fit_sweep(group: tuple[str, list[FrameJob]], options: EvalOptions) -> Any:
    """One sweep segmenter fitted on one sweep's images (read one at a time); the model, or the
    reason there is none as a string. Images that cannot be read are left out of the fit (their
    own job reports them)."""
    name, jobs = group
    bands_nm = next((j.camera.get("bands_nm") for j in jobs if j.camera.get("bands_nm")), None)
    try:
        seg = make_segmenter(name, options.segmenter_options, bands_nm=bands_nm)
        # Each frame's clipping mask is handed over right after its cube: ``fit`` reads the two in
        # step, so only one frame is ever in memory.
        masks = _Handover()

        def cubes() -> Iterator[np.ndarray]:
            for job in jobs:
                try:
                    frame = load_frame(job, options.reprocess, masks=options.clip_masks,
                                       bracket=options.bracket)
                except Exception as exc:  # reported by the image's own job
                    log.warning("sweep fit of %s: %s left out: %s", name, job.image_id, exc)
                    continue
                masks.put(frame.saturated)
                yield sweep_cube(frame.cube, job)

        fit = seg.fit  # type: ignore[attr-defined]
        if not options.clip_masks or not takes_saturated(fit):  # the RGB sweep takes none
            return fit(cubes())
        return fit(cubes(), saturated=masks)
    except Exception as exc:  # the sweep's images report it as this segmenter's error
        return f"{type(exc).__name__}: the sweep's mixture could not be fitted: {exc}"


class _Handover:
    """The masks of the frames read so far, taken one at a time: an iterator that is not exhausted
    when empty, because the next mask is put in only when the next cube is read."""

    def __init__(self) -> None:
        self._pending: deque[np.ndarray | None] = deque()

    def put(self, mask: np.ndarray | None) -> None:
        self._pending.append(mask)

    def __iter__(self) -> _Handover:
        return self

    def __next__(self) -> np.ndarray | None:
        if not self._pending:
            raise StopIteration
        return self._pending.popleft()


def sweep_cube(cube: np.ndarray, job: FrameJob) -> np.ndarray:
    """``cube`` at its sweep's exposure (``FrameJob.sweep_scale``)."""
    return cube if job.sweep_scale == 1.0 else cube * np.float32(job.sweep_scale)


def scaled_to_sweep(members: list[FrameJob]) -> list[FrameJob]:
    """One sweep's jobs with ``sweep_scale`` set: the first frame's exposure over each frame's,
    when every frame has one (else 1)."""
    known = [j.exposure for j in members if j.exposure is not None]
    if not known or len(known) < len(members):
        return members
    return [replace(j, sweep_scale=known[0] / e) for j, e in zip(members, known, strict=True)]


def fit_sweeps(jobs: Sequence[FrameJob], options: EvalOptions, *, client: Any = None,
               names: Sequence[str] | None = None) -> list[FrameJob]:
    """``jobs`` with each sweep segmenter's model for their sweep attached (``FrameJob.sweep``) and
    their scale to the sweep's exposure (``FrameJob.sweep_scale``), in the order given; ``names``:
    these sweep segmenters instead of the evaluated ones."""
    names = [n for n in (options.segmenters if names is None else names) if is_sweep(n)]
    if not names:
        return list(jobs)
    groups: dict[SweepKey, list[FrameJob]] = {}
    for job in jobs:
        groups.setdefault(sweep_key(job), []).append(job)
    groups = {key: scaled_to_sweep(members) for key, members in groups.items()}
    pairs = [(name, key) for name in names for key in groups]
    tasks = [(name, groups[key]) for name, key in pairs]
    models = map_ordered(fit_sweep, tasks, client=client, options=options)
    attached: dict[SweepKey, list[tuple[str, Any]]] = {key: [] for key in groups}
    for (name, key), model in zip(pairs, models, strict=True):
        attached[key].append((name, model))
    done = {j.image_id: replace(j, sweep=tuple(attached[key]))
            for key, members in groups.items() for j in members}
    return [done[job.image_id] for job in jobs]
