"""ASCII (Numato-style) relay boards: driver, simulator, ``rig probe`` and recognition."""

from __future__ import annotations

import re
from typing import Any

from m2s2hil.drivers.interfaces import LightBank
from m2s2hil.rig.devices.findings import ProbeReport
from m2s2hil.rig.devices.kind import RelayKind, Setup, Signature, SimParts, close_quietly, connect_or_close
from m2s2hil.rig.devices.relays import add_channels_finding, channels_needed
from m2s2hil.rig.open_errors import opening


def _simulator(setup: Setup, parts: SimParts) -> Any:
    from m2s2hil.simulators.ascii_relay import AsciiRelaySim

    return AsciiRelaySim(setup.name, setup.clock, parts.faults, on_change=parts.world.set_lamp)


def _board(setup: Setup, **extra: Any) -> Any:
    from m2s2hil.drivers.ascii_relay import AsciiRelayBoard

    dev = setup.device
    return AsciiRelayBoard(dev.port, device=setup.name, baudrate=dev.baudrate, timeout_s=dev.timeout_s,
                           clock=setup.clock, retries=dev.retries, **extra)


def _open_lights(setup: Setup) -> LightBank:
    board = _board(setup)
    connect_or_close(board)
    return board


def _probe(setup: Setup, report: ProbeReport, apply: bool) -> None:
    dev = setup.device
    needed = channels_needed(setup.config)
    board = _board(setup, channels=needed)
    try:
        with opening(setup.name, dev.port, dev.protocol, dev.baudrate):
            # An ASCII board has no way to say how many relays it has: read the lamps' ones.
            try:
                board.connect()
                actual, ok = f"relays 0..{needed - 1} answer", True
            except Exception as exc:  # the board refuses a relay it does not have
                actual, ok = f"reading relays 0..{needed - 1} failed: {exc}", False
        add_channels_finding(report, setup.name, setup.config, actual, ok)
    finally:
        close_quietly(board)


KIND = RelayKind(
    protocol="ascii-relay",
    title="ASCII relay",
    make_simulator=_simulator,
    open_lights=_open_lights,
    probe=_probe,
    # ``ver`` is echoed and followed by the board's ``>`` prompt; a prompt alone could follow
    # anything, so it counts only as the reply to this probe.
    signature=Signature(b"ver\r", re.compile(rb">"), own_probe_only=True),
)
