"""What the engine does to the rig: verified moves, lamps with warm-up, recovery, safe state.

:class:`RigOps` keeps the little the engine must remember about the hardware (the
verified pose, which lamps are lit and since when) so that a capture only moves an
axis or switches a lamp when it has to, and forgets it after a fault (``invalidate``)
so the next capture re-commands everything and re-verifies.

- Moves: ``move_to`` returns the driver's verified read-back; it is checked again here
  against the axis tolerance (a driver that does not verify cannot slip through).
- Lamps: every lamp that was off gets its configured ``warmup_s`` before an exposure;
  the wait overlaps the move.
- Safe state (:meth:`RigOps.make_safe`): lamps off and both axes stopped, tried up to
  ``attempts`` times with a short back-off, every step each time, even when a step
  raises; the errors are returned, never raised, so teardown keeps the original error.
  A stop waits as a move does (:mod:`m2s2hil.drivers.motion_watch`): until the axis is at
  rest, however long a slow rig brakes, failing only when it stops changing without
  coming to rest (GRBL then resets the controller once: drivers/grbl.py).
"""

from __future__ import annotations

import contextlib
import logging
from dataclasses import dataclass, field

from m2s2hil.drivers.errors import MoveNotVerified
from m2s2hil.drivers.interfaces import RestartReport, RotaryAxis
from m2s2hil.rig.opened import AXIS_ROLES, AxisRole, DeviceLink, Rig, Role

log = logging.getLogger(__name__)


@dataclass
class SafeReport:
    safe: bool  # the last attempt left lamps off and motion stopped
    errors: list[Exception] = field(default_factory=list)  # every error met on the way
    attempts: int = 0


