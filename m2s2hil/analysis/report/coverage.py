"""The coverage map of a sweep: every planned pose (lighting × tilt × azimuth) with what became of
it and its capture-time QC, as data (the console draws it) and as an SVG (the session report).

A pose's state: ``captured`` (a frame is stored; ``flagged`` when QC flagged it), ``skipped``
(the fault policy gave it up: the skip's reason is kept), ``failed`` (not captured and the
session failed, so it will not be), ``pending`` (not captured yet: the session is queued,
running, paused or can be resumed). A pose with several frames (``frame`` k of n) shows the
worst of them. The plan comes from the session's own sweep and rig file (``Sweep.expand``).
"""

from __future__ import annotations

import html
import math
from collections.abc import Mapping, Sequence
from typing import Any

from m2s2hil.analysis.qc import qc_of_meta
from m2s2hil.catalog import load_catalog
from m2s2hil.store.session import SessionStore

STATES = ("captured", "flagged", "skipped", "failed", "pending")
#: Fill per state: green, red, amber, dark red, grey (legible on light and dark pages, and the
#: states also differ in their marks: a flagged cell carries ⚑, a skipped one a slash).
COLOURS = {"captured": "#3ccf7a", "flagged": "#ff4d4f", "skipped": "#f0b429", "failed": "#8b1e22",
           "pending": "#6b7580"}
_RANK = {s: i for i, s in enumerate(("pending", "captured", "flagged", "skipped", "failed"))}


def _order(values: Sequence[str], preferred: Sequence[str]) -> list[str]:
    return [v for v in preferred if v in values] + sorted(set(values) - set(preferred))


def coverage(store: SessionStore, qc: Mapping[str, tuple[float | None, list[str]]] | None = None
             ) -> dict[str, Any]:
    """The map's data: lightings, elevations, azimuths (degrees) and one cell per planned pose.
    ``qc``: (score, flags) by event id for frames scored since capture (the report scores those
    without stored QC), used instead of the stored record's."""
    planned = [e for e in store.sweep.expand(store.rig) if e.kind == "frame"]
    frames = {f.event_id: f for f in store.frames()}
    skips = {s.event_id: s for s in store.skips()}
    state = str(store.journal.session()["state"])
    cells: dict[tuple[str, str, float], dict[str, Any]] = {}
    for ev in planned:
        az = float(ev.nominal_azimuth_deg if ev.nominal_azimuth_deg is not None else ev.azimuth_deg or 0.0)
        key = (str(ev.lighting), str(ev.elevation), round(az, 3))
        cell: dict[str, Any] = {"lighting": key[0], "elevation": key[1], "azimuth_deg": key[2],
                                "event_id": ev.event_id, "n": None, "score": None, "flags": [],
                                "reason": None}
        fr = frames.get(ev.event_id)
        if fr is not None:
            score, flags = (qc or {}).get(ev.event_id) or qc_of_meta(fr.meta)
            cell.update(n=fr.index, score=score, flags=flags, state="flagged" if flags else "captured")
        elif ev.event_id in skips:
            cell.update(state="skipped", reason=skips[ev.event_id].reason)
        else:
            cell["state"] = "failed" if state == "failed" else "pending"
        old = cells.get(key)
        if old is None or _RANK[cell["state"]] > _RANK[old["state"]]:
            cells[key] = cell
    cat = load_catalog()
    items = list(cells.values())
    counts = {s: sum(c["state"] == s for c in items) for s in STATES}
    return {"session_id": store.session_id, "state": state,
            "lightings": _order([c["lighting"] for c in items], list(cat.lighting)),
            "elevations": _order([c["elevation"] for c in items], list(cat.elevations)),
            "azimuths_deg": sorted({c["azimuth_deg"] for c in items}),
            "cells": items, "counts": counts,
            "lighting_names": {k: cat.lighting[k].name for k in cat.lighting}}


def _fmt_az(a: float) -> str:
    return f"{a:g}"


