"""Where the rig time of a continuous full build goes, pass by pass, on the virtual clock.

    nice -n 10 .venv/bin/python benchmarks/bench_rig_time_breakdown.py [--blur 2.5] [--rev REV]
                                                                       [--size 64] [--json OUT]

One session (voyager B3, 324 frames, continuous, planned for ``--blur`` px at the mockup's rim as
``bench_rig_time.py`` plans it), built as ``capture`` builds it. The opened rig's device calls
(lamps, moves, the camera's stream start and stop, frame reads, the turntable's rotation and stop)
and the engine's own waits are timed on the virtual clock from outside the engine (the calls are
wrapped here; nothing in the engine is changed), and the time is split into:

- ``sweep``: from a pass's first kept frame to its last (the floor's ``span / ω``, plus any
  acceleration inside the pass);
- ``run-up``: from the rotation command to the pass's first kept frame (the camera's stream start
  is under it when the rotation starts first);
- ``overrun``: from the last kept frame to the stop command (frames read past the last mark);
- ``braking``: the turntable's stop, until it is at rest;
- ``lamp switch`` and ``warm-up wait`` (the engine sleeping until the lamps are warm and the tilt
  has settled), ``tilt move``, ``repositioning`` (turntable moves to a run-up's start),
  ``stream start`` (when the rotation waits for it);
- ``dark frames``: everything before the first pass's lamps (the master darks);
- ``end``: after the last stop (stream stop, lamps off: the safe state);
- ``other``: what is left between those calls (serial round trips, camera settings, darks looked up).

``--rev REV`` measures the engine's continuous steps as they were at git revision ``REV``
(``m2s2hil/engine/marks.py`` and ``continuous_steps.py`` loaded from ``git show``), for a
before/after comparison in one checkout. The totals are exact whatever the machine's load.
"""

from __future__ import annotations

import argparse
import functools
import importlib.util
import json
import subprocess
import sys
import tempfile
from collections import defaultdict
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
SWAPPED = ("m2s2hil.engine.marks", "m2s2hil.engine.continuous_steps")


def load_revision(rev: str, tmp: Path) -> None:
    """Put the continuous steps of ``rev`` in place of the checkout's, before anything imports them."""
    for name in SWAPPED:
        rel = name.replace(".", "/") + ".py"
        src = subprocess.run(["git", "-C", str(ROOT), "show", f"{rev}:{rel}"], check=True,
                             capture_output=True, text=True).stdout
        path = tmp / f"{name}.py"
        path.write_text(src)
        spec = importlib.util.spec_from_file_location(name, path)
        assert spec is not None and spec.loader is not None
        mod = importlib.util.module_from_spec(spec)
        sys.modules[name] = mod
        spec.loader.exec_module(mod)


class Timeline:
    """Top-level timed calls of the engine thread on the rig's clock (a call inside another is
    part of it; a sleep outside any call is the engine waiting)."""

    def __init__(self, clock: Any) -> None:
        self.clock = clock
        self.calls: list[tuple[str, float, float, tuple]] = []
        self._depth = 0

    def wrap(self, obj: Any, name: str, label: str) -> None:
        f = getattr(obj, name)

        @functools.wraps(f)
        def timed(*a: Any, **kw: Any) -> Any:
            t0 = self.clock.monotonic()
            self._depth += 1
            try:
                return f(*a, **kw)
            finally:
                self._depth -= 1
                if self._depth == 0:
                    self.calls.append((label, t0, self.clock.monotonic(), a))

        setattr(obj, name, timed)

    def wrap_sleep(self) -> None:
        sleep = self.clock.sleep

        def timed(seconds: float) -> None:
            t0 = self.clock.monotonic()
            sleep(seconds)
            if self._depth == 0:
                self.calls.append(("wait", t0, self.clock.monotonic(), ()))

        self.clock.sleep = timed


