"""The rig configuration: a TOML file validated by pydantic.

A configuration names every device (protocol, port URL, serial settings), maps the
turntable and tilt axes onto motion devices, assigns lamps to relay channels, and
defines the lighting presets, elevations, camera model and processing defaults.
Without a file the built-in, fully simulated rig is used.
"""

from __future__ import annotations

import hashlib
import json
import tomllib
import weakref
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from functools import cached_property
from importlib import resources
from pathlib import Path
from types import MappingProxyType
from typing import Annotated, Literal

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationError,
    field_validator,
    model_validator,
)

from m2s2hil.drivers.motion_watch import PLAN_MARGIN, STALL_WINDOW_S
from m2s2hil.errors import ConfigError, UsageError, validation_problem
from m2s2hil.sim_config import SimulationConfig, check_devices

#: The device kinds a rig file's ``[devices]`` may name. Everything else about a kind (its
#: driver, simulator, what ``rig probe`` reads, how it is recognised on a wrong port) is its
#: entry in m2s2hil/rig/devices/; tests/test_rig_devices.py checks the two agree.
DeviceProtocol = Literal["grbl", "zaber", "modbus-rtu", "ascii-relay"]
DeviceRole = Literal["motion", "relay"]


@dataclass(frozen=True)
class ProtocolRules:
    """What the rig file itself checks about a device kind: its role and, for motion, which
    axis names the controller has (``axis_problem(name)``: why not, or None)."""

    role: DeviceRole
    axis_problem: Callable[[str], str | None] | None = None


def _grbl_axis(axis: str) -> str | None:
    return None if axis.upper() in ("X", "Y", "Z") else f"GRBL axis must be X, Y or Z, not {axis!r}"


def _zaber_axis(axis: str) -> str | None:
    return None if axis.isdigit() else f"Zaber axis must be a number, not {axis!r}"


PROTOCOLS: Mapping[str, ProtocolRules] = MappingProxyType({
    "grbl": ProtocolRules("motion", _grbl_axis),
    "zaber": ProtocolRules("motion", _zaber_axis),
    "modbus-rtu": ProtocolRules("relay"),
    "ascii-relay": ProtocolRules("relay"),
})  # the keys of DeviceProtocol, in its order (tests/test_rig_devices.py)
MOTION_PROTOCOLS = tuple(p for p, rules in PROTOCOLS.items() if rules.role == "motion")
RELAY_PROTOCOLS = tuple(p for p, rules in PROTOCOLS.items() if rules.role == "relay")

#: The demosaicing methods a rig file (``[processing] method``), ``capture --method``, a sweep
#: and ``evaluate --reprocess`` may name: known here, below processing, so checking a name
#: imports no numba. processing.demosaic has one class per name (tests/test_config.py checks).
DEMOSAIC_METHODS: tuple[str, ...] = ("superpixel", "nearest", "wb", "ppid")


def check_demosaic_method(name: str, error: Callable[[str], Exception] = UsageError) -> str:
    """``name`` if it is a demosaicing method, else ``error(message)`` is raised (a
    ``UsageError`` unless the caller needs its own type: pydantic's ``ValueError``,
    processing's ``UnknownMethodError``)."""
    if name not in DEMOSAIC_METHODS:
        raise error(f"unknown demosaicing method {name!r}; known: {', '.join(DEMOSAIC_METHODS)}")
    return name


# Default MSFA layout (band index 0..9 at each of the 16 positions of the 4x4 cell).
# The TOUCAN's real layout is not public; this documented default spreads the six
# duplicated bands (0-5) so every band's positions are as far apart as the cell allows.
DEFAULT_LAYOUT: tuple[tuple[int, ...], ...] = (
    (0, 1, 2, 3),
    (4, 5, 6, 7),
    (8, 9, 0, 1),
    (2, 3, 4, 5),
)


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class DeviceConfig(_Model):
    protocol: DeviceProtocol
    port: str = Field(min_length=1, description="/dev/ttyUSB0, a pty path, or sim://NAME")
    baudrate: Annotated[int, Field(gt=0)] = 115200
    bytesize: Literal[5, 6, 7, 8] = 8
    parity: Literal["N", "E", "O", "M", "S"] = "N"
    stopbits: Literal[1, 1.5, 2] = 1
    timeout_s: Annotated[float, Field(gt=0, le=60)] = 1.0
    unit: Annotated[int, Field(ge=0, le=247)] = 1  # Modbus unit id / Zaber device address
    retries: Annotated[int, Field(ge=0, le=10)] = 2


