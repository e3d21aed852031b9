"""The plan's vocabulary: exposure and dark policies, the capture events a sweep expands to.

A :class:`CaptureEvent` is frozen and has a stable ``event_id`` (:func:`dark_event_id`,
:func:`frame_event_id`), so a resumed session can skip what it already has. One master dark
is taken per distinct (exposure, gain); frame events point at theirs. A pose of a lighting
condition the sweep brackets has one frame event per exposure: the pose's own (factor 1) and
its bracket members (``exposure_factor`` × that exposure), taken in a row without a move.
"""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from m2s2hil.catalog import load_catalog
from m2s2hil.errors import CatalogError, KeyedError

# Starting exposures per condition (seconds): strong diffuse has ~1.7x the light of
# weak diffuse; the spotlight is brighter still on the lit side of the mockup.
DEFAULT_EXPOSURE_S: dict[str, float] = {"weak": 0.008, "strong": 0.005, "directional": 0.003}
MIN_EXPOSURE_S = 100e-6  # TOUCAN limits (paper, 2.1)
MAX_EXPOSURE_S = 5.0
MAX_BRACKET = 4  # exposures a pose may add: each costs one exposure, one readout and one master dark
AXES = ("light", "tilt", "azimuth")
DEFAULT_AXIS_ORDER = "light>tilt>azimuth"


class PlanError(KeyedError):
    """A sweep that cannot be used: ``source`` names where it came from, ``key`` the field."""


class PlanModel(BaseModel):
    """The base of the plan's records: unknown fields refused, instances frozen."""

    model_config = ConfigDict(extra="forbid", frozen=True)


Seconds = Annotated[float, Field(ge=MIN_EXPOSURE_S, le=MAX_EXPOSURE_S, strict=True)]


def condition_key(name: str) -> str:
    # Any case, and the published release's names (solo, all, dir -> weak, strong, directional).
    try:
        return load_catalog().light(str(name)).key
    except CatalogError as exc:
        raise ValueError(str(exc)) from None


def _round_exposure(s: float) -> float:
    # Exposures are planned to the microsecond so darks can be matched exactly.
    return round(float(s), 6)


def bracket_exposure(base_s: float, factor: float) -> float:
    """A bracket member's exposure: ``factor`` × the pose's, within the camera's limits, to the µs."""
    return _round_exposure(min(max(base_s * factor, MIN_EXPOSURE_S), MAX_EXPOSURE_S))


def _with_defaults(v: dict[str, float]) -> dict[str, float]:
    """Exposures per lighting condition, keys normalised, rounded, the missing ones defaulted."""
    out = dict(DEFAULT_EXPOSURE_S)
    for k, s in v.items():
        out[condition_key(k)] = _round_exposure(s)
    return out


class FixedExposure(PlanModel):
    """One exposure per lighting condition; conditions left out get the default."""

    mode: Literal["fixed"] = "fixed"
    seconds: dict[str, Seconds] = Field(default_factory=lambda: dict(DEFAULT_EXPOSURE_S))

    @field_validator("seconds")
    @classmethod
    def _fill(cls, v: dict[str, float]) -> dict[str, float]:
        return _with_defaults(v)


class AutoExposureSettings(PlanModel):
    """Meter each pose: aim the ``percentile`` of the raw mosaic at ``target_fraction``
    of full scale. ``start_s`` are the first guesses (also used to plan the darks)."""

    mode: Literal["auto"] = "auto"
    target_fraction: Annotated[float, Field(gt=0, le=1, strict=True)] = 0.9
    percentile: Annotated[float, Field(gt=0, le=100, strict=True)] = 99.9
    start_s: dict[str, Seconds] = Field(default_factory=lambda: dict(DEFAULT_EXPOSURE_S))
    min_s: Seconds = MIN_EXPOSURE_S
    max_s: Seconds = 1.0
    max_iterations: Annotated[int, Field(ge=1, le=20, strict=True)] = 4

    @field_validator("start_s")
    @classmethod
    def _fill(cls, v: dict[str, float]) -> dict[str, float]:
        return _with_defaults(v)

    @model_validator(mode="after")
    def _range(self) -> AutoExposureSettings:
        if self.min_s > self.max_s:
            raise ValueError(f"min_s ({self.min_s}) is above max_s ({self.max_s})")
        return self


class DarkPolicy(PlanModel):
    """Master darks: ``frames`` lens-capped frames reduced by ``reduce``, one master per
    distinct (exposure, gain), reused by every frame with that setting. ``frames = 0``
    turns dark subtraction off."""

    frames: Annotated[int, Field(ge=0, le=256, strict=True)] = 8
    reduce: Literal["mean", "median"] = "mean"


class CaptureEvent(PlanModel):
    """One step of a sweep. ``kind == "dark"``: take ``n_frames`` lens-capped frames at
    ``exposure_s``/``gain`` and store their master as ``event_id``. ``kind == "frame"``:
    switch to ``lighting``, move to (``azimuth_deg``, ``tilt_deg``), settle, take one
    frame, subtract the master dark ``dark_id``. A bracket member (``exposure_factor`` != 1) is
    the same pose again at that multiple of the pose's exposure (processing.bracket merges
    them)."""

    event_id: str
    index: int
    kind: Literal["dark", "frame"]
    lighting: str | None = None
    elevation: str | None = None
    tilt_deg: float | None = None
    azimuth_deg: float | None = None  # commanded turntable angle (cable-wrap aware)
    nominal_azimuth_deg: float | None = None  # 0 <= a < 360
    azimuth_index: int | None = None  # position in the azimuth grid (0..35 for 10 deg)
    frame: int = 0  # k-th frame at this pose
    n_frames: int = 1
    exposure_s: float
    gain: float
    auto_exposure: bool = False  # exposure_s is only the starting guess
    dark_id: str | None = None
    settle_s: float | None = None  # None: the rig's per-axis settle_s
    pass_index: int = 0  # which snake pass (run of azimuths at one light + tilt)
    exposure_factor: float = 1.0  # a bracket member: this multiple of the pose's own exposure

    @property
    def bracket_member(self) -> bool:
        """An extra exposure of a pose (its own frame has ``exposure_factor`` 1)."""
        return self.exposure_factor != 1.0


def dark_event_id(exposure_s: float, gain: float) -> str:
    return f"dark/{round(exposure_s * 1e6):d}us/g{gain:g}"


def dark_event(exposure_s: float, gain: float, n_frames: int, index: int = -1) -> CaptureEvent:
    """A dark event outside the plan (e.g. for an exposure found by auto-exposure)."""
    exposure_s = _round_exposure(exposure_s)
    return CaptureEvent(
        event_id=dark_event_id(exposure_s, gain), index=index, kind="dark",
        exposure_s=exposure_s, gain=gain, n_frames=n_frames,
    )


def _az_label(a: float) -> str:
    return f"az{round(a):03d}" if abs(a - round(a)) < 1e-9 else f"az{a:07.3f}"


def frame_event_id(lighting: str, elevation: str, nominal_azimuth_deg: float, frame: int,
                   exposure_factor: float = 1.0) -> str:
    """``<light>/<elevation>/az<deg>/f<k>``, and ``/x<factor>`` for a bracket member."""
    base = f"{lighting}/{elevation}/{_az_label(nominal_azimuth_deg)}/f{frame}"
    return base if exposure_factor == 1.0 else f"{base}/x{exposure_factor:g}"


def bracket_base_id(event_id: str) -> str:
    """The id of the pose's own frame for a bracket member's id (the id itself otherwise)."""
    head, _, last = event_id.rpartition("/")
    return head if head and last.startswith("x") else event_id
