"""Manual control of an idle rig: jog and go-to per axis, lamps by preset or one by one.

The operator console and scripts use it to set a rig up (centre the mockup, check each
lighting preset). Every command is checked against the rig file's soft limits before anything
is sent, so a refused jog never reaches the controller; the driver's own limit check stays as
a second guard. A move is commanded without waiting (``move_to(wait=False)``) and waited for
by :meth:`ManualControl.wait_idle`, one short device conversation at a time, so an emergency
stop can reach the controller between two polls.

Who may call it is decided by the caller (the daemon's session manager refuses manual control
while a session owns the rig); this module only knows the rig.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from m2s2hil.errors import UsageError
from m2s2hil.rig.opened import AXIS_ROLES, AxisRole, Rig


class ManualCommandError(UsageError):
    """A manual command the rig file does not allow (beyond a soft limit, unknown lamp or preset)."""


@dataclass(frozen=True)
class AxisView:
    role: str
    position_deg: float
    moving: bool
    min_deg: float
    max_deg: float
    max_speed_dps: float


class ManualControl:
    def __init__(self, rig: Rig) -> None:
        self.rig = rig

    # -- axes ------------------------------------------------------------------------------
    def limits(self, role: AxisRole) -> tuple[float, float]:
        ax = self.rig.config.axes[role]
        return ax.min_deg, ax.max_deg

    def _target_ok(self, role: AxisRole, target: float) -> float:
        if role not in AXIS_ROLES:
            raise ManualCommandError(f"no axis {role!r}; axes: {', '.join(AXIS_ROLES)}")
        if not math.isfinite(target):
            raise ManualCommandError(f"{role}: target {target!r} is not a number")
        lo, hi = self.limits(role)
        if not lo <= target <= hi:
            raise ManualCommandError(
                f"{role}: {target:.3f}° is outside the soft limits [{lo:g}°, {hi:g}°] of the rig file")
        return float(target)

    def go_to(self, role: AxisRole, target_deg: float) -> float:
        """Command an absolute move (not waited for); returns the target."""
        target = self._target_ok(role, target_deg)
        self.rig.axis(role).move_to(target, wait=False)
        return target

    def jog(self, role: AxisRole, delta_deg: float) -> float:
        """Command a relative move from the axis's read-back position; returns the target."""
        if not math.isfinite(delta_deg):
            raise ManualCommandError(f"{role}: step {delta_deg!r} is not a number")
        here = float(self.rig.axis(role).position())
        return self.go_to(role, here + delta_deg)

    def stop(self, role: AxisRole) -> None:
        self.rig.axis(role).stop()

    def axis_view(self, role: AxisRole) -> AxisView:
        ax = self.rig.axis(role)
        cfg = self.rig.config.axes[role]
        moving, degrees = ax.motion()  # one poll: two could tear mid-move
        return AxisView(role, float(degrees), bool(moving), cfg.min_deg, cfg.max_deg,
                        cfg.max_speed_dps)

    def is_moving(self, role: AxisRole) -> bool:
        return bool(self.rig.axis(role).is_moving())

    def home(self, role: AxisRole) -> object:
        """Home the axis on its switches, where its link can (the rig file's policy decides
        whether it should; see :mod:`m2s2hil.rig.factory`)."""
        if any(self.is_moving(r) for r in AXIS_ROLES):
            raise ManualCommandError(f"{role}: an axis is moving; wait until it stands still (or stop it) "
                                     "before homing")
        for link in self.rig.links:
            if role in link.roles and link.homing is not None:
                return link.homing.home()
        raise ManualCommandError(f"{role}: its controller cannot home (no homing capability)")

    # -- lamps -----------------------------------------------------------------------------
    def lamps_on(self) -> list[str]:
        on = self.rig.lights.state()
        return sorted(n for n, lc in self.rig.config.lamps.items() if lc.channel in on)

    def set_lamps(self, names: list[str]) -> list[str]:
        cfg = self.rig.config
        unknown = sorted(set(names) - set(cfg.lamps))
        if unknown:
            raise ManualCommandError(f"no lamp named {', '.join(map(repr, unknown))}; "
                                     f"lamps: {', '.join(cfg.lamps)}")
        self.rig.lights.set(sorted(cfg.lamps[n].channel for n in names))
        return self.lamps_on()

    def set_preset(self, condition: str | None) -> list[str]:
        """All lamps of a lighting condition on (the others off); ``None``: all off."""
        if condition is None:
            return self.set_lamps([])
        cfg = self.rig.config
        if condition not in cfg.lighting:
            raise ManualCommandError(f"no lighting preset {condition!r}; presets: {', '.join(cfg.lighting)}")
        return self.set_lamps(list(cfg.lighting[condition]))
