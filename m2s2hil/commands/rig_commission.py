"""``m2s2hil rig probe`` and ``m2s2hil rig origin``: commissioning a real rig (docs/rig-setup.md).

    m2s2hil rig probe my_rig.toml            # identities and settings against the rig file
    m2s2hil rig probe my_rig.toml --apply    # write the rig file's motion settings (asks first)
    m2s2hil rig origin turntable --rig my_rig.toml   # this is zero (axes without switches)

Exit codes: 0 all agree; 6 a device could not be reached; 7 a device answered but cannot be
used as the rig file says; 8 (probe) a device's settings differ from the rig file.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import typer
from rich.console import Console
from rich.markup import escape
from rich.table import Table

from m2s2hil.config import RigConfig, load_rig
from m2s2hil.rig.devices.findings import ProbeReport
from m2s2hil.rig.probe import EXIT_MISMATCH, probe_rig
from m2s2hil.sim_config import is_simulated

console = Console()


def _simulators(config: RigConfig) -> tuple[Any, dict[str, Any]]:
    """A clock and the in-process simulators of the rig's ``sim://`` devices (none for a real rig)."""
    from m2s2hil.drivers.clock import SYSTEM_CLOCK

    ports = [d.port for d in config.devices.values()] + [config.camera.port]
    if not any(is_simulated(p) for p in ports):
        return SYSTEM_CLOCK, {}
    from m2s2hil.rig.factory import build_simulators

    clock: Any = SYSTEM_CLOCK
    if all(is_simulated(p) for p in ports):
        from m2s2hil.simulators.clock import VirtualClock

        clock = VirtualClock()
    _world, sims, _frames = build_simulators(config, clock)
    return clock, sims


def _show(report: ProbeReport) -> None:
    t = Table(title=f"rig probe: {report.rig}")
    for col in ("device", "item", "rig file", "device reports", "", "what it causes"):
        t.add_column(col, overflow="fold")
    for f in report.findings:
        mark = {True: "[green]ok[/]", False: "[red]MISMATCH[/]", None: ""}[f.ok]
        t.add_row(*(escape(v) for v in (f.device, f.item, f.expected, f.actual)), mark, escape(f.effect))
    console.print(t)
    for err in report.errors:
        console.print(f"[red]error:[/] {escape(str(err))}")


def _exit_code(report: ProbeReport) -> int:
    if report.errors:
        return report.errors[0].exit_code
    return EXIT_MISMATCH if report.mismatches else 0


def probe(
    rig: Path | None = typer.Argument(None, help="rig TOML file (default: built-in simulated rig)"),
    apply: bool = typer.Option(False, "--apply", help="write the rig file's motion settings to the devices"),
    yes: bool = typer.Option(False, "--yes", "-y", help="with --apply: do not ask"),
) -> None:
    """Every device's identity and settings held against the rig file (exit 8 on a mismatch)."""
    config = load_rig(rig)
    clock, sims = _simulators(config)
    report = probe_rig(config, clock=clock, sims=sims)
    _show(report)
    if apply:
        fixes = [f for f in report.mismatches if f.fix is not None]
        if not fixes:
            typer.echo("nothing to write")
        else:
            listing = ", ".join(f"{f.device} {f.fix[0]}={f.fix[1]:g}" for f in fixes if f.fix)
            if yes or typer.confirm(f"write {listing} to the controllers?", default=False):
                report = probe_rig(config, clock=clock, sims=sims, apply=True)
                console.print("written; read back:")
                _show(report)
    code = _exit_code(report)
    typer.echo("ok: every device agrees with the rig file" if code == 0 else
               f"{len(report.mismatches)} mismatch(es), {len(report.errors)} device(s) not reached")
    raise typer.Exit(code)


def origin(
    axis: str = typer.Argument(..., help="turntable or tilt"),
    rig: Path | None = typer.Option(None, "--rig", help="rig TOML file"),
) -> None:
    """Make where AXIS stands its zero (an axis without home switches) and record it."""
    from m2s2hil.rig.origin import set_origin, state_path

    config = load_rig(rig)
    got = set_origin(config, axis)
    typer.echo(f"{axis}: zero set on {got.device} ({got.controller}), axis {got.axis} offset "
               f"{got.offset_units:g} machine units; recorded in {state_path(config)}")
