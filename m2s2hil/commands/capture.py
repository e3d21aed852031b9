"""``capture``: the operator's command.

    capture --sat hubble --build B2 --light weak
    capture --sat voyager --build B3 --light all --tilt E1 --dry-run
    capture --sat iss --build B3 --light dir --bracket 16
    capture --resume 20261124T213811-hubble-B2-weak-aed7

Exit codes: 0 completed; 1 failed (also: the rig could not be opened, one line naming the
device; or not one frame could be stored); 2 bad input (also: an output folder that cannot
be written, one line naming it); 3 paused by the engine (e.g. disk full, also at the start)
and resumable; 4 aborted; 5 completed with gaps (planned frames skipped, each recorded;
``--resume`` retries them); 130 interrupted with Ctrl-C (paused and resumable).

Ctrl-C asks the run to pause at the next safe boundary (the capture in hand finishes). A
second Ctrl-C stops waiting for one: the lamps go off and motion stops at once (from this
thread, whatever the run's thread is doing), the run is asked to abort, and the command
exits 130 after a short grace; what is stored stays stored and ``--resume`` continues.

Dark frames on a real rig (a camera that is not ``sim://``): before the darks the run stops
at a safe boundary (lamps off, motion stopped) and asks "Put the lens cap on, then press
Enter", and before the first lit frame "Take the lens cap off, then press Enter"; nothing
checks the cap (:mod:`m2s2hil.engine.darks`). Without a terminal (stdin not a tty) a session
with darks still to take is refused (exit 2, one line); a dark needed later (auto exposure,
a temperature retake) with no one to answer leaves the session paused (exit 3).

The run is put together by :func:`m2s2hil.engine.build.build_run` (the daemon's too); this
module only translates the options and renders progress.
"""

from __future__ import annotations

import contextlib
import shlex
import sys
import threading
from pathlib import Path
from typing import TYPE_CHECKING

import typer
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn
from rich.table import Table

from m2s2hil.catalog import load_catalog
from m2s2hil.config import RigConfig, check_demosaic_method, load_rig
from m2s2hil.errors import UsageError
from m2s2hil.sim_config import is_simulated

if TYPE_CHECKING:
    from m2s2hil.engine.runner import Engine
    from m2s2hil.engine.state import EngineStatus
    from m2s2hil.plan import Sweep

EXIT_OK, EXIT_FAILED, EXIT_USAGE, EXIT_PAUSED, EXIT_ABORTED, EXIT_INTERRUPTED = 0, 1, 2, 3, 4, 130
EXIT_GAPS = 5  # completed_with_gaps: the run ended, some planned frames were skipped
HALT_GRACE_S = 3.0  # after a second Ctrl-C: how long (real time) the run may take to end by itself

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


def parse_bracket(values: list[str], lights: list[str]) -> dict[str, list[float]]:
    """``--bracket``: ``16`` or ``4,16`` (extra exposures for every condition captured) or
    ``dir=16`` (that condition only); repeatable."""
    cat = load_catalog()
    out: dict[str, list[float]] = {}
    for v in values:
        name, sep, factors = v.rpartition("=")
        keys = [cat.light(name.strip()).key] if sep else list(lights)
        try:
            numbers = [float(f) for f in factors.split(",") if f.strip()]
        except ValueError:
            raise UsageError(f"--bracket {v!r}: factors are numbers, e.g. 16 or dir=4,16") from None
        if not numbers:
            raise UsageError(f"--bracket {v!r}: no factor given, e.g. 16 or dir=4,16")
        for k in keys:
            listed = out.setdefault(k, [])
            for f in numbers:
                if f not in listed:  # 16 given twice is one exposure
                    listed.append(f)
    return out


def build_sweep(
    *, sat: str, build: str, lights: list[str], tilts: list[str] | None, mode: str, method: str | None,
    exposure: str | None, azimuth_step: float, frames_per_pose: int, config: RigConfig,
    bracket: dict[str, list[float]] | None = None,
) -> Sweep:
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
        "bracket": bracket or {},
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