class AxisConfig(_Model):
    device: str
    axis: str = Field(description="GRBL axis letter (X, Y, Z) or Zaber axis number")
    units_per_degree: Annotated[float, Field(gt=0)] = 1.0
    min_deg: float = -360.0
    max_deg: float = 360.0
    max_speed_dps: Annotated[float, Field(gt=0)] = 30.0
    accel_dps2: Annotated[float, Field(gt=0)] = 60.0
    tolerance_deg: Annotated[float, Field(gt=0)] = 0.05
    cable_wrap_limit_deg: Annotated[float, Field(gt=0)] | None = None
    settle_s: Annotated[float, Field(ge=0)] = 0.0
    #: ``switches``: the controller homes the axis on its switches when the rig opens.
    #: ``none`` (a factory GRBL has homing off, ``$22=0``): the operator sets the origin with
    #: ``m2s2hil rig origin AXIS``; see m2s2hil/rig/origin.py and docs/rig-setup.md.
    homing: Literal["switches", "none"] = "none"
    #: Motor steps per degree of the axis (full steps per turn x microstepping x gear ratio / 360),
    #: if known: ``m2s2hil rig probe`` then checks GRBL's ``$100..$102`` against it.
    steps_per_degree: Annotated[float, Field(gt=0)] | None = None
    #: How long a move may take (m2s2hil/drivers/motion_watch.py, docs/rig-setup.md): no
    #: progress for ``stall_window_s`` while the controller says it moves is a stall; a move
    #: is overdue (logged, not failed) after its planned duration x ``timeout_margin``.
    stall_window_s: Annotated[float, Field(ge=0.5, le=600)] = STALL_WINDOW_S
    timeout_margin: Annotated[float, Field(ge=1.0, le=20)] = PLAN_MARGIN

    @model_validator(mode="after")
    def _limits(self) -> AxisConfig:
        if self.min_deg >= self.max_deg:
            raise ValueError(f"min_deg ({self.min_deg}) must be below max_deg ({self.max_deg})")
        return self


class LampConfig(_Model):
    channel: Annotated[int, Field(ge=0, le=255)]
    kind: Literal["led_bar", "spotlight"]
    warmup_s: Annotated[float, Field(ge=0, le=600)] = 1.0
    lumens: Annotated[float, Field(gt=0)] | None = None


class CameraModel(_Model):
    name: str = "SILIOS TOUCAN"
    width: Annotated[int, Field(gt=0)] = 2048
    height: Annotated[int, Field(gt=0)] = 2048
    bit_depth: Literal[8, 10, 12, 16] = 10
    pixel_pitch_um: Annotated[float, Field(gt=0)] = 5.5
    bands_nm: tuple[float, ...] = (431, 479, 515, 567, 611, 666, 719, 775, 820, 877)
    fwhm_nm: tuple[float, ...] = (65, 47, 42, 37, 36, 34, 33, 31, 31, 31)
    layout: tuple[tuple[int, ...], ...] = DEFAULT_LAYOUT
    max_fps: Annotated[float, Field(gt=0)] = 65.0

    @model_validator(mode="after")
    def _check(self) -> CameraModel:
        nb = len(self.bands_nm)
        if len(self.fwhm_nm) != nb:
            raise ValueError(f"fwhm_nm has {len(self.fwhm_nm)} values for {nb} bands")
        n = len(self.layout)
        if n == 0 or any(len(row) != n for row in self.layout):
            raise ValueError("layout must be a square n x n array of band indices")
        seen = {b for row in self.layout for b in row}
        bad = sorted(b for b in seen if not 0 <= b < nb)
        if bad:
            raise ValueError(f"layout names bands {bad} outside 0..{nb - 1}")
        missing = sorted(set(range(nb)) - seen)
        if missing:
            raise ValueError(f"layout has no position for bands {missing}")
        if self.width % n or self.height % n:
            raise ValueError(f"sensor {self.width}x{self.height} is not a multiple of {n}")
        return self

    @property
    def n_bands(self) -> int:
        return len(self.bands_nm)

    @property
    def period(self) -> int:
        return len(self.layout)

    @property
    def full_scale(self) -> int:
        return (1 << self.bit_depth) - 1


