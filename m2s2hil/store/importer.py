"""Import released data (or raws from other capture software) into sessions.

``import_dataset(path, root)`` reads a folder in the published M2S2 layout,
``[path/]HIL/<Satellite>/b<N>/e<N>/<all|dir|solo>_<k>.<ext>``, and creates ONE SESSION PER
(SATELLITE, BUILD) (a session is one build's sweep, like a capture), returning them
sorted by satellite and build. Files outside ``HIL/`` (README, metadata) and dot-files
are ignored.

- ``HIL16/<same path>`` (written by ``m2s2hil export``): the lossless 16-bit mosaic, used
  instead of the 8-bit one when present: the sensor's DN come back bit for bit.
- ``.png`` without a ``HIL16`` twin: the release's 8-bit mosaic (three identical channels,
  or one). Stored as the raw mosaic with its values unchanged, in a session whose camera
  model says ``bit_depth = 8`` (the two low bits the release dropped are not invented back).
- Raw files LibRaw reads (``.dng``, ``.nef``, ``.cr2``, ``.arw``, ...) through rawpy:
  ``raw_image_visible`` is the mosaic; the bit depth comes from the white level.

Metadata sidecars (``metadata/<session>.csv`` and ``.json``, written by the export) are read
when present (m2s2hil.store.import_meta): each frame gets back its exposure, gain,
temperature, dark id, pose read-backs and timestamp, the session its camera model (bands,
FWHM, mosaic layout, bit depth) and azimuth grid, and the master darks in
``metadata/<session>/`` are stored again under their ids. Without them, ``k`` maps back as
in the export: azimuth index ``k % n`` (n = azimuths per turn for ``azimuth_step_deg``),
extra frame ``k // n``; poses are the nominal ones, exposure is unknown and recorded as
such, and the sensor size and bit depth come from the files (all files of a build must
agree).

Nothing is half-imported: every name is validated before anything is written, the
sessions are built in a hidden staging folder under ``root``, and only renamed into
place once every file of every session was read and stored. Any problem raises
:class:`DatasetImportError` naming the file and leaves ``root`` as it was.
"""

from __future__ import annotations

import hashlib
import re
import secrets
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from m2s2hil.atomic import fsync_dir
from m2s2hil.catalog import load_catalog
from m2s2hil.config import RigConfig, default_rig
from m2s2hil.drivers.clock import SYSTEM_CLOCK, Clock
from m2s2hil.errors import CatalogError, UsageError
from m2s2hil.plan import DarkPolicy, Sweep, dark_event, frame_event_id
from m2s2hil.store import import_meta
from m2s2hil.store.frame_files import InvalidImage, decode_image, decode_tiff
from m2s2hil.store.frame_meta import STORE_KEYS
from m2s2hil.store.import_meta import Sidecar, SidecarError, bit_depth, camera_fields, read_sidecars
from m2s2hil.store.session import SessionStore

RAW_EXTENSIONS = frozenset({
    ".dng", ".nef", ".nrw", ".cr2", ".cr3", ".crw", ".arw", ".srf", ".sr2", ".raf", ".orf", ".rw2",
    ".pef", ".srw", ".3fr", ".erf", ".kdc", ".dcr", ".mos", ".mrw", ".x3f", ".iiq", ".rwl", ".raw",
})
_NAME = re.compile(r"^(?P<light>[A-Za-z]+)_(?P<k>\d+)(?P<ext>\.[A-Za-z0-9]+)$")
EXPECTED = "HIL/<Satellite>/b<N>/e<N>/<all|dir|solo>_<k>.png (or a raw file LibRaw reads)"


class DatasetImportError(UsageError):
    """A file that cannot be imported; ``path`` names it."""

    def __init__(self, path: str | Path, problem: str) -> None:
        self.path = str(path)
        self.problem = problem
        super().__init__(f"{path}: {problem}")


@dataclass(frozen=True)
class _Item:
    path: Path
    rel: str
    satellite: str
    build: str
    elevation: str
    lighting: str
    k: int
    raw: bool


def with_sensor(rig: RigConfig, *, width: int, height: int, bit_depth: int, **model: Any) -> RigConfig:
    """A copy of ``rig`` whose camera model has this sensor size and bit depth (and ``model``'s
    other fields: bands, FWHM, layout, ... as an export recorded them)."""
    data = rig.model_dump(mode="json")
    data["camera"]["model"].update(width=width, height=height, bit_depth=bit_depth, **model)
    return RigConfig.model_validate(data)


