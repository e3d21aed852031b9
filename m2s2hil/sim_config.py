"""The ``[simulation]`` section of a rig file, and the one builder of the simulated world.

The section is validated like the rest of the file (unknown keys and wrong types are
refused), and its faults are checked against the rig: each names a device of the rig (or
the camera by its ``sim://`` name), a kind that device's simulator handles and only the
parameters that kind takes (``simulators.fault_injection.FAULT_KINDS_BY_DEVICE``)::

    [simulation]
    spot_angle_deg = 30.0
    sensor_temperature_c = 40.0

    [simulation.sensor]
    read_noise_e = 9.0

    [[simulation.faults.stage]]
    kind = "alarm"
    after = 3
    code = 1

    [[simulation.faults.toucan]]
    kind = "frame_timeout"
    rate = 0.01        # one frame in a hundred, seeded

    [simulation.mount]   # the mockup as it really sits (MountSettings): off the axis, turned, ...
    offset_mm = [2.0, 0.0]

    [simulation.lamps]   # lamp name -> output factor: a dead (0) or dim lamp
    bar1 = 0.0

:func:`build_world` and :func:`build_frame_source` turn a configuration into the simulated
world and the camera's frame source; the rig factory, ``m2s2hil sim snapshot`` and the
ground-truth scenes all use them. Simulator modules are imported only when something is
built, so validating a rig file stays cheap.
"""

from __future__ import annotations

import urllib.parse
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    TypeAdapter,
    ValidationError,
    field_validator,
    model_validator,
)

from m2s2hil.errors import ConfigError, validation_problem
from m2s2hil.simulators.fault_injection import FAULT_KINDS, FAULT_KINDS_BY_DEVICE, FaultPlan

if TYPE_CHECKING:
    from m2s2hil.config import CameraModel, RigConfig
    from m2s2hil.simulators.frames import SimFrameSource
    from m2s2hil.simulators.sensor import SensorParams
    from m2s2hil.simulators.world import World

DEFAULT_CAMERA_SIM_NAME = "toucan"
SIM_SCHEME = "sim://"


def is_simulated(port: str) -> bool:
    """Whether a rig file's port is an in-process simulator (``sim://NAME``): the one test
    of it, so that a rig, a device and the camera are called simulated alike."""
    return port.startswith(SIM_SCHEME)


def sim_name(port: str) -> str | None:
    """The NAME of a ``sim://NAME`` port, read as the ``sim://`` serial handler reads it
    (simulators/protocol_sim.py), else None."""
    if not is_simulated(port):
        return None
    parts = urllib.parse.urlsplit(port)
    return parts.netloc or parts.path.lstrip("/")

PositiveFloat = Annotated[float, Field(gt=0)]
NonNegativeFloat = Annotated[float, Field(ge=0)]


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class SensorSettings(_Model):
    """Overrides of the simulated sensor's parameters (``simulators.sensor.SensorParams``);
    a key left out keeps the simulator's default."""

    full_well_e: PositiveFloat | None = None
    e_per_dn: PositiveFloat | None = None
    signal_e_per_s: PositiveFloat | None = None
    qe_nm: tuple[float, ...] | None = None
    qe: tuple[Annotated[float, Field(ge=0, le=1)], ...] | None = None
    read_noise_e: NonNegativeFloat | None = None
    black_level_dn: NonNegativeFloat | None = None
    dsnu_dn: NonNegativeFloat | None = None
    dark_current_e_per_s: NonNegativeFloat | None = None
    dark_ref_temp_c: float | None = None
    dark_doubling_c: PositiveFloat | None = None
    dark_nonuniformity: NonNegativeFloat | None = None
    hot_pixel_fraction: Annotated[float, Field(ge=0, lt=1)] | None = None
    hot_pixel_e_per_s: NonNegativeFloat | None = None
    hot_pixel_spread: NonNegativeFloat | None = None
    noise_pool_extra: Annotated[int, Field(ge=1)] | None = None

    @model_validator(mode="after")
    def _curves(self) -> SensorSettings:
        if (self.qe is None) != (self.qe_nm is None):
            raise ValueError("qe and qe_nm go together: give both curves or neither")
        if self.qe is not None and self.qe_nm is not None and (
            len(self.qe) != len(self.qe_nm) or len(self.qe) < 2
        ):
            raise ValueError(f"qe has {len(self.qe)} values for {len(self.qe_nm)} wavelengths (need >= 2)")
        return self

    def params(self) -> SensorParams:
        from m2s2hil.simulators.sensor import SensorParams

        return SensorParams(**self.model_dump(exclude_none=True))


