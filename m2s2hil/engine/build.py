"""The one way to put a capture run together, for ``capture``, the daemon and the benchmarks.

    rig = open_capture_rig(config, realtime=False)           # one line naming the device, no traceback
    engine = build_run(rig, root, sweep=sweep, qc=capture_qc_hook())   # a new session, scored
    engine = build_run(rig, root, resume="20261124T…")        # continue one from disk (no QC)
    engine = build_run(rig, root, store=queued_store)         # a session the daemon queued

:func:`build_run` creates or reopens the session store, checks that a resumed session was
captured with this rig (:func:`check_rig_digest`, the one place that check lives), and
wires the processing (``options.processor_factory``), the capture-time QC hook the front
end passes (a :data:`~m2s2hil.engine.frames.QcHook`, fresh per run: every frame gets a score
in ``meta["qc"]``, and a hook with ``summary()`` gives the run summary its distribution; the
front ends pass ``m2s2hil.analysis.qc.capture_qc_hook()``: the engine does not import the
analysis) and the fault policy into an :class:`~m2s2hil.engine.runner.Engine`. The scene is
mounted once per run, by the steps' set-up. Front ends only translate their arguments into
these calls and render progress.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from m2s2hil.config import RigConfig
from m2s2hil.engine.fault_policy import FaultPolicy
from m2s2hil.engine.frames import QcHook
from m2s2hil.engine.options import EngineOptions
from m2s2hil.engine.runner import Engine
from m2s2hil.engine.state import EngineEvent
from m2s2hil.errors import M2S2Error, UsageError
from m2s2hil.plan import Sweep
from m2s2hil.rig.opened import Rig
from m2s2hil.store.session import SessionStore


class RigUnavailable(M2S2Error):
    """The rig's devices could not be opened (a port missing, a device not answering).

    Exit code 1 (``M2S2Error``'s); the message names the rig file and the error."""


class RigChanged(UsageError):
    """A session is resumed on a rig whose configuration differs from the one it was captured with."""


def open_capture_rig(config: RigConfig, *, realtime: bool = False, seed: int = 0, source: str | None = None,
                     home: bool = True) -> Rig:
    """Open every device of ``config``. Our own typed errors pass unchanged (a bad rig file:
    ``ConfigError``, exit 2; a device that cannot be reached or used: ``RigOpenError``, one
    line naming it, exit 6 or 7, see :mod:`m2s2hil.rig.open_errors`); anything else becomes
    :class:`RigUnavailable` (exit 1) naming ``source`` (the rig file): never a traceback."""
    from m2s2hil.rig.factory import open_rig

    try:
        return open_rig(config, realtime=realtime, seed=seed, home=home)
    except M2S2Error:
        raise
    except Exception as exc:  # a device that is missing or does not answer: say which, no traceback
        raise RigUnavailable(f"cannot open the rig ({source or 'built-in simulated rig'}): "
                             f"{type(exc).__name__}: {exc}") from exc


def check_rig_digest(store: SessionStore, config: RigConfig) -> None:
    """Raise :class:`RigChanged` unless ``store``'s session was captured with ``config``."""
    if store.rig_digest != config.digest:
        raise RigChanged(
            f"session {store.session_id} was captured with a different rig configuration "
            f"(digest {store.rig_digest[:12]}…, this rig {config.digest[:12]}…); "
            f"resume it with the rig it was started on, or: capture --resume {store.session_id} "
            "--allow-rig-change (port paths do not count: only geometry, devices, camera and calibration)"
        )


def build_run(
    rig: Rig,
    root: str | Path | None = None,
    *,
    sweep: Sweep | None = None,
    resume: str | None = None,
    store: SessionStore | None = None,
    session_id: str | None = None,
    options: EngineOptions | None = None,
    policy: FaultPolicy | None = None,
    qc: QcHook | None = None,
    on_event: Callable[[EngineEvent], None] | None = None,
    allow_rig_change: bool = False,
) -> Engine:
    """An engine for one run of a session: exactly one of ``sweep`` (a new session under
    ``root``, optionally named ``session_id``), ``resume`` (the id of a session under ``root``)
    or ``store`` (a session already open, e.g. queued by the daemon; its rig is checked like a
    resumed session's).

    ``qc`` is the capture-time QC hook (None: no QC). A store this function opened is closed
    again if the engine cannot be built.
    """
    if sum(x is not None for x in (sweep, resume, store)) != 1:
        raise UsageError("build_run needs exactly one of sweep, resume or store")
    opened_here = store is None
    if store is None:
        if root is None:
            raise UsageError("build_run needs the data root for a new or resumed session")
        if sweep is not None:
            store = SessionStore.create(root, sweep, rig.config, session_id=session_id, clock=rig.clock)
        else:
            assert resume is not None
            store = SessionStore.open(root, resume, clock=rig.clock, mode="write")
    try:
        if sweep is None and not allow_rig_change:
            check_rig_digest(store, rig.config)
        return Engine(rig, store, sweep, options=options, policy=policy, qc=qc, on_event=on_event)
    except BaseException:
        if opened_here:
            store.close()
        raise
