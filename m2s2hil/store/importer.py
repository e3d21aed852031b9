"""Import released data (or raws from other capture software) into sessions.

``import_dataset(path, root)`` reads a folder in the published M2S2 layout,
``[path/]HIL/<Satellite>/b<N>/e<N>/<all|dir|solo>_<k>.<ext>``, and creates ONE SESSION PER
(SATELLITE, BUILD) (a session is one build's sweep, like a capture), returning them
sorted by satellite and build. Files outside ``HIL/`` (README, metadata) and dot-files
are ignored.

- ``.png``: the release's 8-bit mosaic (three identical channels, or one). Stored as the
  raw mosaic with its values unchanged, in a session whose camera model says
  ``bit_depth = 8`` (the two low bits the release dropped are not invented back).
- Raw files LibRaw reads (``.dng``, ``.nef``, ``.cr2``, ``.arw``, ...) through rawpy:
  ``raw_image_visible`` is the mosaic; the bit depth comes from the white level.

``k`` maps back as in the export: azimuth index ``k % n`` (n = azimuths per turn for
``azimuth_step_deg``), extra frame ``k // n``. Poses are the nominal ones (the release
has no pose metadata); exposure is unknown and recorded as such. The sensor size and bit
depth of the session's rig are taken from the files (all files of a build must agree).

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

import numpy as np

from m2s2hil.catalog import load_catalog
from m2s2hil.config import RigConfig, default_rig
from m2s2hil.drivers.clock import SYSTEM_CLOCK, Clock
from m2s2hil.errors import CatalogError, UsageError
from m2s2hil.plan import DarkPolicy, Sweep, frame_event_id
from m2s2hil.store.atomic import fsync_dir
from m2s2hil.store.frame_files import InvalidImage, decode_png
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


def with_sensor(rig: RigConfig, *, width: int, height: int, bit_depth: int) -> RigConfig:
    """A copy of ``rig`` whose camera model has this sensor size and bit depth."""
    data = rig.model_dump(mode="json")
    data["camera"]["model"].update(width=width, height=height, bit_depth=bit_depth)
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


def _read(item: _Item) -> tuple[np.ndarray, int, str]:
    """(mosaic uint16, bit depth, format) of one file."""
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
        img = decode_png(item.path.read_bytes())
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
    items = scan_published_layout(find_hil_root(Path(path)))
    groups: dict[tuple[str, str], list[_Item]] = {}
    for it in items:
        groups.setdefault((it.satellite, it.build), []).append(it)

    root.mkdir(parents=True, exist_ok=True)
    staging = root / f".import-{secrets.token_hex(4)}"
    staging.mkdir()
    built: list[str] = []
    try:
        for (sat, build), group in sorted(groups.items()):
            built.append(_import_group(staging, sat, build, group, base_rig, azimuth_step_deg, clock))
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
                  step: float, clock: Clock) -> str:
    cat = load_catalog()
    first, bits, first_fmt = _read(group[0])
    h, w = first.shape
    n_probe = Sweep(satellite=sat, build=build, azimuth_step_deg=step)
    n_az = len(n_probe.azimuths())
    lights = [c for c in cat.lighting if any(it.lighting == c for it in group)]
    tilts = [e for e in cat.elevations if any(it.elevation == e for it in group)]
    sweep = Sweep(
        satellite=sat, build=build, lighting=lights, tilts=tilts, azimuth_step_deg=step,
        frames_per_pose=max(it.k // n_az for it in group) + 1, dark=DarkPolicy(frames=0),
        axis_order="light>tilt>azimuth", reorder=False,
    )
    try:
        rig = with_sensor(base_rig, width=w, height=h, bit_depth=bits)
    except ValueError as exc:
        raise DatasetImportError(group[0].path, f"unusable mosaic size {w}x{h}: {exc}") from None
    events = {e.event_id: e for e in sweep.expand(rig) if e.kind == "frame"}
    store = SessionStore.create(staging, sweep, rig, clock=clock)
    try:
        store.set_state("running")
        for i, it in enumerate(group):
            mosaic, b, fmt = (first, bits, first_fmt) if i == 0 else _read(it)
            if mosaic.shape != (h, w):
                raise DatasetImportError(it.path, f"mosaic is {mosaic.shape[1]}x{mosaic.shape[0]}, the "
                                                  f"other files of {sat} {build} are {w}x{h}")
            if b != bits:
                raise DatasetImportError(it.path, f"{b}-bit data among {bits}-bit files of {sat} {build}")
            az_i, f = it.k % n_az, it.k // n_az
            nominal = sweep.azimuths()[az_i]
            ev = events[frame_event_id(it.lighting, it.elevation, nominal, f)]
            store.write_frame(ev, mosaic, meta={
                "source": "import",
                "source_file": it.rel,
                "source_format": fmt,
                "source_sha256": hashlib.sha256(it.path.read_bytes()).hexdigest(),
                "exposure_s": None,
                "gain": None,
                "exposure_known": False,
                "pose_source": "nominal, from the file index",
                "dark_id": None,
                "bit_depth": bits,
            })
        store.record_event("import", {"files": len(group), "bit_depth": bits, "width": w, "height": h})
        store.complete("completed")
        return store.session_id
    finally:
        store.close()
