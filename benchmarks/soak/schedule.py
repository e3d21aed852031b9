"""The soak's seeded random schedule: what it is configured to do, the kill points, and the
sweeps it submits. Everything random in a soak comes from one ``random.Random(seed)``."""

from __future__ import annotations

import random
from dataclasses import dataclass

LIGHTINGS = ("weak", "strong", "directional")
TILTS = ("E0", "E1", "E2")
SATELLITES = (("voyager", "B3"), ("hubble", "B2"), ("iss", "B2"))
# every soak does each of these at least once, however short or loaded
ONCE = ("e-stops", "operator holds", "releases", "live-view viewers", "sessions submitted (small)",
        "sessions submitted (full)")


@dataclass(frozen=True)
class SoakConfig:
    sim_s: float = 3600.0  # simulated capture time to reach (the daemons' virtual clocks)
    kills: int = 6  # kill -9s at random moments, then `serve --resume`
    seed: int = 21
    size: int = 128  # sensor width and height
    full_step_deg: float = 10.0  # a full sweep: every lighting x every tilt at this azimuth step
    full_share: float = 0.25  # of the sessions submitted
    tick_s: float = 0.4  # wall time between the soak's decisions
    p_estop: float = 0.015  # per tick while a session runs
    p_hold: float = 0.02  # per tick, an operator's hold (a mockup swap)
    hold_s: tuple[float, float] = (1.0, 4.0)  # wall seconds a hold lasts once nothing runs
    probe_s: float = 2.0  # wall seconds a held daemon is watched after a restart
    p_viewer: float = 0.06
    p_export: float = 0.04
    max_waiting: int = 2  # sessions kept queued behind the running one
    max_sessions: int = 400
    max_ticks: int = 200_000
    max_wall_s: float = 4 * 3600.0
    drain_wall_s: float = 900.0  # to let the last sessions finish after the target
    idle_samples: int = 8  # of /proc at the end, nothing running


@dataclass(frozen=True)
class KillPoint:
    at_sim_s: float
    held: bool  # hold or e-stop first, so the restart must come back held


def kill_points(cfg: SoakConfig, rng: random.Random) -> list[KillPoint]:
    """``cfg.kills`` moments within the first 70 % of the simulated time (the last daemon then
    lives long enough to show its memory is flat); at least one with the rig held, and, with
    two or more, at least one without."""
    times = sorted(rng.uniform(0.05, 0.7) * cfg.sim_s for _ in range(cfg.kills))
    held = [rng.random() < 0.5 for _ in times]
    if held and not any(held):
        held[rng.randrange(len(held))] = True
    if len(held) >= 2 and all(held):
        held[rng.randrange(len(held))] = False
    return [KillPoint(t, h) for t, h in zip(times, held, strict=True)]


def sweep(rng: random.Random, cfg: SoakConfig, *, full: bool = False) -> tuple[str, dict]:
    """(kind, body of POST /sessions): a small sweep (one lighting, one tilt, 4 or 8 azimuths) or
    a full one (every lighting and tilt at ``cfg.full_step_deg``; always with ``full``)."""
    sat, build = rng.choice(SATELLITES)
    base = {"satellite": sat, "build": build, "dark": {"frames": 1}}
    if rng.random() < cfg.full_share or full:
        return "full", {**base, "lighting": list(LIGHTINGS), "tilts": list(TILTS),
                        "azimuth_step_deg": cfg.full_step_deg}
    return "small", {**base, "lighting": [rng.choice(LIGHTINGS)], "tilts": [rng.choice(TILTS)],
                     "azimuth_step_deg": rng.choice((45.0, 90.0))}
