"""A session's HTML report: QC distribution, QC per pose, and a contact sheet of previews
(a synthetic session's report, its renders and masks, is ``synthetic_html``'s).

One self-contained file (thumbnails and the histogram are inlined as base64, so the
report can be mailed or archived without the session). Sections:

1. the session (satellite, build, state, frames, skips);
2. QC summary (``qc.qc_summary``): distribution, histogram with the flag threshold,
   flag counts, flagged frames;
3. QC per pose: one grid per lighting condition, elevations × azimuths, each cell the
   frame's score coloured against the threshold;
4. contact sheet: per lighting and elevation, every frame's preview (the engine's
   preview, JPEG or PNG; rendered from the cube when the session has none) with its azimuth,
   score and flags; flagged frames are framed in red.

Frames stored without a QC result (captured without the hook, or imported) are scored
here with the same ``qc.capture_stability`` (saturation from the raw mosaic) and marked
"computed at report time".
"""

from __future__ import annotations

import base64
import html
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from m2s2hil.analysis.evaluation.jobs import FrameJob, session_jobs
from m2s2hil.analysis.evaluation.loading import load_cube, load_frame
from m2s2hil.analysis.qc import FLAGS, QcConfig, capture_stability, qc_of_meta, qc_summary
from m2s2hil.analysis.report.charts import qc_histogram_png
from m2s2hil.analysis.report.coverage import coverage_section
from m2s2hil.atomic import write_text_atomic
from m2s2hil.catalog import load_catalog
from m2s2hil.processing.display import false_colour
from m2s2hil.store.frame_files import decode_image
from m2s2hil.store.session import SessionStore

# The operator console's palette (m2s2hil/console/console.css): light, or dark when the system
# asks for it, so the report opened from the console looks like it. The per-pose score cells keep
# their light backgrounds in both (dark text on them).
CSS = """
:root{--bg:#f3f5f7;--card:#fff;--line:#c9d0d7;--fg:#1a1f24;--muted:#5b6670;--head:#e4e8ec;--ok:#137a3f;
--bad:#c8102e;--okline:#8fd1a8;color-scheme:light}
@media (prefers-color-scheme: dark){:root{--bg:#15181c;--card:#1f242a;--line:#323941;--fg:#e6e9ec;
--muted:#8d98a3;--head:#0f1215;--ok:#3ccf7a;--bad:#ff4d4f;--okline:#1d4d33;color-scheme:dark}}
body{font-family:system-ui,sans-serif;margin:1.5em;color:var(--fg);background:var(--bg)}
h1{font-size:1.4em} h2{font-size:1.15em;margin-top:1.6em;border-bottom:1px solid var(--line)}
table{border-collapse:collapse;font-size:.85em;display:block;max-width:100%;overflow-x:auto}
img,svg{max-width:100%;height:auto}
td,th{border:1px solid var(--line);padding:2px 6px;text-align:right}
th{background:var(--head)} td.l,th.l{text-align:left} td.score{color:#1a1f24}
.sheet{display:flex;flex-wrap:wrap;gap:6px}
figure{margin:0;padding:3px;border:3px solid var(--okline);background:var(--card);font-size:.72em;
text-align:center}
figure.flagged{border-color:var(--bad)} figure.noqc{border-color:var(--line)}
figure img{display:block} .flags{color:var(--bad)} a{color:inherit}
"""


@dataclass
class FrameView:
    event_id: str
    lighting: str
    elevation: str
    azimuth_deg: float | None
    frame: int
    score: float | None
    flags: list[str]
    computed: bool = False
    thumbnail: bytes | None = field(default=None, repr=False)  # JPEG
    exposure_factor: float = 1.0  # a bracket's extra exposure of its pose (not QC-checked)


def preview_rgb(
    cube: np.ndarray, bands_nm: Sequence[float], white: Sequence[float] | None = None
) -> np.ndarray:
    """8-bit sRGB preview of a cube (``processing.display.false_colour``): the bands nearest 640/550/470
    nm, white-balanced by grey world (or by ``white``, a white reference's signal per band), scaled to
    the 99.5th percentile, sRGB transfer curve — the same rendering as the engine's stored previews."""
    return false_colour(np.asarray(cube), bands_nm, white=white)


def thumbnail_jpeg(rgb: np.ndarray, width: int) -> bytes:
    h, w = rgb.shape[:2]
    if w > width:
        rgb = cv2.resize(rgb, (width, max(1, round(h * width / w))), interpolation=cv2.INTER_AREA)
    ok, buf = cv2.imencode(
        ".jpg", cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 85]
    )
    return buf.tobytes() if ok else b""


