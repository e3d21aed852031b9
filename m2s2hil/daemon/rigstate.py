"""Each device's state and health, for ``GET /rig``.

While a session owns the rig the values are the engine's own read-back (health ``busy``):
two threads on one serial line would corrupt each other's conversation."""

from __future__ import annotations

import collections
import threading
from typing import Any

from m2s2hil.engine.runner import Engine
from m2s2hil.rig.opened import Rig


def device_states(rig: Rig, hw: threading.Lock, engine: Engine | None) -> list[dict]:
    """One entry per configured device and the camera. ``engine``: the one owning the rig, if
    any; otherwise the devices are asked, holding ``hw`` (the request threads' device lock)."""
    cfg = rig.config
    devices: list[dict] = []
    faults_by_dev: collections.Counter = collections.Counter()
    if engine is not None:
        st = engine.status()
        for f in st.faults:
            faults_by_dev[f.device or "?"] += 1
    with hw:
        for name, dev in cfg.devices.items():
            roles = [r for r, ax in cfg.axes.items() if ax.device == name]
            kind = "motion" if roles else "relay"
            entry: dict[str, Any] = {
                "name": name, "kind": kind, "protocol": dev.protocol, "port": dev.port, "health": "ok",
                "state": {}, "error": None, "recent_faults": faults_by_dev.get(name, 0)}
            if engine is not None:
                entry["health"] = "busy"
                if kind == "motion":
                    entry["state"] = {f"{r}_deg": (st.azimuth_deg if r == "turntable" else st.tilt_deg)
                                      for r in roles}
                else:
                    entry["state"] = {"lamps_on": list(st.lamps_on)}
            else:
                try:
                    if kind == "motion":
                        for r in roles:
                            ax = rig.turntable if r == "turntable" else rig.tilt
                            moving, degrees = ax.motion()
                            entry["state"][f"{r}_deg"] = float(degrees)
                            entry["state"][f"{r}_moving"] = bool(moving)
                    else:
                        on = sorted(rig.lights.state())
                        names = {lc.channel: n for n, lc in cfg.lamps.items()}
                        entry["state"] = {"lamps_on": on,
                                          "lamp_names": [names.get(c, f"ch{c}") for c in on]}
                except Exception as exc:
                    entry["health"] = "error"
                    entry["error"] = f"{type(exc).__name__}: {exc}"
            devices.append(entry)
        cam: dict[str, Any] = {"name": "camera", "kind": "camera", "protocol": "u3v",
                               "port": cfg.camera.port, "health": "ok", "state": {}, "error": None,
                               "recent_faults": faults_by_dev.get("camera", 0)}
        model = cfg.camera.model
        cam["state"] = {"model": model.name, "width": model.width, "height": model.height}
        if engine is not None:
            cam["health"] = "busy"
        else:
            try:
                cam["state"]["temperature_c"] = float(rig.camera.temperature_c())
            except Exception as exc:
                cam["health"] = "error"
                cam["error"] = f"{type(exc).__name__}: {exc}"
        devices.append(cam)
    return devices
