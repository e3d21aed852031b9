"""Mockups from the lab's own files: a 3MF build, or a folder of STL files (one per material).

A satellite build printed on a Bambu Lab (or any) printer exists as the slicer's 3MF, whose
objects and parts each carry a filament, or as one STL per filament exported from it. This
module turns either into a :class:`~m2s2hil.simulators.mockups.Mockup` whose parts each name
exactly one material, so the scene renders and labels the lab's geometry instead of the
built-in parametric primitives (which stay the default).

Where a part's material comes from, first found wins:

1. the slicer's extruder: Bambu Studio and OrcaSlicer write ``Metadata/model_settings.config``
   (``<object id>``/``<part id>`` with ``<metadata key="extruder" value="k"/>``) and the
   filament names in ``Metadata/project_settings.config`` (JSON list ``filament_settings_id``,
   extruder ``k`` is entry ``k - 1``);
2. the 3MF core material extension: ``<basematerials>`` named by the object's or the
   triangle's ``pid``/``pindex`` (``p1``) (3MF Core Specification 1.3, section 4; Materials
   and Properties Extension 1.2, section 2);
3. the object's (or STL file's) name: "pro_silver.stl", "PolyLite PLA Pro Silver".

A name is resolved to a material key by matching the key's words in it ("PolyLite PLA Pro
Silver @BBL X1C" is ``pro_silver``), longest key first. trimesh's own 3MF reader keeps
neither object ids nor materials (trimesh 5.2, ``exchange/threemf.py``), so the 3MF's
structure is read here with lxml and every mesh becomes a :class:`trimesh.Trimesh`
(merged, cleaned, smooth-shaded below 30° between faces); STL files are read by trimesh.

Checks, each failing with one :class:`MeshFileError` line naming the file and the problem:
the file exists and parses; units (3MF ``unit``; STL has none, millimetres as slicers
assume) give a model 10–1000 mm across (a mockup that fits the turntable and the frame);
every part has triangles, finite coordinates, a known material that belongs to the build,
and lies with the others (a part exported about its own origin or in other units stands
apart); every material of the build but the stand's is on some part. The file's origin is
not used: slicers place objects anywhere on the plate, so the turntable axis is taken
through the centre of the model's bounding box and the stand holds its lowest point
(the offset is kept as ``MeshInfo.origin_offset_mm``). Object frame as in
:mod:`~m2s2hil.simulators.mockups`: z up (the print bed's normal).
"""

from __future__ import annotations

import json
import re
import zipfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from m2s2hil.protocols.errors import M2S2Error
from m2s2hil.simulators.geometry import Mesh, rot_x, rot_y, rot_z
from m2s2hil.simulators.materials import MATERIAL_KEYS
from m2s2hil.simulators.mockups import PRIMARY, Mockup, Part

# 3MF Core Specification 1.3, 3.4.1: the model's unit; millimetre when absent.
UNIT_MM = {
    "micron": 0.001, "millimeter": 1.0, "centimeter": 10.0, "inch": 25.4, "foot": 304.8, "meter": 1000.0,
}
MIN_SIZE_MM, MAX_SIZE_MM = 10.0, 1000.0  # a printed mockup on the turntable, in the frame
DETACHED = 0.25  # a part further than this × the rest's size from the rest stands apart
SMOOTH_ANGLE_DEG = 30.0  # faces meeting at less than this share normals (curved surfaces)
MAX_TRIANGLES = 2_000_000  # beyond this the rasteriser's per-frame cost is unreasonable


class MeshFileError(M2S2Error, ValueError):
    """A mockup file that cannot be used: ``source`` names it, ``problem`` says why."""

    exit_code = 2

    def __init__(self, source: str | Path, problem: str) -> None:
        self.source = str(source)
        self.problem = problem
        super().__init__(f"{self.source}: {problem}")


@dataclass(frozen=True)
class MeshInfo:
    """What was loaded, for the record (``sim mockup``-style reports, the session)."""

    source: str
    units: str
    size_mm: tuple[float, float, float]
    origin_offset_mm: tuple[float, float, float]  # the file's origin from the turntable axis / stand
    parts: tuple[tuple[str, str, int], ...]  # (part, material, triangles)