def _compute_qc(job: FrameJob, config: QcConfig) -> tuple[float | None, list[str], np.ndarray | None]:
    # the cube with the clipping mask the processor gave at capture (rebuilt from the raw frame)
    frame = load_frame(job)
    full_scale = (1 << int(job.camera.get("bit_depth", 10))) - 1
    res = capture_stability(frame.cube, frame.saturated_pixels, config=config, full_scale=full_scale)
    return res.score, list(res.flags), frame.cube


def collect_views(
    store: SessionStore, *, thumb_px: int = 160, compute_missing: bool = True, config: QcConfig | None = None
) -> tuple[list[FrameView], dict[str, Any]]:
    """Per-frame views (scores, flags, thumbnails) of an open SessionStore, and its QC summary.
    A synthetic session has neither cube nor QC: no views, and :func:`render` writes its own report
    (``synthetic_html``), at this ``thumb_px``."""
    if store.kind == "synthetic":
        return [], {"kind": "synthetic", "scored": 0, "thumb_px": thumb_px}
    cfg = config or QcConfig()
    jobs = {j.image_id.split("/", 1)[1]: j for j in session_jobs(store, brackets=False)}
    bands = store.rig.camera.model.bands_nm
    views = []
    for fr in store.frames():
        ev = fr.meta.get("event", {})
        score, flags = qc_of_meta(fr.meta)
        computed = False
        cube = None
        factor = float(ev.get("exposure_factor", 1.0) or 1.0)
        if score is None and compute_missing and factor == 1.0:  # a bracket member is not checked
            score, flags, cube = _compute_qc(jobs[fr.event_id], cfg)
            computed = True
        thumb = None
        if thumb_px > 0:
            if "preview" in fr.files:
                thumb = thumbnail_jpeg(decode_image(store.read_file(fr.files["preview"])), thumb_px)
            else:
                cube = load_cube(jobs[fr.event_id]) if cube is None else cube
                thumb = thumbnail_jpeg(preview_rgb(cube, bands), thumb_px)
        views.append(
            FrameView(
                fr.event_id,
                str(ev.get("lighting", "")),
                str(ev.get("elevation", "")),
                ev.get("nominal_azimuth_deg"),
                int(ev.get("frame", 0) or 0),
                score,
                flags,
                computed,
                thumb,
                factor,
            )
        )

    @dataclass
    class _Rec:
        event_id: str
        meta: dict

    summary = qc_summary(
        [_Rec(v.event_id, {"qc": {"score": v.score, "flags": v.flags}}) for v in views
         if v.exposure_factor == 1.0],
        threshold=_stored_threshold(store) or cfg.threshold,
    )
    summary["computed_at_report"] = sum(v.computed for v in views)
    return views, summary


def _stored_threshold(store: SessionStore) -> float | None:
    for fr in store.frames():
        qc = fr.meta.get("qc")
        if isinstance(qc, Mapping) and isinstance(qc.get("threshold"), (int, float)):
            return float(qc["threshold"])
    return None


def _esc(v: Any) -> str:
    return html.escape(str(v))


def _score_text(s: float | None) -> str:
    return "–" if s is None or not math.isfinite(s) else f"{s:.3f}"


def _colour(score: float | None, flags: Sequence[str], threshold: float) -> str:
    if score is None or not math.isfinite(score):
        return "#eeeeee"
    if flags:
        return "#f2b8b5"
    # green above the threshold, deeper with the margin
    margin = min(1.0, max(0.0, (score - threshold) / max(1e-9, 1.0 - threshold)))
    g = int(200 + 40 * (1 - margin))
    return f"rgb({g - 40},{235},{g - 40})"


def _order(values: Sequence[str], preferred: Sequence[str]) -> list[str]:
    return [v for v in preferred if v in values] + sorted(set(values) - set(preferred))