def find_hil_root(path: Path) -> Path:
    """The ``HIL`` folder of a published-layout folder (``path/HIL``, or ``path`` itself)."""
    if not path.is_dir():
        raise DatasetImportError(path, "not a folder")
    if (path / "HIL").is_dir():
        return path / "HIL"
    if path.name == "HIL":
        return path
    raise DatasetImportError(path, f"no HIL folder; expected {EXPECTED}")


def scan_published_layout(hil: Path) -> list[_Item]:
    """Every image under ``hil``, its name validated against the catalog; raises
    :class:`DatasetImportError` on the first file that does not fit (see module doc)."""
    cat = load_catalog()
    items: list[_Item] = []
    seen: dict[tuple, Path] = {}
    for p in sorted(hil.rglob("*")):
        rel_parts = p.relative_to(hil).parts
        if any(part.startswith(".") for part in rel_parts) or p.is_dir():
            continue
        rel = "HIL/" + "/".join(rel_parts)
        if len(rel_parts) != 4:
            raise DatasetImportError(p, f"unexpected file; expected {EXPECTED}")
        sat_dir, b_dir, e_dir, name = rel_parts
        m = _NAME.match(name)
        if not m:
            raise DatasetImportError(p, f"unexpected file name {name!r}; expected {EXPECTED}")
        ext = m["ext"].lower()
        if ext != ".png" and ext not in RAW_EXTENSIONS:
            raise DatasetImportError(p, f"unsupported file type {ext!r}; expected .png or a camera raw")
        try:
            sat = cat.satellite(sat_dir).key
            if not re.fullmatch(r"[bB]\d+", b_dir):
                raise CatalogError(f"build folder {b_dir!r} is not b<N>")
            build = cat.build(sat, b_dir.upper()).key
            if not re.fullmatch(r"[eE]\d+", e_dir):
                raise CatalogError(f"elevation folder {e_dir!r} is not e<N>")
            elev = cat.elevation(e_dir.upper()).key
            datasets = {v.dataset: k for k, v in cat.lighting.items()}
            light = datasets.get(m["light"].lower())
            if light is None:
                raise CatalogError(f"lighting {m['light']!r} is not one of {', '.join(sorted(datasets))}")
        except CatalogError as exc:
            raise DatasetImportError(p, str(exc)) from None
        key = (sat, build, elev, light, int(m["k"]))
        if key in seen:
            raise DatasetImportError(p, f"same capture as {seen[key]}")
        seen[key] = p
        items.append(_Item(p, rel, sat, build, elev, light, int(m["k"]), ext != ".png"))
    if not items:
        raise DatasetImportError(hil, f"no images found; expected {EXPECTED}")
    return items


def _read16(path: Path, bits: int | None) -> tuple[np.ndarray, int, str]:
    """A lossless 16-bit mosaic of ``HIL16/``; the bit depth from the metadata, else the
    smallest of 10, 12, 16 bits holding its largest value."""
    try:
        img = decode_image(path.read_bytes())
    except InvalidImage as exc:
        raise DatasetImportError(path, str(exc)) from None
    if img.dtype != np.uint16 or img.ndim != 2:
        raise DatasetImportError(path, f"expected a 16-bit single-channel PNG, got {img.dtype} {img.shape}")
    top = int(img.max()) if img.size else 0
    if bits is None:
        bits = next(b for b in (10, 12, 16) if top < (1 << b))
    elif top >= (1 << bits):
        raise DatasetImportError(path, f"value {top} does not fit the {bits} bits its metadata gives")
    return img, bits, "png16"


def _hil16(item: _Item) -> Path:
    """Where the export put the lossless 16-bit twin of ``item``: ``HIL16/<same path>``."""
    return item.path.parents[4] / "HIL16" / Path(*item.path.parts[-4:])


