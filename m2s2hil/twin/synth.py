"""The synthetic domain of M2S2, by the paper's protocol, stored as a session of its own kind.

For every pose of the sweep (the rig's HIL elevations plus the catalog's synthetic-only E3,
every azimuth of the grid) the twin renders one RGB image and one image per TOUCAN band lit
with the band's colour (``wavelength_to_rgb(centre, gamma=0.80)``, paper section 2.3), with
the view's material mask (``simulators.synthetic``). The scene is the simulator's: the same
mockup (built-in, or the lab's mesh from the rig file's ``[simulation.mockups]``), the same
lamp directions (one lighting preset, ``strong`` by default: the synthetic split has no
lighting conditions) and the same projection, so a synthetic view and the HIL frame of one
pose show the mockup from the same side.

Storage: a :class:`~m2s2hil.store.session.SessionStore` created with ``kind="synthetic"``;
each view is a frame without a raw mosaic, event id ``synthetic/<elevation>/az<deg>/f0``, its
images as checksummed extra files (``rgb``, ``band_00`` … ``band_09``: 8-bit sRGB PNG;
``truth_labels``: the mask, as in simulated HIL sessions) and metadata ``domain =
"synthetic"``, ``pose``, ``elevation``, ``class_names`` and the rendering's parameters. The
pairing with HIL frames is by pose: (elevation, nominal azimuth) (:func:`pose_key`).

What the twin cannot compute here it is given: the band colours and the band → linear sRGB
weights (``analysis.segmenters.rgb``, a layer above) come from the front end.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from m2s2hil.catalog import Build, Lighting, load_catalog
from m2s2hil.config import RigConfig
from m2s2hil.errors import UsageError
from m2s2hil.plan import CaptureEvent, Sweep
from m2s2hil.plan.model import frame_event_id
from m2s2hil.sim_config import build_world, mesh_mockups
from m2s2hil.simulators.clock import VirtualClock
from m2s2hil.simulators.scene import Scene, SceneParams
from m2s2hil.simulators.synthetic import auto_exposure, render_view
from m2s2hil.store.session import SessionStore

DOMAIN = "synthetic"
RENDERER = "m2s2hil.simulators.synthetic/1"
GAMMA = 0.80  # paper, section 2.3
DEFAULT_SIZE = 512  # the superpixel cube of a 2048² TOUCAN frame: HIL and synthetic views pair 1:1


@dataclass(frozen=True)
class SynthPlan:
    """What to render: one build, one lighting preset's lamps, poses on the azimuth grid."""

    satellite: str
    build: str
    light: str = "strong"
    elevations: tuple[str, ...] = ()  # empty: the rig's HIL elevations and every synthetic one
    azimuth_step_deg: float = 10.0
    size: int = DEFAULT_SIZE


@dataclass(frozen=True)
class SynthResult:
    session_id: str
    path: Path
    views: int
    seconds: float  # wall time of rendering and storing
    state: str = "completed"  # or "aborted": stopped before the last view (``SynthRun.run``'s ``stop``)
    planned: int = 0

    @property
    def views_per_s(self) -> float:
        return self.views / self.seconds if self.seconds > 0 else float("inf")


def pose_key(meta: dict[str, Any], event_id: str = "") -> tuple[str, int] | None:
    """(elevation, nominal azimuth rounded to the degree) of a frame, synthetic or HIL: the key
    the two domains are paired by. None when the frame names no pose."""
    elev = meta.get("elevation")
    az = meta.get("nominal_azimuth_deg")
    if elev is None or az is None:
        parts = event_id.split("/")  # "<lighting|synthetic>/<E?>/az<deg>/f<k>"
        if len(parts) >= 3 and parts[2].startswith("az"):
            try:
                elev, az = parts[1], float(parts[2][2:])
            except ValueError:
                return None
        else:
            return None
    return str(elev), round(float(az)) % 360


def _tilts(rig: RigConfig, elevations: Sequence[str]) -> dict[str, float]:
    cat = load_catalog()
    names = list(elevations) or [*rig.elevations, *cat.synthetic_elevations]
    out: dict[str, float] = {}
    for e in names:
        key = e.strip().upper()
        syn = cat.synthetic_elevations.get(key)
        if syn is not None and syn.tilt_deg is not None:
            out[key] = float(syn.tilt_deg)
        elif key in rig.elevations:
            out[key] = float(rig.elevations[key])
        else:
            known = ", ".join([*rig.elevations, *cat.synthetic_elevations])
            raise UsageError(f"unknown elevation {e!r}; known: {known}")
    return out


