"""Commissioning: what every device of a rig says it is and how it is set, held against the rig file.

:func:`probe_rig` opens each device on its own (no homing, no origin needed), reads its
identity and the settings that decide how the capture behaves, and returns one
:class:`Finding` per item: what the rig file implies, what the device reports, whether they
agree, and what a disagreement causes. With ``apply=True`` it first writes the rig file's
motion settings to the controllers (``m2s2hil rig probe --apply``), then reads them back.

GRBL (``$$``, numbered as in the GRBL v1.1 wiki, "Grbl v1.1 Configuration"), per axis
``i`` (X=0, Y=1, Z=2), in the machine units the rig file's ``units_per_degree`` counts:

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

Zaber (per axis: ``maxspeed``, ``accel``, ``limit.min``, ``limit.max`` in the device's data
units, converted as the driver converts them). The driver writes these when the rig opens,
so a mismatch here only says the stored values differ. The relay board: its channel count
(Modbus: found from its exception replies; an ASCII board: the lamps' relays read back)
against the lamps' highest channel. The camera: model, serial, firmware, sensor size,
pixel format and bit depth against ``[camera.model]``.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

from m2s2hil.config import AxisConfig, DeviceConfig, RigConfig
from m2s2hil.drivers.clock import SYSTEM_CLOCK, Clock
from m2s2hil.rig.open_errors import RigOpenError, opening

#: Exit code of ``m2s2hil rig probe`` when a device disagrees with the rig file.
EXIT_MISMATCH = 8
#: Relative difference below which two rates or accelerations agree (GRBL prints 3 decimals).
REL_TOL = 1e-3

_PIXEL_BITS = {"Mono8": 8, "Mono10": 10, "Mono10p": 10, "Mono10Packed": 10, "Mono12": 12, "Mono12p": 12,
               "Mono12Packed": 12, "Mono14": 14, "Mono16": 16}


@dataclass(frozen=True)
class Finding:
    device: str
    item: str  # "$110 X max rate", "model", ...
    expected: str  # what the rig file implies ("" = nothing to compare: shown for information)
    actual: str  # what the device reports
    ok: bool | None  # None: information only
    effect: str = ""  # what a mismatch causes
    #: For --apply: (setting, value) to write to fix it; None when it cannot be written.
    fix: tuple[str, float] | None = None


@dataclass
class ProbeReport:
    rig: str
    findings: list[Finding] = field(default_factory=list)
    errors: list[RigOpenError] = field(default_factory=list)  # devices that could not be opened

    @property
    def mismatches(self) -> list[Finding]:
        return [f for f in self.findings if f.ok is False]

    @property
    def ok(self) -> bool:
        return not self.mismatches and not self.errors


def _close(drv: Any) -> None:
    with contextlib.suppress(Exception):
        drv.close()


def _agree(actual: float, expected: float) -> bool:
    return math.isclose(actual, expected, rel_tol=REL_TOL, abs_tol=1e-6)


def _num(v: float) -> str:
    return f"{v:.6g}"


# -- GRBL ------------------------------------------------------------------------------------
def _grbl_expected(config: RigConfig, device: str) -> dict[int, tuple[float, str, str]]:
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


def _probe_grbl(name: str, dev: DeviceConfig, config: RigConfig, clock: Clock, report: ProbeReport,
                apply: bool) -> None:
    from m2s2hil.drivers.grbl import GrblController
    from m2s2hil.protocols.grbl import AXES

    ctl = GrblController(dev.port, device=name, baudrate=dev.baudrate, timeout_s=dev.timeout_s, clock=clock,
                         retries=dev.retries)
    try:
        with opening(name, dev.port, dev.protocol, dev.baudrate):
            ctl.connect()
            if apply:
                _apply_grbl(ctl, config, name)
            settings = ctl.read_settings()
            state = ctl.status().state_text
        add = report.findings.append
        add(Finding(name, "firmware", "GRBL 1.1", f"GRBL {ctl.version}", None))
        roles = {r: ax for r, ax in config.axes.items() if ax.device == name}
        switches = any(ax.homing == "switches" for ax in roles.values())
        homing_on = bool(settings.get(22, 0))
        if state == "Alarm" and switches and homing_on:
            add(Finding(name, "state", "", "Alarm (locked until homed: $22=1)", None))
        else:
            add(Finding(name, "state", "", state, None if state != "Alarm" else False,
                        "" if state != "Alarm" else "the controller is in alarm: moves are refused until "
                        "it is cleared (`m2s2hil rig origin AXIS` unlocks it)"))
        for n, (want, label, effect) in sorted(_grbl_expected(config, name).items()):
            have = settings.get(n)
            if have is None:
                add(Finding(name, f"${n} {label}", _num(want), "missing", False, effect))
                continue
            ok = _agree(have, want) if n < 110 else have >= want * (1 - REL_TOL)
            add(Finding(name, f"${n} {label}", _num(want), _num(have), ok, "" if ok else effect,
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
            ok: bool | None = have >= need * (1 - REL_TOL) if soft else None
            add(Finding(name, f"${130 + i} {AXES[i]} max travel ({role})", _num(need) if soft else "",
                        _num(have), ok, "" if ok is not False else
                        "soft limit alarm (ALARM:2) inside the rig's range: the sweep stops",
                        None if ok is not False else (f"${130 + i}", need)))
        effect = ("`$H` answers error:5: the rig cannot open" if switches else
                  "the controller boots locked in alarm: every opening needs an unlock")
        add(Finding(name, "$22 homing", "1 (switches)" if switches else "0 (no switches)",
                    "1" if homing_on else "0", homing_on == switches, "" if homing_on == switches else effect,
                    None if homing_on == switches else ("$22", 1.0 if switches else 0.0)))
    finally:
        _close(ctl)


def _apply_grbl(ctl: Any, config: RigConfig, name: str) -> list[str]:
    """Write the rig file's motion settings ($10x when known, $11x, $12x, $13x, $22) to EEPROM."""
    from m2s2hil.protocols.grbl import AXES, setting_line

    ctl.read_settings()
    lines: list[str] = []
    wanted = {n: v for n, (v, _label, _effect) in _grbl_expected(config, name).items()}
    roles = {r: ax for r, ax in config.axes.items() if ax.device == name}
    for ax in roles.values():
        i = AXES.index(ax.axis.upper())
        wanted[130 + i] = max(ctl.settings.get(130 + i, 0.0), (ax.max_deg - ax.min_deg) * ax.units_per_degree)
    wanted[22] = 1.0 if any(ax.homing == "switches" for ax in roles.values()) else 0.0
    for n, v in sorted(wanted.items()):
        have = ctl.settings.get(n)
        if have is not None and _agree(have, v):
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


