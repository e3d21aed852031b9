"""Request and response bodies of the operator console's endpoints (manual control, live view,
snapshots, calibration, plan estimates)."""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from m2s2hil.plan import Sweep

Degrees = Annotated[float, Field(ge=-3600.0, le=3600.0, allow_inf_nan=False)]
#: The TOUCAN's ExposureTime range (100 µs to 5 s in its GenICam description) and Gain range
#: (a factor of 1 to 16); a camera with narrower ones refuses the rest.
EXPOSURE_RANGE = (1e-4, 5.0)
GAIN_RANGE = (1.0, 16.0)
Exposure = Annotated[float, Field(ge=EXPOSURE_RANGE[0], le=EXPOSURE_RANGE[1], allow_inf_nan=False)]
Gain = Annotated[float, Field(ge=GAIN_RANGE[0], le=GAIN_RANGE[1], allow_inf_nan=False)]
Note = Annotated[str, Field(max_length=200)]


class _In(BaseModel):
    # strict: a number given as a string ("1") is refused, as the schema says
    model_config = ConfigDict(extra="forbid", strict=True)


class Jog(_In):
    delta_deg: Annotated[float, Field(ge=-720.0, le=720.0, allow_inf_nan=False)]


class GoTo(_In):
    position_deg: Degrees


class Lamps(_In):
    """Either a lighting preset (``null``: every lamp off) or the lamps to have on."""

    preset: Literal["weak", "strong", "directional"] | None = None
    lamps: list[Annotated[str, Field(max_length=64)]] | None = Field(default=None, max_length=64)


class AxisOut(BaseModel):
    role: str
    position_deg: float | None
    moving: bool | None
    min_deg: float
    max_deg: float
    max_speed_dps: float
    homing: str
    can_home: bool
    error: str | None = None
    target_deg: float | None = Field(None, description="The last manual move's target still in force: the "
                                                       "next jog starts there (null: from the read-back).")


class AxesOut(BaseModel):
    owner: str | None = Field(description="The session that owns the rig (manual control refused), or null.")
    axes: list[AxisOut]
    lamps_on: list[str] | None = Field(description="Lamps on: read back, or while a session owns the rig "
                                                   "as its engine last set them.")
    lamps: dict[str, str] = Field(description="Every lamp and its kind.")
    presets: dict[str, list[str]]
    busy: list[dict[str, Any]] = Field(default_factory=list,
                                       description="Long actions running now (GET /busy).")


class MoveOut(BaseModel):
    axis: str
    target_deg: float
    position_deg: float
    moving: bool


class LampsOut(BaseModel):
    lamps_on: list[str]


class LiveSettingsIn(_In):
    exposure_s: Exposure | None = None
    gain: Gain | None = None
    view: Literal["rgb"] | Annotated[int, Field(ge=0, le=63)] | None = None
    axis_x: Annotated[float, Field(ge=0.0, le=1.0)] | None = None


class LiveOut(BaseModel):
    settings: dict[str, Any]
    viewers: int
    frames_produced: int
    error: str | None
    stats: dict[str, Any] | None
    bands_nm: list[float]
    state: Literal["idle", "starting", "streaming", "busy", "error"] = Field(
        description="idle: no stream; starting: waiting for the camera's first frame; streaming; "
                    "busy: a session owns the rig; error: a device error (retried)")
    stopped_reason: str | None = Field(description="Why the stream last stopped (None before it ever did).")
    stream_fps: float = Field(description="The frame rate the stream asks of the camera at these settings.")
    fps: float | None = Field(description="Frames per second the daemon produced over the last frames.")
    cold_start_s: float | None = Field(description="From the stream's last start to its first frame.")


class SnapshotIn(_In):
    note: Note = ""
    exposure_s: Exposure | None = None
    gain: Gain | None = None


class ExposureGain(_In):
    exposure_s: Exposure
    gain: Gain = 1.0


class DarksIn(_In):
    """The (exposure, gain) pairs to take darks at: given, or those a plan uses."""

    exposures: list[ExposureGain] | None = Field(default=None, min_length=1, max_length=32)
    plan: Sweep | None = Field(default=None, description="A session plan (as POST /sessions takes).")
    n_frames: Annotated[int, Field(ge=1, le=64)] | None = None
    lens_capped: bool = Field(False, description="The operator confirms the lens cap is on (a real rig).")


class WhiteIn(_In):
    exposure_s: Exposure
    gain: Gain = 1.0
    n_frames: Annotated[int, Field(ge=1, le=64)] = 8
    reflectance: Annotated[float, Field(gt=0.0, le=1.5)] = 0.99
    lighting: Literal["weak", "strong", "directional"] | None = None
    panel_in_place: bool = Field(False, description="The operator confirms the white panel fills the view.")


class PhaseIn(_In):
    exposure_s: Exposure
    gain: Gain = 1.0


class EstimateOut(BaseModel):
    events: int
    frames: int
    darks: int
    estimate_s: float
    lower_bound_s: float
    physical_floor_s: float = Field(description="The least rig time of any mode and order (plan.floor).")
    bytes: int
    breakdown: dict[str, float]
