"""Speed and accuracy of the demosaicing methods, and their behaviour where they fail.

Used by ``m2s2hil bench demosaic`` and ``benchmarks/bench_processing.py``. Timing is wall time of
``FrameProcessor.process`` (dark subtraction with saturation mask, demosaicing, phase / low-light
checks) on a 2048×2048 10-bit frame, best-of-rounds of per-round medians: the machine is shared,
and the least disturbed round is the closest to what the code costs. Accuracy is measured on
noise-free ground-truth cubes (``groundtruth``), any (cube, mosaic) pair will do.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path

import numpy as np

from m2s2hil.processing.chain import FrameProcessor
from m2s2hil.processing.dark import MasterDark, build_master_dark, subtract_dark
from m2s2hil.processing.demosaic import METHODS, check_method, get_demosaicer
from m2s2hil.processing.groundtruth import Scene, mosaic_of
from m2s2hil.processing.image_quality import Quality, evaluate
from m2s2hil.processing.mosaic import MosaicLayout, cell_mean
from m2s2hil.processing.ppid import PPIDDemosaicer


@dataclass
class Timing:
    ms_best: float  # best round's median
    ms_median: float  # median over every timed frame
    rounds: list[float] = field(default_factory=list)  # each round's median

    @property
    def fps(self) -> float:
        return 1000.0 / self.ms_best


@dataclass
class MethodResult:
    method: str
    pipeline: Timing  # dark + mask + demosaic + checks
    demosaic: Timing  # demosaicing alone
    quality: Quality | None = None
    per_scene: dict[str, Quality] = field(default_factory=dict)


def time_call(fn: Callable[[], object], *, frames: int, rounds: int) -> Timing:
    fn()  # warm-up: compilation, first-touch of buffers
    medians, every = [], []
    for _ in range(rounds):
        ts = []
        for _ in range(frames):
            t0 = time.perf_counter()
            fn()
            ts.append(time.perf_counter() - t0)
        medians.append(float(np.median(ts)) * 1e3)
        every.extend(ts)
    return Timing(ms_best=min(medians), ms_median=float(np.median(every)) * 1e3, rounds=medians)


def timing_frame(camera, scene: Scene | None = None, seed: int = 0) -> tuple[np.ndarray, MasterDark]:
    """A full-size raw frame (a scene tiled to the sensor size, plus a dark level) and its master dark."""
    layout = MosaicLayout.from_camera(camera)
    rng = np.random.default_rng(seed)
    h, w = camera.height, camera.width
    if scene is None:
        img = rng.uniform(0.05, 0.9, (camera.n_bands, 64, 64)).astype(np.float32) * camera.full_scale
        cube = np.repeat(np.repeat(img, -(-h // 64), axis=1), -(-w // 64), axis=2)[:, :h, :w]
    else:
        reps = (-(-h // scene.cube.shape[1]), -(-w // scene.cube.shape[2]))
        cube = np.tile(scene.cube, (1, *reps))[:, :h, :w]
    darks = rng.poisson(20.0, (4, h, w)).astype(np.uint16)
    dark = build_master_dark(darks, exposure_s=0.01, gain=1.0, temperature_c=25.0, camera="bench")
    raw = mosaic_of(cube * 0.9 + 20.0, layout, camera.full_scale, read_noise_dn=2.0, seed=seed)
    return raw, dark


def measure_speed(
    camera, methods: Sequence[str], *, frames: int = 20, rounds: int = 3, scene: Scene | None = None
) -> dict[str, tuple[Timing, Timing]]:
    raw, dark = timing_frame(camera, scene)
    out = {}
    for m in methods:
        check_method(m)
        fp = FrameProcessor(m, camera, dark=dark)
        pipe = time_call(partial(fp.process, raw), frames=frames, rounds=rounds)
        corrected, _ = subtract_dark(raw, dark, full_scale=camera.full_scale)
        demo = time_call(partial(fp.demosaicer.process, corrected), frames=frames, rounds=rounds)
        out[m] = (pipe, demo)
    return out


def sample_cube_float(cube: np.ndarray, layout: MosaicLayout) -> np.ndarray:
    from m2s2hil.processing.mosaic import sample_cube

    return sample_cube(cube, layout, dtype=None)


def reference_for(method: str, cube: np.ndarray, n: int) -> np.ndarray:
    """What a method's output is compared with: the cube itself, or its n×n cell means for super-pixel."""
    return cell_mean(cube, n) if method == "superpixel" else cube


def border_for(method: str, n: int) -> int:
    """3·n raw pixels (3 cells for super-pixel): beyond the reach of every method's border handling."""
    return 3 if method == "superpixel" else 3 * n


def measure_accuracy(
    layout: MosaicLayout,
    full_scale: int,
    scenes: Sequence[Scene],
    methods: Sequence[str],
    *,
    ssim: bool = True,
) -> dict[str, tuple[Quality, dict[str, Quality]]]:
    """Mean quality over ``scenes`` (noise-free, quantised mosaics) for each method."""
    out: dict[str, tuple[Quality, dict[str, Quality]]] = {}
    mosaics = [mosaic_of(s.cube, layout, full_scale) for s in scenes]
    for m in methods:
        per = {}
        for s, mos in zip(scenes, mosaics, strict=True):
            est = get_demosaicer(m, layout, mos.shape).process(mos)
            per[s.name] = evaluate(
                est,
                reference_for(m, s.cube, layout.n),
                peak=full_scale,
                border=border_for(m, layout.n),
                ssim=ssim,
            )
        out[m] = (Quality.mean(list(per.values())), per)
    return out


