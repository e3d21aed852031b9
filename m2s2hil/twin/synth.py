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

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from m2s2hil.catalog import load_catalog
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


def synthesise(
    root: str | Path, rig: RigConfig, plan: SynthPlan, band_lights: np.ndarray, colour_weights: np.ndarray,
    *, session_id: str | None = None, progress: Callable[[int, int], None] | None = None,
) -> SynthResult:
    """Render ``plan`` into a new synthetic session under ``root``.

    ``band_lights``: (n_bands, 3) RGB light colour of each band (the paper's wavelength→RGB
    map); ``colour_weights``: (n_bands, 3) band values → linear sRGB, giving each filament's
    RGB colour from its spectrum."""
    cat = load_catalog()
    b = cat.build(plan.satellite, plan.build)
    cond = cat.light(plan.light)
    model = rig.camera.model
    lights = np.asarray(band_lights, dtype=np.float64)
    weights = np.asarray(colour_weights, dtype=np.float64)
    if lights.shape != (model.n_bands, 3) or weights.shape != (model.n_bands, 3):
        raise UsageError(f"band colours and colour weights must be ({model.n_bands}, 3), got "
                         f"{lights.shape} and {weights.shape}")
    if not 16 <= plan.size <= 4096:
        raise UsageError(f"image size {plan.size} px is outside 16 … 4096")
    tilts = _tilts(rig, plan.elevations)
    hil = [e for e in tilts if e in cat.elevations]
    sweep = Sweep(satellite=b.satellite, build=b.key, lighting=[cond.key], tilts=hil or list(cat.elevations),
                  azimuth_step_deg=plan.azimuth_step_deg)
    n_az = max(1, round(360.0 / plan.azimuth_step_deg))
    azimuths = [round(k * plan.azimuth_step_deg, 6) for k in range(n_az) if k * plan.azimuth_step_deg < 360]

    scene = Scene(plan.size, plan.size, model.bands_nm, model.fwhm_nm, model.layout, SceneParams())
    scene.meshes.update(mesh_mockups(rig))
    world = build_world(rig, VirtualClock())
    lamps = {ch: 1.0 for ch in rig.lamp_channels(cond.key)}
    mount = scene.mount(b.satellite, b.materials, b.key)
    albedo = mount.table.rho.astype(np.float64) @ weights
    specular = mount.table.spec.astype(np.float64) @ weights
    if session_id is None:
        stamp = time.strftime("%Y%m%dT%H%M%S", time.gmtime())
        tag = int(np.random.default_rng().integers(1 << 16))
        session_id = f"{stamp}-synthetic-{b.satellite}-{b.key}-{tag:04x}"
    store = SessionStore.create(root, sweep, rig, session_id=session_id, kind="synthetic")
    t0 = time.perf_counter()
    total = len(tilts) * len(azimuths)
    done = 0
    exposure: float | None = None
    try:
        store.set_state("running")
        for elev, tilt in tilts.items():
            for k, az in enumerate(azimuths):
                shaded = scene.render(b.satellite, b.materials, az, tilt, lamps, world.lamp_info,
                                      rig.simulation.spot_angle_deg, build=b.key)
                if exposure is None:
                    exposure = auto_exposure(shaded)  # one scale for the whole session
                view = render_view(shaded, albedo, specular, lights, exposure)
                event = CaptureEvent(
                    event_id=frame_event_id(DOMAIN, elev, az, 0), index=done, kind="frame", lighting=cond.key,
                    elevation=elev, tilt_deg=tilt, azimuth_deg=az, nominal_azimuth_deg=az, azimuth_index=k,
                    exposure_s=0.0, gain=1.0,
                )
                meta = {
                    "domain": DOMAIN, "elevation": elev, "nominal_azimuth_deg": az,
                    "pose": {"turntable_deg": az, "tilt_deg": tilt},
                    "class_names": list(view.class_names),
                    "synthetic": {
                        "renderer": RENDERER, "light": cond.key, "exposure": exposure, "gamma": GAMMA,
                        "bands_nm": list(model.bands_nm), "band_light_rgb": lights.round(6).tolist(),
                        "mockup": mount.source or "built-in", "size": plan.size,
                    },
                }
                extra = {"rgb": view.rgb, "truth_labels": view.mask}
                extra |= {f"band_{i:02d}": img for i, img in enumerate(view.bands)}
                store.write_frame(event, None, preview_rgb=view.rgb, meta=meta, extra=extra)
                done += 1
                if progress is not None:
                    progress(done, total)
        store.complete("completed")
    except BaseException:
        if store.writable:
            store.set_state("failed")
        raise
    finally:
        store.close()
    return SynthResult(session_id=session_id, path=Path(root) / session_id, views=done,
                       seconds=time.perf_counter() - t0)


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