def _layout(rig: RigConfig, plan: SynthPlan) -> tuple[Build, Lighting, dict[str, float], list[float]]:
    """The plan checked: (build, lighting, tilt of each elevation, azimuths); UsageError."""
    cat = load_catalog()
    b = cat.build(plan.satellite, plan.build)
    cond = cat.light(plan.light)
    if not 16 <= plan.size <= 4096:
        raise UsageError(f"image size {plan.size} px is outside 16 … 4096")
    if not 0.01 <= plan.azimuth_step_deg <= 360:
        raise UsageError(f"azimuth step {plan.azimuth_step_deg} deg is outside 0.01 … 360")
    tilts = _tilts(rig, plan.elevations)
    n_az = max(1, round(360.0 / plan.azimuth_step_deg))
    azimuths = [round(k * plan.azimuth_step_deg, 6) for k in range(n_az) if k * plan.azimuth_step_deg < 360]
    return b, cond, tilts, azimuths


def count_views(rig: RigConfig, plan: SynthPlan) -> int:
    """How many views ``plan`` renders (elevations × azimuths), checked as :class:`SynthRun` checks it."""
    _, _, tilts, azimuths = _layout(rig, plan)
    return len(tilts) * len(azimuths)


PLAN_EVENT = "synthetic_plan"  # what a synthetic session will render: its views, for status and show
STOPPED_EVENT = "synthetic_stopped"  # a render ended before its last view (cancelled, daemon shutdown)
FAILED_EVENT = "synthetic_failed"  # a render that raised: the error


class SynthRun:
    """One synthetic session: checked and created by the constructor (state ``queued``, the plan
    recorded as a ``synthetic_plan`` event), rendered by :meth:`run`.

    Split so the daemon can answer a request with the session's id and size at once and render
    it on a worker thread; :func:`synthesise` does both in one call. Bad input (an unknown
    satellite, build, lighting or elevation, a size or step out of range, band tables of the
    wrong shape) raises :class:`~m2s2hil.errors.UsageError` before anything is written."""

    def __init__(self, root: str | Path, rig: RigConfig, plan: SynthPlan, band_lights: np.ndarray,
                 colour_weights: np.ndarray, *, session_id: str | None = None) -> None:
        cat = load_catalog()
        model = rig.camera.model
        lights = np.asarray(band_lights, dtype=np.float64)
        weights = np.asarray(colour_weights, dtype=np.float64)
        if lights.shape != (model.n_bands, 3) or weights.shape != (model.n_bands, 3):
            raise UsageError(f"band colours and colour weights must be ({model.n_bands}, 3), got "
                             f"{lights.shape} and {weights.shape}")
        b, cond, self.tilts, self.azimuths = _layout(rig, plan)
        self.rig, self.plan, self.build, self.light = rig, plan, b, cond
        self.lights, self.weights = lights, weights
        self.total = len(self.tilts) * len(self.azimuths)
        self._scene = Scene(plan.size, plan.size, model.bands_nm, model.fwhm_nm, model.layout, SceneParams())
        self._scene.meshes.update(mesh_mockups(rig))  # MeshFileError (naming the file) before any write
        hil = [e for e in self.tilts if e in cat.elevations]
        sweep = Sweep(satellite=b.satellite, build=b.key, lighting=[cond.key],
                      tilts=hil or list(cat.elevations), azimuth_step_deg=plan.azimuth_step_deg)
        if session_id is None:
            stamp = time.strftime("%Y%m%dT%H%M%S", time.gmtime())
            tag = int(np.random.default_rng().integers(1 << 16))
            session_id = f"{stamp}-synthetic-{b.satellite}-{b.key}-{tag:04x}"
        self.session_id = session_id
        self.path = Path(root) / session_id
        self.store = SessionStore.create(root, sweep, rig, session_id=session_id, kind="synthetic")
        try:
            self.store.record_event(PLAN_EVENT, {
                "views": self.total, "elevations": self.tilts, "azimuths": len(self.azimuths),
                "azimuth_step_deg": plan.azimuth_step_deg, "size": plan.size, "light": cond.key,
            })
            self.store.set_state("queued")
        except BaseException:
            self.store.close()
            raise

    def run(self, *, progress: Callable[[int, int, CaptureEvent], None] | None = None,
            stop: Callable[[], str | None] | None = None) -> SynthResult:
        """Render every view into the session, then close it. ``progress(done, total, event)``
        after each stored view; ``stop()`` is asked before each view and, when it returns a
        reason, the session ends ``aborted`` with what is stored kept (a ``synthetic_stopped``
        event says why). Any other failure marks it ``failed`` and is raised."""
        rig, plan, b, cond, store = self.rig, self.plan, self.build, self.light, self.store
        model = rig.camera.model
        t0 = time.perf_counter()
        done = 0
        state = "completed"
        try:
            scene, world = self._scene, build_world(rig, VirtualClock())
            lamps = {ch: 1.0 for ch in rig.lamp_channels(cond.key)}
            mount = scene.mount(b.satellite, b.materials, b.key)
            albedo = mount.table.rho.astype(np.float64) @ self.weights
            specular = mount.table.spec.astype(np.float64) @ self.weights
            exposure: float | None = None
            store.set_state("running")
            for elev, tilt in self.tilts.items():
                for k, az in enumerate(self.azimuths):
                    reason = stop() if stop is not None else None
                    if reason:
                        store.record_event(STOPPED_EVENT, {"reason": reason, "views": done, "of": self.total})
                        state = "aborted"
                        break
                    shaded = scene.render(b.satellite, b.materials, az, tilt, lamps, world.lamp_info,
                                          rig.simulation.spot_angle_deg, build=b.key)
                    if exposure is None:
                        exposure = auto_exposure(shaded)  # one scale for the whole session
                    view = render_view(shaded, albedo, specular, self.lights, exposure)
                    event = CaptureEvent(
                        event_id=frame_event_id(DOMAIN, elev, az, 0), index=done, kind="frame",
                        lighting=cond.key, elevation=elev, tilt_deg=tilt, azimuth_deg=az,
                        nominal_azimuth_deg=az, azimuth_index=k, exposure_s=0.0, gain=1.0,
                    )
                    meta = {
                        "domain": DOMAIN, "elevation": elev, "nominal_azimuth_deg": az,
                        "pose": {"turntable_deg": az, "tilt_deg": tilt},
                        "class_names": list(view.class_names),
                        "synthetic": {
                            "renderer": RENDERER, "light": cond.key, "exposure": exposure, "gamma": GAMMA,
                            "bands_nm": list(model.bands_nm), "band_light_rgb": self.lights.round(6).tolist(),
                            "mockup": mount.source or "built-in", "size": plan.size,
                        },
                    }
                    extra = {"rgb": view.rgb, "truth_labels": view.mask}
                    extra |= {f"band_{i:02d}": img for i, img in enumerate(view.bands)}
                    store.write_frame(event, None, preview_rgb=view.rgb, meta=meta, extra=extra)
                    done += 1
                    if progress is not None:
                        progress(done, self.total, event)
                if state != "completed":
                    break
            store.complete(state)
        except BaseException as exc:
            if store.writable:
                store.record_event(FAILED_EVENT, {"error": f"{type(exc).__name__}: {exc}", "views": done})
                store.set_state("failed")
            raise
        finally:
            store.close()
        return SynthResult(session_id=self.session_id, path=self.path, views=done,
                           seconds=time.perf_counter() - t0, state=state, planned=self.total)

    def discard(self) -> None:
        """Close a session that will not be rendered (the caller could not queue it): ``cancelled``."""
        if self.store.writable:
            self.store.set_state("cancelled")
        self.store.close()


