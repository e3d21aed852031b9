"""Shared set-up for the engine tests: a small simulated rig, a sweep, a session store."""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from m2s2hil.config import RigConfig, default_rig
from m2s2hil.engine.options import EngineOptions
from m2s2hil.engine.runner import Engine
from m2s2hil.engine.state import EngineEvent, RunState
from m2s2hil.plan import Sweep
from m2s2hil.rig.factory import open_simulated_rig
from m2s2hil.rig.opened import Rig
from m2s2hil.store.session import SessionStore


def small_rig_config(size: int = 256) -> RigConfig:
    """The built-in rig with a ``size``×``size`` sensor, so tests render fast."""
    cfg = default_rig()
    model = cfg.camera.model.model_copy(update={"width": size, "height": size})
    return cfg.model_copy(update={"camera": cfg.camera.model_copy(update={"model": model})})


def small_sweep(**kw: Any) -> Sweep:
    args: dict[str, Any] = dict(satellite="voyager", build="B3", lighting=["weak"], tilts=["E1"],
                                azimuth_step_deg=90, dark={"frames": 2})
    args.update(kw)
    return Sweep(**args)


@dataclass
class Session:
    rig: Rig
    store: SessionStore
    engine: Engine
    events: list[EngineEvent]

    def __iter__(self) -> Iterator[Any]:
        return iter((self.rig, self.store, self.engine, self.events))


@contextlib.contextmanager
def session(tmp_path: Path, sweep: Sweep | None = None, *, faults: dict | None = None,
            config: RigConfig | None = None, session_id: str = "s1",
            **engine_kw: Any) -> Iterator[Session]:
    """An opened simulated rig, a new store and an engine recording every event."""
    cfg = config or small_rig_config()
    sweep = sweep or small_sweep()
    rig = open_simulated_rig(cfg, faults=faults)
    store = SessionStore.create(tmp_path / "data", sweep, cfg, session_id=session_id, clock=rig.clock)
    events: list[EngineEvent] = []
    lock = threading.Lock()

    def record(e: EngineEvent) -> None:
        with lock:
            events.append(e)

    engine = make_engine(rig, store, sweep, on_event=record, **engine_kw)
    try:
        yield Session(rig, store, engine, events)
    finally:
        if engine.state.active:
            with contextlib.suppress(Exception):
                engine.abort()
            engine.wait(timeout=30)
        store.close()
        rig.close()


def make_engine(rig: Rig, store: SessionStore, sweep: Sweep | None = None, **kw: Any) -> Engine:
    """An engine with flat keywords: ``policy``, ``qc`` and ``on_event`` as they are, the rest
    folded into :class:`EngineOptions` (``speed_dps=`` etc. via ``EngineOptions.of``)."""
    direct = {k: kw.pop(k) for k in ("policy", "qc", "on_event") if k in kw}
    return Engine(rig, store, sweep, options=EngineOptions.of(**kw), **direct)


def wait_for_state(engine: Engine, state: RunState, timeout: float = 30.0) -> None:
    """Poll (real time) until the engine reaches ``state``."""
    deadline = time.monotonic() + timeout
    while engine.state is not state:
        if time.monotonic() > deadline:
            raise AssertionError(f"engine still {engine.state.value}, expected {state.value}")
        time.sleep(0.005)


def assert_rig_safe(rig: Rig) -> None:
    """Lamps off (the simulated world's own view) and no axis moving."""
    assert rig.world.lamps_on() == frozenset()
    assert not rig.turntable.is_moving()
    assert not rig.tilt.is_moving()
