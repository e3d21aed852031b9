"""``m2s2hil synth --sat hubble --build B2``: the paper's synthetic domain as a session of its own kind.

Renders, for every pose of the sweep (the rig's elevations plus the synthetic-only E3, every
azimuth of the grid), one RGB image, ten band images lit with ``wavelength_to_rgb(centre,
gamma=0.80)`` and the material mask (m2s2hil.twin.synth), and stores them as a synthetic
session under the data root; ``m2s2hil export`` writes it in the published layout beside the
HIL sessions of the same build. The band colours and the filaments' RGB colours come from
``analysis.segmenters.rgb`` here, so the twin needs no analysis import.
"""

from __future__ import annotations

import contextlib
import signal
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING

import typer

if TYPE_CHECKING:
    from m2s2hil.store.session import SessionStore


def synth_cmd(
    sat: str = typer.Option(..., "--sat", help="satellite: voyager, iss, hubble"),
    build: str = typer.Option(..., "--build", help="build: B1, B2, B3"),
    light: str = typer.Option("strong", "--light", help="the preset whose lamps light the renders"),
    tilts: str = typer.Option("", "--tilts", help="elevations, comma-separated (default: E0,E1,E2 and E3)"),
    step: float = typer.Option(10.0, "--step", help="azimuth step, degrees (the paper: 10)"),
    size: int = typer.Option(512, "--size", help="image side, pixels (512: a superpixel HIL cube's)"),
    rig: Path | None = typer.Option(None, "--rig", help="rig TOML (default: built-in simulated rig)"),
    root: Path | None = typer.Option(None, "--root", help="data root (default: $M2S2HIL_DATA or ./sessions)"),
    session_id: str | None = typer.Option(None, "--session-id", help="session id (default: generated)"),
) -> None:
    """Render the synthetic domain of one build (RGB, ten band renders and masks per pose)."""
    from m2s2hil.analysis.segmenters.rgb import band_colours, camera_weights
    from m2s2hil.config import load_rig
    from m2s2hil.errors import UsageError
    from m2s2hil.store.catalogue import default_data_root
    from m2s2hil.twin.synth import GAMMA, SynthPlan, SynthRun

    if not 0.01 <= step <= 360:
        raise UsageError(f"--step {step} must lie in 0.01 … 360 degrees")
    cfg = load_rig(rig)
    model = cfg.camera.model
    plan = SynthPlan(satellite=sat, build=build, light=light, azimuth_step_deg=step, size=size,
                     elevations=tuple(t for t in tilts.replace(" ", "").split(",") if t))
    lights = band_colours(model.bands_nm, gamma=GAMMA)
    weights = camera_weights(model.bands_nm)

    def progress(done: int, total: int, _event: object) -> None:
        if done == total or done % 36 == 0:
            typer.echo(f"  {done}/{total} views", err=True)

    run = SynthRun(root or default_data_root(), cfg, plan, lights, weights, session_id=session_id)
    with _first_ctrl_c() as interrupted:  # the first Ctrl-C ends the render after the current view
        res = run.run(progress=progress,
                      stop=lambda: "interrupted (Ctrl-C)" if interrupted.is_set() else None)
    if res.state != "completed":
        typer.echo(f"stopped after {res.views} of {res.planned} synthetic views of {sat} {build}; what is "
                   f"rendered is kept in {res.path} (aborted)", err=True)
        raise typer.Exit(130)
    typer.echo(f"rendered {res.views} synthetic views of {sat} {build} into {res.path} "
               f"({res.views_per_s:.1f} views/s)")


@contextlib.contextmanager
def _first_ctrl_c() -> Iterator[threading.Event]:
    """An event set by the first SIGINT (the second raises KeyboardInterrupt, as usual); off the
    main thread (an in-process caller) no handler is installed."""
    flag = threading.Event()
    if threading.current_thread() is not threading.main_thread():
        yield flag
        return

    def handler(signum: int, frame: object) -> None:
        flag.set()
        signal.signal(signal.SIGINT, signal.default_int_handler)

    previous = signal.signal(signal.SIGINT, handler)
    try:
        yield flag
    finally:
        signal.signal(signal.SIGINT, previous)


def evaluate_synthetic_session(
    store: SessionStore, segmenter: str, seg_opts: dict, out: Path, pair_with: str | None, root: Path | None,
    limit: int | None, rho: float,
) -> None:
    """``m2s2hil evaluate SYNTHETIC [--pair-with HIL]``: Table 2's synthetic columns, sim to real."""
    from m2s2hil.analysis.evaluation.options import is_pose, is_sweep
    from m2s2hil.analysis.evaluation.synthetic import evaluate_synthetic
    from m2s2hil.analysis.segmenters.registry import create_segmenter
    from m2s2hil.errors import UsageError
    from m2s2hil.store.catalogue import default_data_root
    from m2s2hil.store.session import SessionStore

    if is_sweep(segmenter) or is_pose(segmenter):  # the synthetic columns go render by render
        what = ("fitted on a HIL session's sweep" if is_sweep(segmenter)
                else "told the materials by a HIL pose's diffuse frame")
        raise UsageError(f"--segmenter {segmenter} is {what}; a synthetic session is evaluated view by view: "
                         "use spectral, spectral-smooth or sam")
    seg = create_segmenter(segmenter, **seg_opts)
    hil = None
    if pair_with is not None:
        p = Path(pair_with)
        hil = SessionStore.open_path(p) if p.is_dir() else SessionStore.open(root or default_data_root(),
                                                                             pair_with)
    try:
        typer.echo(f"evaluating synthetic session {store.session_id} with {segmenter}", err=True)
        files = evaluate_synthetic(store, seg, out, hil=hil, limit=limit, rho=rho)
    finally:
        store.close()
        if hil is not None:
            hil.close()
    typer.echo(files["synthetic_table2.md"].read_text())
    typer.echo(f"wrote {', '.join(sorted(files))} to {out}")