# -- Zaber -----------------------------------------------------------------------------------
def _zaber_expected(ax: AxisConfig) -> dict[str, int]:
    from m2s2hil.protocols.zaber import ACCEL_DATA_PER_USTEP_S2, VELOCITY_DATA_PER_USTEP_S

    upd = ax.units_per_degree
    return {
        "maxspeed": max(1, round(ax.max_speed_dps * upd * VELOCITY_DATA_PER_USTEP_S)),
        "accel": max(1, round(ax.accel_dps2 * upd * ACCEL_DATA_PER_USTEP_S2)),
        "limit.min": round(ax.min_deg * upd),
        "limit.max": round(ax.max_deg * upd),
    }


_ZABER_EFFECTS = {
    "maxspeed": "stored maximum speed differs (the driver sets the rig file's when the rig opens)",
    "accel": "stored acceleration differs (the driver sets the rig file's when the rig opens)",
    "limit.min": "stored travel limit differs (the driver sets the rig file's when the rig opens)",
    "limit.max": "stored travel limit differs (the driver sets the rig file's when the rig opens)",
}


def _probe_zaber(name: str, dev: DeviceConfig, config: RigConfig, clock: Clock, report: ProbeReport,
                 apply: bool) -> None:
    from m2s2hil.drivers.zaber import ZaberDevice

    zd = ZaberDevice(dev.port, device=name, address=dev.unit, baudrate=dev.baudrate, timeout_s=dev.timeout_s,
                     clock=clock, retries=dev.retries)
    add = report.findings.append
    try:
        with opening(name, dev.port, dev.protocol, dev.baudrate):
            info = zd.connect()
            add(Finding(name, "device id", "", info.get("deviceid", "?"), None))
            add(Finding(name, "firmware", "", info.get("version", "?"), None))
            add(Finding(name, "serial", "", info.get("system.serial", "?"), None))
            for role, ax in config.axes.items():
                if ax.device != name:
                    continue
                number = int(ax.axis)
                for setting, want in _zaber_expected(ax).items():
                    if apply:
                        zd.request(number, f"set {setting} {want}", check_faults=False)
                    raw = zd.get(setting, number)
                    try:
                        have = int(raw.split()[0])
                    except (ValueError, IndexError):
                        have = None
                    ok = have == want
                    add(Finding(name, f"axis {number} {setting} ({role})", str(want), raw, ok,
                                "" if ok else _ZABER_EFFECTS[setting],
                                None if ok else (setting, float(want))))
                reply = zd.request(number, "", idempotent=True, check_faults=False)
                add(Finding(name, f"axis {number} flag ({role})", "", reply.warning,
                            False if reply.fault else None, "a fault: moves are refused until it is cleared"))
    finally:
        _close(zd)


# -- relays, camera -------------------------------------------------------------------------
def _count_coils(board: Any) -> int:
    """How many coils a Modbus board has: the largest count (1..64) it reads without refusing.

    A Modbus RTU relay board answers a read beyond its coils with exception 02, ILLEGAL DATA
    ADDRESS (Modbus Application Protocol V1.1b3, 6.1 Read Coils), which the driver raises as
    CommandRejected; six reads find the count by bisection.
    """
    from m2s2hil.drivers.errors import CommandRejected

    lo, hi = 1, 64
    board.channels = 1
    board.state()
    while lo < hi:
        mid = (lo + hi + 1) // 2
        board.channels = mid
        try:
            board.state()
            lo = mid
        except CommandRejected:
            hi = mid - 1
    board.channels = lo
    return lo