def breakdown(calls: list[tuple[str, float, float, tuple]], frames: list[dict], total_s: float,
              origin: float) -> dict:
    """The categories of the module docstring, per pass and summed."""
    by_pass: dict[int, list[float]] = defaultdict(list)
    for f in frames:
        by_pass[f["pass"]].append(f["mid"])
    passes = sorted(by_pass)
    rotations = [c for c in calls if c[0] == "rotate"]
    # each pass's own stop (the teardown's safe state stops the turntable once more)
    stops = [next(c for c in calls if c[0] == "tt_stop" and c[1] >= r[1]) for r in rotations]
    assert len(rotations) == len(passes), (len(rotations), len(passes))  # no pass was retried
    rows = []
    prev_end = next(c[1] for c in calls if c[0] == "lamps")  # the darks end where the lamps first switch
    head = {"dark frames": prev_end - origin}
    for i, p in enumerate(passes):
        first, last = min(by_pass[p]), max(by_pass[p])
        rot, stop = rotations[i][1], stops[i]
        row: dict[str, float] = defaultdict(float)
        row["sweep"] = last - first
        row["run-up"] = first - rot
        row["overrun"] = stop[1] - last
        row["braking"] = stop[2] - stop[1]
        for label, t0, t1, args in calls:
            if not (prev_end <= t0 and t1 <= rot + 1e-9):
                continue
            if label == "lamps":
                row["lamp switch"] += t1 - t0
            elif label == "wait":
                row["warm-up wait"] += t1 - t0
            elif label == "move":
                row["tilt move" if args[0] == "tilt" else "repositioning"] += t1 - t0
            elif label == "stream_start":
                row["stream start"] += t1 - t0
        row["other"] = (rot - prev_end) - sum(row[k] for k in ("lamp switch", "warm-up wait", "tilt move",
                                                                 "repositioning", "stream start"))
        rows.append({"pass": p, **row})
        prev_end = stop[2]
    tail = {"end": origin + total_s - prev_end}
    keys = ["sweep", "run-up", "overrun", "braking", "lamp switch", "warm-up wait", "tilt move",
            "repositioning", "stream start", "other"]
    summed = {k: sum(r.get(k, 0.0) for r in rows) for k in keys}
    summed.update(head)
    summed.update(tail)
    return {"passes": rows, "total": summed, "sum_s": sum(summed.values()), "rig_time_s": total_s}


def run(size: int, blur: float) -> dict:
    from bench_engine import mockup_radius_px, rig_config

    from m2s2hil.engine.build import build_run
    from m2s2hil.engine.options import EngineOptions
    from m2s2hil.plan import Sweep
    from m2s2hil.plan.continuous import SharpnessTarget, plan_continuous
    from m2s2hil.rig.factory import open_simulated_rig
    from m2s2hil.store.session import SessionStore

    cfg = rig_config(size)
    radius = mockup_radius_px(256) * 2048 / 256  # the rim in full-resolution pixels, as bench_rig_time
    plan = plan_continuous(Sweep(satellite="voyager", build="B3"), cfg,
                           SharpnessTarget(max_blur_px=blur, radius_px=radius))
    rig = open_simulated_rig(cfg)
    line = Timeline(rig.clock)
    for obj, name, label in ((rig.camera, "start_stream", "stream_start"),
                             (rig.camera, "stop_stream", "stream_stop"), (rig.camera, "read_frame", "frame"),
                             (rig.turntable, "stop", "tt_stop"), (rig.lights, "set", "lamps")):
        line.wrap(obj, name, label)
    assert rig.rotation is not None
    line.wrap(rig.rotation, "rotate", "rotate")
    line.wrap_sleep()
    readout = 1.0 / cfg.camera.model.max_fps
    try:
        with tempfile.TemporaryDirectory(prefix="bench_rig_breakdown_") as tmp:
            engine = build_run(rig, Path(tmp), sweep=plan.sweep,
                               options=EngineOptions.of(max_blur_px=blur, radius_px=radius, save_truth=False))
            line.wrap(engine.ops, "move", "move")
            st = engine.run()
            engine.store.close()
            store = SessionStore.open_path(engine.store.path)
            frames = [{"pass": f.meta["event"]["pass_index"],
                       "mid": f.meta["clock_s"] - readout - f.meta["exposure_s"] / 2} for f in store.frames()]
            store.close()
    finally:
        rig.close()
    out = breakdown(sorted(line.calls, key=lambda c: c[1]), frames, st.elapsed_s,
                    engine.report.time.started_at)
    out.update(state=st.state.value, frames=len(frames), floor_s=plan.sweep.physical_floor(cfg).total_s)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", type=int, default=64)
    ap.add_argument("--blur", type=float, default=2.5)
    ap.add_argument("--rev", help="measure the continuous steps of this git revision instead")
    ap.add_argument("--json", type=Path)
    a = ap.parse_args()
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    with tempfile.TemporaryDirectory(prefix="bench_rig_rev_") as tmp:
        if a.rev:
            load_revision(a.rev, Path(tmp))
        out = run(a.size, a.blur)
    out["rev"] = a.rev or "working tree"
    t = out["total"]
    print(f"{out['rev']}: rig time {out['rig_time_s']:.2f} s ({out['state']}, {out['frames']} frames), "
          f"floor {out['floor_s']:.2f} s, ratio {out['rig_time_s'] / out['floor_s']:.3f}; "
          f"categories sum to {out['sum_s']:.2f} s")
    print("| category | " + " | ".join(f"pass {r['pass']}" for r in out["passes"]) + " | total |")
    print("|---" * (len(out["passes"]) + 2) + "|")
    for k in t:
        cells = [f"{r.get(k, 0.0):.2f}" for r in out["passes"]] if k not in ("dark frames", "end") else \
            ["—"] * len(out["passes"])
        print(f"| {k} | " + " | ".join(cells) + f" | {t[k]:.2f} |")
    if a.json:
        a.json.write_text(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