class RigOps:
    def __init__(self, rig: Rig) -> None:
        self.rig = rig
        self.clock = rig.clock
        self._warmup = {lamp.channel: lamp.warmup_s for lamp in rig.config.lamps.values()}
        self._lamp_names = {lamp.channel: name for name, lamp in rig.config.lamps.items()}
        self._on_since: dict[int, float] = {}
        self._lit: frozenset[int] | None = None  # None: unknown (start, after a fault)
        self._pose: dict[str, float | None] = dict.fromkeys(AXIS_ROLES)
        self._moved_at = -1e18  # clock time the last move ended
        self._heading: dict[str, tuple[float, float, float]] = {}  # start_move's (start, target, when)
        self.lens_capped = False

    # -- state -----------------------------------------------------------------------
    def axis(self, role: AxisRole) -> RotaryAxis:
        return self.rig.axis(role)

    def pose(self) -> dict[str, float | None]:
        return dict(self._pose)

    @property
    def lit(self) -> frozenset[int]:
        return self._lit or frozenset()

    def lamp_names(self, channels: frozenset[int] | None = None) -> list[str]:
        chans = self.lit if channels is None else channels
        return [self._lamp_names.get(c, f"ch{c}") for c in sorted(chans)]

    def invalidate(self, *, lamps: bool = True, pose: bool = True) -> None:
        """Forget what we believe about the hardware (after a fault or a reconnect)."""
        if lamps:
            self._lit = None
            self._on_since.clear()  # a lamp may have dropped out: warm it up again
        if pose:
            self._pose = dict.fromkeys(AXIS_ROLES)
            self._heading.clear()

    # -- lamps -----------------------------------------------------------------------
    def set_lamps(self, channels: frozenset[int]) -> bool:
        """Switch exactly ``channels`` on (verified by the driver); False if already so."""
        if self._lit == channels:
            return False
        self.rig.lights.set(sorted(channels))
        now = self.clock.monotonic()
        for ch in list(self._on_since):
            if ch not in channels:
                del self._on_since[ch]
        for ch in channels:
            self._on_since.setdefault(ch, now)
        self._lit = channels
        return True

    def lamps_ready_at(self) -> float:
        return max((t + self._warmup.get(ch, 0.0) for ch, t in self._on_since.items()), default=-1e18)

    def lamp_ages(self) -> dict[str, float]:
        now = self.clock.monotonic()
        return {self._lamp_names.get(ch, f"ch{ch}"): now - t for ch, t in sorted(self._on_since.items())}

    # -- motion ----------------------------------------------------------------------
    def move(self, role: AxisRole, target: float) -> bool:
        """Move one axis to ``target`` and verify the read-back; False if it was there."""
        tol = self.rig.config.axes[role].tolerance_deg
        cur = self._pose[role]
        if cur is not None and abs(cur - target) <= tol / 2:
            return False
        self._pose[role] = None
        ax = self.axis(role)
        heading = self._heading.pop(role, None)
        finish = getattr(ax, "finish_move", None)
        if heading is not None and abs(heading[1] - target) <= tol / 2 and finish is not None:
            actual = float(finish(heading[0], target, since=heading[2]))  # from start_move: wait, verify
        else:
            if heading is not None and finish is not None:
                # A guess that was wrong (e.g. a frame retried): let that move end first, so
                # this one is watched from where the axis stands.
                with contextlib.suppress(MoveNotVerified):
                    finish(heading[0], heading[1], since=heading[2])
            actual = float(ax.move_to(target, wait=True))
        if abs(actual - target) > tol:
            raise MoveNotVerified(
                f"read back {actual:.4f} deg after moving to {target:.4f} deg (tolerance {tol} deg)",
                target=target, actual=actual, device=self.axis(role).name,
                command=f"move {role} {target}",
            )
        self._pose[role] = actual
        self._moved_at = self.clock.monotonic()
        return True

    def start_move(self, role: AxisRole, target: float) -> bool:
        """Command a move to ``target`` without waiting (the stage heads for the next pose
        while a frame is read out); the next :meth:`move` to it waits and verifies. False if
        the axis is there already."""
        tol = self.rig.config.axes[role].tolerance_deg
        cur = self._pose[role]
        if cur is not None and abs(cur - target) <= tol / 2:
            return False
        self._pose[role] = None
        ax = self.axis(role)
        # The verified read-back is where the move starts (no status query: it costs a round trip).
        start = float(ax.position()) if cur is None else cur
        ax.move_to(target, wait=False)
        since = self.clock.monotonic()  # once acknowledged, as move_to times its own wait
        self._heading[role] = (start, target, since)
        return True

    def move_pose(self, azimuth_deg: float, tilt_deg: float) -> list[AxisRole]:
        """Tilt first (it changes rarely), then the turntable; returns the axes moved."""
        order: tuple[tuple[AxisRole, float], ...] = (("tilt", tilt_deg), ("turntable", azimuth_deg))
        return [r for r, t in order if self.move(r, t)]

    def settle_s(self, moved: list[AxisRole], override: float | None) -> float:
        if not moved:
            return 0.0
        if override is not None:
            return override
        return max(self.rig.config.axes[r].settle_s for r in moved)

    def wait_ready(self, settle_until: float) -> float:
        """Sleep until the stage has settled and the lamps are warm; returns the wait."""
        now = self.clock.monotonic()
        wait = max(settle_until, self.lamps_ready_at()) - now
        if wait > 0:
            self.clock.sleep(wait)
            return wait
        return 0.0

    # -- recovery --------------------------------------------------------------------
    def links_named(self, device: str | None) -> list[DeviceLink]:
        """The connections an error's ``device`` names (one stage controller serves both axes)."""
        return [link for link in self.rig.links if link.means(device)]

    def roles_named(self, device: str | None) -> set[Role]:
        return {r for link in self.links_named(device) for r in link.roles}

    def reconnect(self, device: str | None) -> list[Role]:
        """Reconnect the devices behind ``device`` (all of them if unknown).

        A motion controller that restarted while it was away has lost its position:
        its axes are homed again.
        """
        targets = self.links_named(device) or list(self.rig.links)
        done: list[Role] = []
        rehome: list[DeviceLink] = []
        for link in targets:
            if link.reconnect is None:
                continue
            report = link.do_reconnect()
            done.extend(link.roles)
            if isinstance(report, RestartReport) and report.reset and link.axis_roles:
                rehome.append(link)
        self.invalidate()
        if rehome:
            from m2s2hil.rig.origin import PositionLost

            lost: list[str] = [r for link in rehome for r in link.axis_roles
                               if self.rig.config.axes[r].homing != "switches"]
            if lost:  # nothing can find their zero again: the operator must (never a silent $X)
                raise PositionLost(rehome[0].device, lost)
            self.home(rehome[0].device)
        return done

    def home(self, device: str | None) -> list[AxisRole]:
        """Clear an alarm and home the axes behind ``device`` (both if it is not an axis).

        A controller that can clear its alarm (GRBL: soft reset, then ``$H``) does that,
        once; otherwise each of its axes is homed.
        """
        links = [link for link in self.links_named(device) if link.axis_roles]
        if not links:
            links = [link for link in self.rig.links if link.axis_roles]
        roles: list[AxisRole] = []
        for link in links:
            axis_roles = link.axis_roles
            roles.extend(axis_roles)
            switched = [r for r in axis_roles if self.rig.config.axes[r].homing == "switches"]
            if link.alarm is not None:
                # Without switches: reset and unlock ($X), never $H (a factory GRBL answers error:5).
                link.alarm.clear_alarm(home=bool(switched))
            else:
                for r in switched:
                    self.rig.axis(r).home()
            for r in axis_roles:
                if r not in switched:
                    self.rig.axis(r).position()  # re-read from the controller; the retried move verifies
        # Homing may move every axis on the controller: trust no remembered position.
        self._pose = dict.fromkeys(AXIS_ROLES)
        self._heading.clear()
        return roles

    # -- safe state ------------------------------------------------------------------
    def make_safe(self, attempts: int = 3, backoff_s: float = 0.2) -> SafeReport:
        """Lamps off, motion stopped, lens uncapped; retried until clean. Never raises."""
        errors: list[Exception] = []
        for i in range(attempts):
            try:
                step_errors = self.rig.safe()
            except Exception as exc:  # a broken safe() must not hide the original error
                step_errors = [exc]
            if self.lens_capped:
                try:
                    self.rig.cap_lens(False)
                    self.lens_capped = False
                except Exception as exc:
                    step_errors.append(exc)
            errors.extend(step_errors)
            if not step_errors:
                self._on_since.clear()
                self._lit = frozenset()
                return SafeReport(True, errors, i + 1)
            log.warning("safe state attempt %d/%d left %d error(s)", i + 1, attempts, len(step_errors))
            self.invalidate()
            with contextlib.suppress(Exception):
                self.clock.sleep(backoff_s * (2**i))
            # A device whose port vanished stays unreachable until reopened: reopen it (no
            # homing here, nothing may move) so the next attempt can switch it off or stop it.
            for err in step_errors:
                if getattr(err, "fault_class", None) == "device_gone":
                    errors.extend(self._reopen(getattr(err, "device", None)))
        return SafeReport(False, errors, attempts)

    def _reopen(self, device: str | None) -> list[Exception]:
        """Reconnect the devices behind ``device`` for the safe state; the errors, never raised."""
        out: list[Exception] = []
        for link in self.links_named(device):
            try:
                link.do_reconnect()
            except Exception as exc:
                out.append(exc)
        return out
