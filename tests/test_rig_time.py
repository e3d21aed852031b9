"""Overlapped stop-and-go on the simulated rig: the stage leaves for the next pose during the
readout, nothing is lost, every frame keeps its own pose, and the run reports its floor."""

from __future__ import annotations

import pytest
from engine_helpers import session, small_sweep

from m2s2hil.engine.state import RunState


def _run(tmp_path, overlap: bool) -> tuple[float, list, dict, object]:
    sweep = small_sweep(azimuth_step_deg=120, dark={"frames": 1})  # 3 azimuths, one condition: 2 moves
    with session(tmp_path / str(overlap), sweep, overlap=overlap) as s:
        st = s.engine.run()
        assert st.state is RunState.COMPLETED and st.done == st.total
        (fin,) = [e["payload"] for e in s.store.events() if e["kind"] == "run_finished"]
        return st.elapsed_s, s.store.frames(), fin, s.rig.config


@pytest.mark.slow  # two small sessions, ~2 s
def test_overlap_saves_the_readouts_and_keeps_every_frame_at_its_pose(tmp_path) -> None:
    plain_s, plain_frames, _, _ = _run(tmp_path, overlap=False)
    over_s, frames, fin, cfg = _run(tmp_path, overlap=True)
    assert sorted(f.event_id for f in frames) == sorted(f.event_id for f in plain_frames)
    readout = 1 / cfg.camera.model.max_fps
    # each of the 2 moves hides the readout of the frame before it (the last frame's is not hidden)
    assert plain_s - over_s >= 1.5 * readout
    tol = cfg.axes["turntable"].tolerance_deg
    for f in frames:
        # the pose recorded is the one read back before the exposure, and the frame shows it
        assert abs(f.meta["pose"]["turntable_deg"] - f.meta["event"]["azimuth_deg"]) <= tol
        assert abs(f.meta["truth"]["azimuth_deg"] - f.meta["pose"]["turntable_deg"]) <= tol
    assert 0 < fin["physical_floor_s"] <= fin["lower_bound_s"] <= fin["duration_s"]
    assert fin["efficiency"] <= 1.0
