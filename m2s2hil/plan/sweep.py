"""A capture plan as data: the serialisable :class:`Sweep`.

A sweep names what to capture (satellite, build, lighting conditions, elevations,
azimuth grid, frames per pose) and how (exposure policy, gain, settle, dark policy,
processing method, loop nesting, stop-and-go or continuous rotation). It validates
against the catalog, round-trips through JSON, and :meth:`Sweep.expand` turns it into
a deterministic list of frozen capture events in the order :mod:`m2s2hil.plan.order`
finds cheapest.
"""

from __future__ import annotations

import json
import math
from typing import Annotated, Any, Literal

from pydantic import Field, ValidationError, ValidationInfo, field_validator, model_validator

from m2s2hil.catalog import load_catalog, satellite_key
from m2s2hil.config import RigConfig
from m2s2hil.errors import CatalogError, validation_problem
from m2s2hil.plan.estimate import PlanEstimate, estimate, estimate_continuous
from m2s2hil.plan.floor import PhysicalFloor
from m2s2hil.plan.model import (
    AXES,
    MAX_BRACKET,
    MAX_EXPOSURE_S,
    MIN_EXPOSURE_S,
    AutoExposureSettings,
    CaptureEvent,
    DarkPolicy,
    FixedExposure,
    PlanError,
    PlanModel,
    bracket_exposure,
    condition_key,
)
from m2s2hil.plan.order import best_plan, sweep_floor

Factor = Annotated[float, Field(gt=0, le=1000, strict=True)]  # a bracket's exposure multiple