def coverage_svg(cov: Mapping[str, Any], *, cell_px: int = 18, link_prefix: str | None = "#frame-") -> str:
    """The map as one SVG: a grid per lighting condition (rows: tilts, columns: azimuths), each
    cell coloured by its state, with a tooltip (``<title>``) and, when ``link_prefix`` is given, a
    link to ``link_prefix + event id`` (the report's contact-sheet anchors)."""
    azs: list[float] = list(cov["azimuths_deg"])
    elevs: list[str] = list(cov["elevations"])
    lights: list[str] = list(cov["lightings"])
    by = {(c["lighting"], c["elevation"], c["azimuth_deg"]): c for c in cov["cells"]}
    names = cov.get("lighting_names", {})
    left, top_pad, gap = 44, 18, 26
    # azimuth labels where they fit: every column when there are few, else the multiples of 90°
    few = len(azs) <= 6 or not any(a % 90 == 0 for a in azs)
    every = max(1, math.ceil(30 / cell_px))
    counts = cov.get("counts", {})
    legend = [(s, counts.get(s, 0)) for s in STATES]
    steps = [16 + 7 * (len(s) + len(str(n)) + 1) + 10 for s, n in legend]
    width = max(left + cell_px * max(1, len(azs)) + 10, sum(steps))
    block = top_pad + cell_px * max(1, len(elevs)) + 16
    legend_h = 22
    height = len(lights) * (block + gap) + legend_h
    esc = html.escape
    out = [f"<svg xmlns='http://www.w3.org/2000/svg' width='{width}' height='{height}' "
           f"viewBox='0 0 {width} {height}' role='img' aria-label='coverage map of session "
           f"{esc(str(cov.get('session_id', '')))}' font-family='system-ui,sans-serif' font-size='11'>"]
    y0 = 0
    for lt in lights:
        out.append(f"<text x='0' y='{y0 + 12}' font-weight='700' fill='currentColor'>"
                   f"{esc(str(names.get(lt, lt)))}</text>")
        gy = y0 + top_pad
        for r, el in enumerate(elevs):
            out.append(f"<text x='{left - 6}' y='{gy + r * cell_px + cell_px * 0.7:.1f}' text-anchor='end' "
                       f"fill='currentColor'>{esc(el)}</text>")
            for k, a in enumerate(azs):
                c = by.get((lt, el, a))
                if c is None:
                    continue
                x, y = left + k * cell_px, gy + r * cell_px
                tip = f"{c['event_id']}: {c['state']}"
                if c["score"] is not None and math.isfinite(c["score"]):
                    tip += f", QC {c['score']:.3f}"
                if c["flags"]:
                    tip += " ⚑ " + ", ".join(c["flags"])
                if c["reason"]:
                    tip += f" ({c['reason']})"
                rect = (f"<rect x='{x}' y='{y}' width='{cell_px - 2}' height='{cell_px - 2}' rx='2' "
                        f"fill='{COLOURS[c['state']]}'><title>{esc(tip)}</title></rect>")
                if c["state"] == "skipped":
                    rect += (f"<line x1='{x + 2}' y1='{y + cell_px - 4}' x2='{x + cell_px - 4}' y2='{y + 2}' "
                             "stroke='#222' stroke-width='1.5'/>")
                if c["state"] == "flagged":
                    rect += (f"<text x='{x + (cell_px - 2) / 2:.1f}' y='{y + cell_px * 0.68:.1f}' "
                             f"text-anchor='middle' font-size='{cell_px * 0.6:.0f}' fill='#fff'>⚑</text>")
                if link_prefix is not None and c["n"] is not None:
                    rect = f"<a href='{esc(link_prefix + c['event_id'])}'>{rect}</a>"
                out.append(rect)
        for k, a in enumerate(azs):
            if (k % every == 0) if few else (a % 90 == 0):
                out.append(f"<text x='{left + k * cell_px + (cell_px - 2) / 2:.1f}' "
                           f"y='{gy + len(elevs) * cell_px + 11}' text-anchor='middle' "
                           f"fill='currentColor'>{_fmt_az(a)}°</text>")
        y0 += block + gap
    x = 0
    for (s, n), step in zip(legend, steps, strict=True):
        out.append(f"<rect x='{x}' y='{y0 + 4}' width='12' height='12' rx='2' fill='{COLOURS[s]}'/>"
                   f"<text x='{x + 16}' y='{y0 + 14}' fill='currentColor'>{s} {n}</text>")
        x += step
    out.append("</svg>")
    return "".join(out)


def coverage_section(store: SessionStore, qc: Mapping[str, tuple[float | None, list[str]]] | None = None
                     ) -> str:
    """The report's coverage section: a sentence and the map, whose captured cells link to the
    frame in the contact sheet (``qc``: as ``coverage`` takes it)."""
    cov = coverage(store, qc)
    counts = ", ".join(f"{n} {s}" for s, n in cov["counts"].items() if n)
    return (f"<p>Every planned pose of the sweep ({counts}): one grid per lighting condition, tilts down, "
            "azimuths across; a captured cell links to its frame in the contact sheet, a flagged one "
            "carries ⚑ (hover for the event, QC score and flags).</p>" + coverage_svg(cov))
