"""GRBL 1.1 motion controllers: driver, simulator, ``rig probe`` and recognition.

``rig probe`` reads ``$$`` (numbered as in the GRBL v1.1 wiki, "Grbl v1.1 Configuration"),
per axis ``i`` (X=0, Y=1, Z=2), in the machine units the rig file's ``units_per_degree``
counts:

- ``$100+i`` steps per unit: against ``steps_per_degree / units_per_degree`` when the rig
  file gives the axis's ``steps_per_degree``; a wrong value turns every angle by the ratio.
- ``$110+i`` maximum rate (units/min) against ``max_speed_dps``: lower, and every move is
  slower than planned (the driver keeps to the firmware's rate): wrong ETA, and moves that
  time out where the timeout was computed from the rig file.
- ``$120+i`` acceleration (units/s²) against ``accel_dps2``: lower, and the ETA is short.
- ``$130+i`` maximum travel against the axis's range: with soft limits on (``$20=1``) a
  shorter travel raises ALARM:2 inside the rig's range.
- ``$20``/``$21`` soft and hard limits (shown); ``$22`` homing against the axes' ``homing``
  policy: ``switches`` needs ``$22=1`` (else ``$H`` answers error:5 and the rig cannot
  open), ``none`` needs ``$22=0`` (else the controller boots locked in alarm).

With ``apply`` the rig file's settings are written first (``rig probe --apply``).

An axis without switches gets its origin with ``G10 L20 P1 X0``: the current place becomes
the axis's zero of the G54 work coordinate system, which GRBL keeps in EEPROM across resets
and power cycles (GRBL v1.1 wiki, "Grbl v1.1 Commands": ``G10 L2``/``G10 L20`` write the work
coordinate offsets, stored in EEPROM; ``G92`` offsets are not persistent). ``$#`` reads it
back. Moves stay in machine coordinates (G53); the driver adds the G54 offset
(:attr:`m2s2hil.drivers.grbl.GrblAxis.origin_units`).
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from typing import Any

from m2s2hil.config import AxisConfig, DeviceConfig, RigConfig
from m2s2hil.drivers.interfaces import RotaryAxis
from m2s2hil.errors import ConfigError
from m2s2hil.rig.devices.findings import REL_TOL, Finding, ProbeReport, agree, num
from m2s2hil.rig.devices.kind import (
    OFFSET_TOLERANCE_UNITS,
    MotionKind,
    OriginReading,
    Setup,
    Signature,
    SimParts,
    close_quietly,
    connect_or_close,
)
from m2s2hil.rig.open_errors import RigOpenError, detail_of, opening


def _simulator(setup: Setup, parts: SimParts) -> Any:
    from m2s2hil.simulators.grbl import grbl_sim_for

    name, axes = setup.name, setup.axes
    try:
        options = dict(setup.config.simulation.device_options(name))
        # A simulated controller has switches where the rig file's axes do, unless told otherwise.
        options.setdefault("homing_switches", any(a.homing == "switches" for a in axes.values()))
        return grbl_sim_for(name, axes, setup.clock, parts.world, parts.faults, options)
    except ValueError as exc:
        raise ConfigError("rig", f"simulation.devices.{name}", str(exc)) from None


def _controller(setup: Setup) -> Any:
    from m2s2hil.drivers.grbl import GrblController

    dev = setup.device
    # A feed hold stops every axis at once: it may stall as long as the most patient axis.
    windows = [ax.stall_window_s for ax in setup.axes.values()]
    kw = {"stall_window_s": max(windows)} if windows else {}
    return GrblController(dev.port, device=setup.name, baudrate=dev.baudrate, timeout_s=dev.timeout_s,
                          clock=setup.clock, retries=dev.retries, **kw)


def _open_axes(setup: Setup) -> tuple[Any, dict[str, RotaryAxis]]:
    ctl = _controller(setup)
    connect_or_close(ctl)
    out: dict[str, RotaryAxis] = {
        role: ctl.axis(
            ax.axis, name=role, units_per_degree=ax.units_per_degree, min_deg=ax.min_deg,
            max_deg=ax.max_deg, max_speed_dps=ax.max_speed_dps, accel_dps2=ax.accel_dps2,
            tolerance_deg=ax.tolerance_deg, settle_s=ax.settle_s, stall_window_s=ax.stall_window_s,
            timeout_margin=ax.timeout_margin,
        )
        for role, ax in setup.axes.items()
    }
    return ctl, out


def _home(ctl: Any, switched: Mapping[str, Any]) -> None:
    ctl.home()  # one $H homes every axis with switches


def _explain(exc: BaseException, device: str, port: str) -> RigOpenError | None:
    """``$H`` answered error:5 (homing not enabled, GRBL v1.1 wiki "Grbl v1.1 Error Codes"):
    the rig file says switches, the controller has ``$22=0``."""
    from m2s2hil.drivers.errors import CommandRejected

    if isinstance(exc, CommandRejected) and int(getattr(exc, "code", 0) or 0) == 5:
        return RigOpenError(device, port, "homing disabled", detail_of(exc))
    return None


def _expected(config: RigConfig, device: str) -> dict[int, tuple[float, str, str]]:
    """setting number -> (the rig file's value, label, what a lower/different value causes)."""
    from m2s2hil.protocols.grbl import AXES

    out: dict[int, tuple[float, str, str]] = {}
    for role, ax in config.axes.items():
        if ax.device != device:
            continue
        i = AXES.index(ax.axis.upper())
        upd = ax.units_per_degree
        letter = AXES[i]
        if ax.steps_per_degree is not None:
            out[100 + i] = (ax.steps_per_degree / upd, f"{letter} steps/unit ({role})",
                            "every angle is off by the ratio: wrong poses, read-back cannot tell")
        out[110 + i] = (ax.max_speed_dps * upd * 60.0, f"{letter} max rate ({role})",
                        "moves slower than planned: ETA wrong, long moves can time out")
        out[120 + i] = (ax.accel_dps2 * upd, f"{letter} acceleration ({role})",
                        "accelerates slower than planned: ETA too short")
    return out


def _probe(setup: Setup, report: ProbeReport, apply: bool) -> None:
    from m2s2hil.protocols.grbl import AXES

    name, dev, config = setup.name, setup.device, setup.config
    ctl = _controller(setup)
    try:
        with opening(name, dev.port, dev.protocol, dev.baudrate):
            ctl.connect()
            if apply:
                _apply(ctl, config, name)
            settings = ctl.read_settings()
            state = ctl.status().state_text
        add = report.findings.append
        add(Finding(name, "firmware", "GRBL 1.1", f"GRBL {ctl.version}", None))
        roles = setup.axes
        switches = any(ax.homing == "switches" for ax in roles.values())
        homing_on = bool(settings.get(22, 0))
        if state == "Alarm" and switches and homing_on:
            add(Finding(name, "state", "", "Alarm (locked until homed: $22=1)", None))
        else:
            add(Finding(name, "state", "", state, None if state != "Alarm" else False,
                        "" if state != "Alarm" else "the controller is in alarm: moves are refused until "
                        "it is cleared (`m2s2hil rig origin AXIS` unlocks it)"))
        for n, (want, label, effect) in sorted(_expected(config, name).items()):
            have = settings.get(n)
            if have is None:
                add(Finding(name, f"${n} {label}", num(want), "missing", False, effect))
                continue
            ok = agree(have, want) if n < 110 else have >= want * (1 - REL_TOL)
            add(Finding(name, f"${n} {label}", num(want), num(have), ok, "" if ok else effect,
                        None if ok else (f"${n}", want)))
        soft = bool(settings.get(20, 0))
        add(Finding(name, "$20 soft limits", "", "on" if soft else "off", None))
        add(Finding(name, "$21 hard limits", "", "on" if settings.get(21, 0) else "off", None))
        for role, ax in roles.items():
            i = AXES.index(ax.axis.upper())
            need = (ax.max_deg - ax.min_deg) * ax.units_per_degree
            have = settings.get(130 + i)
            if have is None:
                continue
            travel_ok: bool | None = have >= need * (1 - REL_TOL) if soft else None
            add(Finding(name, f"${130 + i} {AXES[i]} max travel ({role})", num(need) if soft else "",
                        num(have), travel_ok, "" if travel_ok is not False else
                        "soft limit alarm (ALARM:2) inside the rig's range: the sweep stops",
                        None if travel_ok is not False else (f"${130 + i}", need)))
        effect = ("`$H` answers error:5: the rig cannot open" if switches else
                  "the controller boots locked in alarm: every opening needs an unlock")
        add(Finding(name, "$22 homing", "1 (switches)" if switches else "0 (no switches)",
                    "1" if homing_on else "0", homing_on == switches, "" if homing_on == switches else effect,
                    None if homing_on == switches else ("$22", 1.0 if switches else 0.0)))
    finally:
        close_quietly(ctl)


def _apply(ctl: Any, config: RigConfig, name: str) -> list[str]:
    """Write the rig file's motion settings ($10x when known, $11x, $12x, $13x, $22) to EEPROM."""
    from m2s2hil.protocols.grbl import AXES, setting_line

    ctl.read_settings()
    lines: list[str] = []
    wanted = {n: v for n, (v, _label, _effect) in _expected(config, name).items()}
    roles = {r: ax for r, ax in config.axes.items() if ax.device == name}
    for ax in roles.values():
        i = AXES.index(ax.axis.upper())
        wanted[130 + i] = max(ctl.settings.get(130 + i, 0.0), (ax.max_deg - ax.min_deg) * ax.units_per_degree)
    wanted[22] = 1.0 if any(ax.homing == "switches" for ax in roles.values()) else 0.0
    for n, v in sorted(wanted.items()):
        have = ctl.settings.get(n)
        if have is not None and agree(have, v):
            continue
        line = setting_line(n, v)
        ctl.command(line)  # GRBL writes it to EEPROM and answers ok once it is stored
        lines.append(line)
    ctl.read_settings()
    if "$22=0" in lines and ctl.status().state == "Alarm":
        # It was the lock a homing controller boots with ($22=1); without homing there is no
        # cycle to wait for, so unlock as the controller will boot from now on.
        ctl.unlock()
    return lines


def work_offsets(ctl: Any) -> dict[str, tuple[float, ...]]:
    """``$#``: the stored coordinate tables by name (``G54`` .. ``G59``, ``G28``, ``G30``, ``G92``)."""
    from m2s2hil.protocols.grbl import Feedback

    out: dict[str, tuple[float, ...]] = {}
    for ev in ctl.command("$#", idempotent=True):
        if isinstance(ev, Feedback) and ev.tag.startswith("G"):
            try:
                out[ev.tag] = tuple(float(v) for v in ev.text.split(":")[0].split(","))
            except ValueError:
                continue
    return out


def _identity(ctl: Any) -> str:
    return f"GRBL {ctl.version}"


def _set_origin(ctl: Any, ax: AxisConfig, dev: DeviceConfig) -> OriginReading:
    """``G10 L20`` on a connected controller, read back with ``$#``."""
    from m2s2hil.protocols.grbl import AXES

    letter = ax.axis.upper()
    with opening(ax.device, dev.port, dev.protocol, dev.baudrate):
        st = ctl.status()
        if st.state == "Alarm":
            # The operator is placing the zero by hand: the controller's old position does
            # not matter any more, so unlocking ($X) is safe here.
            st = ctl.clear_alarm(home=False)
        if st.moving:
            raise RigOpenError(ax.device, dev.port, "device error",
                               f"the controller is busy ({st.state_text})",
                               "wait until the axis stands still")
        ctl.command(f"G10 L20 P1 {letter}0")
        g54 = work_offsets(ctl).get("G54")
        here = ctl.axis_position(letter)
    i = AXES.index(letter)
    if g54 is None or abs(g54[i] - here) > OFFSET_TOLERANCE_UNITS:
        raise RigOpenError(ax.device, dev.port, "device error",
                           f"after G10 L20 the controller reports G54 {g54} with the axis at {here}",
                           "run `m2s2hil rig probe` and check the controller's firmware")
    return OriginReading(letter, _identity(ctl), float(g54[i]))


def _stored_origin(ctl: Any, role: str, ax: AxisConfig, dev: DeviceConfig) -> OriginReading:
    """Not in alarm (an alarm means the position is not trusted), and the G54 offset from ``$#``."""
    from m2s2hil.protocols.grbl import AXES

    st = ctl.status()
    if st.state == "Alarm":
        if ctl.settings.get(22):
            raise RigOpenError(
                ax.device, dev.port, "alarm",
                "the controller has homing on ($22=1) and boots locked, but the rig file says "
                f"{role} has no switches (homing = \"none\")",
                "set $22=0 (`m2s2hil rig probe FILE --apply`) or homing = \"switches\"")
        raise RigOpenError(ax.device, dev.port, "alarm",
                           f"the controller is in alarm (last ALARM:{int(ctl.last_alarm or 0)}); "
                           f"{role}'s position is not trusted", None)
    g54 = work_offsets(ctl).get("G54")
    if g54 is None:
        raise RigOpenError(ax.device, dev.port, "device error", "`$#` reported no G54 offset")
    letter = ax.axis.upper()
    return OriginReading(letter, _identity(ctl), g54[AXES.index(letter)])


def _use_origin(axis: Any, offset_units: float) -> None:
    from m2s2hil.drivers.grbl import GrblAxis

    if isinstance(axis, GrblAxis):  # moves in G53 machine coordinates, plus the G54 offset
        axis.origin_units = offset_units


KIND = MotionKind(
    protocol="grbl",
    title="GRBL",
    make_simulator=_simulator,
    open_axes=_open_axes,
    home=_home,
    controller=_controller,
    set_origin=_set_origin,
    stored_origin=_stored_origin,
    use_origin=_use_origin,
    probe=_probe,
    explain=_explain,
    # A soft reset (0x18) is answered with the ``Grbl 1.1h ['$' for help]`` banner; any line
    # GRBL sends (ok, error:N, ALARM:N, [VER:...]) gives it away too.
    signature=Signature(b"\x18", re.compile(rb"Grbl |\[VER:|^(ok|error:\d+|ALARM:\d+)\r?$", re.M)),
)
