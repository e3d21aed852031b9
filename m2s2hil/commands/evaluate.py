"""``m2s2hil evaluate TARGET`` (Table 2, charts) and ``m2s2hil report SESSION`` (QC HTML report).

Register with::

    app.command("evaluate")(evaluate.evaluate_cmd)
    app.command("report")(evaluate.report_cmd)

TARGET is a session folder, a session id under ``--root``, a data root holding sessions
(every session in it), or an exported dataset folder (``HIL/...``; no ground truth, so
mTC only). Work runs on a local Dask cluster with one process per core, on an existing
cluster with ``--scheduler tcp://host:8786``, or in this process with ``--workers 0``.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import typer
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

from m2s2hil.errors import UsageError

console = Console(stderr=True)


def evaluate_cmd(
    target: str = typer.Argument(..., help="session id or folder, data root, or exported dataset folder"),
    root: Path | None = typer.Option(None, "--root", help="data root (default: $M2S2HIL_DATA or ./sessions)"),
    out: Path = typer.Option(Path("evaluation"), "--out", "-o", help="output folder for the report"),
    segmenter: str = typer.Option(
        "spectral",
        "--segmenter",
        help="multispectral segmenter: spectral, spectral-smooth, spectral-sweep (one mixture a session "
             "and lighting) or sam; its RGB counterpart runs with it",
    ),
    also: list[str] = typer.Option(
        [], "--also",
        help="more segmenters to time and score (repeatable), e.g. spectral-pose: each frame labelled "
             "with the materials of its pose under diffuse light",
    ),
    checkpoint: Path | None = typer.Option(None, "--checkpoint", help="SAM checkpoint (for --segmenter sam)"),
    option: list[str] = typer.Option(
        [], "--option", "-O",
        help="segmenter option KEY=VALUE for every segmenter run (repeatable; VALUE as JSON: "
             "censored=false, robust=false, n_superpixels=500), e.g. to evaluate without a step",
    ),
    scheduler: str | None = typer.Option(
        None, "--scheduler", help="existing Dask scheduler, tcp://host:port"
    ),
    workers: int | None = typer.Option(
        None, "--workers", min=0, help="local worker processes (default: all cores; 0: no Dask)"
    ),
    mtc_for: str = typer.Option("multi", "--mtc", help="mTC for: multi (default), all segmenters, none"),
    mtc_mode: str = typer.Option(
        "labels", "--mtc-mode", help="labels (aligned label maps) or binary (paper)"
    ),
    reprocess: str | None = typer.Option(
        None, "--reprocess", help="demosaic the raws again with this method instead of the stored cubes"
    ),
    rho: float = typer.Option(0.9, "--rho", help="assumed within-image correlation of the paired t-test"),
    clip_masks: bool = typer.Option(
        True, "--clip-masks/--no-clip-masks",
        help="give the segmenters which bands clipped in each pixel, from the raw frames (default on)",
    ),
    bracket: bool = typer.Option(
        True, "--bracket/--no-bracket",
        help="merge a bracketed pose's extra exposures into its image (default on); off: its own frame",
    ),
    limit: int | None = typer.Option(None, "--limit", min=1, help="evaluate only the first N images"),
    pair_with: str | None = typer.Option(
        None, "--pair-with", help="a synthetic TARGET: the HIL session to compare with pose by pose"
    ),
) -> None:
    """Evaluate segmenters on TARGET: Table-2-shaped CSV/Markdown, charts, per-image scores.
    A synthetic session (``m2s2hil synth``) gets the paper's synthetic columns instead."""
    from m2s2hil.analysis.evaluation.evaluate import evaluate_jobs
    from m2s2hil.analysis.evaluation.jobs import collect_jobs
    from m2s2hil.analysis.evaluation.options import EvalOptions
    from m2s2hil.analysis.report.evaluation_files import write_evaluation

    if reprocess is not None:
        from m2s2hil.config import check_demosaic_method

        check_demosaic_method(reprocess, lambda problem: UsageError(f"--reprocess: {problem}"))
    seg_opts = parse_options(option)
    if checkpoint is not None:
        seg_opts["checkpoint"] = str(checkpoint)
    options = EvalOptions(
        multi=segmenter,
        extra=tuple(also),
        segmenter_options=seg_opts,
        mtc_for=mtc_for,  # type: ignore[arg-type]
        mtc_mode=mtc_mode,
        reprocess=reprocess,
        rho=rho,
        clip_masks=clip_masks,
        bracket=bracket,
    )  # type: ignore[arg-type]
    from m2s2hil.analysis.evaluation.synthetic import synthetic_target
    from m2s2hil.commands.synth import evaluate_synthetic_session

    synthetic = synthetic_target(target, root)
    if synthetic is not None:  # Table 2's synthetic columns (analysis.evaluation.synthetic)
        evaluate_synthetic_session(synthetic, segmenter, seg_opts, out, pair_with, root, limit, rho)
        return
    jobs, sources = collect_jobs(target, root)
    if limit is not None:
        jobs = jobs[:limit]
    where = scheduler or ("this process" if workers == 0 else f"local cluster, {workers or 'all'} worker(s)")
    console.print(f"evaluating {len(jobs)} image(s) from {', '.join(sources)} on {where}")
    with Progress(
        TextColumn("{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeRemainingColumn(),
        console=console,
        transient=True,
    ) as bar:
        task = bar.add_task("images", total=len(jobs))
        result = evaluate_jobs(
            jobs,
            options,
            scheduler=scheduler,
            workers=workers,
            sources=sources,
            progress=lambda done, total: bar.update(task, completed=done),
        )
    written = write_evaluation(result, out)
    if not result.has_truth:
        console.print("no ground truth in these images: only mTC is reported")
    if result.errors:
        console.print(f"[yellow]{len(result.errors)} image(s) failed; see {out / 'summary.json'}[/yellow]")
    typer.echo((out / "table2.md").read_text())
    typer.echo(f"wrote {', '.join(sorted(written))} to {out} in {result.elapsed_s:.1f} s")


def parse_options(items: list[str]) -> dict[str, Any]:
    """``KEY=VALUE`` strings as segmenter options: VALUE read as JSON where it is JSON (``false``,
    ``0.5``, ``[1, 2]``), else as a string; a malformed item is a ``UsageError`` naming it."""
    out: dict[str, Any] = {}
    for item in items:
        key, sep, raw = item.partition("=")
        key = key.strip()
        if not sep or not key.isidentifier():
            raise UsageError(f"--option {item!r}: expected KEY=VALUE with KEY a parameter name")
        if key in out:
            raise UsageError(f"--option {key!r} is given twice")
        try:
            out[key] = json.loads(raw)
        except ValueError:
            out[key] = raw
    return out


def report_cmd(
    session: str = typer.Argument(..., help="session id (or the session's folder)"),
    root: Path | None = typer.Option(None, "--root", help="data root (default: $M2S2HIL_DATA or ./sessions)"),
    out: Path | None = typer.Option(None, "--out", "-o", help="HTML file (default: <session>/report.html)"),
    thumb: int = typer.Option(160, "--thumb", min=0, help="thumbnail width in pixels (0: no contact sheet)"),
    compute_missing: bool = typer.Option(
        True, "--compute-qc/--stored-qc-only", help="score frames stored without QC"
    ),
) -> None:
    """Write SESSION's HTML report: QC distribution, QC per pose and a contact sheet of previews."""
    from m2s2hil.analysis.report.session_html import write_session_report
    from m2s2hil.commands.export import open_session

    with open_session(session, root) as store:
        path, summary = write_session_report(store, out, thumb_px=thumb, compute_missing=compute_missing)
    if summary.get("kind") == "synthetic":  # renders have no QC: say what the report holds
        typer.echo(f"synthetic: {summary['views']} of {summary['planned']} view(s), "
                   f"{len(summary['incomplete'])} incomplete, "
                   f"{len(summary['empty_masks'])} with an empty mask")
    elif summary.get("scored"):
        typer.echo(
            f"QC: {summary['scored']} frame(s), median {summary['median']:.3f}, min {summary['min']:.3f}, "
            f"{summary['flagged']} flagged (threshold {summary['threshold']:g})"
        )
    else:
        typer.echo("QC: no scores")
    typer.echo(f"wrote {path}")
