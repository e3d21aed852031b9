"""Exposure over time: the stage's recent path, the mid-exposure pose, and motion blur in the frames."""

from __future__ import annotations

import itertools
import math

import cv2
import numpy as np
import pytest
from m2s2hil.simulators.frames import SimFrameSource
from m2s2hil.simulators.grbl import GrblSimulator
from m2s2hil.simulators.grbl_settings import GrblAxisSettings
from m2s2hil.simulators.snapshot import superpixel
from m2s2hil.simulators.world import LampInfo, World
from m2s2hil.simulators.zaber import ZaberAxisSettings, ZaberSimulator

from m2s2hil.catalog import load_catalog
from m2s2hil.config import CameraModel

N = 512
MODEL = CameraModel(width=N, height=N)
LAMPS = {i: LampInfo(f"bar{i + 1}", "led_bar", 1.0) for i in range(5)}
T_MID = 10.0  # clock time of mid-exposure in the frame-source tests
EXPOSURE = 0.02


def materials(sat: str, build: str) -> tuple[str, ...]:
    return load_catalog().build(sat, build).materials


# -- the recent path of the motion simulators ------------------------------------------------
def test_grbl_answers_for_moments_already_past(vclock) -> None:
    sim = GrblSimulator("g", vclock, axes={"X": GrblAxisSettings(max_rate=600.0, accel=100.0)},
                        settings={22: 0})
    sim.receive(b"G1 X8 F600\n")
    live: list[tuple[float, float]] = []
    for _ in range(30):  # 0.6 s of a ~0.9 s move, sampled as it happens
        vclock.advance(0.02)
        live.append((vclock.monotonic(), sim.axis_position("X")))
    sim.receive(b"!")  # feed hold: a braking segment replaces the move
    for _ in range(10):
        vclock.advance(0.02)
        live.append((vclock.monotonic(), sim.axis_position("X")))
    sim.receive(b"~")  # resume towards X8
    for _ in range(60):
        vclock.advance(0.02)
        live.append((vclock.monotonic(), sim.axis_position("X")))
    assert sim.state == "Idle" and live[-1][1] == pytest.approx(8.0)
    assert len({round(p, 6) for _, p in live}) >= 40  # it moved while sampled
    vclock.advance(3.0)
    for t, pos in live:
        assert sim.axis_position("X", at=t) == pytest.approx(pos, abs=1e-9)
    assert sim.axis_position("X", at=vclock.monotonic()) == sim.axis_position("X")


def test_zaber_answers_for_moments_already_past(vclock) -> None:
    sim = ZaberSimulator("z", vclock, address=1, axes=[ZaberAxisSettings(maxspeed=1638, accel=1, start=500)])
    sim.receive(b"/1 1 move abs 1200\n")
    live: list[tuple[float, float]] = []
    for _ in range(25):
        vclock.advance(0.02)
        live.append((vclock.monotonic(), sim.axis_position(1)))
    sim.receive(b"/1 1 stop\n")  # decelerates from here
    for _ in range(20):
        vclock.advance(0.02)
        live.append((vclock.monotonic(), sim.axis_position(1)))
    assert live[-1][1] == live[-2][1] and live[-1][1] > live[0][1] + 100
    vclock.advance(2.0)
    for t, pos in live:
        assert sim.axis_position(1, at=t) == pytest.approx(pos, abs=1e-9)


def test_world_pose_at_asks_timed_axes_and_keeps_the_zero_argument_form(vclock) -> None:
    world = World(vclock)
    asked: list[float] = []

    def turntable(t: float) -> float:
        asked.append(t)
        return 2.0 * t

    world.attach_axis("turntable", turntable, timed=True)
    world.attach_axis("tilt", lambda: 7.0)  # knows only "now"
    vclock.advance(3.0)
    past = world.pose_at(1.25)
    assert (past.azimuth_deg, past.tilt_deg) == (2.5, 7.0) and asked == [1.25]
    now = world.pose()
    assert (now.azimuth_deg, now.tilt_deg) == (6.0, 7.0) and asked[-1] == 3.0


# -- frames ------------------------------------------------------------------------------------
def world_turning(vclock, omega_dps: float, az_mid: float = 30.0) -> World:
    """Turntable at ``az_mid + ω (t - T_MID)``, tilt 0, three LED bars on and warm."""
    world = World(vclock, lamp_info=LAMPS)
    world.attach_axis("turntable", lambda t: az_mid + omega_dps * (t - T_MID), timed=True)
    world.attach_axis("tilt", lambda t: 0.0, timed=True)
    for ch in (0, 1, 2):
        world.set_lamp(ch, True)
    vclock.advance(T_MID + 1.0)  # the frame is rendered after its exposure, as the camera does
    return world


def capture_turning(vclock, omega_dps: float, *, seed: int = 3) -> tuple[np.ndarray, object, SimFrameSource]:
    src = SimFrameSource(world_turning(vclock, omega_dps), MODEL, materials, seed=seed)
    frame = src.capture(EXPOSURE, 1.0, start_s=T_MID - EXPOSURE / 2)
    return frame, src.truth(), src


def gradient_energy(frame: np.ndarray, mask: np.ndarray, band: int) -> tuple[float, float]:
    """(Σ gx², Σ gy²) of one band of the super-pixel cube over ``mask`` (Sobel 3×3)."""
    img = superpixel(frame.astype(np.float32), MODEL.layout)[band]
    gx = cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=3)
    return float(np.sum(gx[mask] ** 2)), float(np.sum(gy[mask] ** 2))


