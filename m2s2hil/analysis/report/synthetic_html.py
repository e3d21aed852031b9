"""A synthetic session's HTML report (``m2s2hil report`` on a session of kind ``synthetic``):
what was rendered against its plan, the ten band renders of one view per elevation, and a
contact sheet of every view's RGB render beside its material mask.

A synthetic view has no raw mosaic, cube or capture QC (``m2s2hil/twin/synth.py``), so the
HIL report's QC sections do not apply; what can go wrong in a render is said instead: views
missing against the plan, a view lacking one of its images, and a mask with no mockup in it.
Self-contained like the HIL report (images inlined as base64).
"""

from __future__ import annotations

import base64
import functools
import html
from collections.abc import Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime
from typing import Any

import cv2
import numpy as np

from m2s2hil.catalog import load_catalog
from m2s2hil.store.frame_files import decode_image
from m2s2hil.store.records import FrameRecord
from m2s2hil.store.session import SessionStore
from m2s2hil.twin.synth import end_reason, planned_views, pose_key

#: A colour per mask label (matplotlib's tab10 without its grey, then tab20's light ones); 0 is
#: the background. The console's label overlay's (``api.console.pictures.PALETTE``, a layer
#: above, which could import this one); tests/test_report_twin.py keeps the two equal.
PALETTE = ("#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2", "#bcbd22", "#17becf",
           "#aec7e8", "#ffbb78", "#98df8a", "#ff9896", "#c5b0d5", "#c49c94", "#f7b6d2", "#dbdb8d", "#9edae5")
BACKGROUND_RGB = (40, 44, 52)
IMAGES = ("rgb", "truth_labels", *(f"band_{i:02d}" for i in range(10)))


def label_colour(k: int) -> str:
    """The colour of mask label ``k`` ≥ 1."""
    return PALETTE[(k - 1) % len(PALETTE)]


@functools.cache
def _lut() -> np.ndarray:
    lut = np.array([BACKGROUND_RGB] + [tuple(int(c[i:i + 2], 16) for i in (1, 3, 5)) for c in PALETTE],
                   dtype=np.uint8)
    return lut


def mask_rgb(mask: np.ndarray) -> np.ndarray:
    """A label map as colours: the background dark, label k in ``label_colour(k)``."""
    lut = _lut()
    m = np.asarray(mask).astype(np.int64)
    idx = np.where(m > 0, (m - 1) % len(PALETTE) + 1, 0)
    return lut[idx]


def _jpeg(rgb: np.ndarray, width: int, *, nearest: bool = False) -> str:
    h, w = rgb.shape[:2]
    if width > 0 and w != width:
        interp = cv2.INTER_NEAREST if nearest else (cv2.INTER_AREA if w > width else cv2.INTER_LINEAR)
        rgb = cv2.resize(rgb, (width, max(1, round(h * width / w))), interpolation=interp)
    ok, buf = cv2.imencode(".png" if nearest else ".jpg",
                           cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2BGR),
                           [] if nearest else [cv2.IMWRITE_JPEG_QUALITY, 85])
    mime = "png" if nearest else "jpeg"
    return f"data:image/{mime};base64,{base64.b64encode(buf.tobytes()).decode()}" if ok else ""


@dataclass
class SyntheticView:
    event_id: str
    elevation: str
    azimuth_deg: float
    tilt_deg: float | None
    missing: list[str]
    foreground: float | None  # fraction of the mask that is mockup
    labels: dict[int, int] = field(default_factory=dict)  # label → pixels
    rgb: str = ""  # data URLs
    mask: str = ""


def _view(store: SessionStore, fr: FrameRecord, thumb_px: int) -> SyntheticView:
    key = pose_key(fr.meta, fr.event_id) or (str(fr.meta.get("elevation", "?")), 0)
    pose: dict[str, Any] = fr.meta["pose"] if isinstance(fr.meta.get("pose"), dict) else {}
    az = fr.meta.get("nominal_azimuth_deg")
    v = SyntheticView(fr.event_id, key[0], float(az) if isinstance(az, int | float) else float(key[1]),
                      pose.get("tilt_deg"), [r for r in IMAGES if r not in fr.files], None)
    if "truth_labels" in fr.files:
        mask = np.asarray(decode_image(store.read_file(fr.files["truth_labels"])))
        counts = np.bincount(mask.ravel().astype(np.int64))
        v.labels = {k: int(n) for k, n in enumerate(counts) if k and n}
        v.foreground = float((mask > 0).mean())
        if thumb_px:
            v.mask = _jpeg(mask_rgb(mask), thumb_px, nearest=True)
    if thumb_px and "rgb" in fr.files:
        v.rgb = _jpeg(np.asarray(decode_image(store.read_file(fr.files["rgb"]))), thumb_px)
    return v


def _esc(v: Any) -> str:
    return html.escape(str(v))


def _ended(store: SessionStore) -> str | None:
    """Why a render ended early (its stop or failure event), None when it did not say."""
    ended = end_reason(store)
    return None if ended is None else f"{ended[0]}: {ended[1]}"


def synthetic_summary(views: Sequence[SyntheticView], planned: int) -> dict[str, Any]:
    """The render's counts: views against the plan, incomplete views, views with an empty mask."""
    return {"kind": "synthetic", "views": len(views), "planned": planned,
            "missing_views": max(0, planned - len(views)),
            "incomplete": [v.event_id for v in views if v.missing],
            "empty_masks": [v.event_id for v in views if v.foreground == 0.0], "scored": 0}


