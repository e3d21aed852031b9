"""The umbrella command's basics, run as a user would: in a subprocess."""

import subprocess
import sys
from pathlib import Path

import m2s2hil.drivers
import m2s2hil.protocols
import m2s2hil.simulators

ROOT = Path(__file__).resolve().parents[1]


def run(*args: str) -> subprocess.CompletedProcess:
    code = "import sys; from m2s2hil.cli import main; sys.argv[0] = 'm2s2hil'; main()"
    return subprocess.run(
        [sys.executable, "-c", code, *args], capture_output=True, text=True, timeout=60
    )


def test_namespace_mapping_points_at_the_folders():
    assert Path(m2s2hil.drivers.__file__).parent == ROOT / "drivers"
    assert Path(m2s2hil.protocols.__file__).parent == ROOT / "protocols"
    assert Path(m2s2hil.simulators.__file__).parent == ROOT / "simulators"


def test_rig_check_builtin():
    res = run("rig", "check")
    assert res.returncode == 0, res.stderr
    assert "built-in simulated rig" in res.stdout


def test_rig_check_bad_file_exit_2(tmp_path):
    bad = tmp_path / "rig.toml"
    bad.write_text('[devices.stage]\nprotocol = "grbl"\nport = "sim://stage"\nbaudrate = -5\n')
    res = run("rig", "check", str(bad))
    assert res.returncode == 2
    assert str(bad) in res.stderr
    assert "devices.stage.baudrate" in res.stderr


def test_unknown_command_exit_2():
    res = run("no-such-command")
    assert res.returncode == 2


def test_dockerfile_lints_clean():
    import shutil

    hadolint = shutil.which("hadolint") or str(Path(sys.executable).parent / "hadolint")
    res = subprocess.run([hadolint, str(ROOT / "Dockerfile")], capture_output=True, text=True)
    assert res.returncode == 0, res.stdout + res.stderr


def test_every_package_folder_is_listed_in_pyproject():
    """A subpackage missing from [tool.setuptools] packages works editable but not installed."""
    import tomllib

    cfg = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    listed = set(cfg["packages"])
    mapping = cfg["package-dir"]
    found = set()
    for name, folder in mapping.items():
        base = ROOT / folder
        for init in base.rglob("__init__.py"):
            rel = init.parent.relative_to(base)
            if "__pycache__" in rel.parts:
                continue
            found.add(".".join([name, *rel.parts]) if rel.parts else name)
    assert found - listed == set()
    assert listed - found == set()
