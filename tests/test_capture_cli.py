"""The operator CLI as a user runs it: `capture ...` through its real entry point, in-process
(``cli_support.run_cli``: exit code and output as a user sees them), and one whole capture in a
subprocess, where a fresh interpreter is the point (the ``sim://`` ports registered by the
command itself, not by the test process)."""

from __future__ import annotations

import subprocess
import sys
import tomllib
from importlib import resources
from pathlib import Path

import pytest
from cli_support import CliResult, run_cli

from m2s2hil.cli import capture_main
from m2s2hil.config import load_rig
from m2s2hil.rig.open_errors import EXIT_UNREACHABLE
from m2s2hil.store.catalogue import list_sessions
from m2s2hil.store.session import SessionStore


def small_rig(tmp_path: Path) -> Path:
    text = resources.files("m2s2hil").joinpath("data/default_rig.toml").read_text()
    text = text.replace("width = 2048", "width = 256").replace("height = 2048", "height = 256")
    assert "width = 256" in text
    p = tmp_path / "small_rig.toml"
    p.write_text(text)
    tomllib.loads(p.read_text())
    return p


def capture(*args: str) -> CliResult:
    """``capture ARGS...`` in-process."""
    return run_cli(*args, entry=capture_main, prog="capture")


def capture_process(*args: str, timeout: float = 180) -> subprocess.CompletedProcess:
    """``capture ARGS...`` in a new interpreter."""
    code = "import sys; from m2s2hil.cli import capture_main; sys.argv[0] = 'capture'; capture_main()"
    cmd = [sys.executable, "-c", code, *args]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)


@pytest.mark.parametrize(
    ("args", "needle"),
    [
        (["--sat", "hubbel", "--build", "B2", "--light", "weak"], "unknown satellite 'hubbel'"),
        (["--sat", "hubble", "--build", "B4", "--light", "weak"], "unknown build of Hubble 'B4'"),
        (["--sat", "hubble", "--build", "B2", "--light", "dim"], "unknown lighting condition 'dim'"),
        (["--sat", "hubble", "--build", "B2", "--light", "weak", "--tilt", "E9"], "unknown elevation 'E9'"),
        (["--sat", "hubble", "--build", "B2"], "--light are required"),
        (["--sat", "hubble", "--build", "B2", "--light", "weak", "--mode", "spin"], "--mode must be"),
        (["--sat", "hubble", "--build", "B2", "--light", "weak", "--method", "magic"],
         "unknown demosaicing method 'magic'"),
    ],
)
def test_bad_input_exit_2(args, needle):
    res = capture(*args, "--dry-run")
    assert res.exit_code == 2, res.output
    assert needle in res.stderr


def test_malformed_rig_file_exit_2(tmp_path):
    bad = tmp_path / "rig.toml"
    bad.write_text("[axes.turntable]\ndevice = 'stage'\n")
    res = capture("--sat", "hubble", "--build", "B2", "--light", "weak", "--rig", str(bad), "--dry-run")
    assert res.exit_code == 2, res.output
    assert str(bad) in res.stderr


def test_dry_run_prints_plan_and_estimate():
    res = capture("--sat", "hubble", "--build", "B2", "--light", "all", "--dry-run")
    assert res.exit_code == 0, res.output
    assert "324" in res.stdout  # 36 azimuths x 3 tilts x 3 lights
    assert "lower bound" in res.stdout
    assert "built-in simulated rig" in res.stderr


@pytest.mark.slow  # a whole capture in a new interpreter: ~5 s
def test_capture_runs_a_complete_checksummed_session(tmp_path):
    rig = small_rig(tmp_path)
    out = tmp_path / "data"
    res = capture_process(
        "--sat", "voyager", "--build", "B2", "--light", "weak,directional", "--tilt", "E1",
        "--azimuth-step", "90", "--rig", str(rig), "--out", str(out),
    )
    assert res.returncode == 0, res.stderr[-2000:]
    (info,) = list_sessions(out)
    assert info.state == "completed"
    store = SessionStore.open(out, info.session_id)
    try:
        assert store.verify() == []
        frames = store.frames()
        assert len(frames) == 2 * 4
        # Every frame says under which lighting it was taken (and which lamps were on).
        lamps = load_rig(rig).lighting  # the lamps the rig file puts in each condition
        for f in frames:
            lighting = f.meta["event"]["lighting"]
            assert lighting == f.event_id.split("/")[0]
            assert sorted(f.meta["lamp_names"]) == sorted(lamps[lighting])
        assert {f.meta["event"]["lighting"] for f in frames} == {"weak", "directional"}
        # The same builder as the daemon's: capture-time QC on every frame and in the summary.
        assert all(isinstance(f.meta.get("qc"), dict) and "score" in f.meta["qc"] for f in frames)
        finished = [e["payload"] for e in store.events() if e["kind"] == "run_finished"]
        assert finished[-1]["qc"]["frames"] == len(frames)
    finally:
        store.close()


def test_a_session_the_engine_pauses_itself_ends_the_command_with_exit_3(tmp_path):
    """E.g. a full disk: the engine parks the rig; `capture` must exit (3), not wait forever."""
    import threading

    from engine_helpers import assert_rig_safe, session

    from m2s2hil.commands.capture import EXIT_PAUSED, _run_engine
    from m2s2hil.engine.fault_policy import FaultPolicy

    policy = FaultPolicy.model_validate({"timeout": {"action": "suspend"}})
    lost = {"toucan": [{"kind": "frame_timeout", "after": 1}]}
    with session(tmp_path, faults=lost, policy=policy) as (rig, store, engine, _events):
        result: list[int] = []
        def run() -> None:
            result.append(_run_engine(engine, virtual=True))

        runner = threading.Thread(target=run, daemon=True)
        runner.start()
        runner.join(timeout=60)
        assert not runner.is_alive(), "capture kept waiting on a paused session"
        assert result == [EXIT_PAUSED]
        assert store.state == "paused"
        assert_rig_safe(rig)


def test_a_rig_that_cannot_be_opened_is_one_line_not_a_traceback(tmp_path):
    text = resources.files("m2s2hil").joinpath("data/default_rig.toml").read_text()
    rig = tmp_path / "rig.toml"
    rig.write_text(text.replace('port = "sim://stage"', f'port = "{tmp_path}/no-such-tty"'))
    assert "no-such-tty" in rig.read_text()
    res = capture("--sat", "voyager", "--build", "B2", "--light", "weak", "--rig", str(rig),
                  "--out", str(tmp_path / "data"))
    assert res.exit_code == EXIT_UNREACHABLE, res.output[-2000:]
    (line,) = res.stderr.strip().splitlines()[-1:]
    assert line.startswith("error: cannot open stage") and "no-such-tty" in line and "missing port" in line
    assert "Traceback" not in res.stderr
    assert list_sessions(tmp_path / "data") == []  # nothing was created before the rig opened