class Sweep(PlanModel):
    """A capture plan for one satellite build (see module docstring)."""

    # Numbers and switches are strict: "10" or 1 where the schema says a number or a boolean
    # is refused, as the API's schema promises (an int is still a valid float).

    satellite: str
    build: str
    lighting: list[str] = Field(default_factory=lambda: ["weak", "strong", "directional"], min_length=1)
    tilts: list[str] = Field(default_factory=lambda: ["E0", "E1", "E2"], min_length=1)
    # 0.01 deg (36,000 poses) bounds the grid in the schema too; the frame limit is checked apart.
    azimuth_step_deg: Annotated[float, Field(ge=0.01, le=360, strict=True)] = 10.0
    azimuth_start_deg: Annotated[float, Field(ge=0, lt=360, strict=True)] = 0.0
    frames_per_pose: Annotated[int, Field(ge=1, le=100, strict=True)] = 1
    exposure: FixedExposure | AutoExposureSettings = Field(
        default_factory=FixedExposure, discriminator="mode"
    )
    gain: Annotated[float, Field(ge=0, le=48, strict=True)] = 1.0
    settle_s: Annotated[float, Field(ge=0, le=60, strict=True)] | None = None
    dark: DarkPolicy = DarkPolicy()
    processing: str = Field(default="superpixel", pattern=r"^[a-z][a-z0-9_-]*$")
    axis_order: str = "auto"
    reorder: Annotated[bool, Field(strict=True)] = True  # choose the order of conditions and tilts by cost
    mode: Literal["stop-and-go", "continuous"] = "stop-and-go"
    # Exposure brackets: lighting condition -> the extra exposures of each of its poses, as
    # multiples of the pose's own (e.g. {"directional": [16]}: the spotlight's shadows at 16 x).
    # Taken at the same pose right after its frame; processing.bracket merges them.
    bracket: dict[str, list[Factor]] = Field(default_factory=dict)

    @field_validator("satellite")
    @classmethod
    def _sat(cls, v: str) -> str:
        return satellite_key(v)

    @field_validator("build")
    @classmethod
    def _build(cls, v: str, info: ValidationInfo) -> str:
        sat = info.data.get("satellite")
        if sat is None:  # the satellite already failed; that error is enough
            return v
        try:
            return load_catalog().build(sat, v).key
        except CatalogError as exc:
            raise ValueError(str(exc)) from None

    @field_validator("lighting")
    @classmethod
    def _lighting(cls, v: list[str]) -> list[str]:
        keys = [condition_key(x) for x in v]
        dup = sorted({k for k in keys if keys.count(k) > 1})
        if dup:
            raise ValueError(f"lighting condition listed twice: {', '.join(dup)}")
        return keys

    @field_validator("tilts")
    @classmethod
    def _tilts(cls, v: list[str]) -> list[str]:
        try:
            keys = [load_catalog().elevation(str(x)).key for x in v]
        except CatalogError as exc:
            raise ValueError(str(exc)) from None
        dup = sorted({k for k in keys if keys.count(k) > 1})
        if dup:
            raise ValueError(f"elevation listed twice: {', '.join(dup)}")
        return keys

    @field_validator("bracket")
    @classmethod
    def _bracket(cls, v: dict[str, list[float]]) -> dict[str, list[float]]:
        out: dict[str, list[float]] = {}
        for name, factors in v.items():
            key = condition_key(name)
            if key in out:
                raise ValueError(f"lighting condition {key!r} listed twice")
            if not factors:
                continue  # no extra exposure: no bracket
            if len(factors) > MAX_BRACKET:
                raise ValueError(f"{key!r}: at most {MAX_BRACKET} extra exposures, got {len(factors)}")
            if any(f == 1.0 for f in factors):
                raise ValueError(f"{key!r}: factor 1 is the pose's own frame; list only the extra ones")
            if len(set(factors)) != len(factors):
                raise ValueError(f"{key!r}: a factor is listed twice")
            out[key] = [float(f) for f in factors]
        return out

    @field_validator("exposure", mode="before")
    @classmethod
    def _exposure_shorthand(cls, v: Any) -> Any:
        if isinstance(v, str):
            if v.strip().lower() == "auto":
                return {"mode": "auto"}
            raise ValueError(f"exposure must be 'auto' or a table condition -> seconds, not {v!r}")
        if isinstance(v, dict) and "mode" not in v:
            return {"mode": "fixed", "seconds": v}
        return v

    @field_validator("axis_order")
    @classmethod
    def _axis_order(cls, v: str) -> str:
        v = v.replace(" ", "").lower()
        if v == "auto":
            return v
        parts = v.split(">")
        if sorted(parts) != sorted(AXES):
            raise ValueError(
                f"axis_order {v!r} must be 'auto' or name light, tilt and azimuth once each, "
                "outermost first, e.g. 'light>tilt>azimuth'"
            )
        return v

    @model_validator(mode="after")
    def _modes(self) -> Sweep:
        order = self.axis_order
        if self.mode == "continuous" and order != "auto" and not order.endswith(">azimuth"):
            raise ValueError("continuous mode sweeps the turntable: azimuth must be the innermost axis")
        if self.bracket and self.mode == "continuous":
            raise ValueError("a bracket takes each pose again at another exposure, which needs the stage to "
                             "stand still: use mode 'stop-and-go'")
        for cond, factors in self.bracket.items():
            if cond not in self.lighting:
                raise ValueError(f"bracket names lighting condition {cond!r}, which the sweep does not "
                                 f"capture ({', '.join(self.lighting)})")
            if self.auto_exposure:  # the metered exposure is only known at run time: clamped then
                continue
            for f in factors:
                t = self.exposure_for(cond) * f
                if not MIN_EXPOSURE_S <= t <= MAX_EXPOSURE_S:
                    raise ValueError(
                        f"bracket {cond!r} x{f:g}: {t:g} s is outside the camera's "
                        f"{MIN_EXPOSURE_S:g}-{MAX_EXPOSURE_S:g} s")
        return self

    # ------------------------------------------------------------------ views
    @property
    def auto_exposure(self) -> bool:
        return isinstance(self.exposure, AutoExposureSettings)

    def exposure_for(self, condition: str) -> float:
        """The planned (fixed) or starting (auto) exposure of a condition."""
        exp = self.exposure
        table = exp.start_s if isinstance(exp, AutoExposureSettings) else exp.seconds
        return table[condition]

    def exposure_factors(self, condition: str) -> tuple[float, ...]:
        """The exposures of each pose of ``condition`` as multiples of its own: (1, *bracket)."""
        return (1.0, *self.bracket.get(condition, ()))

    def pose_exposures(self, condition: str) -> dict[float, float]:
        """Factor -> planned (or, auto, starting) exposure of each frame of a pose of ``condition``."""
        base = self.exposure_for(condition)
        return {f: base if f == 1.0 else bracket_exposure(base, f) for f in self.exposure_factors(condition)}

    def frames_per_pose_of(self, condition: str) -> int:
        """Frame events per pose of ``condition``: ``frames_per_pose`` × its exposures."""
        return self.frames_per_pose * len(self.exposure_factors(condition))

    def azimuths(self) -> list[float]:
        """Nominal azimuths, 0 <= a < 360, in grid order from ``azimuth_start_deg``."""
        n = math.ceil(360.0 / self.azimuth_step_deg - 1e-9)
        return [round((self.azimuth_start_deg + i * self.azimuth_step_deg) % 360.0, 6) for i in range(n)]

    def to_json(self) -> str:
        return self.model_dump_json(indent=2)

    @classmethod
    def from_json(cls, text: str, source: str = "<sweep json>") -> Sweep:
        try:
            data = json.loads(text)
        except json.JSONDecodeError as exc:
            raise PlanError(source, "", f"not valid JSON: {exc}") from None
        return parse_sweep(data, source)

    # -------------------------------------------------------------- expansion
    def expand(self, rig: RigConfig) -> list[CaptureEvent]:
        """The events of this sweep in capture order (darks first). Deterministic."""
        return best_plan(self, rig)[0]

    def chosen_order(self, rig: RigConfig) -> str:
        """The axis nesting :meth:`expand` uses (resolves ``"auto"``)."""
        return best_plan(self, rig)[1]

    def physical_floor(self, rig: RigConfig) -> PhysicalFloor:
        """The least rig time any capture of this sweep can take on ``rig`` (any mode, any
        order): :func:`m2s2hil.plan.order.sweep_floor`."""
        return sweep_floor(self, rig)

    def estimate(self, rig: RigConfig, *, radius_px: float = 400.0) -> PlanEstimate:
        """The mode's duration model and its own bound, with the physical floor beside them."""
        events = self.expand(rig)
        floor = self.physical_floor(rig).total_s
        if self.mode == "continuous":
            return estimate_continuous(self, rig, radius_px=radius_px, events=events).as_plan_estimate(floor)
        return estimate(events, rig).model_copy(update={"physical_floor_s": floor})


def parse_sweep(data: Any, source: str = "<sweep>") -> Sweep:
    """Validate plain data into a :class:`Sweep`, turning pydantic errors into a PlanError."""
    try:
        return Sweep.model_validate(data)
    except ValidationError as exc:
        raise PlanError(source, *validation_problem(exc)) from None
