"""The one-way imports of docs/architecture.md, checked with import-linter.

The contracts live in pyproject.toml (``[tool.importlinter]``). import-linter finds a package
by its folder, and three of ours install under ``m2s2hil`` from outer folders (setuptools'
package-dir mapping), so the check runs on a copy of the sources laid out as installed.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PYPROJECT = ROOT / "pyproject.toml"


def _installed_layout(dest: Path) -> Path:
    """Copy every package folder to where its import name puts it: ``dest/m2s2hil/...``."""
    mapping = tomllib.loads(PYPROJECT.read_text())["tool"]["setuptools"]["package-dir"]
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc", "data", "console")
    for name, folder in sorted(mapping.items(), key=lambda kv: kv[0].count(".")):
        target = dest.joinpath(*name.split("."))
        shutil.copytree(ROOT / folder, target, ignore=ignore, dirs_exist_ok=True)
    return dest


def _lint(tree: Path) -> subprocess.CompletedProcess:
    code = "import sys; from importlinter.cli import lint_imports_command; sys.exit(lint_imports_command())"
    return subprocess.run(
        [sys.executable, "-c", code, str(PYPROJECT), "--no-cache"],
        cwd=tree, env={"PYTHONPATH": str(tree), "PATH": "/usr/bin:/bin"},
        capture_output=True, text=True, timeout=120,
    )


def test_contracts_are_kept(tmp_path):
    res = _lint(_installed_layout(tmp_path))
    assert res.returncode == 0, res.stdout + res.stderr
    assert "0 broken" in res.stdout


def test_a_protocol_importing_a_driver_breaks_them(tmp_path):
    tree = _installed_layout(tmp_path)
    (tree / "m2s2hil" / "protocols" / "_upwards.py").write_text("from m2s2hil.drivers import errors\n")
    (tree / "m2s2hil" / "simulators" / "_into_app.py").write_text("import m2s2hil.config\n")
    res = _lint(tree)
    assert res.returncode == 1, res.stdout + res.stderr
    assert "m2s2hil.protocols._upwards -> m2s2hil.drivers.errors" in res.stdout
    assert "m2s2hil.simulators._into_app -> m2s2hil.config" in res.stdout