def run_bench(
    camera, scenes: Sequence[Scene], methods: Sequence[str] = METHODS, *, frames: int = 20, rounds: int = 3
) -> list[MethodResult]:
    layout = MosaicLayout.from_camera(camera)
    speed = measure_speed(camera, methods, frames=frames, rounds=rounds, scene=scenes[0] if scenes else None)
    acc = measure_accuracy(layout, camera.full_scale, scenes, methods) if scenes else {}
    results = []
    for m in methods:
        q, per = acc.get(m, (None, {}))
        results.append(MethodResult(m, *speed[m], quality=q, per_scene=per))
    return results


# --- stability ----------------------------------------------------------------------------------


@dataclass
class StabilityRow:
    condition: str
    method: str
    rmse_dn: float
    psnr_db: float
    sam_deg: float
    note: str = ""


def demosaic_stability_study(
    camera, base: Scene, star: Scene, star2: Scene, methods: Sequence[str] = METHODS, *, seed: int = 0
) -> list[StabilityRow]:
    """Each method on a clean scene, saturation, very low light, fine stars and a 1-px phase error."""
    from m2s2hil.processing import stability

    layout = MosaicLayout.from_camera(camera)
    fs = camera.full_scale
    n = layout.n
    rows: list[StabilityRow] = []

    def run(m: str, mos: np.ndarray) -> tuple[object, np.ndarray]:
        d = get_demosaicer(m, layout, mos.shape)
        return d, d.process(mos).copy()

    def score(m: str, mos: np.ndarray, truth: np.ndarray, cond: str, note: str = "") -> None:
        _, est = run(m, mos)
        q = evaluate(est, reference_for(m, truth, n), peak=fs, border=border_for(m, n), ssim=False)
        rows.append(StabilityRow(cond, m, q.rmse_dn, q.psnr_db, q.sam_deg, note))

    # 1. clean
    clean = mosaic_of(base.cube, layout, fs)
    for m in methods:
        score(m, clean, base.cube, "clean")

    # 2. saturation: the scene brightened until 3 % of the raw pixels clip; compared with a
    #    sensor that does not clip (same mosaic, 16 bits)
    gain = fs / float(np.percentile(sample_cube_float(base.cube, layout), 97.0))
    bright = base.cube * gain
    ideal_mos = mosaic_of(bright, layout, 65535)
    sat_mos = np.minimum(ideal_mos, fs).astype(np.uint16)
    raw_sat = ideal_mos >= fs
    variants = [(m, m) for m in methods]
    if "ppid" in methods:
        variants.append(("ppid", "ppid, fixed gains"))
    clean_levels = base.cube.mean(axis=(1, 2))  # what a white reference would fix the balance with
    for m, label in variants:
        d = get_demosaicer(m, layout, sat_mos.shape)
        d_ideal = get_demosaicer(m, layout, sat_mos.shape)
        if label.endswith("fixed gains"):
            assert isinstance(d, PPIDDemosaicer) and isinstance(d_ideal, PPIDDemosaicer)
            d.fix_gains(clean_levels)
            d_ideal.fix_gains(clean_levels)
        est = d.process(sat_mos).copy()
        ideal = d_ideal.process(ideal_mos)
        ref = reference_for(m, bright, n)
        b = border_for(m, n)
        q = evaluate(est, ref, peak=fs, border=b, ssim=False)
        mask = (
            stability.grow_mask(raw_sat, d.support_radius)
            if d.full_resolution
            else stability.cell_mask(raw_sat, n)
        )
        inner = np.zeros_like(mask)
        inner[b:-b, b:-b] = True
        outside = ~mask & inner
        out_err = float(np.abs(est - ideal)[:, outside].max()) if outside.any() else 0.0
        at_clip = (raw_sat if d.full_resolution else stability.cell_mask(raw_sat, n)) & inner
        rmse_clip = float(np.sqrt(np.mean((est - ref)[:, at_clip] ** 2)))
        rmse_clip_ideal = float(np.sqrt(np.mean((ideal - ref)[:, at_clip] ** 2)))
        note = (
            f"scene ×{gain:.1f}, {100 * raw_sat.mean():.1f} % raw px clipped; mask grown by "
            f"{d.support_radius} px flags {100 * mask.mean():.1f} % of the cube; at clipped pixels "
            f"RMSE {rmse_clip:.0f} DN (unclipped "
            f"sensor {rmse_clip_ideal:.0f}); outside the mask: max deviation from the unclipped sensor "
            f"{out_err:.2g} DN"
        )
        rows.append(StabilityRow("saturated", label, q.rmse_dn, q.psnr_db, q.sam_deg, note))

    # 3. very low light: mean signal 10 DN, 0.25 DN/e⁻ shot noise + 2 DN read noise: mean SNR ≈ 4
    dim = base.cube * (10.0 / float(base.cube.mean()))
    low = mosaic_of(dim, layout, fs, gain_dn_per_e=0.25, read_noise_dn=2.0, seed=seed)
    snr = float(np.mean(dim) / np.sqrt(np.mean(dim) * 0.25 + 4.0))
    for m in methods:
        score(m, low, dim, "low light", f"mean signal {np.mean(dim):.1f} DN, mean SNR {snr:.1f}")

    # 4. aliasing: Siemens stars (one material: any spectral angle is an artefact)
    for sc, label in ((star, "star, one material"), (star2, "star, two materials")):
        mos = mosaic_of(sc.cube, layout, fs)
        for m in methods:
            score(m, mos, sc.cube, label)

    # 5. wrong phase: the frame read one pixel off (layout shifted by one column)
    shifted = mosaic_of(base.cube, layout, fs, offset=(0, 1))
    check = stability.check_phase(shifted, layout)
    good = stability.check_phase(clean, layout)
    note = (
        f"detected: layout.shifted{check.offset} (duplicates disagree {100 * check.cost_nominal:.1f} % "
        f"vs {100 * check.cost_best:.1f} %); clean frame: {good.offset}"
    )
    for m in methods:
        score(m, shifted, base.cube, "phase +1 px", note)
    return rows