@dataclass(frozen=True)
class _RawPart:
    name: str
    material: str | None  # a name to resolve, None: not given
    vertices: np.ndarray  # (N, 3) mm
    faces: np.ndarray  # (M, 3)
    source: Path | None = None  # the part's own file (an STL of a folder): what its errors name


# -- material names -----------------------------------------------------------------------
def _words(text: str) -> str:
    t = re.sub(r"[^a-z0-9]+", "_", text.lower().replace("gray", "grey"))
    return f"_{t.strip('_')}_"


_BY_LENGTH = sorted(MATERIAL_KEYS, key=len, reverse=True)


def material_key(name: str) -> str | None:
    """The material key a filament or part name names, or None ("PolyLite PLA Pro Silver" →
    ``pro_silver``; the longest key whose words appear in order wins)."""
    w = _words(name)
    return next((k for k in _BY_LENGTH if f"_{k}_" in w), None)


# -- 3MF ---------------------------------------------------------------------------------
def _ns_local(tag: str) -> str:
    return tag.rsplit("}", 1)[-1]


def _attr(el, local: str) -> str | None:
    """An attribute by local name, whatever its namespace (``p:path``, ``path``)."""
    for k, v in el.attrib.items():
        if _ns_local(k) == local:
            return v
    return None


def _transform(text: str | None) -> np.ndarray:
    """3MF ``transform`` (12 numbers, row vectors: p' = p · M) as a 4×4 column-vector matrix."""
    m = np.eye(4)
    if text:
        v = [float(x) for x in text.split()]
        if len(v) != 12:
            raise ValueError(f"transform has {len(v)} numbers, not 12")
        m[:3, :3] = np.array(v[:9]).reshape(3, 3).T
        m[:3, 3] = v[9:]
    return m


@dataclass
class _Object:
    oid: str
    name: str
    vertices: np.ndarray | None
    faces: np.ndarray | None
    tri_mat: list[str | None] | None  # per-triangle material name (from pid/p1), if any
    components: list[tuple[str, str | None, np.ndarray]]  # (object id, model path, transform)


def _read_model(xml: bytes, path: str, objects: dict[tuple[str, str], _Object]) -> tuple[list, float]:
    """Objects of one model part into ``objects`` (keyed (model path, id)); returns the build
    items [(object id, transform)] and the unit's millimetres."""
    from lxml import etree  # type: ignore[import-untyped]  # no stubs ship with lxml

    root = etree.fromstring(xml, parser=etree.XMLParser(resolve_entities=False, huge_tree=True))
    unit = root.get("unit", "millimeter")
    if unit not in UNIT_MM:
        raise ValueError(f"unknown unit {unit!r}; 3MF has {', '.join(UNIT_MM)}")
    bases: dict[str, list[str]] = {}
    for el in root.iter():
        if isinstance(el.tag, str) and _ns_local(el.tag) == "basematerials":
            bases[el.get("id", "")] = [b.get("name", "") for b in el if _ns_local(str(b.tag)) == "base"]
    for el in root.iter():
        if not isinstance(el.tag, str) or _ns_local(el.tag) != "object":
            continue
        oid = el.get("id", "")
        pid, pindex = el.get("pid"), el.get("pindex", "0")
        default = None
        if pid in bases and pindex.isdigit() and int(pindex) < len(bases[pid]):
            default = bases[pid][int(pindex)]
        verts = faces = None
        tri_mat: list[str | None] | None = None
        comps: list[tuple[str, str | None, np.ndarray]] = []
        for sub in el.iter():
            tag = _ns_local(str(sub.tag))
            if tag == "vertices":
                verts = np.array([[float(v.get("x")), float(v.get("y")), float(v.get("z"))] for v in sub],
                                 dtype=np.float64).reshape(-1, 3)
            elif tag == "triangles":
                tris = list(sub)
                faces = np.array([[int(t.get("v1")), int(t.get("v2")), int(t.get("v3"))] for t in tris],
                                 dtype=np.int64).reshape(-1, 3)
                mats = []
                for t in tris:
                    tp, p1 = t.get("pid", pid), t.get("p1", pindex if t.get("pid") is None else "0")
                    names = bases.get(tp or "")
                    mats.append(names[int(p1)] if names and p1 and p1.isdigit() and int(p1) < len(names)
                                else default)
                tri_mat = mats
            elif tag == "component":
                comps.append((sub.get("objectid", ""), _attr(sub, "path"), _transform(sub.get("transform"))))
        objects[(path, oid)] = _Object(oid, el.get("name") or f"object {oid}", verts, faces, tri_mat, comps)
    items = []
    for el in root.iter():
        if isinstance(el.tag, str) and _ns_local(el.tag) == "item":
            items.append((el.get("objectid", ""), _transform(el.get("transform"))))
    return items, UNIT_MM[unit]