def _print_plan(sweep: Sweep, config: RigConfig) -> None:
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
    for cond, factors in sweep.bracket.items():
        t.add_row(f"bracket ({cond})", "x1, " + ", ".join(f"x{f:g}" for f in factors))
    t.add_row("estimated duration", f"{est.total_s:.1f} s")
    for k, v in est.breakdown.items():
        t.add_row(f"  {k}", f"{v:.1f} s")
    t.add_row("lower bound (this mode)", f"{est.lower_bound_s:.1f} s")
    if est.physical_floor_s is not None:  # any mode, any order: m2s2hil/plan/floor.py
        t.add_row("physical floor (any mode)", f"{est.physical_floor_s:.1f} s")
    if sweep.mode == "continuous":
        from m2s2hil.plan import estimate_continuous

        ce = estimate_continuous(sweep, config, radius_px=400)
        t.add_row("continuous estimate", f"{ce.total_s:.1f} s (bound {ce.lower_bound_s:.1f} s)")
    Console().print(t)
    for e in events[:5]:
        typer.echo(f"  {e.index:4d} {e.event_id}")
    if len(events) > 5:
        typer.echo(f"  ... {len(events) - 5} more")


def _stdin_is_terminal() -> bool:
    """Someone can answer a prompt (tests replace this)."""
    return sys.stdin.isatty()


def _check_operator(config: RigConfig, sweep: Sweep, stored: set[str]) -> None:
    """Refuse a session that needs the lens cap put on by hand when no one can be asked."""
    if is_simulated(config.camera.port) or _stdin_is_terminal():
        return  # a simulated camera caps its own lens; a terminal gets the prompt
    pending = [e for e in sweep.expand(config) if e.kind == "dark" and e.event_id not in stored]
    if pending:
        raise UsageError(f"darks need an operator: {len(pending)} dark(s) to take on a real camera "
                         "need the lens cap put on by hand, and stdin is not a terminal; run capture "
                         "from a terminal, or use the daemon (POST /sessions/{id}/lens)")


def _ask_lens(capped: bool) -> bool | None:
    """Prompt the operator; True once they pressed Enter, False with no one to answer (end of
    input), None on Ctrl-C."""
    what = "Put the lens cap on" if capped else "Take the lens cap off"
    try:
        console.input(f"[bold yellow]{what}, then press Enter[/] ")
    except EOFError:
        return False
    except KeyboardInterrupt:
        return None
    return True


def _run_engine(engine: Engine, *, virtual: bool) -> int:
    from m2s2hil.engine.state import Progress as ProgressEvent
    from m2s2hil.engine.state import RunState

    listener = engine.listen()
    interrupts = 0
    halted = False
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
                lens = engine.lens_wait  # parked for the operator's lens cap (a real rig's darks)
                if lens is not None:
                    bar.stop()
                    answer = _ask_lens(lens)
                    bar.start()
                    if answer is None:
                        interrupts += 1
                    if not answer:
                        break  # paused and resumable; the resumed run asks again
                    with contextlib.suppress(UsageError):  # e.g. ended meanwhile: seen next round
                        engine.confirm_lens(lens)
                    continue
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
                    halted = True
                    break
        listener.close()
    sid = f"{engine.session_id} --out {shlex.quote(str(engine.store.path.parent))}"  # the resume command
    if engine.rig.config.source_path is not None:
        sid += f" --rig {shlex.quote(str(engine.rig.config.source_path))}"
    if halted:
        _halt(engine, thread)
        console.print(f"stopped; what was stored is kept; resume with: capture --resume {sid}")
        return EXIT_INTERRUPTED
    final = engine.status()
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
    if final.state is RunState.COMPLETED_WITH_GAPS:
        console.print(f"completed with gaps: {final.skipped} planned event(s) skipped (reasons in the "
                      f"journal); retry them with: capture --resume {sid}")
        return EXIT_GAPS
    if final.state is RunState.ABORTED:
        return EXIT_ABORTED
    return EXIT_FAILED


def _halt(engine: Engine, thread: threading.Thread) -> None:
    """A second Ctrl-C: the rig safe now, not at the next boundary; the run asked to abort and
    given :data:`HALT_GRACE_S` to end by itself (then this process ends without it)."""
    console.print("[red]Ctrl-C again: stopping now (lamps off, motion stopped)[/]")
    with contextlib.suppress(UsageError):
        engine.abort()
    errors = engine.rig.safe()  # beside the run's thread: a move in hand is not waited out
    thread.join(HALT_GRACE_S)
    errors += engine.rig.safe()  # again: the run's thread may have been between two commands
    if errors:
        last = "; ".join(f"{type(e).__name__}: {e}" for e in errors[-3:])
        console.print(f"[red]rig NOT confirmed safe: {last} - check it[/]")
    else:
        console.print("rig safe: lamps off, motion stopped")


