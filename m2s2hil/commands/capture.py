"""``capture``: the operator's command.

    capture --sat hubble --build B2 --light weak
    capture --sat voyager --build B3 --light all --tilt E1 --dry-run
    capture --resume 20261124T213811-hubble-B2-weak-aed7

Exit codes: 0 completed; 1 failed; 2 bad input; 3 paused by the engine (e.g. disk
full) and resumable; 4 aborted; 130 interrupted with Ctrl-C (paused and resumable).
"""

from __future__ import annotations

import contextlib
from pathlib import Path

import typer
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn
from rich.table import Table

from m2s2hil.catalog import load_catalog
from m2s2hil.config import RigConfig, load_rig
from m2s2hil.errors import UsageError

EXIT_OK, EXIT_FAILED, EXIT_USAGE, EXIT_PAUSED, EXIT_ABORTED, EXIT_INTERRUPTED = 0, 1, 2, 3, 4, 130

app = typer.Typer(help="Capture a session on the rig.", add_completion=False)
console = Console(stderr=True)


def parse_lights(values: list[str]) -> list[str]:
    """``weak``/``strong``/``directional`` (or published names solo/dir), ``all`` = all three."""
    cat = load_catalog()
    out: list[str] = []
    for v in values:
        for part in v.split(","):
            part = part.strip()
            if not part:
                continue
            keys = list(cat.lighting) if part.lower() == "all" else [cat.light(part).key]
            out.extend(k for k in keys if k not in out)
    if not out:
        raise UsageError("--light needs weak, strong, directional or all")
    return out


def build_sweep(
    *, sat: str, build: str, lights: list[str], tilts: list[str] | None, mode: str, method: str | None,
    exposure: str | None, azimuth_step: float, frames_per_pose: int, config: RigConfig,
):
    from m2s2hil.plan import parse_sweep

    cat = load_catalog()
    data: dict = {
        "satellite": cat.satellite(sat).key,
        "build": cat.build(sat, build).key,
        "lighting": lights,
        "tilts": [cat.elevation(t).key for t in tilts] if tilts else sorted(cat.elevations),
        "mode": mode,
        "azimuth_step_deg": azimuth_step,
        "frames_per_pose": frames_per_pose,
        "processing": method or config.processing.method,
    }
    if exposure is not None:
        if exposure.lower() == "auto":
            data["exposure"] = "auto"
        else:
            try:
                ms = float(exposure.lower().removesuffix("ms"))
            except ValueError:
                raise UsageError(f"--exposure must be 'auto' or milliseconds, not {exposure!r}") from None
            data["exposure"] = {c: ms / 1000.0 for c in lights}
    return parse_sweep(data, "command line")


def _print_plan(sweep, config: RigConfig) -> None:
    events = sweep.expand(config)
    est = sweep.estimate(config)
    frames = sum(1 for e in events if e.kind == "frame")
    darks = sum(1 for e in events if e.kind == "dark")
    t = Table(title=f"plan: {sweep.satellite} {sweep.build}, {', '.join(sweep.lighting)}")
    t.add_column("item")
    t.add_column("value", justify="right")
    t.add_row("frames", str(frames))
    t.add_row("dark events", str(darks))
    t.add_row("axis order", sweep.chosen_order(config))
    t.add_row("mode", sweep.mode)
    t.add_row("estimated duration", f"{est.total_s:.1f} s")
    t.add_row("lower bound", f"{est.lower_bound_s:.1f} s")
    for k, v in est.breakdown.items():
        t.add_row(f"  {k}", f"{v:.1f} s")
    if sweep.mode == "continuous":
        from m2s2hil.plan import estimate_continuous

        ce = estimate_continuous(sweep, config, radius_px=400)
        t.add_row("continuous estimate", f"{ce.total_s:.1f} s (bound {ce.lower_bound_s:.1f} s)")
    Console().print(t)
    for e in events[:5]:
        typer.echo(f"  {e.index:4d} {e.event_id}")
    if len(events) > 5:
        typer.echo(f"  ... {len(events) - 5} more")


