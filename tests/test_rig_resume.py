"""Resume survives what does not change the data: port paths are not part of the rig's fingerprint;
geometry, devices, the camera model and its calibration are. A real change needs
``--allow-rig-change``, and the error says so; the printed resume command carries --out and --rig."""

from __future__ import annotations

import threading
from pathlib import Path

import numpy as np
import pytest
from engine_helpers import session, small_sweep
from rig_files import rig_text

from m2s2hil.config import load_rig
from m2s2hil.engine.build import RigChanged, build_run
from m2s2hil.rig.factory import open_simulated_rig


def _fresh(config, **update):
    """A new configuration (``model_copy`` would carry the digest already computed along)."""
    return type(config).model_validate({**config.model_dump(), **update})


def _with(config, **devices_ports):
    devices = {n: d.model_copy(update={"port": devices_ports.get(n, d.port)})
               for n, d in config.devices.items()}
    return _fresh(config, devices=devices)


def test_ports_are_not_part_of_the_fingerprint(tmp_path):
    path = tmp_path / "rig.toml"
    path.write_text(rig_text(homing="switches"))
    config = load_rig(path)
    moved = _with(config, stage="/dev/pts/7", relays="/dev/ttyUSB3")
    camera = config.camera.model_copy(update={"port": "usb://"})
    assert moved.digest == config.digest
    assert _fresh(config, camera=camera).digest == config.digest
    # What does change the data changes the fingerprint.
    axes = dict(config.axes)
    axes["turntable"] = axes["turntable"].model_copy(update={"units_per_degree": 2.0})
    assert _fresh(config, axes=axes).digest != config.digest
    devices = dict(config.devices)
    devices["relays"] = devices["relays"].model_copy(update={"unit": 2})
    assert _fresh(config, devices=devices).digest != config.digest
    model = config.camera.model.model_copy(update={"bit_depth": 12})
    changed_cam = config.camera.model_copy(update={"model": model})
    assert _fresh(config, camera=changed_cam).digest != config.digest


def test_calibration_counts_by_content_not_by_where_it_lies(tmp_path):
    from m2s2hil.processing.calibration import CameraCalibration, save_calibration

    def rig_in(folder: Path, mix: np.ndarray) -> str:
        folder.mkdir()
        config = load_rig(None)
        save_calibration(folder / "cal.json", CameraCalibration(crosstalk=mix),
                         bands_nm=list(config.camera.model.bands_nm))
        text = rig_text(homing="switches").replace('port = "sim://toucan"',
                                                  'port = "sim://toucan"\ncalibration_file = "cal.json"')
        (folder / "rig.toml").write_text(text)
        return load_rig(folder / "rig.toml").digest

    mix = np.eye(10) + 0.01
    assert rig_in(tmp_path / "a", mix) == rig_in(tmp_path / "b", mix)
    assert rig_in(tmp_path / "c", mix) != rig_in(tmp_path / "d", np.eye(10) + 0.02)


def test_a_changed_rig_needs_allow_rig_change_and_the_error_says_so(tmp_path):
    root = tmp_path / "data"
    config = load_rig(None)
    rig = open_simulated_rig(config)
    try:
        engine = build_run(rig, root, sweep=small_sweep())
        sid = engine.session_id
        engine.store.close()
    finally:
        rig.close()
    axes = dict(config.axes)
    axes["tilt"] = axes["tilt"].model_copy(update={"settle_s": 0.5})
    changed = _fresh(config, axes=axes)
    rig = open_simulated_rig(changed)
    try:
        with pytest.raises(RigChanged) as info:
            build_run(rig, root, resume=sid)
        assert f"capture --resume {sid} --allow-rig-change" in str(info.value)
        engine = build_run(rig, root, resume=sid, allow_rig_change=True)
        assert engine.session_id == sid
        engine.store.close()
    finally:
        rig.close()


def test_the_printed_resume_command_carries_out_and_rig(tmp_path, capsys, monkeypatch):
    import shlex

    from m2s2hil.commands import capture as capture_cmd
    from m2s2hil.commands.capture import EXIT_PAUSED, _run_engine

    monkeypatch.setattr(capture_cmd.console, "width", 1000)  # one line, as in a wide terminal
    from m2s2hil.engine.fault_policy import FaultPolicy

    path = tmp_path / "my rig.toml"
    path.write_text(rig_text(homing="switches"))
    config = load_rig(path)
    policy = FaultPolicy.model_validate({"timeout": {"action": "suspend"}})
    lost = {"toucan": [{"kind": "frame_timeout", "after": 1}]}
    with session(tmp_path, config=config, faults=lost, policy=policy) as (_rig, store, engine, _events):
        result: list[int] = []
        runner = threading.Thread(target=lambda: result.append(_run_engine(engine, virtual=True)),
                                  daemon=True)
        runner.start()
        runner.join(timeout=60)
        assert result == [EXIT_PAUSED]
    err = capsys.readouterr().err
    hint = next(ln for ln in err.splitlines() if "resume with:" in ln)
    assert f"--resume {store.session_id}" in hint
    # Quoted for the shell: this rig file's name has a space.
    assert f"--out {shlex.quote(str(store.path.parent))}" in hint
    assert f"--rig {shlex.quote(str(path))}" in hint
