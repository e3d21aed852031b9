"""Live view for setting a rig up: what the camera sees, downsampled, with the numbers that matter.

A frame becomes a :class:`LiveFrame`: a JPEG of the super-pixel cube (one value per mosaic
cell, so a 2048² sensor gives 512², cheap and free of demosaicing artefacts) shown as a
white-balanced false-colour image or as one band, plus the statistics the operator sets
exposure and focus by: a histogram of the raw values, the saturated fraction, a focus measure
(variance of the Laplacian of the brightest band, larger is sharper) and the frame's exposure,
gain and timestamps.

:class:`LiveStream` runs one producer while at least one viewer is connected, so any number of
browsers share one camera conversation: a grab thread and a render thread with a one-slot
handoff between them, so the next exposure and readout overlap the last frame's render, and a
frame the renderer had no time for is dropped, never queued. Each viewer gets the newest frame
when it is ready for one (a slow viewer skips frames instead of queueing them). A viewer on an
event loop (the daemon's) waits with :meth:`LiveStream.aframes`, which holds no thread while it
waits: the producer wakes it through its loop. A viewer is never dropped for want of a frame while
the producer runs (a cold start at 2048² — the camera starting, the first readout, the kernels
compiling — may take longer than any fixed timeout on a loaded machine): it gets a
:class:`LiveNotice` saying what the stream waits for instead, and :attr:`LiveStream.state` and
:attr:`LiveStream.stopped_reason` say what the stream does and why it last stopped; a viewer that
gets neither a frame nor a busy notice for ``give_up_s`` (a stuck camera, or one that only fails)
is ended with the reason, so no client waits for ever. Every wait here has a timeout. Each grab
goes through ``grab`` (a callable the daemon wraps with its device lock and its session check), so
the live view never talks to the camera while a session owns it.
"""

from __future__ import annotations

import asyncio
import logging
import math
import threading
import time
from collections.abc import AsyncGenerator, Callable
from dataclasses import dataclass, field, replace
from typing import Any

import cv2
import numpy as np

from m2s2hil.config import CameraModel
from m2s2hil.drivers.interfaces import Frame
from m2s2hil.processing.demosaic import Demosaicer, get_demosaicer
from m2s2hil.processing.display import SRGB_LUT, rgb_bands, srgb_encode

log = logging.getLogger("m2s2hil.rig.live_view")

HIST_BINS = 64
JPEG_QUALITY = 80


@dataclass(frozen=True)
class LiveSettings:
    exposure_s: float = 0.01
    gain: float = 1.0
    #: "rgb" for the white-balanced false-colour view, or a band index (0-based).
    view: str | int = "rgb"
    #: Where the turntable's axis crosses the image, as a fraction of the width (overlay only).
    axis_x: float = 0.5


@dataclass(frozen=True)
class LiveFrame:
    seq: int
    jpeg: bytes
    stats: dict[str, Any] = field(default_factory=dict)
    #: The raw mosaic it was rendered from (the camera's own buffer, not copied), for the
    #: spectrum at a point (m2s2hil/api/console/pictures.py).
    raw: np.ndarray | None = field(default=None, repr=False, compare=False)


@dataclass(frozen=True)
class LiveNotice:
    """What a viewer gets instead of a frame: ``state`` is ``"waiting"`` (the camera is starting or
    slow; the stream goes on), ``"busy"`` (a session owns the rig) or ``"error"`` (a device error,
    retried); ``reason`` says it in words."""

    state: str
    reason: str


#: How long a viewer waits for a frame before it is told what the stream waits for.
WAIT_NOTICE_S = 2.0
#: How long a viewer waits without a frame, an error or a busy notice before its stream ends
#: (a camera stuck in a read): far beyond a cold start (5 s at 2048² on a loaded machine).
GIVE_UP_S = 60.0


def _hist_stride(period: int) -> int:
    """A sampling stride for the histogram: about every 25th pixel, coprime with the mosaic period so
    the sample visits every band's position (every 2nd pixel of a 4×4 mosaic sees only 4 of 16)."""
    stride = 5
    while math.gcd(stride, period) != 1:
        stride += 1
    return stride