def _run_engine(engine, *, virtual: bool) -> int:
    from m2s2hil.engine.state import Progress as ProgressEvent
    from m2s2hil.engine.state import RunState

    listener = engine.listen()
    interrupts = 0
    status = engine.status()
    columns = [
        TextColumn("{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("ETA {task.fields[eta]}"),
    ]
    with Progress(*columns, console=console, transient=False) as bar:
        task = bar.add_task("starting", total=status.total, completed=status.done, eta="?")
        thread = engine.start()
        while True:
            try:
                ev = listener.get(timeout=0.1)
                s = engine.status()
                if isinstance(ev, ProgressEvent) or ev is None:
                    if s.azimuth_deg is None:
                        where = s.state.value
                    else:
                        where = f"{s.lighting or '-'} {s.elevation or '-'} az {s.azimuth_deg:6.1f}°"
                    eta = "?" if s.eta_s is None else f"{s.eta_s:.0f} s" + (" (simulated)" if virtual else "")
                    bar.update(task, completed=s.done + s.skipped, description=where, eta=eta)
                # Paused (by Ctrl-C or by the engine itself, e.g. a full disk): the session is
                # saved and resumable, so the command ends rather than waiting for a resume.
                if s.state is RunState.PAUSED or not thread.is_alive():
                    break
            except KeyboardInterrupt:
                interrupts += 1
                if interrupts == 1:
                    console.print("[yellow]Ctrl-C: pausing at the next safe boundary "
                                  "(press again to abort)[/]")
                    with contextlib.suppress(UsageError):
                        engine.pause()
                else:
                    console.print("[red]aborting[/]")
                    with contextlib.suppress(UsageError):
                        engine.abort()
        listener.close()
    final = engine.status()
    sid = engine.session_id
    if final.state is RunState.PAUSED:
        if interrupts:
            console.print(f"paused and saved; resume with: capture --resume {sid}")
            return EXIT_INTERRUPTED
        console.print(f"paused ({final.pause_reason}); resume with: capture --resume {sid}")
        return EXIT_PAUSED
    engine.wait()
    final = engine.status()
    _summary(final, engine)
    if final.state is RunState.COMPLETED:
        return EXIT_OK
    if final.state is RunState.ABORTED:
        return EXIT_ABORTED
    return EXIT_FAILED


def _summary(s, engine) -> None:
    t = Table(title=f"session {s.session_id}: {s.state.value}")
    t.add_column("item")
    t.add_column("value", justify="right")
    t.add_row("events stored", f"{s.done} / {s.total}")
    t.add_row("skipped (recorded with reasons)", str(s.skipped))
    t.add_row("faults", str(len(s.faults)))
    t.add_row("duration (engine clock)", f"{s.elapsed_s:.1f} s")
    if s.efficiency is not None:
        t.add_row("efficiency vs lower bound", f"{s.efficiency:.3f}")
    t.add_row("folder", str(engine.store.path))
    if s.error:
        t.add_row("error", s.error)
    Console().print(t)


@app.command()
def capture(
    sat: str | None = typer.Option(None, "--sat", help="voyager, iss or hubble"),
    build: str | None = typer.Option(None, "--build", help="B1, B2 or B3"),
    light: list[str] = typer.Option(
        [], "--light", help="weak, strong, directional, or all (repeatable; comma-separated)"
    ),
    tilt: list[str] = typer.Option([], "--tilt", help="E0, E1, E2 (repeatable; default all)"),
    rig: Path | None = typer.Option(None, "--rig", help="rig TOML (default: built-in simulated rig)"),
    out: Path | None = typer.Option(None, "--out", help="data root (default: $M2S2HIL_DATA or ./sessions)"),
    resume: str | None = typer.Option(None, "--resume", help="session id to continue"),
    dry_run: bool = typer.Option(False, "--dry-run", help="print the plan and its time estimate"),
    mode: str = typer.Option("stop-and-go", "--mode", help="stop-and-go or continuous"),
    method: str | None = typer.Option(None, "--method", help="demosaicing method (default: the rig's)"),
    exposure: str | None = typer.Option(None, "--exposure", help="'auto' or milliseconds"),
    azimuth_step: float = typer.Option(10.0, "--azimuth-step", help="degrees between azimuths"),
    frames_per_pose: int = typer.Option(1, "--frames-per-pose", min=1),
    realtime: bool = typer.Option(False, "--realtime", help="simulated rig in real time, not virtual"),
) -> None:
    """Capture one satellite build under the chosen lighting conditions."""
    from m2s2hil.store.session import default_data_root

    if mode not in ("stop-and-go", "continuous"):
        raise UsageError(f"--mode must be stop-and-go or continuous, not {mode!r}")
    config = load_rig(rig)
    root = out or default_data_root()
    if rig is None:
        console.print("using the built-in simulated rig (every device simulated, virtual clock)"
                      if not realtime else "using the built-in simulated rig (real time)")
    if resume is None:
        if not (sat and build and light):
            raise UsageError("--sat, --build and --light are required (or --resume SESSION)")
        sweep = build_sweep(
            sat=sat, build=build, lights=parse_lights(light), tilts=tilt or None, mode=mode,
            method=method, exposure=exposure, azimuth_step=azimuth_step,
            frames_per_pose=frames_per_pose, config=config,
        )
        _check_method(sweep.processing)
        if dry_run:
            _print_plan(sweep, config)
            raise typer.Exit(EXIT_OK)
    elif dry_run or sat or build or light:
        raise UsageError("--resume takes the plan from the session: drop --sat/--build/--light/--dry-run")

    from m2s2hil.engine.runner import Engine
    from m2s2hil.rig.factory import open_rig
    from m2s2hil.store.session import SessionStore

    opened = open_rig(config, realtime=realtime)
    try:
        if resume is not None:
            engine = Engine.resume_session(opened, root, resume, qc=_qc_hook())
            n_done = len(engine.store.completed_event_ids())
            console.print(f"resuming {resume}: {n_done} events already stored")
        else:
            store = SessionStore.create(root, sweep, config, clock=opened.clock)
            engine = Engine(opened, store, sweep, qc=_qc_hook())
            console.print(f"session {store.session_id} in {store.path}")
        opened.mount(engine.sweep.satellite, engine.sweep.build)
        code = _run_engine(engine, virtual=opened.clock.__class__.__name__ == "VirtualClock")
    finally:
        opened.safe()
        opened.close()
    raise typer.Exit(code)


def _check_method(name: str) -> None:
    from m2s2hil.processing.demosaic import METHODS

    if name not in METHODS:
        raise UsageError(f"unknown processing method {name!r}; known: {', '.join(METHODS)}")


def _qc_hook():
    try:
        from m2s2hil.analysis.qc import capture_qc_hook
    except ImportError:
        return None
    return capture_qc_hook()

