"""The rig's door for request threads: who may talk to the devices, and the emergency stop.

While a session's engine owns the rig, device state comes from the engine's own read-back,
never from a second conversation on the same serial line; a request thread talks to the
devices only through :meth:`RigGuard.manual_access`, refused while a session owns the rig.
The emergency stop is the one exception (:meth:`RigGuard.emergency_stop`): it switches the
lamps off beside the engine and stops the axes once the engine had its grace period.

Locks: the queue's lock (:attr:`SessionManager.lock`) before :attr:`RigGuard.hw`, always.
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from collections.abc import Callable, Iterator
from typing import TYPE_CHECKING

from m2s2hil.engine.runner import Engine
from m2s2hil.engine.state import RunState
from m2s2hil.rig.opened import Rig
from m2s2hil.rig.operations import RigOps

from . import estop, listing
from .errors import HoldNotSaved
from .estop import SafeCheck
from .move_targets import MoveTargets
from .rigstate import device_states

if TYPE_CHECKING:
    from .manager import SessionManager

log = logging.getLogger(__name__)


class RigGuard:
    def __init__(self, sessions: SessionManager, *, estop_grace_s: float = 0.5,
                 estop_timeout_s: float = 30.0) -> None:
        self._sessions = sessions
        self.rig: Rig = sessions.rig
        self.estop_grace_s = estop_grace_s
        self.estop_timeout_s = estop_timeout_s
        self.hw = threading.Lock()  # request threads' own device conversations
        # The camera alone (the live view's grabs): taken after ``hw`` by those that hold both,
        # so the emergency stop, which needs only ``hw``, never waits for a frame to arrive.
        self.cam = threading.Lock()
        #: Called with the rig, holding the device lock, just before a session's engine starts.
        self.before_session: list[Callable[[Rig], None]] = []
        #: The last manual move's target per axis: relative jogs start there (:mod:`.move_targets`).
        self.targets = MoveTargets()

    # ------------------------------------------------------------------ sessions
    def start_engine(self, engine: Engine) -> None:
        """Hand the rig to a session: the before-session hooks (e.g. the console's live view
        stops streaming), then the engine, holding the device lock."""
        with self.hw, self.cam:
            self.targets.forget()  # the session moves the axes itself
            for hook in self.before_session:
                try:
                    hook(self.rig)
                except Exception as exc:
                    log.warning("before-session hook failed: %s", exc)
            engine.start()

    def home_switched_axes(self) -> list[str]:
        """Home the axes that have switches (deferred when the daemon started held); those
        without switches keep the origin checked when the rig opened. Returns the axes homed."""
        cfg = self.rig.config
        homed: list[str] = []
        with self.hw:
            ops = RigOps(self.rig)
            for link in self.rig.links:
                if any(cfg.axes[r].homing == "switches" for r in link.axis_roles):
                    homed.extend(ops.home(link.device))
        if homed:
            log.info("homed %s (deferred while the rig was held)", ", ".join(homed))
        return homed

    def park(self) -> tuple[SafeCheck, list[str]]:
        """Lamps off and axes stopped (the daemon's shutdown), then read back."""
        with self.hw:
            errors = estop.make_safe(self.rig)
        check = self.check_safe()
        return check, errors + check.errors

    def check_safe(self) -> SafeCheck:
        """Read the devices back: which lamps are on, which axis moves."""
        return estop.check_safe(self.rig)

    # ------------------------------------------------------------------ request threads
    @contextlib.contextmanager
    def manual_access(self, what: str = "manual control") -> Iterator[Rig]:
        """The rig for one short conversation from a request thread (jog, lamps, a live-view
        frame, a calibration capture); :class:`Conflict` while a session owns it (running,
        paused or starting). Taking ``hw`` under the queue's lock keeps the dispatcher from
        starting a session meanwhile; the emergency stop still switches the lamps off."""
        with self._sessions.lock:
            self._sessions.check_rig_free(what)
            self.hw.acquire()
        try:
            with self.cam:
                yield self.rig
        finally:
            self.hw.release()

    @contextlib.contextmanager
    def camera_access(self, what: str = "live view") -> Iterator[Rig]:
        """The rig for a conversation with the camera only (a live-view grab): like
        :meth:`manual_access`, but it leaves ``hw`` free, so lamps and axes (the emergency stop
        first) are not held up while a frame is exposed, read out and rendered. The caller
        touches nothing but ``rig.camera``."""
        with self._sessions.lock:
            self._sessions.check_rig_free(what)
            self.cam.acquire()
        try:
            yield self.rig
        finally:
            self.cam.release()

    def rig_state(self) -> dict:
        """Each device's state and health (see :mod:`.rigstate`): the engine's read-back while
        a session owns the rig."""
        cfg = self.rig.config
        cur = self._sessions.owner()
        eng = cur.engine if cur is not None and cur.engine is not None and not cur.finished.is_set() else None
        devices = device_states(self.rig, self.hw, eng)
        return {"name": cfg.rig.name, "simulated": bool(self.rig.simulated), "digest": cfg.digest,
                "session_id": cur.session_id if cur is not None and eng is not None else None,
                "held": self._sessions.held, "devices": devices}

    # ------------------------------------------------------------------ emergency stop
    def emergency_stop(self) -> dict:
        """Lamps off and motion stopped now, whatever runs.

        Order: hold the queue; switch every lamp off (the relay driver serialises its own
        I/O, so this is safe beside the engine thread); write the hold to the data root (it
        outlives this daemon; an error doing so is reported, the stop goes on); ask the running
        session to abort; give it ``estop_grace_s`` to reach its own teardown (which stops
        motion too), then stop the axes from this thread anyway (a move is not waited out);
        once the engine has ended, make safe again and read the devices back to confirm (see
        :func:`.estop.stop_rig`)."""
        t0 = time.monotonic()
        sessions = self._sessions
        sessions.metrics.count_estop()
        job = sessions.hold_at_once("emergency stop")
        log.warning("EMERGENCY STOP requested%s", f" (session {job.session_id} running)" if job else "")
        sessions.activity.record("queue", "EMERGENCY STOP: lamps off, motion stopped, queue held"
                                 + (f", session {job.session_id} aborted" if job else ""), level="error",
                                 session_id=job.session_id if job else None)
        errors = estop.lamps_off(self.rig)
        try:
            sessions.save_hold()
        except HoldNotSaved as exc:
            log.error("%s", exc)
            errors.append(str(exc))
        check, stop_errors = estop.stop_rig(self.rig, self.hw, job, grace_s=self.estop_grace_s,
                                            timeout_s=self.estop_timeout_s)
        errors += stop_errors
        self.targets.forget()  # the axes stopped wherever they were
        eng = job.engine if job is not None else None
        if job is not None and eng is not None and eng.state is RunState.ABORTED:
            job.finished.wait(5.0)  # its run has given the session's owner lock back
            if self._mark_estopped(job.session_id, check):
                job.final_state = "estopped"  # what its status says from now on, as the journal does
        return {
            "safe": check.safe, "lamps_on": check.lamps_on, "moving": check.moving,
            "session_id": job.session_id if job else None,
            "session_state": eng.state.value if eng is not None else None,
            "held": sessions.held or "emergency stop", "errors": errors,
            "elapsed_s": time.monotonic() - t0,
        }

    def _mark_estopped(self, session_id: str, check: SafeCheck) -> bool:
        """``estopped``, not ``aborted``: the operator did not give the capture up, so it may be
        resumed once the stop is cleared (POST /queue/release), never before. False when the
        journal could not be written (the session then stays ``aborted``)."""
        try:
            store = listing.open_store(self._sessions.root, session_id, self.rig.clock, mode="write")
            try:
                store.record_event("estopped", {"rig_safe": check.safe, "lamps_on": check.lamps_on})
                store.set_state("estopped")
            finally:
                store.close()
        except Exception as exc:
            log.error("could not mark session %s as e-stopped: %s", session_id, exc)
            return False
        return True
