"""What ``rig probe`` asks any relay board: whether it has the channels the lamps are on."""

from __future__ import annotations

from m2s2hil.config import RigConfig
from m2s2hil.rig.devices.findings import Finding, ProbeReport


def channels_needed(config: RigConfig) -> int:
    """How many channels the rig file's lamps need: one past the highest."""
    return max((lamp.channel for lamp in config.lamps.values()), default=0) + 1


def add_channels_finding(report: ProbeReport, name: str, config: RigConfig, actual: str, ok: bool) -> None:
    needed = channels_needed(config)
    expected = f">= {needed} (the lamps' highest channel is {needed - 1})"
    report.findings.append(Finding(name, "channels", expected, actual, ok,
                                   "" if ok else "a lamp on a missing channel never lights"))