def _slicer_extruders(
    z: zipfile.ZipFile,
) -> tuple[dict[str, str], dict[tuple[str, str], str], dict[tuple[str, str], str], list[str]]:
    """Bambu Studio / OrcaSlicer: extruder per object and per (object, part), part names,
    filament names."""
    from lxml import etree

    obj_ext: dict[str, str] = {}
    part_ext: dict[tuple[str, str], str] = {}
    part_name: dict[tuple[str, str], str] = {}
    names = set(z.namelist())
    if "Metadata/model_settings.config" in names:
        root = etree.fromstring(z.read("Metadata/model_settings.config"),
                                parser=etree.XMLParser(resolve_entities=False))
        for obj in root.iter("object"):
            oid = obj.get("id", "")
            for md in obj.findall("metadata"):
                if md.get("key") == "extruder":
                    obj_ext[oid] = md.get("value", "")
            for part in obj.iter("part"):
                for md in part.findall("metadata"):
                    if md.get("key") == "extruder":
                        part_ext[(oid, part.get("id", ""))] = md.get("value", "")
                    elif md.get("key") == "name":
                        part_name[(oid, part.get("id", ""))] = md.get("value", "")
    filaments: list[str] = []
    if "Metadata/project_settings.config" in names:
        settings = json.loads(z.read("Metadata/project_settings.config"))
        filaments = [str(f) for f in settings.get("filament_settings_id", [])]
    return obj_ext, part_ext, part_name, filaments


def _filament(ext: str | None, filaments: Sequence[str]) -> str | None:
    if ext is None:
        return None
    if not ext.isdigit() or not 1 <= int(ext) <= len(filaments):
        raise ValueError(f"extruder {ext!r} has no filament (the project lists {len(filaments)})")
    return filaments[int(ext) - 1]


def _read_3mf(path: Path) -> tuple[list[_RawPart], str]:
    try:
        z = zipfile.ZipFile(path)
    except (zipfile.BadZipFile, OSError) as exc:
        raise MeshFileError(path, f"not a 3MF (zip) file: {exc}") from None
    with z:
        main = next((n for n in z.namelist() if n.lower() == "3d/3dmodel.model"), None)
        if main is None:
            raise MeshFileError(path, "no 3D/3dmodel.model in the archive: not a 3MF file")
        objects: dict[tuple[str, str], _Object] = {}
        try:
            items, mm = _read_model(z.read(main), main, objects)
            obj_ext, part_ext, part_name, filaments = _slicer_extruders(z)
        except Exception as exc:  # lxml, JSON, numbers: whatever is malformed, one line
            raise MeshFileError(path, f"malformed 3MF: {exc}") from None
        loaded = {main}

        def obj(model: str, oid: str) -> _Object:
            if (model, oid) not in objects and model not in loaded:
                if model not in z.namelist():
                    raise MeshFileError(path, f"a component names {model!r}, which the archive lacks")
                try:
                    _read_model(z.read(model), model, objects)
                except Exception as exc:
                    raise MeshFileError(path, f"malformed 3MF part {model}: {exc}") from None
                loaded.add(model)
            if (model, oid) not in objects:
                raise MeshFileError(path, f"object id {oid} is used but not defined in {model}")
            return objects[(model, oid)]

        parts: list[_RawPart] = []

        def walk(o: _Object, model: str, tf: np.ndarray, top: str, top_name: str, ext: str | None,
                 depth: int) -> None:
            if depth > 16:
                raise MeshFileError(path, f"components of object {top} nest too deep (a cycle?)")
            if o.vertices is not None and o.faces is not None and len(o.faces):
                v = (np.c_[o.vertices, np.ones(len(o.vertices))] @ tf.T)[:, :3] * mm
                name = part_name.get((top, o.oid)) or (o.name if o.oid != top else top_name)
                try:
                    filament = _filament(part_ext.get((top, o.oid), ext), filaments)
                except ValueError as exc:
                    raise MeshFileError(path, f"part {name!r}: {exc}") from None
                if filament is not None or not o.tri_mat or len(set(o.tri_mat)) == 1:
                    mat = filament or (o.tri_mat[0] if o.tri_mat else None) or name
                    parts.append(_RawPart(name, mat, v, o.faces))
                else:  # one object painted with several base materials: a part per material
                    tm = np.array([m or "" for m in o.tri_mat])
                    for m in dict.fromkeys(tm.tolist()):
                        parts.append(_RawPart(f"{name} [{m or 'unnamed'}]", m or name, v, o.faces[tm == m]))
            for cid, cpath, ctf in o.components:
                cmodel = cpath.lstrip("/") if cpath else model
                child = obj(cmodel, cid)
                walk(child, cmodel, tf @ ctf, top, top_name, part_ext.get((top, cid), ext), depth + 1)

        if not items:
            raise MeshFileError(path, "the 3MF's build has no items: nothing to print")
        for oid, tf in items:
            o = obj(main, oid)
            walk(o, main, tf, oid, o.name, obj_ext.get(oid), 0)
    unit = next(k for k, v in UNIT_MM.items() if v == mm)
    return parts, unit


