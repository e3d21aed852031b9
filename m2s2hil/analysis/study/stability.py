"""Simulated sessions and the failure study (docs/evaluation.md).

``simulate_session`` captures a session on the simulated rig with the real engine (truth
labels stored with every frame); ``stability_study`` simulates each of ``SCENARIOS``,
evaluates every segmenter with mTC and writes stability.csv/.md/.png.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from m2s2hil.analysis.evaluation import table2
from m2s2hil.analysis.evaluation.aggregates import machine, speed_accuracy
from m2s2hil.analysis.evaluation.evaluate import evaluate_jobs
from m2s2hil.analysis.evaluation.jobs import FrameJob, session_jobs
from m2s2hil.analysis.evaluation.options import EvalOptions, is_rgb
from m2s2hil.analysis.qc import capture_qc_hook, qc_of_meta
from m2s2hil.analysis.report import charts
from m2s2hil.atomic import write_text_atomic
from m2s2hil.config import default_rig, parse_rig
from m2s2hil.engine.build import build_run
from m2s2hil.plan import Sweep
from m2s2hil.rig.factory import open_simulated_rig
from m2s2hil.store.session import SessionStore


def simulate_session(
    root: str | Path,
    *,
    satellite: str,
    build: str,
    lighting: Sequence[str] = ("weak",),
    tilts: Sequence[str] = ("E0",),
    azimuth_step_deg: float = 90.0,
    exposure: Mapping[str, float] | None = None,
    size: int = 256,
    seed: int = 0,
    qc: Any = True,
    session_id: str | None = None,
    dark_frames: int = 2,
    store_cubes: bool = False,
    bracket: Mapping[str, Sequence[float]] | None = None,
    spot_angle_deg: float | None = None,
) -> Path:
    """Capture a session on the simulated rig with the real engine (truth labels stored with
    every frame); ``size`` is the sensor width = height; ``qc``: True (default hook), a
    hook, or None; ``store_cubes``: cache each cube beside its raw frame (``storage.cubes``);
    ``bracket``: the sweep's exposure brackets (``Sweep.bracket``); ``spot_angle_deg``: the
    simulated spotlight's incidence (the rig's ``[simulation]``, 45° by default).
    Returns the session folder."""
    data = default_rig().model_dump(mode="json")
    data["camera"]["model"].update(width=int(size), height=int(size))
    data.setdefault("storage", {})["cubes"] = bool(store_cubes)
    if spot_angle_deg is not None:
        data.setdefault("simulation", {})["spot_angle_deg"] = float(spot_angle_deg)
    cfg = parse_rig(data, f"simulated rig ({size}x{size})")
    sweep_data: dict[str, Any] = {
        "satellite": satellite,
        "build": build,
        "lighting": list(lighting),
        "tilts": list(tilts),
        "azimuth_step_deg": azimuth_step_deg,
        "dark": {"frames": dark_frames},
    }
    if exposure:
        sweep_data["exposure"] = dict(exposure)
    if bracket:
        sweep_data["bracket"] = {k: list(v) for k, v in bracket.items()}
    sweep = Sweep.model_validate(sweep_data)
    hook = capture_qc_hook() if qc is True else (qc or None)
    rig = open_simulated_rig(cfg, seed=seed)
    try:
        # the one builder of a run, as capture and the daemon use it
        engine = build_run(rig, root, sweep=sweep, session_id=session_id, qc=hook)
        with engine.store as store:
            engine.run()
            return Path(store.path)
    finally:
        rig.close()


# The failure study (docs/evaluation.md): one simulated session per scenario.
SCENARIOS: dict[str, dict[str, Any]] = {
    "diffuse": {"satellite": "voyager", "build": "B2", "lighting": ("weak", "strong")},
    "directional": {"satellite": "voyager", "build": "B2", "lighting": ("directional",)},
    "11 classes (ISS B3)": {"satellite": "iss", "build": "B3", "lighting": ("weak",)},
    "low light (0.2 ms)": {
        "satellite": "voyager",
        "build": "B2",
        "lighting": ("weak",),
        "exposure": {"weak": 0.0002},
    },
    "saturation (50 ms)": {
        "satellite": "voyager",
        "build": "B2",
        "lighting": ("strong",),
        "exposure": {"strong": 0.05},
    },
}


def stability_study(
    root: str | Path,
    out: str | Path,
    *,
    size: int = 512,
    azimuth_step_deg: float = 45.0,
    segmenters: Sequence[str] = ("spectral", "rgb", "spectral-smooth"),
    scenarios: Mapping[str, Mapping[str, Any]] | None = None,
    scheduler: str | None = None,
    workers: int | None = None,
    processes: bool = True,
    seed: int = 0,
) -> list[dict[str, Any]]:
    """Simulate each scenario, evaluate every segmenter with mTC, write stability.csv/.md/.png to ``out``."""
    chosen = dict(scenarios or SCENARIOS)
    root = Path(root)
    jobs: list[FrameJob] = []
    scenario_of: dict[str, str] = {}
    qc: dict[str, list[tuple[float | None, list[str]]]] = {}
    for i, (name, spec) in enumerate(chosen.items()):
        sid = f"stability-{i}"
        folder = simulate_session(
            root, size=size, azimuth_step_deg=azimuth_step_deg, seed=seed, session_id=sid, **dict(spec)
        )
        with SessionStore.open_path(folder) as store:
            jobs += session_jobs(store)
            qc[name] = [qc_of_meta(fr.meta) for fr in store.frames()]
        scenario_of[sid] = name
    multi = next((s for s in segmenters if not is_rgb(s)), "spectral")
    opts = EvalOptions(multi=multi, extra=tuple(s for s in segmenters if s != multi), mtc_for="all")
    result = evaluate_jobs(
        jobs,
        opts,
        scheduler=scheduler,
        workers=workers,
        processes=processes,
        sources=[f"scenario {n}" for n in chosen],
    )
    rows = []
    for name in chosen:
        recs = [r for r in result.records if scenario_of.get(r["source"]) == name and not r.get("error")]
        scores = [s for s, _ in qc[name] if s is not None]
        for seg in opts.segmenters:
            res = [r["results"][seg] for r in recs if seg in r["results"]]

            def mean(key: str, res: list[dict[str, Any]] = res) -> float:
                vals = [
                    float(x[key]) for x in res if key in x and x[key] is not None and math.isfinite(x[key])
                ]
                return float(np.mean(vals)) if vals else math.nan

            rows.append(
                {
                    "scenario": name,
                    "segmenter": seg,
                    "images": len(res),
                    "precision": mean("precision"),
                    "recall": mean("recall"),
                    "dice": mean("dice"),
                    "mtc": mean("mtc"),
                    "time_s": mean("time_s"),
                    "qc_mean": float(np.mean(scores)) if scores else math.nan,
                    "qc_flagged": sum(bool(f) for _, f in qc[name]),
                }
            )
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    write_text_atomic(out / "stability.csv", table2.rows_csv(rows))
    write_text_atomic(out / "stability.md", stability_markdown(rows))
    charts.stability_chart(rows, out / "stability.png")
    charts.speed_accuracy_chart(
        speed_accuracy(result.records),
        out / "speed_accuracy.png",
        title="Speed against accuracy (all scenarios)",
    )
    write_text_atomic(
        out / "stability_records.json",
        json.dumps(
            {
                "records": result.records,
                "compute": result.compute,
                "elapsed_s": result.elapsed_s,
                "machine": machine(),
                "size": size,
            },
            indent=1,
            default=str,
        )
        + "\n",
    )
    return rows


def stability_markdown(rows: Sequence[Mapping[str, Any]]) -> str:
    def f(v: Any) -> str:
        return "–" if not isinstance(v, (int, float)) or not math.isfinite(v) else f"{v:.3f}"

    lines = [
        "| Scenario | Segmenter | Images | Macro P | Macro R | Dice | mTC | s/image | QC mean | QC flagged |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['scenario']} | {r['segmenter']} | {r['images']} | {f(r['precision'])} | "
            f"{f(r['recall'])} | {f(r['dice'])} | {f(r['mtc'])} | {f(r['time_s'])} | {f(r['qc_mean'])} | "
            f"{r['qc_flagged']} |"
        )
    return "\n".join(lines) + "\n"
