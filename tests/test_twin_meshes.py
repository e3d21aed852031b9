"""Mockups from the lab's files: 3MF (slicer extruders, base materials, names) and STL folders.

Every file here is built by the test itself with trimesh: a small Hubble-like model (tube,
band, two panels, a door), about 130 mm across, one part per material of Hubble B2.
"""

from __future__ import annotations

import io
import json
import zipfile
from pathlib import Path

import numpy as np
import pytest
import trimesh
from m2s2hil.simulators.clock import VirtualClock
from m2s2hil.simulators.meshes import MeshFileError, load_mesh_mockup, material_key
from m2s2hil.simulators.scene import Scene
from m2s2hil.simulators.world import LampInfo

from m2s2hil.catalog import load_catalog
from m2s2hil.config import DEFAULT_LAYOUT, ConfigError, load_rig
from m2s2hil.sim_config import build_frame_source, build_world

BANDS = (431, 479, 515, 567, 611, 666, 719, 775, 820, 877)
FWHM = (65, 47, 42, 37, 36, 34, 33, 31, 31, 31)
B2 = load_catalog().build("hubble", "B2").materials
LAMPS = {i: LampInfo(f"bar{i + 1}", "led_bar", 0.0) for i in range(3)}
WEAK = {0: 1.0, 1: 1.0, 2: 1.0}


def hubble_parts(scale: float = 1.0) -> dict[str, trimesh.Trimesh]:
    """Part name → mesh (mm × ``scale``), in the order tube, band, panels, door."""
    tube = trimesh.creation.cylinder(radius=20, height=100)
    tube.apply_translation((0, 0, 50))
    band = trimesh.creation.cylinder(radius=21, height=10)
    band.apply_translation((0, 0, 50))
    panels = trimesh.util.concatenate([trimesh.creation.box((30, 2, 80)).apply_translation((s * 45, 0, 50))
                                       for s in (-1, 1)])
    door = trimesh.creation.cylinder(radius=20, height=3)
    door.apply_translation((0, 0, 101.5))
    parts = {"tube": tube, "band": band, "panels": panels, "door": door}
    for m in parts.values():
        m.apply_scale(scale)
    return parts


MATERIAL_OF = {"tube": "pro_silver", "band": "dark_grey", "panels": "pro_metallic_blue",
               "door": "pro_metallic_magenta"}


def write_3mf(path: Path, names: dict[str, str], *, unit: str = "millimeter", scale: float = 1.0,
              extra: dict[str, str] | None = None) -> Path:
    """A 3MF (written by trimesh) whose objects are named ``names[part]``; ``extra`` adds files."""
    scene = trimesh.Scene()
    for part, mesh in hubble_parts(scale).items():
        scene.add_geometry(mesh, geom_name=names[part])
    data = scene.export(file_type="3mf")
    with zipfile.ZipFile(path, "w") as out, zipfile.ZipFile(io.BytesIO(data)) as src:
        for n in src.namelist():
            body = src.read(n)
            if n == "3D/3dmodel.model" and unit != "millimeter":
                body = body.replace(b'unit="millimeter"', f'unit="{unit}"'.encode())
            out.writestr(n, body)
        for n, text in (extra or {}).items():
            out.writestr(n, text)
    return path


