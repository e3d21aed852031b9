"""``m2s2hil bench``: speed against accuracy of the processing stages."""

from __future__ import annotations

from pathlib import Path

import typer
from rich.console import Console
from rich.table import Table

from m2s2hil.errors import UsageError

app = typer.Typer(help="Benchmarks of the processing stages.", no_args_is_help=True)


@app.command("demosaic")
def demosaic(
    methods: str = typer.Option("superpixel,nearest,wb,ppid", help="comma-separated methods to compare"),
    rig: Path | None = typer.Option(None, help="rig TOML whose camera model to use (default: built-in)"),
    frames: int = typer.Option(20, min=1, help="timed frames per round"),
    rounds: int = typer.Option(3, min=1, help="timing rounds; the best round's median is reported"),
    scenes: str = typer.Option(
        "full",
        help="'full' (4 pictures at native size), 'quick' (2 crops of 256²) or 'synthetic' (no data files)",
    ),
    chart: Path = typer.Option(Path("demosaic_speed_accuracy.png"), help="where to write the PNG chart"),
    per_band: bool = typer.Option(False, "--per-band", help="also print PSNR and SSIM per band"),
    markdown: bool = typer.Option(False, "--markdown", help="print the tables as Markdown too"),
) -> None:
    """Time each method on a full-size frame, score it on ground-truth scenes, chart speed vs PSNR and SAM."""
    from m2s2hil.config import load_rig
    from m2s2hil.processing import bench, groundtruth
    from m2s2hil.processing.demosaic import check_method

    names = [m.strip() for m in methods.split(",") if m.strip()]
    if not names:
        raise UsageError("--methods: give at least one method")
    for m in names:
        check_method(m)
    if scenes not in ("full", "quick", "synthetic"):
        raise UsageError(f"--scenes must be 'full', 'quick' or 'synthetic', not {scenes!r}")
    camera = load_rig(rig).camera.model
    console = Console()
    with console.status("building ground-truth scenes"):
        if scenes == "full":
            sc = groundtruth.reference_scenes(camera)
        elif scenes == "synthetic":
            size = min(256, camera.width, camera.height)
            sc = [groundtruth.synthetic_scene(camera, size, seed=s) for s in (1, 2)]
        else:
            sc = [
                groundtruth.colorchecker_scene(camera, "astronaut", size=256),
                groundtruth.earthlib_scene(camera, "rocket", size=256),
            ]
    with console.status("timing and scoring"):
        results = bench.run_bench(camera, sc, names, frames=frames, rounds=rounds)

    t = Table(title=f"Demosaicing {camera.width}×{camera.height}, {camera.bit_depth}-bit, {len(sc)} scenes")
    for col in ("method", "ms/frame", "frames/s", "demosaic ms", "PSNR dB", "SSIM", "SAM °"):
        t.add_column(col, justify="right" if col != "method" else "left")
    for r in results:
        q = r.quality
        t.add_row(
            r.method,
            f"{r.pipeline.ms_best:.2f}",
            f"{r.pipeline.fps:.0f}",
            f"{r.demosaic.ms_best:.2f}",
            f"{q.psnr_db:.2f}",
            f"{q.ssim:.4f}",
            f"{q.sam_deg:.2f}",
        )
    console.print(t)
    console.print(
        "ms/frame: dark subtraction + saturation mask + demosaic + checks, best of "
        f"{rounds} round medians ({frames} frames each). super-pixel is scored against the cell-averaged "
        "ground truth (1/4 resolution); the others at full resolution. Border of 3 cells excluded."
    )
    if per_band:
        console.print(bench.per_band_table(results, camera.bands_nm, "psnr"))
        console.print(bench.per_band_table(results, camera.bands_nm, "ssim"))
    if markdown:
        typer.echo(bench.markdown_table(results))
    path = bench.chart(results, chart, target_fps=camera.max_fps)
    typer.echo(f"chart: {path}")
    typer.echo(f"machine: {bench.machine_description()}")
