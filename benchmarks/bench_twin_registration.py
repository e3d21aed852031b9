"""Registration accuracy against its cost, and the projected labels against the simulator's truth.

    nice -n 10 .venv/bin/python benchmarks/bench_twin_registration.py [--size 512]
        [--chart docs/images/twin_registration.png]

registration  the simulated rig with the mockup placed off (offset (3, −2) mm, yaw 3°, tilt
              bias 1°; scale 1), 8 frames at 45° steps at E0 (15°) and E1 (0°), each
              satellite, weak light: the fit at several effort settings (the levels, px and
              blur σ, and the iterations per level; "+N debiased": then N rounds at 96 and
              128 px, 4× supersampled, against the masks less the twin's predicted mask bias,
              as ``sessions register`` fits); error of the offset (mm), yaw and tilt bias (°),
              wall and CPU time per frame fitted. A chart of offset error against cost.
              Where it fails: the same fit from 3 frames spanning 20° (the first frames of a
              sweep).
labels        the session fit (``session_registrar``) from 8 (and from all 24) frames, then
              the projected label map of 24 frames (15° steps, E0 and E1) at the sensor's
              size against the simulator's truth: foreground IoU and mean IoU over the
              classes (background included).
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
from m2s2hil.twin.registration import Observation, Registrar, session_registrar
from m2s2hil.twin.simulated import SimBench, rig_with

TRUE = Placement(3.0, -2.0, 3.0, 1.0)
SATS = (("voyager", "B3"), ("iss", "B3"), ("hubble", "B2"))
SETTINGS = {
    "32px": (((32, 1.2),), 8),
    "48px": (((48, 1.5),), 12),
    "48+96px": (((48, 1.5), (96, 0.8)), 12),
    "48+96+128px": (((48, 1.5), (96, 0.8), (128, 0.6)), 12),
    "48+96px +1 debiased": (((48, 1.5), (96, 0.8)), 12),
    "48+96px +3 debiased": (((48, 1.5), (96, 0.8)), 12),
    "48+96px +3 debiased +polish": (((48, 1.5), (96, 0.8)), 12),
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
        o = Observation.from_meta(sat, build, f.cube, f.meta)
        assert o is not None
        obs.append(o)
        frames.append(f)
    return obs, frames


def registration(size: int, only: set[str] | None = None) -> dict[str, Any]:
    rows = []
    model = rig(size).camera.model
    for sat, build in SATS:
        bench = SimBench(rig(size))
        obs, _ = observations(bench, sat, build, [float(a) for a in range(0, 360, 45)])
        for name, (levels, nfev) in SETTINGS.items():
            if only is not None and name not in only:
                continue
            c0 = time.process_time()
            if "debiased" in name:
                rounds = int(name.split(" +")[1][0])
                fitter = session_registrar(rig(size), levels=levels, max_nfev=nfev, rounds=rounds,
                                           polish=name.endswith("+polish"))
            else:
                fitter = Registrar(model, levels=levels, max_nfev=nfev)
            r = fitter.register(obs)
            cpu = time.process_time() - c0
            rows.append({"satellite": sat, "setting": name, "ms_per_frame": 1e3 * r.elapsed_s / r.frames,
                         "cpu_ms_per_frame": 1e3 * cpu / r.frames,
                         "renders": r.evaluations, "residual": r.residual, **errors(r.placement)})
            print(rows[-1], flush=True)
        few = [o for o in obs if o.azimuth_deg in (0.0, 45.0)]
        bench_few = SimBench(rig(size))
        extra, _ = observations(bench_few, sat, build, [10.0, 20.0])
        c0 = time.process_time()
        r = session_registrar(rig(size)).register([*few[:1], *extra])
        rows.append({"satellite": sat, "setting": "3 frames over 20 deg",
                     "ms_per_frame": 1e3 * r.elapsed_s / r.frames,
                     "cpu_ms_per_frame": 1e3 * (time.process_time() - c0) / r.frames,
                     "renders": r.evaluations, "residual": r.residual, **errors(r.placement)})
        print(rows[-1], flush=True)
    return {"rows": rows}


def labels(size: int) -> dict[str, Any]:
    out: dict[str, Any] = {}
    model = rig(size).camera.model
    twin = TwinCamera(model, 64)
    fitter = session_registrar(rig(size))
    for every in (3, 1):  # registered from 8 of the 24 frames, and from all 24
        key = f"from_{24 // every}"
        rows: list[dict[str, Any]] = []
        for sat, build in SATS:
            bench = SimBench(rig(size))
            obs, frames = observations(bench, sat, build, [float(a) for a in range(0, 360, 15)])
            c0 = time.process_time()
            reg = fitter.register(obs[::every])
            cpu = time.process_time() - c0
            for o, f in zip(obs, frames, strict=True):
                pl = projected_labels(twin, sat, build, o.azimuth_deg, o.tilt_deg, reg, f.truth.labels.shape)
                fg = label_iou((pl.labels > 0).astype(np.uint8), (f.truth.labels > 0).astype(np.uint8))
                rows.append({"satellite": sat, "azimuth": o.azimuth_deg, "tilt": o.tilt_deg,
                             "miou": label_iou(pl.labels, f.truth.labels), "fg_iou": fg,
                             "confidence": pl.confidence})
            out.setdefault(f"{key}_fits", []).append({"satellite": sat, **errors(reg.placement),
                                                      "residual": reg.residual, "cpu_s": cpu,
                                                      "wall_s": reg.elapsed_s})
            print(key, sat, reg.placement, reg.residual, round(cpu, 1), flush=True)
        res: dict[str, Any] = {"per_frame": rows}
        for k in ("miou", "fg_iou"):
            v = np.array([r[k] for r in rows])
            res[k] = {"median": float(np.median(v)), "p05": float(np.percentile(v, 5)), "min": float(v.min())}
            for sat, _ in SATS:
                vs = np.array([r[k] for r in rows if r["satellite"] == sat])
                res[f"{k}_{sat}"] = {"median": float(np.median(vs)), "p05": float(np.percentile(vs, 5))}
        out[key] = res
    return out


def chart(res: dict[str, Any], path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    for sat, _ in SATS:
        rows = sorted((r for r in res["rows"] if r["satellite"] == sat and r["setting"] in SETTINGS),
                      key=lambda r: list(SETTINGS).index(r["setting"]))
        ax.plot([r["cpu_ms_per_frame"] for r in rows], [r["offset_mm"] for r in rows], "o-", label=sat)
        for r in rows:
            ax.annotate(r["setting"], (r["cpu_ms_per_frame"], r["offset_mm"]), fontsize=7)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("fit time per frame (ms CPU, shared 2-core machine)")
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
    ap.add_argument("--settings", default=None, help="comma-separated settings (default: all)")
    ap.add_argument("--merge", default=None,
                    help="an earlier run's JSON: its rows of the other settings join the chart")
    args = ap.parse_args()
    only = set(args.settings.split(",")) if args.settings else None
    res: dict[str, Any] = {"registration": registration(args.size, only), "labels": labels(args.size),
                           "machine": describe_machine(),
                           "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())}
    if args.merge:
        with open(args.merge) as fh:
            earlier = json.load(fh)["registration"]["rows"]
        have = {(r["satellite"], r["setting"]) for r in res["registration"]["rows"]}
        res["registration"]["rows"] += [r for r in earlier if (r["satellite"], r["setting"]) not in have]
    if args.chart:
        chart(res["registration"], args.chart)
    with open(args.out, "w") as fh:
        json.dump(res, fh, indent=1)
    summary = {key: {k: v for k, v in res["labels"][key].items() if k != "per_frame"}
               for key in ("from_8", "from_24")}
    print(json.dumps({"labels": summary}, indent=1))


if __name__ == "__main__":
    main()