def twin_section(store: SessionStore, counts: Mapping[str, int]) -> str:
    """How the twin placed the mockup (the stored registration: offset from the turntable axis, yaw,
    tilt bias, scale, residual) and how many frames carry each of its flags."""
    from m2s2hil.twin.checks import FLAGS as TWIN_FLAGS
    from m2s2hil.twin.projection import Placement
    from m2s2hil.twin.registration import registration_text, stored_registration

    out = ["<h2>Twin</h2>"]
    reg = stored_registration(store)  # the twin's placement of the mockup (docs/twin.md)
    if reg is None:
        out.append("<p>No registration stored (<code>m2s2hil sessions register</code> fits one; "
                   "<code>capture --twin-checks</code> fits one during the sweep).</p>")
    else:
        pl = Placement.from_dict(reg.get("placement") or {})
        rows = [("offset from the axis", f"({pl.dx_mm:+.2f}, {pl.dy_mm:+.2f}) mm"),
                ("yaw at azimuth 0", f"{pl.yaw_deg:+.2f}°"), ("tilt bias", f"{pl.tilt_bias_deg:+.2f}°"),
                ("scale", f"{pl.scale:.3f}"),
                ("residual", f"{float(reg.get('residual', 1.0)):.3f} (1 − mean IoU)"),
                ("frames", f"{int(reg.get('frames', 0))} over {float(reg.get('azimuth_span_deg', 0.0)):.0f}° "
                 "of azimuth"), ("fitted by", str(reg.get("source", "session")))]
        out.append("<table>" + "".join(f"<tr><th class=l>{_esc(k)}</th><td class=l>{_esc(v)}</td></tr>"
                                       for k, v in rows) + "</table>")
        out.append(f"<p class=reg>Registration: {_esc(registration_text(reg))}.</p>")
    raised = {k: counts.get(k, 0) for k in TWIN_FLAGS if counts.get(k, 0)}
    listed = ", ".join(f"<span class=flags>{_esc(k)}</span> {n}" for k, n in raised.items())
    out.append(f"<p>Twin flags: {listed or 'none'}.</p>")
    return "\n".join(out)