def _read(item: _Item, sidecar: Sidecar | None = None) -> tuple[np.ndarray, int, str]:
    """(mosaic uint16, bit depth, format) of one file (its lossless HIL16 twin if there is one)."""
    p16 = _hil16(item)
    if not item.raw and p16.is_file():
        return _read16(p16, bit_depth(sidecar))
    if item.raw:
        import rawpy

        try:
            with rawpy.imread(str(item.path)) as r:
                mosaic = np.array(r.raw_image_visible, dtype=np.uint16, copy=True)
                white = int(r.white_level)
        except (rawpy.LibRawError, OSError) as exc:
            raise DatasetImportError(item.path, f"LibRaw cannot read this raw file: {exc}") from None
        need = max(8, int(white).bit_length())
        bits = next((b for b in (8, 10, 12, 16) if b >= need), None)
        if bits is None:
            raise DatasetImportError(item.path, f"white level {white} needs more than 16 bits")
        return mosaic, bits, f"raw:{item.path.suffix.lower().lstrip('.')}"
    try:
        img = decode_image(item.path.read_bytes())
    except InvalidImage as exc:
        raise DatasetImportError(item.path, str(exc)) from None
    if img.dtype != np.uint8:
        raise DatasetImportError(item.path, f"expected an 8-bit PNG as released, got {img.dtype}")
    if img.ndim == 3:
        if img.shape[2] not in (3, 4) or not (np.array_equal(img[..., 0], img[..., 1])
                                               and np.array_equal(img[..., 0], img[..., 2])):
            raise DatasetImportError(item.path, "not a mosaic: the colour channels differ")
        img = img[..., 0]
    return img.astype(np.uint16), 8, "png8"


def import_dataset(path: str | Path, root: str | Path, layout: str = "m2s2", *,
                   rig: RigConfig | None = None, azimuth_step_deg: float = 10.0,
                   clock: Clock = SYSTEM_CLOCK) -> list[SessionStore]:
    """Import a published-layout folder; one session per (satellite, build). See module doc."""
    if layout != "m2s2":
        raise UsageError(f"unknown import layout {layout!r}; known: m2s2")
    base_rig = rig or default_rig()
    root = Path(root)
    hil = find_hil_root(Path(path))
    items = scan_published_layout(hil)
    try:
        sidecars = read_sidecars(hil.parent)
    except SidecarError as exc:
        raise DatasetImportError(exc.path, exc.problem) from None
    groups: dict[tuple[str, str], list[_Item]] = {}
    for it in items:
        groups.setdefault((it.satellite, it.build), []).append(it)

    root.mkdir(parents=True, exist_ok=True)
    staging = root / f".import-{secrets.token_hex(4)}"
    staging.mkdir()
    built: list[str] = []
    try:
        for (sat, build), group in sorted(groups.items()):
            built.append(_import_group(staging, sat, build, group, base_rig, azimuth_step_deg, clock,
                                       {it.rel: sidecars[it.rel] for it in group if it.rel in sidecars}))
        clash = [sid for sid in built if (root / sid).exists()]
        if clash:
            raise DatasetImportError(root / clash[0], "a session with this id already exists")
        for sid in built:
            (staging / sid).rename(root / sid)
        fsync_dir(root)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return [SessionStore.open(root, sid, clock=clock) for sid in built]