# -- STL folder --------------------------------------------------------------------------
def _read_stl_folder(path: Path) -> tuple[list[_RawPart], str]:
    import trimesh

    files = sorted(p for p in path.iterdir() if p.suffix.lower() == ".stl" and p.is_file())
    if not files:
        raise MeshFileError(path, "no .stl files in the folder (one STL per material is expected)")
    parts = []
    for f in files:
        try:
            m = trimesh.load(f, file_type="stl", force="mesh", process=False)
        except Exception as exc:  # trimesh raises many kinds on a bad file
            raise MeshFileError(f, f"not a readable STL: {exc}") from None
        faces = np.asarray(getattr(m, "faces", np.zeros((0, 3))))
        parts.append(_RawPart(f.stem, f.stem, np.asarray(getattr(m, "vertices", np.zeros((0, 3)))), faces, f))
    return parts, "millimeter (STL has no units; assumed, as slicers do)"


# -- the mockup ----------------------------------------------------------------------------
def _rotation(rotate_deg: Sequence[float]) -> np.ndarray:
    rx, ry, rz = (float(a) for a in rotate_deg)
    return rot_z(rz) @ rot_y(ry) @ rot_x(rx)


def _gap(lo: np.ndarray, hi: np.ndarray, lo2: np.ndarray, hi2: np.ndarray) -> float:
    """Distance between two axis-aligned boxes (0 when they touch or overlap)."""
    d = np.maximum(0.0, np.maximum(lo2 - hi, lo - hi2))
    return float(np.linalg.norm(d))


