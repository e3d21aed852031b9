"""Run the real ``m2s2hil`` (or ``capture``) command line in-process, as a user would.

The entry points turn our typed errors into one line on stderr and an exit code; these
helpers go through them (not through a Typer app built for the test), so a test sees the
exit code and the output a user sees, without a subprocess per call.
"""

from __future__ import annotations

import contextlib
import io
import sys
from collections.abc import Callable
from dataclasses import dataclass


@dataclass(frozen=True)
class CliResult:
    exit_code: int
    stdout: str
    stderr: str

    @property
    def output(self) -> str:
        return self.stdout + self.stderr


def run_cli(*args: object, entry: Callable[[], None] | None = None, prog: str = "m2s2hil") -> CliResult:
    """``m2s2hil ARGS...`` (or ``entry``, e.g. ``m2s2hil.cli.capture_main``): exit code and output."""
    from m2s2hil.cli import main

    out, err = io.StringIO(), io.StringIO()
    argv = sys.argv
    sys.argv = [prog, *map(str, args)]
    code = 0
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                (entry or main)()
            except SystemExit as exc:
                code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
    finally:
        sys.argv = argv
    return CliResult(code, out.getvalue(), err.getvalue())
