"""Rig files for the commissioning tests: the built-in rig changed the way a real bench differs."""

from __future__ import annotations

import re
from importlib import resources
from pathlib import Path


def rig_text(*, homing: str = "none", switches_in_sim: bool | None = None, small: bool = True,
             fast: bool = True) -> str:
    """The built-in rig's TOML with both axes' ``homing`` set to ``homing``; the simulated
    stage has switches only if ``switches_in_sim`` (default: as the policy says)."""
    text = resources.files("m2s2hil").joinpath("data/default_rig.toml").read_text()
    text, n = re.subn(r'(?m)^homing = "switches"$', f'homing = "{homing}"', text)
    assert n == 2
    switches = (homing == "switches") if switches_in_sim is None else switches_in_sim
    text = text.replace("homing_switches = true", f"homing_switches = {str(switches).lower()}")
    if small:
        text = text.replace("width = 2048", "width = 64").replace("height = 2048", "height = 64")
    if fast:  # real time on ptys: quick moves, no lamp warm-up
        text = text.replace("max_speed_dps = 60.0", "max_speed_dps = 720.0")
        text = text.replace("accel_dps2 = 120.0", "accel_dps2 = 5000.0")
        text = text.replace("max_speed_dps = 20.0", "max_speed_dps = 360.0")
        text = text.replace("accel_dps2 = 40.0", "accel_dps2 = 5000.0")
        text = text.replace("warmup_s = 1.0", "warmup_s = 0.0").replace("warmup_s = 2.0", "warmup_s = 0.0")
    return text


def write_rig(path: Path, **kw: object) -> Path:
    path.write_text(rig_text(**kw))  # type: ignore[arg-type]
    return path


def zaber_rig_text(*, homing: str = "none") -> str:
    """The same rig with a two-axis Zaber device (100 microsteps per degree) as the stage."""
    text = rig_text(homing=homing).split("# The simulated GRBL controller")[0]  # GRBL-only options
    text = text.replace('protocol = "grbl"', 'protocol = "zaber"')
    text = text.replace('axis = "X"', 'axis = "1"').replace('axis = "Y"', 'axis = "2"')
    return text.replace("units_per_degree = 1.0", "units_per_degree = 100.0")