def synthesise(
    root: str | Path, rig: RigConfig, plan: SynthPlan, band_lights: np.ndarray, colour_weights: np.ndarray,
    *, session_id: str | None = None, progress: Callable[[int, int], None] | None = None,
) -> SynthResult:
    """Render ``plan`` into a new synthetic session under ``root``.

    ``band_lights``: (n_bands, 3) RGB light colour of each band (the paper's wavelength→RGB
    map); ``colour_weights``: (n_bands, 3) band values → linear sRGB, giving each filament's
    RGB colour from its spectrum."""
    run = SynthRun(root, rig, plan, band_lights, colour_weights, session_id=session_id)
    return run.run(progress=None if progress is None else lambda done, total, _ev: progress(done, total))


def planned_views(store: SessionStore) -> int | None:
    """How many views a synthetic session was planned to render (its ``synthetic_plan``
    event), or None for a session without one (a HIL session, or one rendered before the plan
    was recorded)."""
    rows = store.journal.query("SELECT payload FROM events WHERE kind = ? ORDER BY seq LIMIT 1",
                               (PLAN_EVENT,))
    if not rows:
        return None
    views = json.loads(rows[0]["payload"]).get("views")
    return int(views) if isinstance(views, int | float) else None


def end_reason(store: SessionStore) -> tuple[str, str] | None:
    """Why a render ended before its last view: ("failed", the error) or ("stopped", the
    reason) from its last stop or failure event; None when it recorded neither."""
    rows = store.journal.query("SELECT kind, payload FROM events WHERE kind IN (?, ?) ORDER BY seq DESC"
                               " LIMIT 1", (FAILED_EVENT, STOPPED_EVENT))
    if not rows:
        return None
    p = json.loads(rows[0]["payload"] or "{}") or {}
    if rows[0]["kind"] == FAILED_EVENT:
        return "failed", str(p.get("error"))
    return "stopped", str(p.get("reason"))


def band_images(store: SessionStore, event_id: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A synthetic frame's (RGB (H, W, 3), bands (n_bands, H, W, 3), mask (H, W)) as stored."""
    from m2s2hil.store.frame_files import decode_image

    fr = store.frame(event_id)
    roles = sorted(r for r in fr.files if r.startswith("band_"))
    if "rgb" not in fr.files or not roles:
        raise UsageError(f"frame {event_id} of session {store.session_id} is not a synthetic view")
    rgb = decode_image(store.read_file(fr.files["rgb"]))
    bands = np.stack([decode_image(store.read_file(fr.files[r])) for r in roles])
    mask = decode_image(store.read_file(fr.files["truth_labels"]))
    return rgb, bands, mask