class FaultSpec(_Model):
    """One injected fault: ``kind``, when it fires (``after``, ``count``, ``rate``) and the
    kind's parameters. Which parameters a kind takes depends on the device (checked
    against the rig by :func:`check_faults`)."""

    kind: str
    count: Annotated[int, Field(ge=-1)] | None = None  # default 1, or forever with a rate
    after: Annotated[int, Field(ge=0)] = 0
    rate: Annotated[float, Field(gt=0, le=1)] | None = None  # probability per opportunity
    # parameters (see simulators.fault_injection)
    delay_s: Annotated[float, Field(gt=0)] | None = None
    duration_s: Annotated[float, Field(gt=0)] | None = None  # a long one: gone for good
    fraction: Annotated[float, Field(gt=0, lt=1)] | None = None
    at: Annotated[float, Field(ge=0, le=1)] | None = None
    code: int | None = None
    flag: Annotated[str, Field(pattern=r"^F[A-Z]$")] | None = None
    channel: Annotated[int, Field(ge=0, le=255)] | None = None
    status: Annotated[int, Field(ge=0, le=0xFFFF)] | None = None
    bytes: Annotated[int, Field(ge=1)] | None = None
    factor: Annotated[float, Field(ge=1)] | None = None  # slow_motion: times slower than configured

    @field_validator("kind")
    @classmethod
    def _known_kind(cls, v: str) -> str:
        if v not in FAULT_KINDS:
            raise ValueError(f"unknown fault kind {v!r}; known: {', '.join(sorted(FAULT_KINDS))}")
        return v

    @field_validator("code")
    @classmethod
    def _grbl_alarm(cls, v: int | None) -> int | None:
        from m2s2hil.protocols.grbl import GrblAlarm

        if v is not None and v not in set(GrblAlarm):
            raise ValueError(f"not a GRBL 1.1 alarm code: {v} (1 … {max(GrblAlarm)})")
        return v

    def params(self) -> dict[str, Any]:
        """The kind's parameters that were given."""
        return self.model_dump(exclude_none=True, exclude={"kind", "count", "after", "rate"})


class GrblSimOptions(_Model):
    """``[simulation.devices.NAME]`` of a GRBL device: how its simulated controller is
    commissioned (``simulators.grbl.grbl_sim_for``); a key left out keeps its default."""

    homing_switches: bool | None = None  # home switches fitted and homing enabled ($22=1)
    factory_rates: bool | None = None  # keep GRBL's factory $110..$132
    settings: dict[Annotated[str, Field(pattern=r"^\$?[0-9]{1,3}$")], float] | None = None
    version: str | None = None
    build: str | None = None

    def options(self) -> dict[str, Any]:
        return self.model_dump(exclude_none=True)


class MountSettings(_Model):
    """``[simulation.mount]``: the mockup as it really sits on the simulated rig, where a
    bench set up wrong differs from the nominal mount (``simulators.world.Placement``)::

        [simulation.mount]
        offset_mm = [2.0, 0.0]   # centre off the turntable axis: x right, y away from the camera
        yaw_deg = 2.0            # turned about its own axis at azimuth 0
        tilt_bias_deg = 0.5      # the tilt stage's true angle minus its read-back
        build = "B1"             # the build really on the turntable, whatever the session says
    """

    offset_mm: tuple[Annotated[float, Field(ge=-50, le=50)], Annotated[float, Field(ge=-50, le=50)]] = (
        0.0, 0.0)
    yaw_deg: Annotated[float, Field(ge=-180, le=180)] = 0.0
    tilt_bias_deg: Annotated[float, Field(ge=-30, le=30)] = 0.0
    satellite: str | None = Field(None, min_length=1)
    build: Annotated[str, Field(pattern=r"^[Bb][0-9]+$")] | None = None
    diameter_mm: Annotated[float, Field(gt=10, le=2000)] = Field(
        160.0, description="the mockup's bounding-sphere diameter (turns mm into the scene's units)"
    )

    @field_validator("satellite")
    @classmethod
    def _known_satellite(cls, v: str | None) -> str | None:
        if v is None:
            return v
        from m2s2hil.catalog import satellite_key

        return satellite_key(v)

    @field_validator("build")
    @classmethod
    def _known_build(cls, v: str | None) -> str | None:
        if v is None:
            return v
        from m2s2hil.catalog import load_catalog

        v = v.upper()
        known = sorted({b for sat in load_catalog().satellites.values() for b in sat.builds})
        if v not in known:
            raise ValueError(f"no satellite has a build {v!r}; known: {', '.join(known)}")
        return v

    def placement(self) -> Any:
        from m2s2hil.simulators.world import Placement

        return Placement(
            offset_x_mm=float(self.offset_mm[0]), offset_y_mm=float(self.offset_mm[1]),
            yaw_deg=float(self.yaw_deg), tilt_bias_deg=float(self.tilt_bias_deg),
            satellite=self.satellite, build=self.build, diameter_mm=float(self.diameter_mm),
        )


