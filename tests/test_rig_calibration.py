"""A camera calibration file named in the rig file reaches the processing of every frame."""

from __future__ import annotations

from importlib import resources

import numpy as np
import pytest

from m2s2hil.config import load_rig
from m2s2hil.engine.runner import Engine
from m2s2hil.errors import UsageError
from m2s2hil.plan import Sweep
from m2s2hil.processing.calibration import CameraCalibration, save_calibration
from m2s2hil.rig.factory import open_rig
from m2s2hil.store.session import SessionStore


def _rig_file(tmp_path, calibration: str) -> str:
    text = resources.files("m2s2hil").joinpath("data/default_rig.toml").read_text()
    text = text.replace("width = 2048", "width = 128").replace("height = 2048", "height = 128")
    text = text.replace('port = "sim://toucan"', f'port = "sim://toucan"\ncalibration_file = "{calibration}"')
    path = tmp_path / "rig" / "rig.toml"
    path.parent.mkdir()
    path.write_text(text)
    return str(path)


def test_calibration_file_is_loaded_relative_to_the_rig_file_and_used(tmp_path):
    mix = np.eye(10) + 0.02 * (np.ones((10, 10)) - np.eye(10))  # 2 % crosstalk between bands
    rig_path = _rig_file(tmp_path, "cam_cal.json")
    save_calibration(tmp_path / "rig" / "cam_cal.json", CameraCalibration(camera_serial="TOUCAN-SIM-0001",
                                                                          crosstalk=mix))
    cfg = load_rig(rig_path)
    assert cfg.camera.calibration_file == tmp_path / "rig" / "cam_cal.json"
    rig = open_rig(cfg)
    try:
        assert rig.calibration is not None
        np.testing.assert_allclose(rig.calibration.crosstalk, mix)
        sweep = Sweep(satellite="hubble", build="B2", lighting=["weak"], tilts=["E1"], azimuth_step_deg=180,
                      dark={"frames": 2})
        store = SessionStore.create(tmp_path / "data", sweep, cfg, clock=rig.clock)
        rig.mount("hubble", "B2")
        Engine(rig, store, sweep).run()
        frames = store.frames()
        assert len(frames) == 2
        for fr in frames:
            assert fr.meta["calibration"]["source"].endswith("cam_cal.json")
        store.close()
    finally:
        rig.safe()
        rig.close()


def test_a_broken_calibration_file_is_a_clear_usage_error(tmp_path):
    rig_path = _rig_file(tmp_path, "missing.json")
    with pytest.raises(UsageError, match="missing.json"):
        open_rig(load_rig(rig_path))
