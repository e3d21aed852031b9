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
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from m2s2hil.analysis.errors import AnalysisInputError
from m2s2hil.analysis.evaluation.jobs import EvaluationError, FileRef, FrameJob
from m2s2hil.config import CameraModel
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


def load_cube(job: FrameJob, reprocess: str | None = None) -> np.ndarray:
    """The image's float32 cube (bands, H, W): stored, or processed from the raw."""
    if job.cube is not None and reprocess is None:
        cube, _ = decode_tiff(_read(job.cube))
        return np.asarray(cube, dtype=np.float32)
    if job.raw is None:
        raise EvaluationError(f"{job.image_id}: neither a cube nor a raw mosaic to evaluate")
    data = _read(job.raw)
    if job.raw_kind == "png":
        raw = decode_image(data)
        if raw.ndim == 3:
            raw = raw[..., 0]
        raw = raw.astype(np.uint16)
        proc = _processor(job, reprocess or job.method, raw.shape)
    else:
        raw = decode_tiff(data)[0].astype(np.uint16)
        proc = _processor(job, reprocess or job.method)
    return np.array(proc.process(raw).cube, dtype=np.float32, copy=True)


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
