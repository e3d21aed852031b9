"""Registration accuracy against its cost, and the projected labels against the simulator's truth.

    nice -n 10 .venv/bin/python benchmarks/bench_twin_registration.py [--size 512]
        [--chart docs/images/twin_registration.png]

registration  the simulated rig with the mockup placed off (offset (3, −2) mm, yaw 3°, tilt
              bias 1°; scale 1), 8 frames at 45° steps at E0 (15°) and E1 (0°), each
              satellite, weak light: the fit at several effort settings (the levels, px and
              blur σ, and the iterations per level); error of the offset (mm), yaw and tilt
              bias (°), wall time per frame fitted. A chart of offset error against cost.
              Where it fails: the same fit from 3 frames spanning 20° (the first frames of a
              sweep).
labels        the fit of the default setting, then the projected label map of 24 frames
              (15° steps, E0 and E1) at the sensor's size against the simulator's truth:
              foreground IoU and mean IoU over the classes (background included).
"""

from __future__ import annotations

import argparse
import json
import math
import time
from typing import Any

import numpy as np

from m2s2hil.hostinfo import describe_machine
from m2s2hil.twin.labels import label_iou, projected_labels
from m2s2hil.twin.projection import Placement, TwinCamera
from m2s2hil.twin.registration import Observation, Registrar
from m2s2hil.twin.simulated import SimBench, rig_with

TRUE = Placement(3.0, -2.0, 3.0, 1.0)
SATS = (("voyager", "B3"), ("iss", "B3"), ("hubble", "B2"))
SETTINGS = {
    "32px": (((32, 1.2),), 8),
    "48px": (((48, 1.5),), 12),
    "48+96px": (((48, 1.5), (96, 0.8)), 12),
    "48+96+128px": (((48, 1.5), (96, 0.8), (128, 0.6)), 12),
}


def rig(size: int) -> Any:
    return rig_with(size, mount={"offset_mm": [TRUE.dx_mm, TRUE.dy_mm], "yaw_deg": TRUE.yaw_deg,
                                 "tilt_bias_deg": TRUE.tilt_bias_deg})


def errors(p: Placement) -> dict[str, float]:
    return {"offset_mm": math.hypot(p.dx_mm - TRUE.dx_mm, p.dy_mm - TRUE.dy_mm),
            "yaw_deg": abs(p.yaw_deg - TRUE.yaw_deg), "tilt_deg": abs(p.tilt_bias_deg - TRUE.tilt_bias_deg),
            "scale": abs(p.scale - 1.0)}


def observations(bench: SimBench, sat: str, build: str,
                 azimuths: list[float]) -> tuple[list[Observation], list]:
    obs, frames = [], []
    for i, az in enumerate(azimuths):
        tilt = 15.0 if i % 2 == 0 else 0.0
        f = bench.frame(sat, build, "weak", az, tilt)
        obs.append(Observation.from_cube(sat, build, az, tilt, f.cube))
        frames.append(f)
    return obs, frames


def registration(size: int) -> dict[str, Any]:
    rows = []
    model = rig(size).camera.model
    for sat, build in SATS:
        bench = SimBench(rig(size))
        obs, _ = observations(bench, sat, build, [float(a) for a in range(0, 360, 45)])
        for name, (levels, nfev) in SETTINGS.items():
            r = Registrar(model, levels=levels, max_nfev=nfev).register(obs)
            rows.append({"satellite": sat, "setting": name, "ms_per_frame": 1e3 * r.elapsed_s / r.frames,
                         "renders": r.evaluations, "residual": r.residual, **errors(r.placement)})
            print(rows[-1], flush=True)
        few = [o for o in obs if o.azimuth_deg in (0.0, 45.0)]
        bench_few = SimBench(rig(size))
        extra, _ = observations(bench_few, sat, build, [10.0, 20.0])
        r = Registrar(model).register([*few[:1], *extra])
        rows.append({"satellite": sat, "setting": "3 frames over 20 deg",
                     "ms_per_frame": 1e3 * r.elapsed_s / r.frames,
                     "renders": r.evaluations, "residual": r.residual, **errors(r.placement)})
        print(rows[-1], flush=True)
    return {"rows": rows}


def labels(size: int) -> dict[str, Any]:
    out: dict[str, Any] = {"per_frame": []}
    model = rig(size).camera.model
    twin = TwinCamera(model, 64)
    for sat, build in SATS:
        bench = SimBench(rig(size))
        obs, frames = observations(bench, sat, build, [float(a) for a in range(0, 360, 15)])
        reg = Registrar(model).register(obs[::3])
        for o, f in zip(obs, frames, strict=True):
            pl = projected_labels(twin, sat, build, o.azimuth_deg, o.tilt_deg, reg, f.truth.labels.shape)
            fg = label_iou((pl.labels > 0).astype(np.uint8), (f.truth.labels > 0).astype(np.uint8))
            out["per_frame"].append({"satellite": sat, "azimuth": o.azimuth_deg, "tilt": o.tilt_deg,
                                     "miou": label_iou(pl.labels, f.truth.labels), "fg_iou": fg,
                                     "confidence": pl.confidence})
        print(sat, reg.placement, reg.residual, flush=True)
    for k in ("miou", "fg_iou"):
        v = np.array([r[k] for r in out["per_frame"]])
        out[k] = {"median": float(np.median(v)), "p05": float(np.percentile(v, 5)), "min": float(v.min())}
    return out


def chart(res: dict[str, Any], path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    for sat, _ in SATS:
        rows = [r for r in res["rows"] if r["satellite"] == sat and r["setting"] in SETTINGS]
        ax.plot([r["ms_per_frame"] for r in rows], [r["offset_mm"] for r in rows], "o-", label=sat)
        for r in rows:
            ax.annotate(r["setting"], (r["ms_per_frame"], r["offset_mm"]), fontsize=7)
    ax.set_xlabel("fit time per frame (ms, wall, shared 2-core machine)")
    ax.set_ylabel("offset error (mm)")
    ax.set_title("Twin registration: accuracy against cost (8 frames, 512² sensor)")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--out", default="/tmp/twin_registration.json")
    ap.add_argument("--chart", default=None)
    args = ap.parse_args()
    res: dict[str, Any] = {"registration": registration(args.size), "labels": labels(args.size),
                           "machine": describe_machine(),
                           "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())}
    if args.chart:
        chart(res["registration"], args.chart)
    with open(args.out, "w") as fh:
        json.dump(res, fh, indent=1)
    print(json.dumps({"labels": {k: res["labels"][k] for k in ("miou", "fg_iou")}}, indent=1))


if __name__ == "__main__":
    main()