def bambu_3mf(path: Path) -> Path:
    """One object of four parts (components in another model file, as Bambu Studio writes),
    each part's extruder in Metadata/model_settings.config, filaments in project_settings."""
    parts = list(hubble_parts().values())
    objs = []
    for i, m in enumerate(parts, start=2):
        vs = "".join(f'<vertex x="{x}" y="{y}" z="{z}"/>' for x, y, z in m.vertices)
        ts = "".join(f'<triangle v1="{a}" v2="{b}" v3="{c}"/>' for a, b, c in m.faces)
        objs.append(f'<object id="{i}" type="model"><mesh><vertices>{vs}</vertices>'
                    f'<triangles>{ts}</triangles></mesh></object>')
    ns = 'xmlns="http://schemas.microsoft.com/3dmanufacturing/core/2015/02" ' \
         'xmlns:p="http://schemas.microsoft.com/3dmanufacturing/production/2015/06"'
    sub = f'<?xml version="1.0"?><model unit="millimeter" {ns}><resources>{"".join(objs)}</resources></model>'
    comps = "".join(f'<component p:path="/3D/Objects/object_1.model" objectid="{i}" '
                    f'transform="1 0 0 0 1 0 0 0 1 0 0 0"/>' for i in range(2, 6))
    main = (f'<?xml version="1.0"?><model unit="millimeter" {ns}><resources><object id="1" name="hubble" '
            f'type="model"><components>{comps}</components></object></resources>'
            '<build><item objectid="1" transform="1 0 0 0 1 0 0 0 1 128 128 0"/></build></model>')
    names = ["tube", "band", "panels", "door"]
    ext = {"tube": 1, "band": 2, "panels": 3, "door": 4}
    cfg = "".join(f'<part id="{i}" subtype="normal_part"><metadata key="name" value="{n}"/>'
                  f'<metadata key="extruder" value="{ext[n]}"/></part>' for i, n in enumerate(names, start=2))
    settings = {"filament_settings_id": [
        "PolyLite PLA Pro Silver @BBL X1C", "Polymaker PolyLite PLA Dark Gray",
        "PolyLite PLA Pro Metallic Blue",
        "PolyLite PLA Pro Metallic Magenta",
    ]}
    with zipfile.ZipFile(path, "w") as z:
        z.writestr("3D/3dmodel.model", main)
        z.writestr("3D/Objects/object_1.model", sub)
        z.writestr("Metadata/model_settings.config",
                   f'<?xml version="1.0"?><config><object id="1"><metadata key="extruder" value="1"/>{cfg}'
                   "</object></config>")
        z.writestr("Metadata/project_settings.config", json.dumps(settings))
    return path


def painted_3mf(path: Path) -> Path:
    """One object whose triangles name their base material (3MF core materials, pid/p1)."""
    parts = list(hubble_parts().values())
    mesh = trimesh.util.concatenate(parts)
    owner = np.repeat(np.arange(len(parts)), [len(m.faces) for m in parts])
    vs = "".join(f'<vertex x="{x}" y="{y}" z="{z}"/>' for x, y, z in mesh.vertices)
    ts = "".join(f'<triangle v1="{a}" v2="{b}" v3="{c}" pid="9" p1="{k}"/>'
                 for (a, b, c), k in zip(mesh.faces, owner, strict=True))
    bases = "".join(f'<base name="PolyLite PLA {n}" displaycolor="#808080"/>'
                    for n in ("Pro Silver", "Dark Grey", "Pro Metallic Blue", "Pro Metallic Magenta"))
    model = ('<?xml version="1.0"?><model unit="millimeter" '
             'xmlns="http://schemas.microsoft.com/3dmanufacturing/core/2015/02"><resources>'
             f'<basematerials id="9">{bases}</basematerials><object id="1" name="hubble" pid="9" pindex="0">'
             f'<mesh><vertices>{vs}</vertices><triangles>{ts}</triangles></mesh></object></resources>'
             '<build><item objectid="1"/></build></model>')
    with zipfile.ZipFile(path, "w") as z:
        z.writestr("3D/3dmodel.model", model)
    return path


def stl_folder(path: Path, names: dict[str, str] | None = None, scale: float = 1.0) -> Path:
    path.mkdir()
    for part, mesh in hubble_parts(scale).items():
        mesh.export(path / f"{(names or MATERIAL_OF)[part]}.stl")
    return path


def materials_of(mockup) -> dict[str, str]:
    return {p.name: p.prefs[0] for p in mockup.parts}


def test_material_names_resolve_to_catalog_keys():
    assert material_key("PolyLite PLA Pro Silver @BBL X1C") == "pro_silver"
    assert material_key("Polymaker PolyLite PLA Dark Gray") == "dark_grey"
    assert material_key("pro_metallic_blue.stl") == "pro_metallic_blue"
    assert material_key("Azure Blue") == "azure_blue" and material_key("Bambu PLA Basic") is None