class CameraConfig(_Model):
    port: str = Field(
        default="sim://toucan",
        description="sim://NAME for the simulated TOUCAN, or usb:// to open a U3V camera",
    )
    vendor_id: Annotated[int, Field(ge=0, le=0xFFFF)] | None = None
    product_id: Annotated[int, Field(ge=0, le=0xFFFF)] | None = None
    serial: str | None = None
    calibration_file: Path | None = None
    timeout_s: Annotated[float, Field(gt=0, le=60)] = 2.0
    model: CameraModel = CameraModel()


class ProcessingConfig(_Model):
    method: str = "superpixel"

    @field_validator("method")
    @classmethod
    def _known_method(cls, v: str) -> str:
        return check_demosaic_method(v, ValueError)

    dark_reduce: Literal["mean", "median"] = "mean"
    dark_frames: Annotated[int, Field(ge=1, le=256)] = 8
    dark_temperature_tolerance_c: Annotated[float, Field(gt=0)] = 2.0


class StorageConfig(_Model):
    """How sessions store frames (m2s2hil.store.frame_files; measured in docs/benchmarks.md).

    ``format = "compressed"``: raw mosaics and darks as deflate-compressed uint16 TIFF, cubes
    computed from raw + dark when read. ``"legacy"``: the format before 0.2 (uncompressed raw,
    float32 darks, float32 cubes always stored), kept to compare against. ``cubes = true``
    also caches the cubes (compressed), for slow demosaicing methods."""

    format: Literal["compressed", "legacy"] = "compressed"
    cubes: bool = False


class RigInfo(_Model):
    name: str = "rig"


class RigConfig(_Model):
    rig: RigInfo = RigInfo()
    devices: dict[str, DeviceConfig]
    axes: dict[Literal["turntable", "tilt"], AxisConfig]
    lamps: dict[str, LampConfig]
    lighting: dict[str, tuple[str, ...]]
    elevations: dict[str, float]
    camera: CameraConfig = CameraConfig()
    processing: ProcessingConfig = ProcessingConfig()
    storage: StorageConfig = StorageConfig()
    simulation: SimulationConfig = Field(
        default_factory=SimulationConfig, description="simulator parameters (scene, sensor, faults)"
    )

    @field_validator("axes")
    @classmethod
    def _both_axes(cls, v: dict) -> dict:
        missing = {"turntable", "tilt"} - set(v)
        if missing:
            raise ValueError(f"missing axes: {', '.join(sorted(missing))}")
        return v

    @model_validator(mode="after")
    def _cross(self) -> RigConfig:
        # Cross-field problems raise ConfigError (not a ValueError, so pydantic lets it
        # through with its key); parse_rig adds the file name.
        from m2s2hil.catalog import load_catalog

        cat = load_catalog()
        for role, ax in self.axes.items():
            dev = self.devices.get(ax.device)
            if dev is None:
                raise ConfigError("", f"axes.{role}.device", f"no device named {ax.device!r}")
            rules = PROTOCOLS[dev.protocol]
            if rules.role != "motion":
                raise ConfigError(
                    "", f"axes.{role}.device", f"device {ax.device!r} speaks {dev.protocol}, not motion"
                )
            problem = rules.axis_problem(ax.axis) if rules.axis_problem is not None else None
            if problem is not None:
                raise ConfigError("", f"axes.{role}.axis", problem)
        relays = [n for n, d in self.devices.items() if d.protocol in RELAY_PROTOCOLS]
        if self.lamps and len(relays) != 1:
            raise ConfigError("", "devices", f"lamps need exactly one relay board, found {len(relays)}")
        chans: dict[int, str] = {}
        for name, lamp in self.lamps.items():
            if lamp.channel in chans:
                raise ConfigError(
                    "", f"lamps.{name}.channel",
                    f"channel {lamp.channel} already used by lamp {chans[lamp.channel]!r}",
                )
            chans[lamp.channel] = name
        for cond in cat.lighting:
            if cond not in self.lighting:
                raise ConfigError("", "lighting", f"missing preset for condition {cond!r}")
        for cond, lamps in self.lighting.items():
            if cond not in cat.lighting:
                raise ConfigError("", f"lighting.{cond}", f"unknown condition; known: {sorted(cat.lighting)}")
            for lamp in lamps:
                if lamp not in self.lamps:
                    raise ConfigError("", f"lighting.{cond}", f"no lamp named {lamp!r}")
        for e in cat.elevations:
            if e not in self.elevations:
                raise ConfigError("", "elevations", f"missing tilt angle for {e}")
        tilt = self.axes["tilt"]
        for e, ang in self.elevations.items():
            if e not in cat.elevations:
                raise ConfigError(
                    "", f"elevations.{e}", f"unknown elevation; known: {sorted(cat.elevations)}"
                )
            if not tilt.min_deg <= ang <= tilt.max_deg:
                raise ConfigError(
                    "", f"elevations.{e}", f"{ang} deg is outside the tilt soft limits "
                    f"[{tilt.min_deg}, {tilt.max_deg}]"
                )
        check_devices(self)
        return self

    # Convenience views -------------------------------------------------------------
    @property
    def relay_device(self) -> str:
        return next(n for n, d in self.devices.items() if d.protocol in RELAY_PROTOCOLS)

    def lamp_channels(self, condition: str) -> tuple[int, ...]:
        return tuple(sorted(self.lamps[n].channel for n in self.lighting[condition]))

    def warmup_s(self, condition: str) -> float:
        return max((self.lamps[n].warmup_s for n in self.lighting[condition]), default=0.0)

    @property
    def source_path(self) -> Path | None:
        """The file this configuration was loaded from (None: built-in, parsed from a document
        or copied); the rig's state file (m2s2hil/rig/origin.py) sits next to it. Kept outside
        the model, so two configurations with the same content stay equal."""
        return _SOURCES.get(id(self))

    @cached_property
    def digest(self) -> str:
        """sha256 of the canonical JSON form; recorded with every frame. The simulation
        section counts only where it differs from the defaults, so a rig's digest is the
        same whether its defaults were written out or left implicit."""
        doc = self.model_dump(mode="json")
        doc["simulation"] = self.simulation.model_dump(mode="json", exclude_defaults=True)
        # Where a device is plugged in does not change the data: ports stay out (a pty number,
        # USB adapters enumerated in another order); the calibration counts by its content.
        for dev in doc["devices"].values():
            dev.pop("port", None)
        doc["camera"].pop("port", None)
        cal = self.camera.calibration_file
        if cal is not None and Path(cal).is_file():  # else its path stands in; opening reports it
            doc["camera"]["calibration_file"] = hashlib.sha256(Path(cal).read_bytes()).hexdigest()
        blob = json.dumps(doc, sort_keys=True).encode()
        return hashlib.sha256(blob).hexdigest()