def cell_mask(labels: np.ndarray) -> np.ndarray:
    n = len(MODEL.layout)
    cells = labels.reshape(N // n, n, N // n, n).max(axis=(1, 3)) > 0
    return cv2.dilate(cells.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0


def test_sub_exposures_follow_the_motion_odd_and_capped(vclock) -> None:
    src = SimFrameSource(world_turning(vclock, 0.0), MODEL, materials)
    assert src.rim_px == pytest.approx(0.45 * N)  # the default fill of the frame
    got = [src.sub_exposures(px) for px in (0.0, 0.5, 0.51, 2.5, 4.0, 7.2, 14.9, 40.0)]
    assert got == [1, 1, 3, 3, 5, 9, 15, 15]
    capped = SimFrameSource(world_turning(vclock, 0.0), MODEL, materials, max_sub_exposures=8)
    assert capped.sub_exposures(40.0) == 7
    with pytest.raises(ValueError, match="blur threshold"):
        SimFrameSource(world_turning(vclock, 0.0), MODEL, materials, blur_threshold_px=0.0)


def test_a_frame_at_rest_is_unchanged(vclock) -> None:
    world = world_turning(vclock, 0.0)
    old = SimFrameSource(world, MODEL, materials, seed=5)
    new = SimFrameSource(world, MODEL, materials, seed=5)
    before = old.capture(EXPOSURE, 1.0)  # the pose at the call
    after = new.capture(EXPOSURE, 1.0, start_s=T_MID - EXPOSURE / 2)
    assert np.array_equal(before, after)
    t_old, t_new = old.truth(), new.truth()
    assert np.array_equal(t_old.labels, t_new.labels) and np.array_equal(t_old.signal(), t_new.signal())
    assert (t_new.sub_exposures, t_new.motion_px, t_new.exposure_start_s) == (1, 0.0, T_MID - EXPOSURE / 2)
    assert t_old.exposure_start_s is None


def test_frames_taken_while_turning_are_blurred_more_the_faster_it_turns(vclock) -> None:
    speeds = (0.0, 30.0, 60.0, 120.0)  # at 512² the rim moves 0, 2.4, 4.8, 9.6 px in 20 ms
    shots = {w: capture_turning(vclock, w) for w in speeds}
    still, truth0, _ = shots[0.0]
    mask = cell_mask(truth0.labels)
    cube = superpixel(still.astype(np.float32), MODEL.layout)
    band = int(np.argmax([cube[b][mask].mean() for b in range(cube.shape[0])]))
    ex0, ey0 = gradient_energy(still, mask, band)
    ratios = []
    for w in speeds[1:]:
        frame, truth, src = shots[w]
        assert truth.sub_exposures > 1 and truth.sub_exposures % 2 == 1
        assert truth.motion_px == pytest.approx(src.rim_px * math.radians(w * EXPOSURE), rel=1e-6)
        ex, ey = gradient_energy(frame, mask, band)
        ratios.append((ex + ey) / (ex0 + ey0))
    assert ratios[0] < 0.999 and ratios[-1] < 0.98
    assert all(a > b for a, b in itertools.pairwise(ratios))  # blurrier with ω


def test_the_truth_is_the_mid_exposure_pose(vclock) -> None:
    omega = 120.0
    frame, truth, _ = capture_turning(vclock, omega)
    assert truth.azimuth_deg == pytest.approx(30.0, abs=1e-9) and truth.tilt_deg == 0.0
    assert truth.exposure_start_s == pytest.approx(T_MID - EXPOSURE / 2)
    # The labels are those of a stop-and-go frame at the mid-exposure pose ...
    _, still, _ = capture_turning(vclock, 0.0)
    assert np.array_equal(truth.labels, still.labels)
    # ... while the signal is what the sensor integrated: spread along the motion, light conserved.
    moving, resting = truth.signal(), still.signal()
    assert not np.allclose(moving, resting)
    assert moving.sum() == pytest.approx(resting.sum(), rel=0.02)
    assert frame.shape == (N, N)


def test_the_camera_exposes_over_its_exposure_interval(tmp_path) -> None:
    """Through the simulated rig: the camera tells the source when the exposure started and the
    frame shows the turntable where it was at mid-exposure, blurred by its turning."""
    from engine_helpers import small_rig_config

    from m2s2hil.rig.factory import open_simulated_rig

    rig = open_simulated_rig(small_rig_config(256))
    try:
        rig.mount("voyager", "B3")
        rig.lights.set(rig.config.lamp_channels("strong"))
        exposure = 0.05
        rig.camera.configure(exposure_s=exposure, gain=1.0)
        rig.turntable.move_to(0.0)
        rig.turntable.rotate(60.0, direction=1)
        rig.clock.sleep(1.0)  # past the run-up: turning at 60 °/s
        before = rig.clock.monotonic()
        frame = rig.camera.snap(timeout=5)
        after = rig.clock.monotonic()
        truth = rig.frame_source.truth()
        az_now = rig.turntable.position()
        rig.turntable.stop()
        start = truth.exposure_start_s
        assert start is not None and before <= start <= after - exposure
        mid = rig.world.pose_at(start + exposure / 2)
        assert truth.azimuth_deg == pytest.approx(mid.azimuth_deg, abs=1e-9)
        # mid-exposure lies at least half an exposure before the frame arrived
        assert az_now - truth.azimuth_deg >= 60.0 * exposure / 2 - 1e-6
        assert truth.sub_exposures > 1 and truth.motion_px == pytest.approx(
            rig.frame_source.rim_px * math.radians(60.0 * exposure), rel=1e-3)
        assert frame.data.shape == (256, 256)
    finally:
        rig.close()
