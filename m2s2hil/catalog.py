"""The M2S2 catalog as data: satellites, builds, materials, lighting, elevations.

Everything comes from ``data/catalog.toml``; nothing here branches on a name. Builds follow
Table 1 of the paper, including Hubble B3 = the four filaments of B2 (5 classes), not Table 2's
11 classes; the reasons are in catalog.toml and docs/analysis.md ("Hubble B2 and B3"). Where
the filaments sit on a mockup is the simulator's (``simulators/mockups.py``).
"""

from __future__ import annotations

import difflib
import tomllib
from functools import cache
from importlib import resources

from pydantic import BaseModel, ConfigDict

from m2s2hil.errors import CatalogError


class _Frozen(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")


class Material(_Frozen):
    key: str
    name: str
    line: str
    metallic: bool


class Build(_Frozen):
    satellite: str
    key: str  # "B1".."B3"
    materials: tuple[str, ...]

    @property
    def number(self) -> int:
        return int(self.key[1:])


class Satellite(_Frozen):
    key: str
    name: str
    builds: dict[str, Build]


class Lighting(_Frozen):
    key: str  # weak | strong | directional
    name: str
    dataset: str  # solo | all | dir
    description: str


class Elevation(_Frozen):
    key: str  # E0 | E1 | E2 (E3: synthetic only)
    description: str
    tilt_deg: float | None = None  # a synthetic-only elevation's tilt (HIL tilts are the rig file's)

    @property
    def number(self) -> int:
        return int(self.key[1:])


class Catalog(_Frozen):
    materials: dict[str, Material]
    satellites: dict[str, Satellite]
    lighting: dict[str, Lighting]
    elevations: dict[str, Elevation]
    synthetic_elevations: dict[str, Elevation] = {}  # rendered only (m2s2hil synth), never captured

    def satellite(self, name: str) -> Satellite:
        return self.satellites[_match("satellite", name, self.satellites, _alias_sat(self))]

    def build(self, satellite: str, build: str) -> Build:
        sat = self.satellite(satellite)
        key = _match(f"build of {sat.name}", build.upper(), sat.builds)
        return sat.builds[key]

    def light(self, name: str) -> Lighting:
        aliases = {lt.dataset: k for k, lt in self.lighting.items()}
        aliases.update({lt.name.replace(" ", "-"): k for k, lt in self.lighting.items()})
        return self.lighting[_match("lighting condition", name, self.lighting, aliases)]

    def elevation(self, name: str) -> Elevation:
        return self.elevations[_match("elevation", name.upper(), self.elevations)]

    def material(self, name: str) -> Material:
        return self.materials[_match("material", name, self.materials)]

    def class_names(self, satellite: str, build: str) -> list[str]:
        """Label names of a build: index 0 is background, then its materials in catalog order."""
        return ["background", *self.build(satellite, build).materials]


def _alias_sat(cat: Catalog) -> dict[str, str]:
    return {s.name.lower(): k for k, s in cat.satellites.items()}


def _match(kind: str, name: str, known: dict, aliases: dict[str, str] | None = None) -> str:
    if name in known:
        return name
    low = name.strip().lower()
    for k in known:
        if k.lower() == low:
            return k
    if aliases:
        for a, k in aliases.items():
            if a.lower() == low:
                return k
    choices = sorted(known)
    close = difflib.get_close_matches(low, [c.lower() for c in choices], n=1)
    hint = f"; did you mean {close[0]!r}?" if close else ""
    raise CatalogError(f"unknown {kind} {name!r}; known: {', '.join(choices)}{hint}")


@cache
def load_catalog() -> Catalog:
    raw = tomllib.loads(resources.files("m2s2hil").joinpath("data/catalog.toml").read_text())
    materials = {k: Material(key=k, **v) for k, v in raw["materials"].items()}
    sats = {}
    for k, v in raw["satellites"].items():
        builds = {}
        for b, mats in v["builds"].items():
            unknown = [m for m in mats if m not in materials]
            if unknown:
                raise CatalogError(f"catalog.toml: satellites.{k}.builds.{b}: unknown {unknown}")
            builds[b] = Build(satellite=k, key=b, materials=tuple(mats))
        sats[k] = Satellite(key=k, name=v["name"], builds=builds)
    lighting = {k: Lighting(key=k, **v) for k, v in raw["lighting"].items()}
    elevations = {k: Elevation(key=k, **v) for k, v in raw["elevations"].items()}
    synthetic = {k: Elevation(key=k, **v) for k, v in raw.get("synthetic_elevations", {}).items()}
    return Catalog(materials=materials, satellites=sats, lighting=lighting, elevations=elevations,
                   synthetic_elevations=synthetic)


def satellite_key(name: str) -> str:
    """The catalog key of satellite ``name`` (aliases accepted) for a pydantic validator: an
    unknown name raises ``ValueError`` with the catalog's message (known names, a hint)."""
    try:
        return load_catalog().satellite(name).key
    except CatalogError as exc:
        raise ValueError(str(exc)) from None
