"""Pixels of a ``FrameJob``: its cube (stored, or processed from the raw mosaic) and its
ground truth reduced to the cube's grid.

Every file is read through ``_read``, which checks the sha256 the session journal recorded.
A cube comes from the store unless ``reprocess`` names a demosaicing method (or the frame
has no cube); then the raw mosaic goes through ``processing.FrameProcessor`` with the
session's dark. Exported datasets are processed from their PNG mosaic, without dark
subtraction.
"""

from __future__ import annotations

import hashlib
import json
import threading
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from m2s2hil.analysis.errors import AnalysisInputError
from m2s2hil.analysis.evaluation.jobs import EvaluationError, FileRef, FrameJob
from m2s2hil.config import CameraModel
from m2s2hil.processing.bracket import merge_bracket
from m2s2hil.processing.errors import BracketError
from m2s2hil.processing.mosaic import MosaicLayout
from m2s2hil.processing.stability import band_saturation
from m2s2hil.store.cubes import master_dark_from
from m2s2hil.store.frame_files import decode_image, decode_tiff
from m2s2hil.store.zarr_export import read_ref

if TYPE_CHECKING:
    from m2s2hil.processing.dark import MasterDark


def labels_to_cube(labels: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Ground truth on the cube's grid: as is if the shapes agree, else the majority label
    of each n×n cell (ties: the lowest id) when the sensor is n times larger."""
    lab = np.asarray(labels)
    if lab.ndim != 2:
        raise AnalysisInputError("labels", f"expected an (H, W) label map, got shape {lab.shape}")
    if lab.shape == tuple(shape):
        return lab.astype(np.int64)
    h, w = shape
    n = lab.shape[0] // h if h else 0
    if n < 1 or lab.shape != (h * n, w * n):
        raise AnalysisInputError(
            "labels", f"label map {lab.shape} is not an integer multiple of the cube {shape}"
        )
    cells = lab.reshape(h, n, w, n).transpose(0, 2, 1, 3).reshape(h * w, n * n).astype(np.int64)
    k = int(cells.max()) + 1
    counts = np.zeros((h * w, k), dtype=np.int32)
    np.add.at(counts, (np.repeat(np.arange(h * w), n * n), cells.ravel()), 1)
    return counts.argmax(axis=1).reshape(h, w)


def _read(ref: FileRef) -> bytes:
    if "#zarr:" in ref.path:  # a frame of a zarr export (m2s2hil.store.zarr_export)
        return read_ref(ref.path)
    data = Path(ref.path).read_bytes()
    if ref.sha256 and hashlib.sha256(data).hexdigest() != ref.sha256:
        raise EvaluationError(f"{ref.path}: sha256 does not match the session journal")
    return data


# Per-thread cache: a FrameProcessor reuses its output buffers, so worker threads of a
# threaded cluster must not share one.
_LOCAL = threading.local()


def _processors() -> dict[tuple, Any]:
    d = getattr(_LOCAL, "processors", None)
    if d is None:
        d = _LOCAL.processors = {}
    return d


def load_dark(job: FrameJob) -> MasterDark | None:
    """The job's master dark (None without one), rebuilt from its file as the store rebuilds
    it (m2s2hil.store.cubes.master_dark_from): its read noise and camera serial kept."""
    if job.dark is None:
        return None
    return master_dark_from(*decode_tiff(_read(job.dark)))


def _processor(job: FrameJob, method: str, shape: tuple[int, int] | None = None) -> Any:
    """A FrameProcessor per (method, camera, dark), cached per worker process (its buffers
    are large for the full-resolution methods)."""
    # Here, not at the top: the chain imports numba (seconds), which only reprocessing needs,
    # not a stored cube, the session report or the daemon.
    from m2s2hil.processing.chain import FrameProcessor

    camera = dict(job.camera)
    if shape is not None:  # exported PNGs: the sensor size is the file's
        camera.update(height=int(shape[0]), width=int(shape[1]))
    key = (method, json.dumps(camera, sort_keys=True), job.dark.path if job.dark else None)
    procs = _processors()
    proc = procs.get(key)
    if proc is None:
        dark = load_dark(job)
        if len(procs) >= 4:
            procs.clear()
        proc = procs[key] = FrameProcessor(method, CameraModel.model_validate(camera), dark=dark)
    return proc


def _load_raw(job: FrameJob) -> np.ndarray:
    assert job.raw is not None
    data = _read(job.raw)
    if job.raw_kind == "png":
        raw = decode_image(data)
        if raw.ndim == 3:
            raw = raw[..., 0]
        return raw.astype(np.uint16)
    return decode_tiff(data)[0].astype(np.uint16)


@dataclass(frozen=True)
class LoadedFrame:
    """A job's cube with its clipping mask (None when the job has no raw frame to rebuild it from)."""

    cube: np.ndarray  # float32 (bands, H, W)
    # bool (bands, H, W): where each band holds a clipped raw value; its ``any`` over bands is the
    # processor's ``saturated_mask``
    saturated: np.ndarray | None
    mask_error: str | None = None  # why a stored cube's mask could not be rebuilt (the cube still counts)
    bracket_frames: int = 1  # frames merged into the cube (a bracketed pose: processing.bracket)
    bracket_error: str | None = None  # why a pose's bracket was not merged (its own frame is used)

    @property
    def saturated_pixels(self) -> np.ndarray | None:
        """bool (H, W): some band clipped, the processor's ``saturated_mask``."""
        return None if self.saturated is None else np.asarray(self.saturated.any(axis=0))

    @property
    def clipped_fraction(self) -> float | None:
        """The share of the image with some band clipped."""
        pixels = self.saturated_pixels
        return None if pixels is None else float(pixels.mean())


def clipping_mask(raw: np.ndarray, method: str, layout: MosaicLayout, full_scale: int) -> np.ndarray:
    """(bands, H', W') where each band of ``method``'s cube of ``raw`` holds a raw value at full scale
    (``processing.stability.band_saturation``; before any dark, as the processor flags it)."""
    return band_saturation(np.asarray(raw) >= full_scale, method, layout)


def stored_saturation(job: FrameJob, shape: tuple[int, int]) -> np.ndarray | None:
    """The per-band clipping mask of the job's stored cube, rebuilt from its raw frame as the
    processor flagged it at capture (raw pixels at full scale, spread by the method's support);
    None without a raw frame. A stored cube does not keep its mask."""
    if job.raw is None:
        return None
    camera = CameraModel.model_validate(job.camera)
    mask = clipping_mask(_load_raw(job), job.method, MosaicLayout.from_camera(camera), camera.full_scale)
    if mask.shape[1:] != tuple(shape):
        raise EvaluationError(f"{job.image_id}: the raw frame's clipping mask is {mask.shape[1:]} with the "
                              f"{job.method!r} method, the stored cube {tuple(shape)}")
    return mask


def load_frame(job: FrameJob, reprocess: str | None = None, *, masks: bool = True,
               bracket: bool = True) -> LoadedFrame:
    """The image's float32 cube (bands, H, W), stored or processed from the raw, and (``masks``)
    its clipping mask: the processor's when the raw is processed here, else rebuilt from the raw
    (a raw frame that cannot be read leaves the mask out, with the reason, not the image).

    A bracketed pose (``job.bracket``) is merged with its extra exposures (``bracket``:
    :func:`processing.bracket.merge_bracket`, each frame with its own dark and clipping mask),
    on this frame's scale. Merging needs every frame's mask and exposure; without them the pose's
    own frame is used and ``bracket_error`` says why."""
    if not (bracket and job.bracket):
        return _load_one(job, reprocess, masks=masks)
    own = _load_one(job, reprocess, masks=True)
    try:
        merged = merge_pose(job, own, reprocess)
    except (EvaluationError, BracketError, AnalysisInputError, OSError, ValueError) as exc:
        kept = own if masks else replace(own, saturated=None)
        return replace(kept, bracket_error=f"{type(exc).__name__}: {exc}")
    return merged if masks else replace(merged, saturated=None)


def merge_pose(job: FrameJob, own: LoadedFrame, reprocess: str | None = None) -> LoadedFrame:
    """``own`` (the job's frame, loaded with its mask) merged with the job's bracket frames."""
    frames = [own]
    for member in job.bracket:
        part = replace(job, image_id=f"{job.image_id} ({member.event_id})", cube=member.cube, raw=member.raw,
                       dark=member.dark, exposure=member.exposure, bracket=())
        frames.append(_load_one(part, reprocess, masks=True))
    names = [job.image_id, *(m.event_id for m in job.bracket)]
    scales, masks = [], []
    for f, scale, name in zip(frames, [job.exposure, *(m.exposure for m in job.bracket)], names, strict=True):
        if f.saturated is None:
            raise EvaluationError(f"{name}: no clipping mask ({f.mask_error or 'no raw frame'}), so its "
                                  "clipped bands cannot be left out of the merge")
        if scale is None:
            raise EvaluationError(f"{name}: no exposure recorded")
        scales.append(scale)
        masks.append(f.saturated)
    out = merge_bracket([f.cube for f in frames], scales, masks)
    return LoadedFrame(out.cube, out.clipped, bracket_frames=len(frames))


def _load_one(job: FrameJob, reprocess: str | None = None, *, masks: bool = True) -> LoadedFrame:
    """One frame's cube and (``masks``) clipping mask (:func:`load_frame` without the bracket)."""
    if job.cube is not None and reprocess is None:
        cube, _ = decode_tiff(_read(job.cube))
        arr = np.asarray(cube, dtype=np.float32)
        if arr.ndim != 3:
            raise EvaluationError(f"{job.image_id}: the stored cube has shape {arr.shape}, not (bands, H, W)")
        if not masks:
            return LoadedFrame(arr, None)
        try:
            return LoadedFrame(arr, stored_saturation(job, arr.shape[1:]))
        except Exception as exc:  # the segmenters fall back on the cube's own clipping test
            return LoadedFrame(arr, None, f"{type(exc).__name__}: {exc}")
    if job.raw is None:
        raise EvaluationError(f"{job.image_id}: neither a cube nor a raw mosaic to evaluate")
    raw = _load_raw(job)
    proc = _processor(job, reprocess or job.method, raw.shape if job.raw_kind == "png" else None)
    out = proc.process(raw)
    cube = np.array(out.cube, dtype=np.float32, copy=True)
    if not masks:
        return LoadedFrame(cube, None)
    return LoadedFrame(cube, clipping_mask(raw, proc.method, proc.layout, proc.full_scale))


def load_cube(job: FrameJob, reprocess: str | None = None) -> np.ndarray:
    """The image's float32 cube (bands, H, W): stored, or processed from the raw."""
    return load_frame(job, reprocess, masks=False).cube


def load_truth(job: FrameJob, shape: tuple[int, int]) -> np.ndarray | None:
    """The job's label map on the cube's grid (``labels_to_cube``), or None without one."""
    if job.labels is None:
        return None
    data = _read(job.labels)
    arr = decode_tiff(data)[0] if job.labels.path.endswith((".tif", ".tiff")) else decode_image(data)
    return labels_to_cube(arr, shape)


def load_projected(job: FrameJob, shape: tuple[int, int]) -> np.ndarray | None:
    """The twin's projected labels of the job's frame on the cube's grid, or None without them."""
    if job.projected is None:
        return None
    return labels_to_cube(decode_image(_read(job.projected)), shape)