DEFAULT_RIG_SOURCE = "<built-in simulated rig>"
_SOURCES: dict[int, Path] = {}  # id(config) -> the file load_rig read it from (RigConfig.source_path)


def parse_rig(data: dict, source: str) -> RigConfig:
    try:
        return RigConfig.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(source, *validation_problem(exc)) from None
    except ConfigError as exc:  # a cross-field check (raised through pydantic): add the file
        raise ConfigError(source, exc.key, exc.problem) from None


def read_toml(path: str | Path) -> dict:
    """A TOML file's tables; a missing, unreadable or malformed file is a ConfigError."""
    source = str(path)
    try:
        text = Path(path).read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError(source, "", "no such file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(source, "", f"cannot read: {exc}") from None
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(source, "", f"not valid TOML: {exc}") from None


def load_rig(path: str | Path | None = None) -> RigConfig:
    """Load and validate a rig file; ``None`` gives the built-in simulated rig."""
    if path is None:
        text = resources.files("m2s2hil").joinpath("data/default_rig.toml").read_text()
        source = DEFAULT_RIG_SOURCE
        data = tomllib.loads(text)
    else:
        source = str(path)
        data = read_toml(path)
    rig = parse_rig(data, source)
    cal = rig.camera.calibration_file
    if path is not None and cal is not None and not cal.is_absolute():
        # A calibration file named in a rig file is found next to that file.
        camera = rig.camera.model_copy(update={"calibration_file": Path(path).parent / cal})
        rig = rig.model_copy(update={"camera": camera})
    if path is not None and rig.simulation.mockups:  # so are the lab's mockup meshes
        rig = rig.model_copy(update={"simulation": rig.simulation.resolved(Path(path).parent)})
    if path is not None:
        _SOURCES[id(rig)] = Path(path)
        weakref.finalize(rig, _SOURCES.pop, id(rig), None)
    return rig


def default_rig() -> RigConfig:
    return load_rig(None)