def render(store: SessionStore, views: Sequence[FrameView], summary: Mapping[str, Any]) -> str:
    """The report's HTML text (a synthetic session's: ``synthetic_html.render_synthetic``)."""
    if store.kind == "synthetic":
        from m2s2hil.analysis.report.synthetic_html import render_synthetic

        return render_synthetic(store, thumb_px=int(summary.get("thumb_px", 160)))[0]
    cat = load_catalog()
    s = store.summary()
    thr = float(summary.get("threshold", QcConfig().threshold))
    title = f"Session {store.session_id}"
    sat_name = cat.satellites[store.sweep.satellite].name
    out = [
        f"<!doctype html><html><head><meta charset='utf-8'><title>{_esc(title)}</title>",
        f"<style>{CSS}</style></head><body>",
        f"<h1>{_esc(title)}</h1>",
        "<table>",
    ]
    info = [
        ("satellite", sat_name),
        ("build", store.sweep.build),
        ("state", s["state"]),
        ("frames", f"{s['frames']} of {s['planned_frames']} planned"),
        ("skipped", s["skipped"]),
        ("created", datetime.fromtimestamp(s["created"], UTC).isoformat(timespec="seconds")),
        ("report written", datetime.now(UTC).isoformat(timespec="seconds")),
    ]
    out += [f"<tr><th class=l>{_esc(k)}</th><td class=l>{_esc(v)}</td></tr>" for k, v in info]
    out.append("</table>")

    out.append("<h2>QC summary</h2>")
    out.append(
        "<p>Score: agreement (micro-IoU, background left out) between this frame's segmentation and "
        "simulated re-captures with the frame's own noise; saturated object pixels count as unstable. "
        f"Flagged when the score is below {thr:g} or a check fails (docs/evaluation.md).</p>"
    )
    if summary.get("scored"):
        keys = ("frames", "scored", "flagged", "mean", "min", "p05", "p25", "median", "p75", "p95", "max")
        out.append("<table><tr>" + "".join(f"<th>{k}</th>" for k in keys) + "</tr><tr>")
        out.append(
            "".join(
                f"<td>{_score_text(summary[k]) if isinstance(summary[k], float) else summary[k]}</td>"
                for k in keys
            )
            + "</tr></table>"
        )
        png = qc_histogram_png([v.score for v in views if v.score is not None], thr)
        out.append(
            f"<p><img alt='QC histogram' src='data:image/png;base64,{base64.b64encode(png).decode()}'></p>"
        )
    else:
        out.append("<p>No QC scores.</p>")
    counts = summary.get("flag_counts", {})
    out.append("<p>Flags: " + ", ".join(f"{_esc(k)} {counts.get(k, 0)}" for k in FLAGS) + ".")
    if summary.get("computed_at_report"):
        out.append(
            f" {summary['computed_at_report']} frame(s) had no stored QC and were scored at report time."
        )
    out.append("</p>")
    out.append(twin_section(store, counts))

    lights = _order([v.lighting for v in views], list(cat.lighting))
    elevs = _order([v.elevation for v in views], list(cat.elevations))
    out.append("<h2>Coverage</h2>")
    # the map (m2s2hil/analysis/report/coverage.py) with the scores given here, also those computed
    # at report time, so its flags agree with the contact sheet's; the table below
    out.append(coverage_section(store, {v.event_id: (v.score, v.flags) for v in views}))
    out.append("<details><summary>QC per pose (table)</summary>")
    for lt in lights:
        vs = [v for v in views if v.lighting == lt and v.exposure_factor == 1.0]  # a pose: its own frame
        azs = sorted({v.azimuth_deg for v in vs if v.azimuth_deg is not None})
        name = cat.lighting[lt].name if lt in cat.lighting else lt
        out.append(f"<h3>{_esc(name)}</h3><table><tr><th>elev \\ az</th>")
        out.append("".join(f"<th>{a:g}</th>" for a in azs) + "</tr>")
        for el in elevs:
            cells = []
            for a in azs:
                hits = [v for v in vs if v.elevation == el and v.azimuth_deg == a]
                if not hits:
                    cells.append("<td></td>")
                    continue
                v = min(hits, key=lambda x: x.score if x.score is not None else -1.0)
                tip = _esc(f"{v.event_id}: {', '.join(v.flags) or 'ok'}")
                cells.append(
                    f"<td class=score title='{tip}' style='background:{_colour(v.score, v.flags, thr)}'>"
                    f"{_score_text(v.score)}</td>"
                )
            if any(c != "<td></td>" for c in cells):
                out.append(f"<tr><th>{_esc(el)}</th>{''.join(cells)}</tr>")
        out.append("</table>")
    out.append("</details>")

    out.append("<h2>Contact sheet</h2>")
    for lt in lights:
        for el in elevs:
            vs = sorted(
                [v for v in views if v.lighting == lt and v.elevation == el],
                key=lambda v: (v.azimuth_deg if v.azimuth_deg is not None else 1e9, v.frame),
            )
            if not vs:
                continue
            out.append(f"<h3>{_esc(lt)} · {_esc(el)}</h3><div class=sheet>")
            for v in vs:
                cls = "noqc" if v.score is None else ("flagged" if v.flags else "ok")
                img = (
                    f"<img alt='{_esc(v.event_id)}' src='data:image/jpeg;base64,"
                    f"{base64.b64encode(v.thumbnail).decode()}'>"
                    if v.thumbnail
                    else ""
                )
                az = "?" if v.azimuth_deg is None else f"{v.azimuth_deg:g}°"
                extra = (f" f{v.frame}" if v.frame else "") + (
                    f" ×{v.exposure_factor:g}" if v.exposure_factor != 1.0 else "")
                flags = f"<br><span class=flags>{_esc(', '.join(v.flags))}</span>" if v.flags else ""
                star = "†" if v.computed else ""
                out.append(
                    f"<figure class={cls} id='frame-{_esc(v.event_id)}' title='{_esc(v.event_id)}'>"
                    f"{img}<figcaption>{az}{extra} · "
                    f"QC {_score_text(v.score)}{star}{flags}</figcaption></figure>"
                )
            out.append("</div>")
    if any(v.computed for v in views):
        out.append("<p>† scored at report time (no QC stored with the frame).</p>")

    flagged = [v for v in views if v.flags]
    out.append(f"<h2>Flagged frames ({len(flagged)})</h2>")
    if flagged:
        out.append("<table><tr><th class=l>event</th><th>score</th><th class=l>flags</th></tr>")
        out += [
            f"<tr><td class=l>{_esc(v.event_id)}</td><td>{_score_text(v.score)}</td>"
            f"<td class=l>{_esc(', '.join(v.flags))}</td></tr>"
            for v in flagged
        ]
        out.append("</table>")
    out.append("</body></html>")
    return "\n".join(out)


def write_session_report(
    store: SessionStore,
    out: str | Path | None = None,
    *,
    thumb_px: int = 160,
    compute_missing: bool = True,
    config: QcConfig | None = None,
) -> tuple[Path, dict[str, Any]]:
    """Write the HTML report (default ``<session folder>/report.html``); returns (path, QC summary).
    A synthetic session gets its own report (``synthetic_html``: renders and masks, no QC)."""
    path = Path(out) if out is not None else Path(store.path) / "report.html"
    if store.kind == "synthetic":
        from m2s2hil.analysis.report.synthetic_html import render_synthetic

        text, summary = render_synthetic(store, thumb_px=thumb_px)
        write_text_atomic(path, text)
        return path, summary
    views, summary = collect_views(store, thumb_px=thumb_px, compute_missing=compute_missing, config=config)
    write_text_atomic(path, render(store, views, summary))
    return path, summary