class MockupFile(_Model):
    """``[simulation.mockups.SATELLITE.BUILD]``: the build's geometry from the lab's own files
    instead of the built-in mockup (``simulators.meshes``): ``mesh`` is a slicer's 3MF or a
    folder of STL files, one per material; a relative path is found next to the rig file."""

    mesh: Path
    rotate_deg: tuple[float, float, float] = Field(
        (0.0, 0.0, 0.0), description="turn the model about x, then y, then z (printed lying down)"
    )


class SimulationConfig(_Model):
    """What the simulators need beyond the devices: the scene, the sensor and injected faults."""

    spot_angle_deg: Annotated[float, Field(gt=-90, lt=90)] = Field(
        45.0, description="spotlight incidence from the camera axis, about vertical"
    )
    sensor_temperature_c: Annotated[float, Field(ge=-40, le=100)] = 35.0
    camera_serial: str = Field("TOUCAN-SIM-0001", min_length=1)
    sensor: SensorSettings = SensorSettings()
    devices: dict[str, GrblSimOptions] = Field(
        default_factory=dict, description="device name -> options of its simulator (GRBL only)"
    )
    faults: dict[str, list[FaultSpec]] = Field(
        default_factory=dict, description="device name -> faults injected into its simulator"
    )
    mount: MountSettings = MountSettings()
    lamps: dict[str, Annotated[float, Field(ge=0, le=1)]] = Field(
        default_factory=dict, description="lamp name -> output factor (0: dead, 0.5: dim to half)"
    )

    mockups: dict[str, dict[str, MockupFile]] = Field(
        default_factory=dict, description="satellite -> build -> the lab's mesh of it (3MF or STL folder)"
    )

    def device_options(self, name: str) -> dict[str, Any]:
        """The options of device ``name``'s simulator (empty: its defaults)."""
        opts = self.devices.get(name)
        return opts.options() if opts is not None else {}

    @field_validator("mockups")
    @classmethod
    def _catalog_builds(cls, v: dict[str, dict[str, MockupFile]]) -> dict[str, dict[str, MockupFile]]:
        from m2s2hil.catalog import load_catalog
        from m2s2hil.errors import CatalogError

        cat = load_catalog()
        out: dict[str, dict[str, MockupFile]] = {}
        for sat, builds in v.items():
            for build, spec in builds.items():
                try:
                    b = cat.build(sat, build)
                except CatalogError as exc:
                    raise ValueError(f"{sat}.{build}: {exc}") from None
                out.setdefault(b.satellite, {})[b.key] = spec
        return out

    def resolved(self, folder: Path) -> SimulationConfig:
        """This section with every relative mesh path taken from ``folder`` (the rig file's)."""
        def where(spec: MockupFile) -> MockupFile:
            return spec if spec.mesh.is_absolute() else spec.model_copy(update={"mesh": folder / spec.mesh})

        mockups = {sat: {b: where(spec) for b, spec in builds.items()}
                   for sat, builds in self.mockups.items()}
        return self.model_copy(update={"mockups": mockups})


_FAULTS = TypeAdapter(dict[str, list[FaultSpec]])


def camera_sim_name(rig: RigConfig) -> str:
    """The name the camera's simulator (and its faults) goes by: its ``sim://`` name."""
    return sim_name(rig.camera.port) or DEFAULT_CAMERA_SIM_NAME


def check_devices(rig: RigConfig) -> None:
    """Refuse simulator options for a device the rig does not have or whose simulator takes none."""
    for name in rig.simulation.devices:
        dev = rig.devices.get(name)
        if dev is None:
            known = ", ".join(rig.devices)
            raise ConfigError("", f"simulation.devices.{name}", f"no device named {name!r}; known: {known}")
        if dev.protocol != "grbl":
            raise ConfigError(
                "", f"simulation.devices.{name}",
                f"{name!r} speaks {dev.protocol}: only GRBL simulators take options",
            )
    for name in rig.simulation.lamps:
        if name not in rig.lamps:
            known = ", ".join(rig.lamps)
            raise ConfigError("", f"simulation.lamps.{name}", f"no lamp named {name!r}; known: {known}")
    mount = rig.simulation.mount
    if mount.satellite is not None and mount.build is not None:
        from m2s2hil.catalog import load_catalog

        builds = load_catalog().satellite(mount.satellite).builds
        if mount.build not in builds:
            raise ConfigError("", "simulation.mount.build",
                              f"{mount.satellite} has no build {mount.build!r}; it has: {', '.join(builds)}")
    check_faults(rig, rig.simulation.faults)