def _import_group(staging: Path, sat: str, build: str, group: list[_Item], base_rig: RigConfig,
                  step: float, clock: Clock, sidecars: dict[str, Sidecar]) -> str:
    cat = load_catalog()
    first, bits, first_fmt = _read(group[0], sidecars.get(group[0].rel))
    h, w = first.shape
    side0 = sidecars.get(group[0].rel)
    exported = side0.session.get("sweep", {}) if side0 is not None else {}
    step = float(exported.get("azimuth_step_deg", step))
    start = float(exported.get("azimuth_start_deg", 0.0))
    n_probe = Sweep(satellite=sat, build=build, azimuth_step_deg=step, azimuth_start_deg=start)
    n_az = len(n_probe.azimuths())

    def pose_index(it: _Item) -> tuple[int, int]:  # (azimuth index, frame)
        side = sidecars.get(it.rel)
        r = side.row if side is not None else {}
        if r.get("azimuth_index", "").isdigit() and r.get("frame", "").isdigit():
            return int(r["azimuth_index"]), int(r["frame"])
        return it.k % n_az, it.k // n_az

    lights = [c for c in cat.lighting if any(it.lighting == c for it in group)]
    tilts = [e for e in cat.elevations if any(it.elevation == e for it in group)]
    sweep = Sweep(
        satellite=sat, build=build, lighting=lights, tilts=tilts, azimuth_step_deg=step,
        azimuth_start_deg=start, frames_per_pose=max(pose_index(it)[1] for it in group) + 1,
        dark=DarkPolicy(frames=0), axis_order="light>tilt>azimuth", reorder=False,
    )
    try:
        rig = with_sensor(base_rig, width=w, height=h, bit_depth=bits,
                          **(camera_fields(side0) if side0 is not None else {}))
    except ValueError as exc:
        raise DatasetImportError(group[0].path, f"unusable mosaic size {w}x{h}: {exc}") from None
    events = {e.event_id: e for e in sweep.expand(rig) if e.kind == "frame"}
    store = SessionStore.create(staging, sweep, rig, clock=clock)
    try:
        store.set_state("running")
        _import_darks(store, sidecars)
        dark_ids = {d.dark_id for d in store.darks()}
        for i, it in enumerate(group):
            side = sidecars.get(it.rel)
            mosaic, b, fmt = (first, bits, first_fmt) if i == 0 else _read(it, side)
            if mosaic.shape != (h, w):
                raise DatasetImportError(it.path, f"mosaic is {mosaic.shape[1]}x{mosaic.shape[0]}, the "
                                                  f"other files of {sat} {build} are {w}x{h}")
            if b != bits:
                raise DatasetImportError(it.path, f"{b}-bit data among {bits}-bit files of {sat} {build}")
            az_i, f = pose_index(it)
            if az_i >= n_az:
                raise DatasetImportError(it.path, f"azimuth index {az_i} is outside the {n_az} azimuths")
            nominal = sweep.azimuths()[az_i]
            ev = events[frame_event_id(it.lighting, it.elevation, nominal, f)]
            src = it.path if fmt != "png16" else _hil16(it)
            meta = {
                "source": "import",
                "source_file": it.rel if fmt != "png16" else "HIL16/" + it.rel.split("/", 1)[1],
                "source_format": fmt,
                "source_sha256": hashlib.sha256(src.read_bytes()).hexdigest(),
                "bit_depth": bits,
            }
            if side is not None:
                meta.update(import_meta.frame_meta(side))
            else:
                meta.update({"exposure_s": None, "gain": None, "exposure_known": False,
                             "pose_source": "nominal, from the file index", "dark_id": None})
            if meta.get("dark_id") and meta["dark_id"] not in dark_ids:
                meta["dark_id"] = None  # its master dark was not exported with it
            store.write_frame(ev, mosaic, meta=meta)
        store.record_event("import", {"files": len(group), "bit_depth": bits, "width": w, "height": h,
                                      "sidecars": len(sidecars)})
        store.complete("completed")
        return store.session_id
    finally:
        store.close()


def _import_darks(store: SessionStore, sidecars: dict[str, Sidecar]) -> None:
    """Store the master darks the group's exported sessions came with, under their ids."""
    seen: dict[str, str] = {}  # dark id -> sha256 of its file
    sources = {id(s.session): s for s in sidecars.values()}
    for side in sources.values():
        try:
            entries = import_meta.darks(side)
        except SidecarError as exc:
            raise DatasetImportError(exc.path, exc.problem) from None
        for d, path in entries:
            data = path.read_bytes()
            digest = hashlib.sha256(data).hexdigest()
            did = str(d["dark_id"])
            if did in seen:
                if seen[did] != digest:
                    raise DatasetImportError(path, f"two different master darks are named {did!r}")
                continue
            seen[did] = digest
            try:
                arr, desc = decode_tiff(data)
            except Exception as exc:  # tifffile raises several kinds on a damaged file
                raise DatasetImportError(path, f"unreadable master dark: {exc}") from None
            ev = dark_event(float(d["exposure_s"]), float(d["gain"]), int(d.get("n_frames") or 1))
            ev = ev.model_copy(update={"event_id": did, "exposure_s": float(d["exposure_s"])})
            meta = {k: v for k, v in desc.items() if k not in STORE_KEYS and k not in ("dark_id", "shape")}
            meta.update({"source": "import", "source_file": path.relative_to(side.folder.parent).as_posix()})
            try:
                store.write_dark(ev, arr, meta=meta)
            except InvalidImage as exc:
                raise DatasetImportError(path, str(exc)) from None
