"""``m2s2hil compile-kernels`` (m2s2hil/warmup.py): every method's real path, once, on a tiny frame."""

from __future__ import annotations

from typer.testing import CliRunner

from m2s2hil.cli import app
from m2s2hil.config import DEMOSAIC_METHODS
from m2s2hil.warmup import compile_kernels


def test_every_method_and_the_simulated_camera_are_compiled() -> None:
    steps: list[str] = []
    total = compile_kernels(progress=lambda name, s: steps.append(name))
    assert steps == [f"demosaic {m}" for m in DEMOSAIC_METHODS] + ["simulated camera"]
    assert total > 0


def test_the_command_reports_each_step() -> None:
    result = CliRunner().invoke(app, ["compile-kernels"])
    assert result.exit_code == 0, result.output
    assert "demosaic ppid:" in result.output and "kernels ready in" in result.output
