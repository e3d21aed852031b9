"""Benchmarks of the evaluation reports and the capture-time QC (results: docs/benchmarks.md).

    .venv/bin/python benchmarks/bench_evaluate.py qc        # QC cost per frame at 2048² / 1024²
    .venv/bin/python benchmarks/bench_evaluate.py scaling   # images/s: in-process vs local Dask cluster
    .venv/bin/python benchmarks/bench_evaluate.py study     # the failure study + speed/accuracy chart

``study`` writes ``bench-out/stability/`` (stability.md, stability.png, speed_accuracy.png)
and ``bench-out/table2/`` (a Table-2 report over the diffuse session).
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from m2s2hil.analysis.evaluation.aggregates import machine
from m2s2hil.analysis.evaluation.evaluate import evaluate_jobs
from m2s2hil.analysis.evaluation.jobs import collect_jobs
from m2s2hil.analysis.evaluation.options import EvalOptions
from m2s2hil.analysis.qc import QcConfig, capture_stability
from m2s2hil.analysis.report.evaluation_files import write_evaluation
from m2s2hil.analysis.study.stability import simulate_session, stability_study


def bench_qc(repeats: int = 7) -> None:
    """Per-frame QC cost on the cube the engine hands to the hook (super-pixel, dark-subtracted)."""
    from m2s2hil.config import default_rig, parse_rig
    from m2s2hil.processing import FrameProcessor, build_master_dark
    from m2s2hil.rig.factory import open_simulated_rig

    print(f"machine: {machine()}")
    print(
        f"| sensor | cube | lighting | exposure | demosaic ms | QC ms (median of {repeats}) | score | flags |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for size in (2048, 1024):
        data = default_rig().model_dump(mode="json")
        data["camera"]["model"].update(width=size, height=size)
        cfg = parse_rig(data, "bench")
        rig = open_simulated_rig(cfg)
        try:
            rig.mount("iss", "B3")
            for light, exp in (("weak", 0.008), ("directional", 0.003), ("weak", 0.0003), ("strong", 0.03)):
                rig.world.set_lens_cap(True)
                rig.camera.configure(exposure_s=exp, gain=1.0)
                dark = build_master_dark(
                    [rig.camera.snap().data for _ in range(2)], exposure_s=exp, gain=1.0, temperature_c=35.0
                )
                rig.world.set_lens_cap(False)
                rig.lights.set(cfg.lamp_channels(light))
                rig.clock.sleep(3.0)
                rig.tilt.move_to(15.0)
                rig.turntable.move_to(40.0)
                raw = rig.camera.snap().data
                proc = FrameProcessor("superpixel", cfg.camera.model, dark=dark)
                t = []
                for _ in range(repeats):
                    t0 = time.perf_counter()
                    pf = proc.process(raw)
                    t.append(time.perf_counter() - t0)
                cube, sat = pf.cube.copy(), pf.saturated_mask.copy()
                q = []
                for _ in range(repeats):
                    res = capture_stability(
                        cube, sat, config=QcConfig(), full_scale=cfg.camera.model.full_scale
                    )
                    q.append(res.elapsed_s)
                demosaic_ms, qc_ms = 1e3 * statistics.median(t), 1e3 * statistics.median(q)
                print(
                    f"| {size}² | {cube.shape[1]}² | {light} | {exp * 1e3:g} ms | {demosaic_ms:.1f} | "
                    f"{qc_ms:.0f} | {res.score:.3f} | {', '.join(res.flags) or '–'} |"
                )
        finally:
            rig.close()


def bench_engine_overhead(size: int = 2048) -> None:
    """The engine's processing stage with and without the QC hook (virtual clock: capture time is the
    simulated rig's, processing time is real), from the session's ``run_finished`` summary."""
    from m2s2hil.store.session import SessionStore

    print(f"engine, {size}² sensor, voyager B2, weak, 8 azimuths (virtual clock)")
    print("| QC hook | frames | simulated capture s/frame | processing stage ms/frame | QC ms/frame (meta) |")
    print("|---|---|---|---|---|")
    for qc in (None, True):
        with tempfile.TemporaryDirectory() as tmp:
            folder = simulate_session(
                tmp,
                satellite="voyager",
                build="B2",
                lighting=("weak",),
                azimuth_step_deg=45.0,
                size=size,
                qc=qc,
                session_id="overhead",
            )
            with SessionStore.open_path(folder) as store:
                fin = [e for e in store.events() if e.get("kind") == "run_finished"][-1]["payload"]
                frames = store.frames()
                qc_ms = [
                    1e3 * f.meta["qc"]["elapsed_s"] for f in frames if isinstance(f.meta.get("qc"), dict)
                ]
            n = len(frames)
            print(
                f"| {'on' if qc else 'off'} | {n} | {fin['duration_s'] / n:.2f} | "
                f"{1e3 * fin['pipeline']['process_s'] / n:.0f} | "
                f"{statistics.median(qc_ms) if qc_ms else float('nan'):.0f} |"
            )


def bench_scaling(size: int = 512, workers: tuple[int, ...] = (0, 1, 2)) -> None:
    """Throughput of the same evaluation in process and on local clusters (processes)."""
    with tempfile.TemporaryDirectory() as tmp:
        folder = simulate_session(
            tmp,
            satellite="voyager",
            build="B2",
            lighting=("weak", "directional"),
            azimuth_step_deg=60.0,
            size=size,
            session_id="scaling",
        )
        jobs, _ = collect_jobs(folder)
        print(f"machine: {machine()}; {len(jobs)} images, cube {size // 4}², spectral + rgb + mTC(multi)")
        print("| workers | wall s | images/s | s/image (spectral) | s/image (mTC) |")
        print("|---|---|---|---|---|")
        for n in workers:
            t0 = time.perf_counter()
            res = evaluate_jobs(jobs, EvalOptions(), workers=n)
            wall = time.perf_counter() - t0
            seg = np.mean([r["results"]["spectral"]["time_s"] for r in res.records])
            mt = np.mean([r["results"]["spectral"]["mtc_time_s"] for r in res.records])
            label = "0 (in process)" if n == 0 else f"{n} (LocalCluster, processes)"
            print(f"| {label} | {wall:.1f} | {len(jobs) / wall:.2f} | {seg:.3f} | {mt:.2f} |")


def bench_study(out: Path, size: int = 512, step: float = 90.0, workers: int | None = None) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        rows = stability_study(
            Path(tmp) / "sessions", out / "stability", size=size, azimuth_step_deg=step, workers=workers
        )
        print(f"study: {time.perf_counter() - t0:.0f} s, machine: {machine()}")
        print((out / "stability" / "stability.md").read_text())
        _ = rows
        folder = Path(tmp) / "sessions" / "stability-0"
        jobs, sources = collect_jobs(folder)
        res = evaluate_jobs(jobs, EvalOptions(extra=("spectral-smooth",)), workers=workers, sources=sources)
        write_evaluation(res, out / "table2")
        print((out / "table2" / "table2.md").read_text())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("what", choices=("qc", "scaling", "study"))
    ap.add_argument("--size", type=int, default=512, help="sensor size for scaling/study")
    ap.add_argument("--step", type=float, default=90.0, help="azimuth step of the study")
    ap.add_argument("--workers", type=int, default=None)
    ap.add_argument("--out", type=Path, default=Path("bench-out"))
    a = ap.parse_args()
    if a.what == "qc":
        bench_qc()
        bench_engine_overhead()
    elif a.what == "scaling":
        bench_scaling(a.size)
    else:
        bench_study(a.out, a.size, a.step, a.workers)


if __name__ == "__main__":
    main()
