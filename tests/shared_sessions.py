"""Sessions written once per test process and shared by the tests that only read them.

Writing a session (frames, darks, previews, the journal) costs far more than copying its
folder: the tests that export, import, report or evaluate a session read one written here,
through the session-scoped ``shared_sessions`` fixture (tests/conftest.py), and open it with
``SessionStore.open`` in its default read mode, which refuses every write. A test that changes
a session (completes, compacts, repairs it) works on ``copy_to(tmp_path)``. When the run ends
the fixture checks that no file of a shared session changed, so sharing cannot hide a write
made around the store.

Each xdist worker is its own process and writes its own copy on first use.
"""

from __future__ import annotations

import shutil
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from m2s2hil.config import RigConfig, default_rig
from m2s2hil.plan import Sweep
from m2s2hil.store.session import SessionStore

N = 64  # sensor width and height of the sessions written here: the pixels are not the point


@dataclass(frozen=True)
class Written:
    """A closed session on disk and what was written into it, by event id (the raw mosaics
    of the export sessions, the engine's cubes of the legacy one)."""

    root: Path
    session_id: str
    arrays: dict[str, np.ndarray] = field(default_factory=dict)

    @property
    def path(self) -> Path:
        return self.root / self.session_id

    def open(self) -> SessionStore:
        """Read-only: the store refuses writes (``ReadOnlySession``)."""
        return SessionStore.open(self.root, self.session_id)

    def copy_to(self, root: Path) -> Written:
        """The session copied under ``root`` (same id), for a test that changes it."""
        root.mkdir(parents=True, exist_ok=True)
        shutil.copytree(self.path, root / self.session_id)
        return Written(root, self.session_id, self.arrays)


def _stat(folder: Path) -> dict[str, tuple[int, int]]:
    return {p.relative_to(folder).as_posix(): (p.stat().st_mtime_ns, p.stat().st_size)
            for p in sorted(folder.rglob("*"))}


class SharedSessions:
    """Written sessions by key, each made on first use under ``base``."""

    def __init__(self, base: Path) -> None:
        self._base = base
        self._made: dict[str, tuple[Any, dict[str, tuple[int, int]]]] = {}
        self._lock = threading.Lock()

    def get(self, key: str, make: Callable[[Path], Written]) -> Written:
        """The session ``make(root)`` wrote for ``key`` (it must close its store)."""
        with self._lock:
            if key not in self._made:
                written = make(self._base / key)
                self._made[key] = (written, _stat(written.path))
            return self._made[key][0]

    def changed(self) -> list[str]:
        """Keys of the shared sessions whose files are no longer as they were written."""
        return [key for key, (written, before) in self._made.items() if _stat(written.path) != before]


# -- the sessions the export, import and compact tests share ------------------------------------------


def small_rig() -> RigConfig:
    data = default_rig().model_dump(mode="json")
    data["camera"]["model"].update(width=N, height=N)
    return RigConfig.model_validate(data)


def raw_for(ev: Any) -> np.ndarray:
    seed = abs(hash(ev.event_id)) % 2**32
    return np.random.default_rng(seed).integers(0, 1024, (N, N), dtype=np.uint16)


def write_session(root: Path, satellite: str = "hubble", build: str = "B2", frames_per_pose: int = 1,
                  session_id: str | None = None, **kw: Any) -> tuple[SessionStore, dict[str, np.ndarray]]:
    """Two lightings × two tilts × four azimuths of random 10-bit mosaics and two darks, as
    the store receives them from the engine (read-back pose, sensor temperature); still open."""
    sweep = Sweep(satellite=satellite, build=build, lighting=["weak", "directional"], tilts=["E0", "E2"],
                  azimuth_step_deg=90, frames_per_pose=frames_per_pose, dark={"frames": 2}, **kw)
    st = SessionStore.create(root, sweep, small_rig(), session_id=session_id)
    raws = {}
    for ev in sweep.expand(st.rig):
        if ev.kind == "dark":
            st.write_dark(ev, np.full((N, N), 3.0, np.float32))
            continue
        raws[ev.event_id] = raw_for(ev)
        st.write_frame(ev, raws[ev.event_id], meta={
            "temperature_c": 30.5, "pose": {"turntable_deg": ev.azimuth_deg + 0.01, "tilt_deg": ev.tilt_deg}})
    return st, raws


def export_session_of(shared: SharedSessions, satellite: str = "hubble", build: str = "B2") -> Written:
    """The shared, closed :func:`write_session` of ``satellite``/``build`` (16 frames, 2 darks)."""

    def make(root: Path) -> Written:
        st, raws = write_session(root, satellite, build)
        st.close()
        return Written(root, st.session_id, raws)

    return shared.get(f"export-{satellite}-{build}", make)


def synthetic_session_of(shared: SharedSessions, satellite: str = "hubble", build: str = "B2") -> Written:
    """The shared synthetic session (m2s2hil.twin.synth) of ``satellite``/``build``: E0 and the
    synthetic-only E3 × azimuths 0 and 180 of 32² renders (four views)."""

    def make(root: Path) -> Written:
        from m2s2hil.analysis.segmenters.rgb import band_colours, camera_weights
        from m2s2hil.twin.synth import SynthPlan, synthesise

        rig = small_rig()
        bands = rig.camera.model.bands_nm
        plan = SynthPlan(satellite, build, elevations=("E0", "E3"), azimuth_step_deg=180, size=32)
        res = synthesise(root, rig, plan, band_colours(bands, gamma=0.8), camera_weights(bands))
        return Written(root, res.session_id)

    return shared.get(f"synthetic-{satellite}-{build}", make)


def hil_with_labels(root) -> tuple[str, dict[str, tuple[np.ndarray, np.ndarray]]]:
    """Hubble B2, weak light, E0 × azimuths 0 and 180, each frame with a truth mask and projected labels."""
    sweep = Sweep(satellite="hubble", build="B2", lighting=["weak"], tilts=["E0"], azimuth_step_deg=180,
                  dark={"frames": 1})
    labels = {}
    with SessionStore.create(root, sweep, small_rig()) as st:
        rng = np.random.default_rng(7)
        for ev in sweep.expand(st.rig):
            if ev.kind == "dark":
                st.write_dark(ev, np.full((N, N), 3.0, np.float32))
                continue
            truth = rng.integers(0, 5, (N, N), dtype=np.uint8)
            projected = np.roll(truth, 1, axis=1)
            labels[ev.event_id] = (truth, projected)
            st.write_frame(ev, rng.integers(0, 1024, (N, N), dtype=np.uint16),
                           extra={"truth_labels": truth, "projected_labels": projected})
        return st.session_id, labels