# --- reporting ----------------------------------------------------------------------------------


def machine_description() -> str:
    """The machine line plus the versions of the libraries the kernels run on."""
    import cv2
    import numba

    from m2s2hil.hostinfo import describe_machine

    return (
        f"{describe_machine()}; numpy {np.__version__}, OpenCV {cv2.__version__}, "
        f"numba {numba.__version__} ({numba.get_num_threads()} threads)"
    )


def markdown_table(results: Sequence[MethodResult]) -> str:
    lines = [
        "| method | ms/frame (dark + demosaic) | frames/s | demosaic alone, ms | PSNR dB | SSIM | SAM ° |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in results:
        q = r.quality
        acc = f"{q.psnr_db:.2f} | {q.ssim:.4f} | {q.sam_deg:.2f}" if q else "– | – | –"
        lines.append(
            f"| {r.method} | {r.pipeline.ms_best:.2f} (median {r.pipeline.ms_median:.2f}) | "
            f"{r.pipeline.fps:.0f} | {r.demosaic.ms_best:.2f} | {acc} |"
        )
    return "\n".join(lines)


def per_band_table(results: Sequence[MethodResult], bands_nm: Sequence[float], what: str = "psnr") -> str:
    head = "| method | " + " | ".join(f"{b:g} nm" for b in bands_nm) + " |"
    lines = [head, "|---|" + "---|" * len(bands_nm)]
    for r in results:
        if r.quality is None:
            continue
        vals = r.quality.psnr_bands if what == "psnr" else r.quality.ssim_bands
        fmt = "{:.2f}" if what == "psnr" else "{:.4f}"
        lines.append(f"| {r.method} | " + " | ".join(fmt.format(v) for v in vals) + " |")
    return "\n".join(lines)


def stability_table(rows: Sequence[StabilityRow]) -> str:
    lines = ["| condition | method | RMSE DN | PSNR dB | SAM ° | notes |", "|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(
            f"| {r.condition} | {r.method} | {r.rmse_dn:.2f} | {r.psnr_db:.2f} | {r.sam_deg:.2f} | {r.note} |"
        )
    return "\n".join(lines)


def chart(
    results: Sequence[MethodResult], path: Path | str, *, target_fps: float | None = 65.0, title: str = ""
) -> Path:
    """frames/s against PSNR and against SAM, one point per method."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    pts = [r for r in results if r.quality is not None]
    fig, axes = plt.subplots(1, 2, figsize=(10, 4.2), dpi=110)
    for ax, key, label in (
        (axes[0], "psnr_db", "PSNR (dB, higher is better)"),
        (axes[1], "sam_deg", "SAM (degrees, lower is better)"),
    ):
        for r in pts:
            x = getattr(r.quality, key)
            ax.scatter(x, r.pipeline.fps, s=60)
            tag = r.method + (" (1/4 res.)" if r.method == "superpixel" else "")
            ax.annotate(tag, (x, r.pipeline.fps), textcoords="offset points", xytext=(6, 4))
        if target_fps:
            ax.axhline(target_fps, ls="--", lw=1, color="grey")
            ax.text(
                ax.get_xlim()[0],
                target_fps * 1.05,
                f"camera max {target_fps:g} fps",
                color="grey",
                fontsize=8,
            )
        ax.set_yscale("log")
        ax.margins(x=0.2, y=0.15)
        ax.set_xlabel(label)
        ax.set_ylabel("frames/s (dark + demosaic, 2048×2048)")
        ax.grid(True, which="both", alpha=0.3)
    if pts and pts[0].per_scene:
        fig.suptitle(title or f"Demosaicing speed vs accuracy (mean over {len(pts[0].per_scene)} scenes)")
    fig.tight_layout()
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(p)
    plt.close(fig)
    return p
