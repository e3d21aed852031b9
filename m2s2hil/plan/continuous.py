"""A continuous pass planned for a sharpness target: exposure, gain and ω chosen together.

Rotating at ω during an exposure ``t`` smears a point at ``radius_px`` from the axis over
``radius_px · ω·t`` (radians) pixels. A target (:class:`SharpnessTarget`) bounds that blur
and asks for a signal-to-noise floor; the camera's noise model (:class:`NoiseModel`) and
the lighting's brightness (the DN/s at gain 1 of its brightest pixels: what auto exposure
measured, or what the planned exposure was set for) say what an exposure yields:

    electrons   e = f · B · t · e_per_dn            (f: the fraction of the brightest signal
                                                     the SNR floor is held at)
    noise       σ = √(e + D·t + σ_read² + (e_per_dn / g)² / 12)      (shot, dark, read,
                                                     quantisation at gain g)
    SNR         e / σ

The pass is fastest at the largest ω, and ω ≤ ω_blur = θ_blur / t, so the exposure is the
shortest one that keeps the SNR floor, unless the turntable's top speed caps ω first (then
the longest exposure that still keeps the blur at that speed: more signal for free). The gain
restores the brightest pixels to ``fill`` of full scale (as long exposures had them), within
``max_gain``; it is one gain for the whole sweep (the darks are per exposure and gain), the
largest any condition needs, and each condition's exposure is then shortened to keep its own
brightest pixels at ``fill`` (its ω can only grow). Where the SNR floor cannot be held at the
blur bound the plan says so (``feasible``) rather than silently blurring more.

The noise defaults are the simulated TOUCAN's (``simulators/sensor.py`` ``SensorParams``,
itself from the CMV4000's datasheet figures: 13.5 ke⁻ full well, 13 e⁻ read noise, 10 bits).
"""

from __future__ import annotations

import math
from typing import Annotated

from pydantic import Field

from m2s2hil.config import RigConfig
from m2s2hil.plan.estimate import ContinuousEstimate, estimate_continuous
from m2s2hil.plan.model import MAX_EXPOSURE_S, MIN_EXPOSURE_S, PlanError, PlanModel
from m2s2hil.plan.sweep import Sweep

FULL_SCALE_FILL = 0.9  # auto exposure's default target for the brightest pixels


class SharpnessTarget(PlanModel):
    """Blur at ``radius_px`` (sensor pixels from the rotation axis: the mockup's rim) at most
    ``max_blur_px``; SNR at least ``min_snr`` at ``snr_fraction`` of the brightest signal."""

    max_blur_px: Annotated[float, Field(gt=0, le=50)] = 1.0
    min_snr: Annotated[float, Field(gt=0, le=1000)] = 20.0
    snr_fraction: Annotated[float, Field(gt=0, le=1)] = 0.25
    radius_px: Annotated[float, Field(gt=0)] = 400.0
    max_gain: Annotated[float, Field(ge=1, le=48)] = 16.0
    fill: Annotated[float, Field(gt=0, le=1)] = FULL_SCALE_FILL


class NoiseModel(PlanModel):
    """The camera's noise in electrons, at gain 1 unless stated."""

    e_per_dn: float = 13.2
    read_noise_e: float = 13.0
    dark_e_per_s: float = 125.0
    full_well_e: float = 13500.0
    bit_depth: int = 10

    @property
    def full_scale_dn(self) -> float:
        return float(2**self.bit_depth - 1)

    def snr(self, electrons: float, exposure_s: float, gain: float) -> float:
        q = self.e_per_dn / gain  # one DN step in electrons
        var = electrons + self.dark_e_per_s * exposure_s + self.read_noise_e**2 + q * q / 12.0
        return electrons / math.sqrt(var)


class ConditionPlan(PlanModel):
    exposure_s: float
    omega_dps: float
    blur_px: float
    snr: float
    brightest_fill: float  # brightest pixels' fraction of full scale at this exposure and gain
    limited_by: str  # "blur" (ω = θ/t), "speed" (the turntable's top speed) or "frame rate"


class ContinuousPlan(PlanModel):
    gain: float
    conditions: dict[str, ConditionPlan]
    feasible: bool  # every condition keeps both the blur bound and the SNR floor
    sweep: Sweep  # the sweep with these exposures and gain, mode continuous
    estimate: ContinuousEstimate  # its duration on the rig, at the target's blur bound


