"""What the operator console's endpoints share: the live stream, the dark library, the calibration
file's path, all made once per application on first use."""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

from fastapi import Depends, HTTPException, Request

from m2s2hil.daemon.errors import Conflict
from m2s2hil.daemon.manager import SessionManager
from m2s2hil.drivers.errors import DeviceError
from m2s2hil.drivers.interfaces import Frame
from m2s2hil.errors import UsageError
from m2s2hil.processing.dark import DarkLibrary
from m2s2hil.rig.live_view import LiveSettings, LiveStream, LiveViewBusy
from m2s2hil.rig.opened import Rig

from ..common import get_manager

_init_lock = threading.Lock()


class LiveCamera:
    """The camera as the live view uses it: streaming (continuous acquisition, the way a live view
    runs on a real camera: no per-frame trigger round trip) while viewers watch, stopped before
    anything else uses the camera. Every method runs with the rig's device lock held (inside
    :meth:`SessionManager.manual_access`, or in the dispatcher just before a session starts)."""

    #: Streaming rate asked of the camera: above what the viewers get on this machine, low
    #: enough that a 2048² stream does not keep two cores busy for frames nobody sees.
    STREAM_FPS = 20.0

    def __init__(self, mg: SessionManager) -> None:
        self.mg = mg
        self.streaming = False
        self.applied: tuple[float, float] | None = None

    def grab(self, settings: LiveSettings) -> Frame:
        try:
            with self.mg.guard.camera_access("live view") as rig:
                wanted = (settings.exposure_s, settings.gain)
                if self.applied != wanted:
                    self.release(rig)
                    rig.camera.configure(exposure_s=settings.exposure_s, gain=settings.gain)
                    self.applied = wanted
                if not self.streaming:
                    rig.camera.start_stream(fps=self.stream_fps(settings))
                    self.streaming = True
                try:
                    return rig.camera.read_frame(timeout=settings.exposure_s + rig.config.camera.timeout_s)
                except DeviceError:
                    # a stalled stream stays stalled (the driver: it needs a restart): the next grab
                    # starts it afresh instead of timing out for ever
                    self.streaming = False
                    raise
        except Conflict as exc:
            raise LiveViewBusy(str(exc)) from None

    def stream_fps(self, settings: LiveSettings) -> float:
        """The rate asked of the camera: :attr:`STREAM_FPS`, or less when the camera or the
        exposure cannot go so fast."""
        return min(self.STREAM_FPS, self.mg.rig.config.camera.model.max_fps, 1.0 / settings.exposure_s)

    def release(self, rig: Rig) -> None:
        """Stop streaming (the caller holds the device lock) so the camera can be used otherwise."""
        if self.streaming:
            self.streaming = False
            self.applied = None  # someone else will configure it
            rig.camera.stop_stream()

    def idle(self) -> None:
        """The last viewer left: stop the stream."""
        if self.streaming:
            try:
                with self.mg.guard.camera_access("live view") as rig:
                    self.release(rig)
            except Conflict:
                self.streaming = False  # a session took the rig (and stopped the stream first)


@dataclass
class Console:
    manager: SessionManager
    live: LiveStream
    darks: DarkLibrary
    calibration_path: Path
    camera: LiveCamera


def calibration_path_for(mg: SessionManager) -> Path:
    """The rig file's calibration file, or ``<data root>/calibration/camera.json`` when it names none."""
    named = mg.rig.config.camera.calibration_file
    return Path(named) if named is not None else mg.root / "calibration" / "camera.json"


async def get_console(request: Request, mg: SessionManager = Depends(get_manager)) -> Console:
    console = getattr(request.app.state, "console", None)
    if console is None:
        with _init_lock:
            console = getattr(request.app.state, "console", None)
            if console is None:
                cam = LiveCamera(mg)
                live = LiveStream(mg.rig.config.camera.model, cam.grab, on_idle=cam.idle)
                console = Console(mg, live, DarkLibrary(mg.root / "darks"), calibration_path_for(mg), cam)
                mg.guard.before_session.append(cam.release)  # a session never meets a streaming camera
                request.app.state.console = console
    return console


ConsoleDep = Annotated[Console, Depends(get_console)]


@contextlib.contextmanager
def device_errors(what: str) -> Iterator[None]:
    """A device error during a console command becomes 503 with what failed and where (the
    daemon stays up; the operator sees the device's own message)."""
    try:
        yield
    except DeviceError as exc:
        raise HTTPException(503, f"{what} failed: {exc}") from None


def check_camera_range(pairs: list[tuple[float, float]]) -> None:
    """Exposures and gains a plan asks for, held against the camera's range before it is asked
    (a plan may name exposures the camera cannot make: that is the plan's fault, not a device's)."""
    from . import models as cm

    lo_e, hi_e = cm.EXPOSURE_RANGE
    lo_g, hi_g = cm.GAIN_RANGE
    for exposure, gain in pairs:
        if not (lo_e <= exposure <= hi_e and lo_g <= gain <= hi_g):
            raise UsageError(f"body.plan: exposure {exposure:g} s at gain {gain:g} is outside the camera's "
                             f"range ({lo_e:g}–{hi_e:g} s, gain {lo_g:g}–{hi_g:g})")
