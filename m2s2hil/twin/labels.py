"""Labels for HIL frames: the registered twin's label map, projected at each frame's pose.

The paper could score HIL frames only by a consistency proxy (mTC): "exhaustive ground truth
is unavailable for HIL images". Once the twin is registered to a session
(``twin.registration``), the mockup's parts are known to sit where the fitted placement puts
them, so every frame gets a label map: the twin's mesh, its build's filaments, projected at
the frame's recorded pose and the session's placement. These *projected labels* are kept
apart from the simulator's truth (``truth_labels``, only on the simulated rig) and carry the
registration's residual as their confidence (1 − residual): a placement that explains the
silhouettes badly gives labels to trust less.

:func:`projected_labels` draws one frame's; :func:`session_labels` every frame of a stored
session; :func:`label_iou` scores them against the simulator's truth (docs/benchmarks.md).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np

from m2s2hil.twin.projection import Placement, TwinCamera
from m2s2hil.twin.registration import Registration, rig_meshes

LABELS_VERSION = 1


@dataclass(frozen=True)
class ProjectedLabels:
    """One frame's projected label map and where it came from."""

    labels: np.ndarray  # (H, W) uint8, index into class_names
    class_names: tuple[str, ...]
    placement: Placement
    confidence: float  # 1 − the registration's residual

    def meta(self) -> dict[str, Any]:
        """What goes into the frame's metadata beside the map (``meta["projected_labels"]``)."""
        return {"class_names": list(self.class_names), "placement": self.placement.as_dict(),
                "confidence": round(self.confidence, 4), "source": "twin", "labels_version": LABELS_VERSION}


def projected_labels(twin: TwinCamera, satellite: str, build: str, azimuth_deg: float, tilt_deg: float,
                     registration: Registration, shape: tuple[int, int]) -> ProjectedLabels:
    """The twin's label map at ``shape`` (H, W) for a frame at this pose, placed as registered."""
    m = twin.mounted(satellite, build)
    lab = twin.labels(m, azimuth_deg, tilt_deg, registration.placement, shape=shape)
    return ProjectedLabels(lab, tuple(m.class_names), registration.placement,
                           max(0.0, 1.0 - float(registration.residual)))


def session_labels(store: Any, registration: Registration, *, shape: tuple[int, int] | None = None,
                   twin: TwinCamera | None = None) -> Iterator[tuple[str, ProjectedLabels]]:
    """``(event_id, labels)`` for every frame of a stored session, at the cube's size (or ``shape``)."""
    model = store.rig.camera.model
    twin = twin or TwinCamera(model, 64, meshes=rig_meshes(store.rig))
    side = shape or (int(model.height) // 4, int(model.width) // 4)  # the superpixel cube's
    sweep = store.sweep
    for fr in store.frames():
        pose = fr.meta.get("pose") or {}
        az, tilt = pose.get("turntable_deg"), pose.get("tilt_deg")
        if isinstance(az, (int, float)) and isinstance(tilt, (int, float)):
            yield fr.event_id, projected_labels(twin, sweep.satellite, sweep.build, float(az), float(tilt),
                                                registration, side)


def label_iou(projected: np.ndarray, truth: np.ndarray) -> float:
    """Mean IoU over the classes either map has, background included (as mIoU is computed)."""
    if projected.shape != truth.shape:
        raise ValueError(f"projected labels {projected.shape} and truth {truth.shape} differ in shape")
    ious = []
    for k in np.union1d(np.unique(projected), np.unique(truth)):
        a, b = projected == k, truth == k
        u = np.logical_or(a, b).sum()
        if u:
            ious.append(np.logical_and(a, b).sum() / u)
    return float(np.mean(ious)) if ious else 1.0