def test_3mf_named_objects_load_with_units_origin_and_materials(tmp_path):
    f = write_3mf(tmp_path / "h.3mf", MATERIAL_OF)
    m, info = load_mesh_mockup(f, "hubble B2", B2)
    assert sorted(materials_of(m).values()) == sorted(B2)
    assert info.units == "millimeter" and info.size_mm == pytest.approx((120, 42, 103), abs=0.5)
    verts = np.concatenate([p.mesh.vertices for p in m.parts])
    assert np.allclose([verts[:, 0].min() + verts[:, 0].max(), verts[:, 1].min() + verts[:, 1].max()], 0,
                       atol=1e-6) and verts[:, 2].min() == pytest.approx(0.0)  # axis through the middle
    # The same model in centimetres is 10x larger: still a mockup (1200 mm > 1000 mm is refused).
    with pytest.raises(MeshFileError, match=r"1200 mm across in centimeter"):
        load_mesh_mockup(write_3mf(tmp_path / "cm.3mf", MATERIAL_OF, unit="centimeter"), "hubble B2", B2)


def test_bambu_3mf_parts_take_their_extruders_filament(tmp_path):
    _, info = load_mesh_mockup(bambu_3mf(tmp_path / "b.3mf"), "hubble B2", B2)
    assert [(n, k) for n, k, _ in info.parts] == [
        ("tube", "pro_silver"), ("band", "dark_grey"), ("panels", "pro_metallic_blue"),
        ("door", "pro_metallic_magenta"),
    ]
    assert info.origin_offset_mm[:2] == pytest.approx((-128.0, -128.0))  # the plate position, dropped


def test_painted_3mf_splits_an_object_by_its_triangles_base_material(tmp_path):
    _, info = load_mesh_mockup(painted_3mf(tmp_path / "p.3mf"), "hubble B2", B2)
    got = {k: n for _, k, n in info.parts}
    assert set(got) == set(B2) and sum(got.values()) == sum(len(m.faces) for m in hubble_parts().values())


def test_stl_folder_one_file_per_material_renders_its_labels(tmp_path):
    m, _ = load_mesh_mockup(stl_folder(tmp_path / "stl"), "hubble B2", B2)
    scene = Scene(96, 96, BANDS, FWHM, DEFAULT_LAYOUT)
    scene.meshes[("hubble", "B2")] = m
    sh = scene.render("hubble", B2, 0.0, 0.0, WEAK, LAMPS, build="B2")
    seen = {sh.mount.class_names[i] for i in np.unique(sh.label)}
    assert seen == {"background", *B2} and sh.mount.source == m.name
    # Without the build the built-in mockup is rendered: another silhouette.
    builtin = scene.render("hubble", B2, 0.0, 0.0, WEAK, LAMPS)
    assert builtin.mount.source == "" and (builtin.label > 0).sum() != (sh.label > 0).sum()


@pytest.mark.parametrize("case, match", [
    ("missing", "no such file or folder"),
    ("not_zip", "not a 3MF"),
    ("single_stl", "one STL carries no materials"),
    ("metres", r"0.12 mm across"),
    ("not_in_build", "is red, which the build hubble B2"),
    ("unknown", "'tube' is none of the known filaments"),
    ("missing_material", "no part is pro_metallic_magenta"),
    ("detached", "pro_metallic_magenta.stl: part 'pro_metallic_magenta' lies"),
    ("empty_folder", "no .stl files"),
])
def test_a_bad_file_is_one_line_naming_it(tmp_path, case, match):
    names = dict(MATERIAL_OF)
    if case == "missing":
        path = tmp_path / "none.3mf"
    elif case == "not_zip":
        path = tmp_path / "x.3mf"
        path.write_text("solid nothing")
    elif case == "single_stl":
        path = tmp_path / "tube.stl"
        hubble_parts()["tube"].export(path)
    elif case == "metres":  # exported in metres, read as STL's millimetres
        path = stl_folder(tmp_path / "stl", scale=0.001)
    elif case in ("not_in_build", "unknown", "missing_material"):
        names["door"] = {"not_in_build": "red", "unknown": "tube", "missing_material": "dark_grey"}[case]
        if case == "unknown":
            names = {**MATERIAL_OF, "tube": "tube"}
        path = write_3mf(tmp_path / "h.3mf", names)
    elif case == "detached":  # the door exported about its own origin, far from the rest
        path = stl_folder(tmp_path / "stl")
        door = hubble_parts()["door"]
        door.apply_translation((400, 0, 0))
        door.export(path / "pro_metallic_magenta.stl")
    else:
        path = tmp_path / "empty"
        path.mkdir()
    with pytest.raises(MeshFileError, match=match) as err:
        load_mesh_mockup(path, "hubble B2", B2)
    assert str(err.value).startswith(str(path)) and "\n" not in str(err.value)