def _probe_relays(name: str, dev: DeviceConfig, config: RigConfig, clock: Clock, report: ProbeReport) -> None:
    needed = max((lamp.channel for lamp in config.lamps.values()), default=0) + 1
    expected = f">= {needed} (the lamps' highest channel is {needed - 1})"
    if dev.protocol == "modbus-rtu":
        from m2s2hil.drivers.modbus_relay import ModbusRelayBoard

        board: Any = ModbusRelayBoard(dev.port, device=name, unit=dev.unit, baudrate=dev.baudrate,
                                      timeout_s=dev.timeout_s, clock=clock, retries=dev.retries,
                                      parity=dev.parity, stopbits=dev.stopbits, channels=1)
    else:
        from m2s2hil.drivers.ascii_relay import AsciiRelayBoard

        board = AsciiRelayBoard(dev.port, device=name, baudrate=dev.baudrate, timeout_s=dev.timeout_s,
                                clock=clock, retries=dev.retries, channels=needed)
    try:
        with opening(name, dev.port, dev.protocol, dev.baudrate):
            if dev.protocol == "modbus-rtu":
                board.connect()
                count = _count_coils(board)
                actual, ok = str(count), count >= needed
            else:
                # An ASCII board has no way to say how many relays it has: read the lamps' ones.
                try:
                    board.connect()
                    actual, ok = f"relays 0..{needed - 1} answer", True
                except Exception as exc:  # the board refuses a relay it does not have
                    actual, ok = f"reading relays 0..{needed - 1} failed: {exc}", False
        report.findings.append(Finding(name, "channels", expected, actual, ok,
                                       "" if ok else "a lamp on a missing channel never lights"))
    finally:
        _close(board)


def _probe_camera(config: RigConfig, clock: Clock, sims: dict[str, Any], report: ProbeReport) -> None:
    from m2s2hil.protocols.u3v_bootstrap import ABRM
    from m2s2hil.rig.factory import open_camera

    cam_cfg = config.camera
    model = cam_cfg.model
    cam = open_camera(config, clock, sims)
    try:
        with opening("camera", cam_cfg.port, "u3v"):
            vendor = cam.control.read_string(ABRM.MANUFACTURER_NAME)
            name = cam.control.read_string(ABRM.MODEL_NAME)
            version = cam.control.read_string(ABRM.DEVICE_VERSION)
            fmt = cam.pixel_format
            width, height = cam.width, cam.height
        add = report.findings.append
        shown = f"{vendor} {name}".strip()
        ok = name.lower() in model.name.lower() or model.name.lower() in shown.lower()
        add(Finding("camera", "model", model.name, shown, ok, "" if ok else
                    "another camera: the band layout and calibration of the rig file do not apply"))
        add(Finding("camera", "serial", cam_cfg.serial or "", cam.serial or "?",
                    None if cam_cfg.serial is None else cam.serial == cam_cfg.serial))
        add(Finding("camera", "firmware", "", version, None))
        size_ok = (width, height) == (model.width, model.height)
        add(Finding("camera", "sensor size", f"{model.width}x{model.height}", f"{width}x{height}", size_ok,
                    "" if size_ok else "frames do not match the mosaic layout: demosaicking fails"))
        bits = _PIXEL_BITS.get(fmt)
        add(Finding("camera", "pixel format", "", fmt, None))
        bits_ok = bits == model.bit_depth
        add(Finding("camera", "bit depth", str(model.bit_depth), str(bits) if bits else f"? ({fmt})", bits_ok,
                    "" if bits_ok else "full scale differs: saturation and exposure search are wrong"))
    finally:
        _close(cam)


# -- the rig ---------------------------------------------------------------------------------
def _each_device(config: RigConfig) -> Iterator[tuple[str, DeviceConfig]]:
    used = {ax.device for ax in config.axes.values()}
    for name, dev in config.devices.items():
        if dev.protocol in ("grbl", "zaber") and name not in used:
            continue
        yield name, dev


def probe_rig(config: RigConfig, *, clock: Clock | None = None, apply: bool = False,
              sims: dict[str, Any] | None = None) -> ProbeReport:
    """Probe every device of ``config``; with ``apply`` write the motion settings first.

    ``sims`` holds in-process simulators for ``sim://`` ports (``build_simulators``); a
    device that cannot be opened is recorded in ``report.errors`` and the others are
    still probed.
    """
    clock = clock or SYSTEM_CLOCK
    report = ProbeReport(config.rig.name)
    steps: list[Callable[[], None]] = []
    for name, dev in _each_device(config):
        if dev.protocol == "grbl":
            steps.append(lambda n=name, d=dev: _probe_grbl(n, d, config, clock, report, apply))
        elif dev.protocol == "zaber":
            steps.append(lambda n=name, d=dev: _probe_zaber(n, d, config, clock, report, apply))
        else:
            steps.append(lambda n=name, d=dev: _probe_relays(n, d, config, clock, report))
    steps.append(lambda: _probe_camera(config, clock, sims or {}, report))
    for step in steps:
        try:
            step()
        except RigOpenError as exc:
            report.errors.append(exc)
    return report