def _summary(s: EngineStatus, engine: Engine) -> None:
    t = Table(title=f"session {s.session_id}: {s.state.value}")
    t.add_column("item")
    t.add_column("value", justify="right")
    t.add_row("events stored", f"{s.done} / {s.total}")
    t.add_row("skipped (recorded with reasons)", str(s.skipped))
    t.add_row("faults", str(s.fault_count))
    t.add_row("duration (engine clock)", f"{s.elapsed_s:.1f} s")
    if s.efficiency is not None:
        t.add_row("efficiency vs lower bound", f"{s.efficiency:.3f}")
    t.add_row("folder", str(engine.store.path))
    safe = engine.rig_safe  # the rig's outcome, apart from the data's
    if safe is not None:
        t.add_row("rig at the end", "safe (lamps off, motion stopped)" if safe else "NOT SAFE: check it")
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
    bracket: list[str] = typer.Option(
        [], "--bracket", help="extra exposures of each pose, as multiples: 16, 4,16 or dir=16 (repeatable)"),
    realtime: bool = typer.Option(False, "--realtime", help="simulated rig in real time, not virtual"),
    twin_checks: bool = typer.Option(
        False, "--twin-checks", help="check frames against the digital twin (wrong build, lamp out, ...)"),
    allow_rig_change: bool = typer.Option(
        False, "--allow-rig-change", help="with --resume: continue although the rig file changed"),
) -> None:
    """Capture one satellite build under the chosen lighting conditions."""
    from m2s2hil.store.catalogue import default_data_root

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
        lights = parse_lights(light)
        sweep = build_sweep(
            sat=sat, build=build, lights=lights, tilts=tilt or None, mode=mode,
            method=method, exposure=exposure, azimuth_step=azimuth_step,
            frames_per_pose=frames_per_pose, config=config, bracket=parse_bracket(bracket, lights),
        )
        check_demosaic_method(sweep.processing)
        if dry_run:
            _print_plan(sweep, config)
            raise typer.Exit(EXIT_OK)
    elif dry_run or sat or build or light or bracket:
        raise UsageError(
            "--resume takes the plan from the session: drop --sat/--build/--light/--bracket/--dry-run")

    from m2s2hil.analysis.qc import capture_qc_hook
    from m2s2hil.engine.build import build_run, open_capture_rig
    from m2s2hil.engine.state import RunState

    if resume is not None:  # a missing or damaged session is refused before any device moves
        from m2s2hil.store.session import SessionStore

        stored = SessionStore.open(root, resume)
        try:
            sweep, done = stored.sweep, stored.completed_event_ids()
        finally:
            stored.close()
        _check_operator(config, sweep, done)
    else:
        _check_operator(config, sweep, set())
    opened = open_capture_rig(config, realtime=realtime, source=str(rig) if rig is not None else None)
    stuck = False  # halted by a second Ctrl-C while its thread is still inside a device call
    try:
        if resume is not None:
            engine = build_run(opened, root, resume=resume, allow_rig_change=allow_rig_change,
                               qc=capture_qc_hook(twin=twin_checks))
            n_done = len(engine.store.completed_event_ids())
            console.print(f"resuming {resume}: {n_done} events already stored")
        else:
            engine = build_run(opened, root, sweep=sweep, qc=capture_qc_hook(twin=twin_checks))
            console.print(f"session {engine.session_id} in {engine.store.path}")
        code = _run_engine(engine, virtual=opened.simulated and not realtime)  # open_rig's clock rule
        stuck = engine.alive and engine.state is RunState.ABORTING
        if not stuck:  # ended or parked: the session's owner lock goes with the command
            engine.store.close()
    finally:
        opened.safe()
        if not stuck:  # else that call holds its device: closing would wait for it; the exit frees it
            opened.close()
    raise typer.Exit(code)