def rig_with_mesh(tmp_path: Path, body: str) -> Path:
    from rig_files import rig_text

    rig = tmp_path / "rig.toml"
    rig.write_text(rig_text() + "\n" + body)
    return rig


def test_rig_file_mesh_is_found_next_to_it_and_rendered(tmp_path):
    write_3mf(tmp_path / "meshes.3mf", MATERIAL_OF)
    rig = load_rig(rig_with_mesh(tmp_path, '[simulation.mockups.Hubble.b2]\nmesh = "meshes.3mf"\n'))
    assert rig.simulation.mockups["hubble"]["B2"].mesh == tmp_path / "meshes.3mf"
    world = build_world(rig, clock=VirtualClock())
    source = build_frame_source(rig, world)
    assert set(source.scene.meshes) == {("hubble", "B2")}
    world.mount("hubble", "B2")
    for ch in (0, 1, 2):
        world.set_lamp(ch, True)
    source.capture(0.01)
    truth = source.truth()
    assert {truth.class_names[i] for i in np.unique(truth.labels)} == {"background", *B2}


def test_rig_file_mesh_errors_name_the_key_or_the_file(tmp_path):
    with pytest.raises(ConfigError, match=r"simulation.mockups.*unknown satellite 'apollo'"):
        load_rig(rig_with_mesh(tmp_path, '[simulation.mockups.apollo.B2]\nmesh = "m.3mf"\n'))
    rig = load_rig(rig_with_mesh(tmp_path, '[simulation.mockups.hubble.B2]\nmesh = "gone.3mf"\n'))
    world = build_world(rig, clock=VirtualClock())
    with pytest.raises(MeshFileError, match=r"gone.3mf: no such file"):
        build_frame_source(rig, world)


def test_synth_renders_the_lab_mesh_the_rig_file_names(tmp_path):
    from cli_support import run_cli

    from m2s2hil.store.session import SessionStore
    from m2s2hil.twin.synth import band_images

    stl_folder(tmp_path / "stl")
    rig = rig_with_mesh(tmp_path, '[simulation.mockups.hubble.B2]\nmesh = "stl"\n')
    r = run_cli("synth", "--sat", "hubble", "--build", "B2", "--tilts", "E1", "--step", "180", "--size", "48",
                "--rig", rig, "--root", tmp_path / "root", "--session-id", "syn-mesh")
    assert r.exit_code == 0, r.stderr
    with SessionStore.open(tmp_path / "root", "syn-mesh") as st:
        fr = st.frames()[0]
        _, _, mask = band_images(st, fr.event_id)
    assert fr.meta["synthetic"]["mockup"] == f"hubble B2:{tmp_path / 'stl'}"
    assert {fr.meta["class_names"][i] for i in np.unique(mask)} == {"background", *B2}
    # A file that cannot be used is one line naming it, and no session is created.
    (tmp_path / "stl" / "dark_grey.stl").write_text("solid broken\nfacet oops\n")
    r = run_cli("synth", "--sat", "hubble", "--build", "B2", "--size", "16", "--rig", rig,
                "--root", tmp_path / "root2")
    assert r.exit_code == 2 and len(r.stderr.strip().splitlines()) == 1
    assert f"{tmp_path / 'stl' / 'dark_grey.stl'}: part 'dark_grey' has no triangles" in r.stderr
    assert not (tmp_path / "root2").exists() or not any((tmp_path / "root2").iterdir())