def load_mesh_mockup(
    path: str | Path, satellite: str, materials: Sequence[str], *,
    rotate_deg: Sequence[float] = (0.0, 0.0, 0.0),
) -> tuple[Mockup, MeshInfo]:
    """The mockup of a build from ``path`` (a ``.3mf`` file or a folder of ``.stl`` files),
    checked against the build's ``materials`` (module docstring). ``rotate_deg`` turns the
    model (about x, then y, then z, degrees) when it was printed lying down."""
    import trimesh

    path = Path(path)
    if not path.exists():
        raise MeshFileError(path, "no such file or folder")
    if path.is_dir():
        raw, units = _read_stl_folder(path)
    elif path.suffix.lower() == ".3mf":
        raw, units = _read_3mf(path)
    elif path.suffix.lower() == ".stl":
        raise MeshFileError(path, "one STL carries no materials: give a folder of STL files, one per "
                                  "material (named after it), or the slicer's 3MF")
    else:
        kind = path.suffix or "(none)"
        raise MeshFileError(path, f"unknown mockup file type {kind!r}: a .3mf or a folder of .stl files")
    build = list(materials)
    rot = _rotation(rotate_deg)
    meshes: list[tuple[str, str, trimesh.Trimesh]] = []
    sources: dict[str, Path] = {}
    for p in raw:
        where = f"part {p.name!r}"
        src = p.source or path  # an STL of a folder is named itself
        if len(p.faces) == 0 or len(p.vertices) == 0:
            raise MeshFileError(src, f"{where} has no triangles")
        if not np.isfinite(p.vertices).all():
            raise MeshFileError(src, f"{where} has non-finite vertex coordinates")
        if p.faces.min() < 0 or p.faces.max() >= len(p.vertices):
            raise MeshFileError(src, f"{where} has triangles naming vertices it does not have")
        key = material_key(p.material or "") or material_key(p.name)
        if key is None:
            raise MeshFileError(src, f"{where}: material {p.material!r} is none of the known filaments "
                                      f"({', '.join(MATERIAL_KEYS)})")
        if key not in build:
            raise MeshFileError(src, f"{where} is {key}, which the build {satellite} ({', '.join(build)}) "
                                      "does not have")
        tm = trimesh.Trimesh(p.vertices @ rot.T, p.faces, process=True)
        tm.update_faces(tm.nondegenerate_faces())
        tm.remove_unreferenced_vertices()
        if len(tm.faces) == 0:
            raise MeshFileError(src, f"{where} has only degenerate triangles")
        meshes.append((p.name, key, tm))
        sources[p.name] = src
    n_tri = sum(len(m.faces) for _, _, m in meshes)
    if n_tri > MAX_TRIANGLES:
        raise MeshFileError(path, f"{n_tri} triangles: more than {MAX_TRIANGLES}; decimate it in the slicer")
    lo = np.min([m.bounds[0] for _, _, m in meshes], axis=0)
    hi = np.max([m.bounds[1] for _, _, m in meshes], axis=0)
    size = hi - lo
    if not MIN_SIZE_MM <= float(size.max()) <= MAX_SIZE_MM:
        raise MeshFileError(path, f"the model is {float(size.max()):.4g} mm across in {units}: a mockup is "
                                  f"{MIN_SIZE_MM:g}–{MAX_SIZE_MM:g} mm (wrong units or scale?)")
    if len(meshes) > 1:
        for i, (name, _, m) in enumerate(meshes):
            rest = [mm for j, (_, _, mm) in enumerate(meshes) if j != i]
            rlo = np.min([r.bounds[0] for r in rest], axis=0)
            rhi = np.max([r.bounds[1] for r in rest], axis=0)
            gap = _gap(m.bounds[0], m.bounds[1], rlo, rhi)
            if gap > DETACHED * float((rhi - rlo).max()):
                why = "exported about its own origin, or in other units?"
                raise MeshFileError(sources[name], f"part {name!r} lies {gap:.4g} mm away from the rest of "
                                                   f"the model: {why}")
    used = {k for _, k, _ in meshes}
    primary = PRIMARY if PRIMARY in build else build[0]
    missing = [m for m in build if m not in used and m != primary]
    if missing:
        raise MeshFileError(path, f"no part is {', '.join(missing)}, which the build {satellite} has")
    centre = np.array([(lo[0] + hi[0]) / 2.0, (lo[1] + hi[1]) / 2.0, lo[2]])
    parts = []
    for name, key, m in meshes:
        # Split at edges sharper than the angle: a box stays flat-faced, a cylinder smooth.
        sm = trimesh.graph.smooth_shade(m, angle=np.radians(SMOOTH_ANGLE_DEG))
        normals = np.asarray(sm.vertex_normals, dtype=np.float64)
        parts.append(Part(name, Mesh(np.asarray(sm.vertices, dtype=np.float64) - centre, normals,
                                     np.asarray(sm.faces, dtype=np.int32)), (key,)))
    info = MeshInfo(
        source=str(path), units=units, size_mm=(float(size[0]), float(size[1]), float(size[2])),
        origin_offset_mm=(float(-centre[0]), float(-centre[1]), float(-centre[2])),
        parts=tuple((name, key, len(m.faces)) for name, key, m in meshes),
    )
    return Mockup(f"{satellite}:{path}", tuple(parts), (0.0, 0.0, 0.0)), info