def render_synthetic(store: SessionStore, *, thumb_px: int = 160) -> tuple[str, dict[str, Any]]:
    """The report's HTML text and its summary (:func:`synthetic_summary`)."""
    from m2s2hil.analysis.report.session_html import CSS

    cat = load_catalog()
    frames = store.frames()
    views = [_view(store, fr, thumb_px) for fr in frames]
    planned = planned_views(store) or len(views)
    summary = synthetic_summary(views, planned)
    meta: dict[str, Any] = next((fr.meta["synthetic"] for fr in frames
                                 if isinstance(fr.meta.get("synthetic"), dict)), {})
    names = next((list(fr.meta.get("class_names") or []) for fr in frames if fr.meta.get("class_names")), [])
    row = store.journal.session()
    sat = cat.satellites.get(store.sweep.satellite)
    title = f"Synthetic session {store.session_id}"
    out = [f"<!doctype html><html><head><meta charset='utf-8'><title>{_esc(title)}</title>",
           f"<style>{CSS}</style></head><body>", f"<h1>{_esc(title)}</h1>", "<table>"]
    info: list[tuple[str, Any]] = [
        ("kind", "synthetic (rendered by the twin, docs/twin.md)"),
        ("satellite", sat.name if sat is not None else store.sweep.satellite),
        ("build", store.sweep.build),
        ("state", row["state"]),
        ("views", f"{len(views)} of {planned} planned"),
        ("light", meta.get("light", "?")),
        ("size", f"{meta.get('size', '?')} px"),
        ("renderer", meta.get("renderer", "?")),
        ("exposure", f"{meta['exposure']:.4g}" if isinstance(meta.get("exposure"), float) else "?"),
        ("mockup", meta.get("mockup", "?")),
        ("created", datetime.fromtimestamp(row["created"], UTC).isoformat(timespec="seconds")),
        ("report written", datetime.now(UTC).isoformat(timespec="seconds")),
    ]
    why = _ended(store)
    if why:
        info.insert(4, ("ended", why))
    out += [f"<tr><th class=l>{_esc(k)}</th><td class=l>{_esc(v)}</td></tr>" for k, v in info]
    out.append("</table>")

    out.append("<h2>Checks</h2><ul>")
    out.append(f"<li>views missing against the plan: {summary['missing_views']}</li>")
    out.append(f"<li>views lacking an image (RGB, mask or a band): {len(summary['incomplete'])}"
               + "".join(f"<br><span class=flags>{_esc(v.event_id)}: {_esc(', '.join(v.missing))}</span>"
                         for v in views if v.missing) + "</li>")
    out.append(f"<li>views whose mask has no mockup: {len(summary['empty_masks'])}"
               + "".join(f"<br><span class=flags>{_esc(e)}</span>" for e in summary["empty_masks"]) + "</li>")
    out.append("</ul>")

    if names:
        out.append("<h2>Mask labels</h2><table>"
                   "<tr><th>label</th><th class=l>material</th><th>views</th></tr>")
        for k, name in enumerate(names):
            if k == 0:
                continue
            n = sum(1 for v in views if k in v.labels)
            swatch = f"<span style='background:{label_colour(k)}'>&nbsp;&nbsp;&nbsp;</span>"
            out.append(f"<tr><td>{k}</td><td class=l>{swatch} {_esc(name)}</td><td>{n}</td></tr>")
        out.append("</table>")

    elevs = [e for e in [*cat.elevations, *cat.synthetic_elevations] if any(v.elevation == e for v in views)]
    elevs += sorted({v.elevation for v in views} - set(elevs))
    if thumb_px:
        bands_nm = meta.get("bands_nm") or []
        out.append("<h2>Band renders</h2><p>The ten band renders of the first view of each elevation, "
                   "each lit with its band's colour (wavelength to RGB, gamma 0.80, paper section 2.3).</p>")
        for el in elevs:
            first = min((fr for fr in frames if (pose_key(fr.meta, fr.event_id) or ("",))[0] == el),
                        key=lambda fr: fr.index)
            out.append(f"<h3>{_esc(el)} · {_esc(first.event_id)}</h3><div class=sheet>")
            for i in range(10):
                f = first.files.get(f"band_{i:02d}")
                if f is None:
                    continue
                src = _jpeg(np.asarray(decode_image(store.read_file(f))), max(48, thumb_px // 2))
                nm = f"{bands_nm[i]:g} nm" if i < len(bands_nm) else f"band {i + 1}"
                out.append(f"<figure><img alt='band {i + 1}' src='{src}'><figcaption>band {i + 1} · "
                           f"{_esc(nm)}</figcaption></figure>")
            out.append("</div>")

        out.append("<h2>Contact sheet</h2>")
        for el in elevs:
            vs = sorted((v for v in views if v.elevation == el), key=lambda v: v.azimuth_deg)
            tilt = next((v.tilt_deg for v in vs if v.tilt_deg is not None), None)
            out.append(f"<h3>{_esc(el)}" + (f" · tilt {tilt:g}°" if tilt is not None else "")
                       + "</h3><div class=sheet>")
            for v in vs:
                cls = "flagged" if v.missing or v.foreground == 0.0 else "ok"
                imgs = "".join(f"<img alt='{_esc(v.event_id)} {what}' src='{src}'>"
                               for what, src in (("rgb", v.rgb), ("mask", v.mask)) if src)
                fg = "" if v.foreground is None else f" · mockup {100 * v.foreground:.0f} %"
                out.append(f"<figure class={cls} id='frame-{_esc(v.event_id)}' title='{_esc(v.event_id)}'>"
                           f"<div style='display:flex;gap:2px'>{imgs}</div>"
                           f"<figcaption>{v.azimuth_deg:g}°{fg}</figcaption></figure>")
            out.append("</div>")
    out.append("</body></html>")
    return "\n".join(out), summary