def check_faults(
    rig: RigConfig, faults: Mapping[str, list[FaultSpec]], prefix: str = "simulation.faults"
) -> None:
    """Refuse a fault for a device the rig does not have, a kind its simulator does not
    handle, or a parameter the kind does not take (ConfigError naming the key)."""
    device_kind: dict[str, str] = {name: dev.protocol for name, dev in rig.devices.items()}
    device_kind[camera_sim_name(rig)] = "u3v"
    for name, specs in faults.items():
        kind_of_device = device_kind.get(name)
        if kind_of_device is None:
            known = ", ".join(device_kind)
            raise ConfigError("", f"{prefix}.{name}", f"no device named {name!r}; known: {known}")
        kinds = FAULT_KINDS_BY_DEVICE[kind_of_device]
        for i, spec in enumerate(specs):
            if spec.kind not in kinds:
                raise ConfigError(
                    "", f"{prefix}.{name}.{i}.kind",
                    f"{name!r} ({kind_of_device}) has no fault {spec.kind!r}; it has: {', '.join(kinds)}",
                )
            extra = sorted(set(spec.params()) - set(kinds[spec.kind]))
            if extra:
                takes = ", ".join(kinds[spec.kind]) or "no parameters"
                raise ConfigError(
                    "", f"{prefix}.{name}.{i}.{extra[0]}",
                    f"fault {spec.kind!r} of {name!r} does not take {extra[0]!r}; it takes: {takes}",
                )


def fault_plans(
    rig: RigConfig, extra: Mapping[str, Sequence[Mapping[str, Any]]] | None = None, *, seed: int = 0
) -> dict[str, FaultPlan]:
    """A seeded fault plan per simulated device: the rig file's faults plus ``extra`` (a
    test's or a benchmark's, checked the same way)."""
    merged: dict[str, list[FaultSpec]] = {k: list(v) for k, v in rig.simulation.faults.items()}
    if extra:
        try:
            more = _FAULTS.validate_python(dict(extra))
        except ValidationError as exc:
            raise ConfigError("faults", *validation_problem(exc)) from None
        try:
            check_faults(rig, more, prefix="faults")
        except ConfigError as exc:
            raise ConfigError("faults", exc.key, exc.problem) from None
        for k, v in more.items():
            merged.setdefault(k, []).extend(v)
    plans: dict[str, FaultPlan] = {}
    for name in [*rig.devices, camera_sim_name(rig)]:
        plan = FaultPlan(seed=f"{seed}:{name}")
        for spec in merged.get(name, []):
            plan.add(spec.kind, count=spec.count, after=spec.after, rate=spec.rate, **spec.params())
        plans[name] = plan
    return plans


def build_world(
    rig: RigConfig, clock: Any, *, spot_angle_deg: float | None = None,
    sensor_temperature_c: float | None = None,
) -> World:
    """The simulated world of ``rig``: its lamps on their relay channels and the scene
    parameters of its ``[simulation]`` section (``spot_angle_deg`` and
    ``sensor_temperature_c`` override the file's)."""
    from m2s2hil.simulators.world import LampInfo, World

    sim = rig.simulation
    return World(
        clock,
        lamp_info={lc.channel: LampInfo(name, lc.kind, lc.warmup_s) for name, lc in rig.lamps.items()},
        placement=sim.mount.placement(),
        lamp_factor={rig.lamps[name].channel: float(f) for name, f in sim.lamps.items()},
        spot_angle_deg=sim.spot_angle_deg if spot_angle_deg is None else float(spot_angle_deg),
        sensor_temperature_c=(
            sim.sensor_temperature_c if sensor_temperature_c is None else float(sensor_temperature_c)
        ),
    )


def build_frame_source(
    rig: RigConfig, world: World, *, seed: int = 0, model: CameraModel | None = None
) -> SimFrameSource:
    """The simulated camera's frame source over ``world``: the catalog's materials, the
    rig's camera model (or ``model``) and the configured sensor."""
    from m2s2hil.catalog import load_catalog
    from m2s2hil.simulators.frames import SimFrameSource

    cat = load_catalog()
    source = SimFrameSource(
        world, model or rig.camera.model, lambda sat, build: list(cat.build(sat, build).materials),
        sensor_params=rig.simulation.sensor.params(), seed=seed,
    )
    source.scene.meshes.update(mesh_mockups(rig))
    return source


def mesh_mockups(rig: RigConfig) -> dict[tuple[str, str], Any]:
    """The lab's meshes the rig file names, loaded and checked against their builds
    (``simulators.meshes.MeshFileError``, one line naming the file, when one cannot be used)."""
    if not rig.simulation.mockups:
        return {}
    from m2s2hil.catalog import load_catalog
    from m2s2hil.simulators.meshes import load_mesh_mockup

    cat = load_catalog()
    out: dict[tuple[str, str], Any] = {}
    for sat, builds in rig.simulation.mockups.items():
        for build, spec in builds.items():
            mats = cat.build(sat, build).materials
            out[(sat, build)], _ = load_mesh_mockup(spec.mesh, f"{sat} {build}", mats,
                                                    rotate_deg=spec.rotate_deg)
    return out
