"""One mixture for a whole sweep: the materials fitted once on every frame's fit pixels, each frame
labelled with them (issue 23, ninth pass).

A session sweeps one build under one lighting through 36 azimuths (× tilts): every frame shows the
same materials, each from another side. Fitted frame by frame, the count of a build with small parts
hangs on the few pixels one view gives them (Voyager B3 at 5 % peak: K within ±1 on 10 of 36
frames, 2 materials short on average; docs/evaluation.md, "The goal on the whole sweep"). Pooled
over the sweep, a part seen from any side adds its pixels to the fit.

``SweepSegmenter.fit(cubes)`` takes each cube's clean fit rows as ``SpectralSegmenter`` makes them
(``fit_sample(clean_only=True)``: foreground, reliability, denoising, homogeneous interior, none
of a frame's fallbacks to unreliable pixels, which in an over-exposed frame are the mosaic's
blends beside clipped cells and, pooled, split ISS B1 at 150 % peak), an equal share of
``sweep_sample_size`` rows from every frame (a frame with fewer gives all of its rows), and selects
one mixture on them (``SpectralSegmenter.select``: BIC over 1..``max_materials``). ``analyse(cube)``
then labels a frame with that mixture: merging, the weight floor, the interior test, saturated
pixels and smoothing run per frame as in ``SpectralSegmenter``, so a material the frame does not
show gets no pixels, and the frame's count is what it shows. The near-tie step does not run (one
mixture, no counts to weigh).

``sweep_sample_size`` (5 000) is the one new setting, and the count depends on it: BIC's penalty
grows as log n while a component's gain grows as n, so more rows let smaller parts in, and also
let a single glossy material split along its specular tint. 2 500 rows (about one frame's) left
Voyager B3 as short as frame by frame; 10 000 split ISS B1 into three on most frames. The figures
are in docs/evaluation.md ("Ninth pass: one mixture per sweep").

The frame segmenter gets ``SWEEP_FRAME_OPTIONS`` unless told otherwise (``SpectralSegmenter`` step
3b): blends darker than a neighbour by e^0.2 out of the fit, and those darker by e^0.5 whose shape
is more than 12° from that neighbour's out of the guided filter's averages. Pooled over a
sweep, the blends beside ISS B1's one-pixel panel gaps are in every view's rows, and one mixture
fitted to them splits it on every frame. Of the variants tried on the goal's cells over three
noise seeds these met the most cells (docs/evaluation.md, "Ninth pass").

Frames whose features have another width than the sweep's (a band dropped for clipping in that
frame only) do not add rows, and are labelled by a mixture of their own (``shared`` is false).
Every frame is read twice (once to fit, once to label), so memory holds one frame at a time plus
the sample. The brightness coordinate of the features is log energy, so frames of other
exposures are scaled to one: ``fit(cubes, exposures=…)`` scales each to the first frame's
exposure × gain, and ``analyse(cube, exposure_s=…)`` then needs each frame's.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterable
from dataclasses import dataclass, field

import numpy as np

from m2s2hil.analysis.arrays import as_cube
from m2s2hil.analysis.errors import AnalysisInputError
from m2s2hil.analysis.segmenters.spectral import (
    MIN_FIT_PIXELS,
    Mixture,
    SpectralSegmentation,
    SpectralSegmenter,
)

SWEEP_SAMPLE_SIZE = 5_000
#: the frame segmenter's settings unless told otherwise: blends inside the object out of the fit
#: (``edge_step``) and, where the mosaic garbled their shape, out of the guided filter's averages
#: (``blend_filter_step``, ``blend_filter_angle``). A sweep pools every view's blends, and ISS B1's
#: panel gaps then split it on every frame, not on some (docs/evaluation.md, ninth pass)
SWEEP_FRAME_OPTIONS: dict[str, float] = {"edge_step": 0.2, "blend_filter_step": 0.5,
                                         "blend_filter_angle": 12.0}


@dataclass(frozen=True)
class SweepModel:
    """The mixture of one sweep and what it was fitted on."""

    mixture: Mixture
    width: int  # features per row (bands used + brightness)
    frames: int  # frames whose rows were pooled
    skipped: int  # frames with no rows or of another width
    rows: int  # rows the mixture was fitted on
    bic: dict[int, float] = field(default_factory=dict)
    exposure_s: float | None = None  # the exposure every frame is scaled to (None: frames as given)

    @property
    def n_components(self) -> int:
        return int(self.mixture.n_components)


class SweepSegmenter:
    """``SpectralSegmenter`` with one mixture for a sweep (module docstring): ``fit`` on the sweep's
    cubes, then ``analyse``/``segment`` each; ``analyse_sweep`` does both."""

    name = "spectral-sweep"

    def __init__(self, *, sweep_sample_size: int = SWEEP_SAMPLE_SIZE, **options: object) -> None:
        if not isinstance(sweep_sample_size, int) or sweep_sample_size < 2:
            problem = f"must be an integer ≥ 2, got {sweep_sample_size!r}"
            raise AnalysisInputError("sweep_sample_size", problem)
        self.sweep_sample_size = sweep_sample_size
        self.frame = SpectralSegmenter(**{**SWEEP_FRAME_OPTIONS, **options})  # type: ignore[arg-type]
        self.model: SweepModel | None = None

    def fit(self, cubes: Iterable[object], *, exposures: Iterable[float] | None = None,
            saturated: Iterable[np.ndarray | None] | None = None) -> SweepModel:
        """Pool an equal share of every cube's fit rows and select the sweep's mixture. ``exposures``
        (seconds × gain, one a cube): each cube is scaled to the first one's, so the brightness
        coordinate of a material is the same in every frame. ``saturated``: the processor's clipping
        mask of each cube (or None), as ``analyse`` takes it; read in step with ``cubes`` (the i-th
        mask is taken just after the i-th cube), so both may be produced lazily.

        A frame gives only its clean fit pixels (``fit_sample(clean_only=True)``); only when the
        whole sweep has fewer than ``MIN_FIT_PIXELS`` of them are the frames' rows as each would be
        fitted alone used instead (kept aside, small, for frames with fewer than that)."""
        times = None if exposures is None else iter(exposures)
        masks = None if saturated is None else iter(saturated)
        reference: float | None = None
        clean: list[np.ndarray] = []  # each frame's clean rows
        fallback: list[np.ndarray] = []  # each frame's rows as it would be fitted alone
        empty = 0
        for i, cube in enumerate(cubes):  # one frame in memory at a time: each is read once
            t = None if times is None else _exposure(next(times, None), i)
            mask = None if masks is None else next(masks, None)
            try:
                arr = as_cube(cube)
                if t is not None:
                    reference = reference or t
                    arr = arr * np.float32(reference / t)
                rows = self.frame.fit_sample(arr, saturated=mask, clean_only=True)
                alone = rows
                if rows is not None and rows.shape[0] < MIN_FIT_PIXELS:  # it would fall back alone
                    alone = self.frame.fit_sample(arr, saturated=mask)
            except AnalysisInputError as exc:
                raise AnalysisInputError(f"sweep frame {i}", exc.problem) from exc
            if alone is None or alone.shape[0] == 0:
                empty += 1
                continue
            assert rows is not None
            clean.append(rows)
            fallback.append(alone)
        enough = sum(r.shape[0] for r in clean) >= MIN_FIT_PIXELS
        samples = [r for r in clean if r.shape[0] > 0] if enough else fallback
        empty += len(clean) - len(samples)
        if not samples:
            problem = f"none of the {empty} frames has foreground to fit" if empty else "no frames to fit"
            raise AnalysisInputError("cubes", problem)
        width = Counter(s.shape[1] for s in samples).most_common(1)[0][0]
        usable = [s for s in samples if s.shape[1] == width]
        share = max(1, self.sweep_sample_size // len(usable))
        rng = np.random.default_rng(self.frame.seed)
        pooled = np.concatenate([s if s.shape[0] <= share else s[rng.choice(s.shape[0], share, replace=False)]
                                 for s in usable])
        mixture, bic = self.frame.select(pooled)
        self.model = SweepModel(mixture, width, len(usable), empty + len(samples) - len(usable),
                                int(pooled.shape[0]), bic, reference)
        return self.model

    def use(self, model: SweepModel) -> None:
        """Label with ``model`` (fitted elsewhere: an evaluation fits each sweep once, then sends the
        model with every frame's job)."""
        if not isinstance(model, SweepModel):
            raise AnalysisInputError("model", f"expected a SweepModel, got {type(model).__name__}")
        self.model = model

    def analyse(self, cube: object, *, saturated: np.ndarray | None = None, exposure_s: float | None = None
                ) -> SpectralSegmentation:
        """Label one frame of the fitted sweep (``exposure_s``: its exposure × gain, when the sweep
        was fitted with exposures)."""
        if self.model is None:
            problem = "not fitted: call fit(cubes) with the sweep's frames first"
            raise AnalysisInputError("spectral-sweep", problem)
        arr = as_cube(cube)
        if self.model.exposure_s is not None:
            if exposure_s is None:
                problem = "the sweep was fitted with exposures: give this frame's"
                raise AnalysisInputError("exposure_s", problem)
            arr = arr * np.float32(self.model.exposure_s / _exposure(exposure_s, 0))
        return self.frame.analyse(arr, saturated=saturated, mixture=self.model.mixture)

    def segment(self, cube: np.ndarray, *, saturated: np.ndarray | None = None) -> np.ndarray:
        return self.analyse(cube, saturated=saturated).labels

    def analyse_sweep(self, cubes: list[object], exposures: list[float] | None = None,
                      saturated: list[np.ndarray | None] | None = None) -> list[SpectralSegmentation]:
        """Fit on ``cubes``, then label each."""
        self.fit(cubes, exposures=exposures, saturated=saturated)
        times: list[float | None] = [None] * len(cubes) if exposures is None else list(exposures)
        masks: list[np.ndarray | None] = [None] * len(cubes) if saturated is None else list(saturated)
        return [self.analyse(c, exposure_s=t, saturated=m)
                for c, t, m in zip(cubes, times, masks, strict=True)]


def _exposure(value: object, index: int) -> float:
    """A frame's exposure as a positive number, or a typed error naming the frame."""
    try:
        t = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        t = float("nan")
    if not (np.isfinite(t) and t > 0):
        problem = f"must be a positive number of seconds, got {value!r}"
        raise AnalysisInputError(f"exposures[{index}]", problem)
    return t