class LiveRenderer:
    """Raw mosaic → :class:`LiveFrame` (JPEG + statistics); buffers kept between frames.

    Made for 2048² at 20 frames/s on a shared 2-core machine: the super-pixel cube is the display
    size already (512² for a 4×4 mosaic), the false colour is scaled and sRGB-encoded one channel
    at a time into preallocated buffers, written in OpenCV's BGR order (no copy for the JPEG), and
    the white balance, the display scale and the histogram are taken from subsamples.
    """

    def __init__(self, model: CameraModel) -> None:
        self.model = model
        self._demosaic: Demosaicer = get_demosaicer("superpixel", model, (model.height, model.width))
        self._rgb = rgb_bands(model.bands_nm)
        self._stride = _hist_stride(model.period)
        self._lut_top = len(SRGB_LUT) - 1
        self._scaled: np.ndarray | None = None  # float32 (h, w) scratch
        self._index: np.ndarray | None = None  # uint16 (h, w) scratch (the LUT index)

    def _bgr(self, cube: np.ndarray) -> np.ndarray:
        """The white-balanced false colour (as :func:`m2s2hil.processing.display.false_colour`:
        grey world over the lit pixels, 99.5th percentile white, sRGB) as a BGR uint8 image."""
        bands = [cube[i] for i in self._rgb]
        h, w = bands[0].shape
        sample = np.stack([b[::4, ::4] for b in bands], axis=-1).astype(np.float32)  # 1/16: for the eye
        lum = sample.sum(axis=-1)
        lit = lum > lum.mean() if lum.size else np.zeros(0, bool)
        means = sample[lit].mean(axis=0) if np.any(lit) else sample.reshape(-1, 3).mean(axis=0)
        gains = np.where(means > 0, means.max() / np.where(means > 0, means, 1.0), 1.0)
        balanced = (sample * gains.astype(np.float32)).ravel()
        top = 0.0
        if balanced.size:
            k = round(0.995 * (balanced.size - 1))
            top = float(np.partition(balanced, k)[k])
        if self._scaled is None or self._scaled.shape != (h, w):
            self._scaled = np.empty((h, w), np.float32)
            self._index = np.empty((h, w), np.uint16)
        scaled, index = self._scaled, self._index
        assert index is not None
        out = np.empty((h, w, 3), np.uint8)
        for c, band in enumerate(bands):  # R, G, B → BGR planes 2, 1, 0
            factor = self._lut_top * float(gains[c]) / top if top > 0 else float(gains[c]) * self._lut_top
            np.multiply(band, np.float32(factor), out=scaled)
            np.add(scaled, np.float32(0.5), out=scaled)
            np.clip(scaled, 0.0, float(self._lut_top), out=scaled)
            np.copyto(index, scaled, casting="unsafe")
            out[..., 2 - c] = SRGB_LUT[index]
        return out

    def render(self, frame: Frame, settings: LiveSettings, seq: int,
               grabbed_at: float | None = None) -> LiveFrame:
        """``grabbed_at``: wall time the frame reached the host (default: now)."""
        t0 = time.perf_counter()
        grabbed_at = time.time() if grabbed_at is None else grabbed_at
        raw = frame.data
        full = self.model.full_scale
        cube = self._demosaic.process(raw)  # (bands, h/n, w/n) float32
        if settings.view == "rgb":
            img = self._bgr(cube)
        else:
            band = cube[int(settings.view)]
            img8 = srgb_encode(np.clip(band / full, 0.0, 1.0))
            img = np.repeat(img8[..., None], 3, axis=2)
        ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
        if not ok:  # pragma: no cover - OpenCV encodes any uint8 image
            raise RuntimeError("JPEG encoding failed")
        # One bincount over about every 25th pixel (all mosaic positions, see _hist_stride) gives
        # the histogram, the saturated fraction and the 99.9th percentile (np.percentile would
        # sort a million values per frame).
        s = self._stride
        counts = np.bincount(raw[::s, ::s].ravel(), minlength=full + 1)[: full + 1]
        n = int(counts.sum())
        edges = np.linspace(0, full + 1, HIST_BINS + 1).astype(int)
        hist = np.add.reduceat(counts, edges[:-1])
        p999 = float(np.searchsorted(np.cumsum(counts), 0.999 * n))
        brightest = int(np.argmax(cube.reshape(cube.shape[0], -1).mean(axis=1)))
        focus = float(cv2.Laplacian(cube[brightest] / max(full, 1), cv2.CV_32F).var())
        stats = {
            "seq": seq,
            "block_id": int(frame.block_id),
            # to the ns: the camera's µs register makes 0.2 s read back as 0.19999999999999998
            "exposure_s": round(float(frame.exposure_s), 9),
            "gain": float(frame.gain),
            "temperature_c": float(frame.temperature_c),
            "width": int(img.shape[1]),
            "height": int(img.shape[0]),
            "sensor": [int(raw.shape[1]), int(raw.shape[0])],
            "view": settings.view,
            "axis_x": settings.axis_x,
            "histogram": hist.astype(int).tolist(),
            "full_scale": full,
            "saturated_fraction": float(counts[full] / max(n, 1)),
            "p999": p999,
            "focus": focus,
            "focus_band_nm": float(self.model.bands_nm[brightest]),
            "captured_at": grabbed_at,  # the frame in host memory (the live view's latency starts here)
            "render_ms": round(1e3 * (time.perf_counter() - t0), 2),
        }
        return LiveFrame(seq, buf.tobytes(), stats, raw=raw)


