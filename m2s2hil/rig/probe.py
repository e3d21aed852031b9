"""Commissioning: what every device of a rig says it is and how it is set, held against the rig file.

:func:`probe_rig` opens each device on its own (no homing, no origin needed), reads its
identity and the settings that decide how the capture behaves, and returns one
:class:`~m2s2hil.rig.devices.findings.Finding` per item: what the rig file implies, what the
device reports, whether they agree, and what a disagreement causes. With ``apply=True`` it
first writes the rig file's motion settings to the controllers (``m2s2hil rig probe
--apply``), then reads them back.

What is read from each kind is its registry entry's ``probe`` (m2s2hil/rig/devices/): GRBL's
``$$`` against the axes (``devices/grbl.py``), a Zaber's stored speeds and limits
(``devices/zaber.py``), a relay board's channel count against the lamps' highest channel
(``devices/modbus_relay.py``, ``devices/ascii_relay.py``), the camera's model, serial, firmware,
sensor size, pixel format and bit depth against ``[camera.model]`` (``devices/u3v.py``).
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

from m2s2hil.config import DeviceConfig, RigConfig
from m2s2hil.drivers.clock import SYSTEM_CLOCK, Clock
from m2s2hil.rig.devices import CAMERA, kind_of
from m2s2hil.rig.devices.findings import ProbeReport
from m2s2hil.rig.devices.kind import DeviceKind, Setup
from m2s2hil.rig.open_errors import RigOpenError

#: Exit code of ``m2s2hil rig probe`` when a device disagrees with the rig file.
EXIT_MISMATCH = 8


def _each_device(config: RigConfig) -> Iterator[tuple[str, DeviceConfig]]:
    """The devices to probe: every relay board, and the motion devices that drive an axis."""
    used = {ax.device for ax in config.axes.values()}
    for name, dev in config.devices.items():
        if kind_of(dev.protocol).role == "motion" and name not in used:
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
    targets: list[tuple[DeviceKind, Setup]] = [
        (kind_of(dev.protocol), Setup(name, config, clock)) for name, dev in _each_device(config)
    ]
    targets.append((CAMERA, Setup("camera", config, clock, sims or {})))
    for kind, setup in targets:
        try:
            kind.probe(setup, report, apply)
        except RigOpenError as exc:
            report.errors.append(exc)
    return report
