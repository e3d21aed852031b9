"""The soak's tables: what ran, and what was checked with its result (Markdown)."""

from __future__ import annotations

import datetime as dt
import os
import platform
from collections import Counter

from m2s2hil.hostinfo import cpu_model

from .run import Result


def machine() -> str:
    return (f"{cpu_model()}, nproc {os.cpu_count()}, Python {platform.python_version()}, "
            f"{dt.datetime.now(dt.UTC):%Y-%m-%d %H:%M} UTC")


def ran_table(r: Result) -> str:
    sim = sum(c.sim_s for c in r.sessions)
    states = Counter(c.state for c in r.sessions)
    holds = ", ".join(f"{k}: {n}" for k, n in sorted(Counter(w.kind for w in r.windows).items()))
    rows = [
        ("simulated capture time", f"{sim:.0f} s ({sim / 60:.1f} min; target {r.cfg.sim_s:.0f} s)"),
        ("wall time", f"{r.wall_s:.0f} s"),
        ("sessions (final state)", ", ".join(f"{n} {s}" for s, n in sorted(states.items())) or "none"),
        ("frames stored / planned",
         f"{sum(c.stored for c in r.sessions)} / {sum(c.planned for c in r.sessions)}"),
        ("engine runs", str(sum(c.runs for c in r.sessions))),
        *((k, str(v)) for k, v in sorted(r.ran.items())),
        ("hold windows (kind: count)", holds or "none"),
        ("requests answered / cut by a kill", f"{sum(r.traffic.by_route.values())} / {r.traffic.cut}"),
        ("daemon samples (/proc: RSS, fds)", f"{len(r.samples)} ({sum(s.idle for s in r.samples)} idle)"),
    ]
    return "\n".join(["| what ran | count |", "|---|---|", *(f"| {k} | {v} |" for k, v in rows)])


def _scope(r: Result, invariant: str) -> str:
    files = sum(1 for _ in r.sessions)
    kills_held = sum(w.kills for w in r.windows)
    if invariant.startswith("journal"):
        return f"{files} sessions, every file hashed"
    if invariant == "no frame stored twice":
        return f"{sum(c.stored for c in r.sessions)} frames: journal rows and commit events"
    if invariant == "no acknowledged frame lost":
        return f"{r.acked} frames acknowledged (event streams, frame lists)"
    if invariant == "holds honoured":
        return (f"{len(r.windows)} holds, {kills_held} kill -9 while held, "
                f"{sum(len(w.held_after_restart) for w in r.windows)} restarts checked held")
    if invariant == "rig safe after every stop":
        return f"{r.ran['e-stops']} e-stop answers, {r.ran['rig read-backs']} read-backs, the final SIGTERM"
    if invariant == "memory and file descriptors flat":
        return "; ".join(f"daemon {f.incarnation}: RSS {f.rss_first_kib / 1024:.0f}→"
                         f"{f.rss_last_kib / 1024:.0f} MiB, fds {f.fds_first}→{f.fds_last} besides "
                         f"≤ {f.journals_max} journals ({f.samples} idle samples)" for f in r.flat) or "-"
    if invariant == "no 5xx answer":
        return f"{sum(r.traffic.by_route.values())} answers"
    if invariant == "exports one at a time":
        rounds = sum(v for k, v in r.ran.items() if k.startswith("exports"))
        return f"{rounds} export rounds: 201, 409, or 422 for an existing one without overwrite"
    if invariant == "daemon up until stopped":
        return f"{r.ran['daemon starts']} starts; exit 0 after SIGTERM; the queue drained"
    if invariant.startswith("GET"):
        return "every session at the end"
    return ""


def checked_table(r: Result) -> str:
    lines = ["| invariant | scope | result |", "|---|---|---|"]
    for inv, bad in r.violations.items():
        res = ("holds" if not bad else
               f"**BROKEN** ({len(bad)}): " + "; ".join(b.replace("|", "/") for b in bad[:3]))
        lines.append(f"| {inv} | {_scope(r, inv)} | {res} |")
    return "\n".join(lines)


def markdown(r: Result) -> str:
    c = r.cfg
    head = (f"Run {machine()}: seed {c.seed}, sensor {c.size}×{c.size}, full sweeps at {c.full_step_deg:g}°, "
            f"{c.kills} kill -9s planned.")
    return f"{head}\n\n{ran_table(r)}\n\n{checked_table(r)}\n"