#: How long the producer waits for its render thread when it stops.
RENDER_JOIN_S = 5.0


@dataclass(frozen=True)
class _Grabbed:
    frame: Frame
    settings: LiveSettings
    generation: int
    grabbed_at: float
    grab_ms: float


class _Handoff:
    """One slot from the grab thread to the render thread. :meth:`put` never blocks (a frame still
    waiting is replaced: the renderer is behind, so that frame is stale); :meth:`take` waits at most
    ``timeout_s``."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._item: _Grabbed | None = None
        self.closed = False
        self.dropped = 0
        self.failure: BaseException | None = None
        self._fastest: float | None = None  # the least (host arrival − device exposure start) seen

    def waited(self, frame: Frame) -> float:
        """How much longer than the quickest frame of this stream ``frame`` took from its exposure
        start (device clock) to the host: time it waited in the camera's buffer because the host
        read late (the two clocks' offset cancels out; it is 0 while the host keeps up)."""
        if not (frame.host_time_s and frame.timestamp_s):
            return 0.0
        delay = frame.host_time_s - frame.timestamp_s
        if self._fastest is None or delay < self._fastest:
            self._fastest = delay
        return delay - self._fastest

    def put(self, item: _Grabbed) -> None:
        with self._cond:
            if self._item is not None:
                self.dropped += 1
            self._item = item
            self._cond.notify()

    def take(self, timeout_s: float) -> _Grabbed | None:
        with self._cond:
            self._cond.wait_for(lambda: self._item is not None or self.closed, timeout=timeout_s)
            item, self._item = self._item, None
            return None if self.closed else item

    def close(self) -> None:
        with self._cond:
            self.closed = True
            self._item = None
            self._cond.notify_all()


def _set_all(events: list[asyncio.Event]) -> None:
    for event in events:
        event.set()


class LiveViewBusy(RuntimeError):
    """The camera cannot be used for live view now (a session owns the rig)."""


class LiveStream:
    """One producer (a grab and a render thread) shared by every viewer (see the module docstring).

    ``grab(settings)`` snaps one frame (the caller's locking and ownership checks inside);
    it raises :class:`LiveViewBusy` when the camera is not available.
    """

    def __init__(self, model: CameraModel, grab: Callable[[LiveSettings], Frame], *,
                 idle_stop_s: float = 2.0, max_fps: float = 30.0,
                 on_idle: Callable[[], None] | None = None) -> None:
        self.renderer = LiveRenderer(model)
        self.grab = grab
        self.idle_stop_s = idle_stop_s
        self.on_idle = on_idle  # called when the producer stops (no viewer left)
        # A cap on the grab rate: a faster camera (or a simulated one on a virtual clock) would
        # otherwise take the rig's device lock back-to-back and starve jogs and session starts.
        self.min_interval_s = 1.0 / max_fps
        self._settings = LiveSettings()
        self._cond = threading.Condition()
        self._latest: LiveFrame | None = None
        self._error: str | None = None
        self._viewers = 0
        self._last_viewer = 0.0
        self._thread: threading.Thread | None = None
        self._seq = 0
        self._generation = 0  # bumped by every settings change
        self._waiters: set[tuple[asyncio.AbstractEventLoop, asyncio.Event]] = set()  # aframes() viewers
        self.frames_produced = 0
        #: "idle" (no producer), "starting" (no frame yet), "streaming", "busy", "error".
        self.state = "idle"
        #: Why the producer last stopped (None before its first stop).
        self.stopped_reason: str | None = None
        #: Seconds from the producer's start to its first frame, for the last start.
        self.cold_start_s: float | None = None
        self._started_at = 0.0
        self._frame_times: list[float] = []  # monotonic times of the last frames (rate)

    # -- settings ----------------------------------------------------------------------------
    @property
    def settings(self) -> LiveSettings:
        with self._cond:
            return self._settings

    def update(self, **changes: Any) -> LiveSettings:
        """New settings; a frame grabbed with the old ones is not shown after this returns."""
        with self._cond:
            self._settings = replace(self._settings, **{k: v for k, v in changes.items() if v is not None})
            self._generation += 1
            self._latest = None
            return self._settings

    def _notify(self) -> None:
        """Wake every viewer (the caller holds ``_cond``)."""
        self._cond.notify_all()
        by_loop: dict[asyncio.AbstractEventLoop, list[asyncio.Event]] = {}
        for loop, event in self._waiters:
            by_loop.setdefault(loop, []).append(event)
        for loop, events in by_loop.items():  # one wake-up per loop, not one per viewer
            try:
                loop.call_soon_threadsafe(_set_all, events)
            except RuntimeError:  # its loop has closed: those viewers are gone
                self._waiters -= {(loop, e) for e in events}

    @property
    def error(self) -> str | None:
        return self._error

    @property
    def viewers(self) -> int:
        return self._viewers

    @property
    def fps(self) -> float | None:
        """Frames per second produced over the last (up to) 20 frames, while streaming."""
        with self._cond:
            t = self._frame_times
            if self.state != "streaming" or len(t) < 2 or t[-1] <= t[0]:
                return None
            return (len(t) - 1) / (t[-1] - t[0])

    @property
    def running(self) -> bool:
        """True while the producer thread runs (the stream is starting, streaming or retrying)."""
        thread = self._thread
        return thread is not None and thread.is_alive()

    # -- producing ---------------------------------------------------------------------------
    def _ensure_running(self) -> None:
        if self._thread is None or not self._thread.is_alive():
            self.state, self._started_at, self.cold_start_s = "starting", time.monotonic(), None
            self._frame_times = []
            self._thread = threading.Thread(target=self._produce_or_fail, name="live-view", daemon=True)
            self._thread.start()

    def _produce_or_fail(self) -> None:
        try:
            self._produce()
        except BaseException as exc:  # the producer died: its viewers end with the reason
            with self._cond:
                self._thread = None
                self.state = "error"
                self.stopped_reason = f"the live view failed: {type(exc).__name__}: {exc}"
                self._notify()
            if not isinstance(exc, Exception):
                raise
            log.exception("the live view failed")  # the viewers have the reason; the log has the trace

    def _produce(self) -> None:
        """Grab here, render on a second thread: the next exposure and readout overlap the last
        frame's render (a one-slot handoff; a frame not yet rendered when a newer one arrives is
        dropped, never queued, so the view stays current)."""
        handoff = _Handoff()
        renderer = threading.Thread(target=self._render_loop, args=(handoff,), name="live-view-render",
                                    daemon=True)
        renderer.start()
        try:
            self._grab_loop(handoff)
        finally:
            handoff.close()
            # bounded: a render takes milliseconds; a wedged one must not keep the producer from ending
            renderer.join(timeout=RENDER_JOIN_S)

    def _grab_loop(self, handoff: _Handoff) -> None:
        next_at = 0.0
        while True:
            if handoff.failure is not None:  # the renderer died: the producer ends with its reason
                raise handoff.failure
            wait = next_at - time.monotonic()
            if wait > 0:
                time.sleep(wait)
            next_at = time.monotonic() + self.min_interval_s
            with self._cond:
                if self._viewers == 0 and time.monotonic() - self._last_viewer > self.idle_stop_s:
                    self._thread = None
                    self.state = "idle"
                    self.stopped_reason = (f"no viewer for {self.idle_stop_s:g} s: the camera stopped "
                                           "streaming")
                    handoff.closed = True  # under _cond: no frame is published after the stop
                    stopping = True
                else:
                    stopping = False
            if stopping:
                handoff.close()
                if self.on_idle is not None:
                    self.on_idle()
                return
            with self._cond:
                settings = self._settings
                generation = self._generation
            t0 = time.perf_counter()
            try:
                frame = self.grab(settings)
                grabbed_at = time.time()
            except LiveViewBusy as exc:
                with self._cond:
                    self._error = str(exc)
                    self.state = "busy"
                    self._notify()
                time.sleep(0.25)
                continue
            except Exception as exc:  # a device error: shown to the viewers, retried
                with self._cond:
                    self._error = f"{type(exc).__name__}: {exc}"
                    self.state = "error"
                    self._notify()
                time.sleep(0.5)
                continue
            with self._cond:
                # cleared here, not when the frame is published: the render of an earlier frame,
                # running meanwhile, must not hide the error of a grab that came after it
                self._error = None
            handoff.put(_Grabbed(frame, settings, generation, grabbed_at, 1e3 * (time.perf_counter() - t0)))

    def _render_loop(self, handoff: _Handoff) -> None:
        try:
            while True:
                item = handoff.take(timeout_s=0.5)
                if item is None:
                    if handoff.closed:
                        return
                    continue
                with self._cond:
                    if item.generation != self._generation or handoff.closed:
                        continue  # grabbed with settings that changed meanwhile
                    self._seq += 1
                    seq = self._seq
                live = self.renderer.render(item.frame, item.settings, seq, item.grabbed_at)
                live.stats["grab_ms"] = round(item.grab_ms, 2)
                live.stats["dropped"] = handoff.dropped  # frames grabbed but superseded before rendering
                live.stats["waited_ms"] = round(1e3 * handoff.waited(item.frame), 2)
                with self._cond:
                    if item.generation != self._generation or handoff.closed:
                        continue
                    self._latest = live
                    self.frames_produced += 1
                    now = time.monotonic()
                    if self.cold_start_s is None:
                        self.cold_start_s = now - self._started_at
                    if self._error is None:  # a later grab's error stands until a grab succeeds
                        self.state = "streaming"
                    self._frame_times = [*self._frame_times[-19:], now]
                    self._notify()
        except BaseException as exc:  # the grab loop raises it, and the producer ends with its reason
            handoff.failure = exc

    async def aframes(self, *, max_frames: int | None = None, notice_s: float = WAIT_NOTICE_S,
                      give_up_s: float = GIVE_UP_S) -> AsyncGenerator[LiveFrame | LiveNotice, None]:
        """Newest frames for one viewer on an event loop, each at most once; it waits without a
        thread. Instead of a frame: a :class:`LiveNotice` when the camera is unavailable (``busy``,
        ``error``), and one every ``notice_s`` without a frame (``waiting``: starting, or slow).
        Ends after ``max_frames`` frames, when the producer has stopped for good
        (:attr:`stopped_reason`), or after ``give_up_s`` without a frame and without a busy notice
        (nothing, or only device errors: a last notice, state ``ended``, says so), so no viewer
        waits for ever. The viewer counts from its first step until the
        generator is closed (the daemon closes it when the connection goes)."""
        waiter = (asyncio.get_running_loop(), asyncio.Event())
        with self._cond:
            self._viewers += 1
            self._waiters.add(waiter)
            self._ensure_running()
            last = self._latest.seq if self._latest is not None else 0
        sent = 0
        progress_at = time.monotonic()  # the last frame, or the last busy notice
        last_error: str | None = None  # the last device error since then
        try:
            while max_frames is None or sent < max_frames:
                with self._cond:
                    item: LiveFrame | LiveNotice | None = None
                    if self._latest is not None and self._latest.seq > last:
                        item = self._latest
                        last = self._latest.seq
                    elif self._error is not None:
                        item = LiveNotice("busy" if self.state == "busy" else "error", self._error)
                        self._error = None
                    elif not self.running and self.state != "starting":
                        return  # the producer has stopped for good: stopped_reason says why
                    else:
                        waiter[1].clear()  # under the lock: a frame after this sets it again
                if item is None:
                    try:
                        await asyncio.wait_for(waiter[1].wait(), notice_s)
                    except TimeoutError:
                        if time.monotonic() - progress_at > give_up_s:
                            yield self._give_up(give_up_s, last_error)
                            return
                        yield LiveNotice("waiting", self._waiting_for())
                    continue
                if isinstance(item, LiveFrame) or item.state == "busy":
                    progress_at = time.monotonic()
                else:
                    last_error = item.reason
                    if time.monotonic() - progress_at > give_up_s:  # only errors: the camera never recovers
                        yield self._give_up(give_up_s, last_error)
                        return
                yield item
                if isinstance(item, LiveNotice):
                    await asyncio.sleep(0.25)
                else:
                    sent += 1
        finally:
            with self._cond:
                self._viewers -= 1
                self._waiters.discard(waiter)
                self._last_viewer = time.monotonic()

    @staticmethod
    def _give_up(give_up_s: float, last_error: str | None) -> LiveNotice:
        if last_error is not None:
            return LiveNotice("ended", f"no frame from the camera for {give_up_s:g} s, only errors (the "
                              f"last: {last_error}): the live view gave up; start it again")
        return LiveNotice("ended", f"no frame from the camera for {give_up_s:g} s: the live view gave up "
                          "(the camera may be stuck); start it again")

    def _waiting_for(self) -> str:
        since = time.monotonic() - self._started_at
        if self.state == "starting":
            return f"waiting for the camera's first frame ({since:.0f} s since the stream started)"
        return "waiting for the next frame from the camera"

    def snapshot(self) -> LiveFrame | None:
        with self._cond:
            return self._latest