def brightness_from_plan(sweep: Sweep, rig: RigConfig, fill: float = FULL_SCALE_FILL) -> dict[str, float]:
    """DN/s at gain 1 of each condition's brightest pixels, assuming its planned exposure at
    the sweep's gain put them at ``fill`` of full scale (what the default exposures are set
    for); pass measured values (auto exposure's results) to :func:`plan_continuous` instead
    when there are some."""
    fs = float(2**rig.camera.model.bit_depth - 1)
    return {c: fill * fs / (sweep.exposure_for(c) * sweep.gain) for c in sweep.lighting}


def _snr_exposure(n: NoiseModel, rate_e: float, gain: float, snr: float) -> float:
    """Shortest exposure with SNR >= ``snr`` at ``rate_e`` electrons/s: the root of
    (r t)² = snr² (r t + D t + σ²) in t."""
    a = rate_e * rate_e
    b = -snr * snr * (rate_e + n.dark_e_per_s)
    c = -snr * snr * (n.read_noise_e**2 + (n.e_per_dn / gain) ** 2 / 12.0)
    return (-b + math.sqrt(b * b - 4 * a * c)) / (2 * a)


def plan_continuous(sweep: Sweep, rig: RigConfig, target: SharpnessTarget | None = None, *,
                    noise: NoiseModel | None = None,
                    brightness_dn_s: dict[str, float] | None = None) -> ContinuousPlan:
    """Exposure per condition, one gain and ω per condition for ``sweep`` in continuous mode
    (see the module docstring)."""
    target = target or SharpnessTarget()
    noise = noise or NoiseModel(bit_depth=rig.camera.model.bit_depth)
    bright = brightness_dn_s or brightness_from_plan(sweep, rig, target.fill)
    missing = [c for c in sweep.lighting if c not in bright or not bright[c] > 0]
    if missing:
        raise PlanError("continuous plan", "brightness", f"no positive brightness for {', '.join(missing)}")
    tt = rig.axes["turntable"]
    fps = rig.camera.model.max_fps
    theta = math.degrees(target.max_blur_px / target.radius_px)  # largest ω·t
    step_cap = sweep.azimuth_step_deg / sweep.frames_per_pose  # per frame interval
    fs = noise.full_scale_dn

    def exposure_at(c: str, gain: float) -> float:
        rate_e = target.snr_fraction * bright[c] * noise.e_per_dn  # electrons/s where the SNR is held
        t_snr = _snr_exposure(noise, rate_e, gain, target.min_snr)
        t_speed = theta / tt.max_speed_dps  # beyond this the top speed, not the blur, caps ω
        return max(t_snr, t_speed)

    # The gain that brings each condition's brightest pixels back to `fill` at its exposure.
    t0 = {c: exposure_at(c, 1.0) for c in sweep.lighting}
    need = {c: target.fill * fs / (bright[c] * t0[c]) for c in sweep.lighting}
    gain = min(target.max_gain, max(1.0, max(need.values())))
    out: dict[str, ConditionPlan] = {}
    feasible = True
    for c in sweep.lighting:
        t_snr = exposure_at(c, gain)
        t_fill = target.fill * fs / (bright[c] * gain)  # no brighter than `fill` at this gain
        # Planned to the microsecond (as every exposure is), rounded up: the SNR floor holds.
        t = min(math.ceil(max(t_snr, MIN_EXPOSURE_S) * 1e6) / 1e6, math.floor(t_fill * 1e6) / 1e6)
        t = min(max(t, MIN_EXPOSURE_S), MAX_EXPOSURE_S)
        caps = {"blur": theta / t, "speed": tt.max_speed_dps, "frame rate": step_cap * min(fps, 1.0 / t)}
        limited_by = min(caps, key=lambda k: caps[k])
        w = caps[limited_by]
        e = target.snr_fraction * bright[c] * noise.e_per_dn * t
        snr = noise.snr(e, t, gain)
        feasible &= snr >= target.min_snr * (1 - 1e-6)
        out[c] = ConditionPlan(exposure_s=t, omega_dps=w, blur_px=target.radius_px * math.radians(w * t),
                               snr=snr, brightest_fill=bright[c] * t * gain / fs, limited_by=limited_by)
    planned = sweep.model_copy(update={
        "mode": "continuous", "gain": round(gain, 3),
        "exposure": sweep.exposure.model_copy(update={"seconds": {c: p.exposure_s for c, p in out.items()}})
        if sweep.exposure.mode == "fixed" else sweep.exposure,
    })
    planned = Sweep.model_validate(planned.model_dump())  # re-validated: exposures within limits
    est = estimate_continuous(planned, rig, radius_px=target.radius_px, max_blur_px=target.max_blur_px)
    return ContinuousPlan(gain=planned.gain, conditions=out, feasible=feasible, sweep=planned, estimate=est)
