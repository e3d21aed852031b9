"""Command-line entry points: ``m2s2hil`` (umbrella) and ``capture`` (operator).

Subcommand groups live in ``m2s2hil/commands/``, one module each.
"""

from __future__ import annotations

import typer

from m2s2hil.commands.running import run_app

app = typer.Typer(
    name="m2s2hil",
    help="Hardware-in-the-loop capture of multispectral satellite-mockup datasets (M2S2).",
    no_args_is_help=True,
    pretty_exceptions_enable=False,
)


def _register() -> None:
    from m2s2hil.commands import bench, evaluate, export, importer, rig, serve, sessions, sim, sim_serve

    sim.app.command("serve")(sim_serve.serve)
    from m2s2hil.commands import rig_commission  # rig probe, rig origin (commissioning)

    rig.app.command("probe")(rig_commission.probe)
    rig.app.command("origin")(rig_commission.origin)
    app.add_typer(sim.app, name="sim")
    app.add_typer(rig.app, name="rig")
    app.add_typer(sessions.app, name="sessions")
    app.add_typer(bench.app, name="bench")
    app.command("export")(export.export_cmd)
    app.command("import")(importer.import_cmd)
    app.command("evaluate")(evaluate.evaluate_cmd)
    app.command("report")(evaluate.report_cmd)
    app.command("serve")(serve.serve)
    from m2s2hil.commands import synth  # the synthetic domain (m2s2hil.twin.synth)

    app.command("synth")(synth.synth_cmd)
    from m2s2hil.commands import kernels  # compile-kernels: numba's cache filled ahead of the first frame

    app.command("compile-kernels")(kernels.compile_kernels_cmd)


_register()


def main() -> None:
    run_app(app)


def capture_main() -> None:
    from m2s2hil.commands.capture import app as capture_app

    run_app(capture_app)
