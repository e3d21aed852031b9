"""The console's frame viewer reports the registered twin's placement of the mockup (offset from
the turntable axis, yaw, tilt bias, scale, residual: issue 22 item 3) from the frames' metadata,
in headless Chromium under the console's own Content Security Policy (so the waits are
playwright's locators, not script strings); a value that is not a number is shown as "?", never
as markup."""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np
import pytest
from api_support import daemon, small_rig_config, uvicorn_thread

from m2s2hil.plan import Sweep
from m2s2hil.store.session import SessionStore

N = 64
REG = {"placement": {"dx_mm": 2.5, "dy_mm": -1.25, "yaw_deg": 3.0, "tilt_bias_deg": -0.5, "scale": 1.012},
       "residual": 0.0712, "frames": 6, "azimuth_span_deg": 90.0}
HOSTILE = "<img src=x id=injected onerror=\"document.title='pwned'\">"


def write_session(root: Path) -> tuple[str, list[int]]:
    """voyager B3, weak, E0 × 4 azimuths: frame 0 before the twin had a placement, 1 checked with
    the sweep's registration, 2 unchecked (its placement is frame 1's), 3 with projected labels
    only and a placement whose values are not numbers."""
    sweep = Sweep(satellite="voyager", build="B3", lighting=["weak"], tilts=["E0"], azimuth_step_deg=90,
                  dark={"frames": 1})
    st = SessionStore.create(root, sweep, small_rig_config(N))
    rng = np.random.default_rng(5)
    idx = []
    for ev in sweep.expand(st.rig):
        if ev.kind == "dark":
            st.write_dark(ev, np.full((N, N), 3.0, np.float32))
    frames = [e for e in sweep.expand(st.rig) if e.kind == "frame"]
    qcs = [{"score": 0.95, "flags": [], "twin": {"flags": [], "frame_flags": []}},
           {"score": 0.95, "flags": ["yawed"], "twin": {"flags": ["yawed"], "frame_flags": ["yawed"],
                                                        "registration": REG}},
           {"score": 0.95, "flags": []},
           {"score": 0.95, "flags": [], "projected_labels": {
               "class_names": ["background"], "confidence": 0.9, "source": "twin",
               "placement": {"dx_mm": HOSTILE, "dy_mm": 0.5, "yaw_deg": None, "tilt_bias_deg": 0.0,
                             "scale": 1.0}}}]
    for ev, qc in zip(frames, qcs, strict=True):
        rgb = np.full((N // 4, N // 4, 3), 90, np.uint8)
        rec = st.write_frame(ev, rng.integers(0, 1024, (N, N), dtype=np.uint16), preview_rgb=rgb,
                             meta={"exposure_s": 0.01, "gain": 1.0, "qc": qc})
        idx.append(rec.index)
    st.close()
    return st.session_id, idx


@pytest.mark.slow  # a daemon, a server and the browser
@pytest.mark.timeout(240)
def test_the_frame_viewer_reports_the_twins_placement(tmp_path, new_page) -> None:
    from playwright.sync_api import expect  # (the browser fixture skips the test without playwright)

    from m2s2hil.api import create_app

    root = tmp_path / "data"
    sid, idx = write_session(root)
    with daemon(root, rig_config=small_rig_config(N)) as d, uvicorn_thread(create_app(d.manager)) as base:
        page = new_page(viewport={"width": 1280, "height": 900})
        errors: list[str] = []
        page.on("pageerror", lambda e: errors.append(str(e)))
        page.goto(base + "/")
        page.click("#tabs button[data-view='browser']")
        page.locator("#sessions-table tbody tr", has_text=sid).click()
        page.wait_for_selector(f"#b-coverage rect[data-n='{idx[1]}']")
        page.locator(f"#b-coverage rect[data-n='{idx[1]}']").click()
        page.wait_for_selector("#frame-viewer:not([hidden])")
        expect(page.locator("#fv-title")).to_have_text(re.compile(f"frame {idx[1]}$"))
        placed = page.locator("#fv-placement")
        text = placed.inner_text()
        assert text == ("twin placement: offset (+2.50, -1.25) mm from the axis · yaw +3.00° · "
                        "tilt bias -0.50° · scale 1.012 · residual 0.071 over 6 frames (90° of azimuth)"
                        ), text
        expect(page.locator("#fv-twin")).to_contain_text("yawed")
        assert "no projected labels on this frame" in page.locator("#fv-twin").inner_text()
        shots = os.environ.get("M2S2HIL_SCREENSHOTS")
        if shots:
            Path(shots).mkdir(parents=True, exist_ok=True)
            page.screenshot(path=str(Path(shots) / "console_twin_placement.png"))
        # a frame the twin did not check: the placement known then, said to be another frame's
        page.click("#fv-next")
        expect(page.locator("#fv-title")).to_have_text(re.compile(f"frame {idx[2]}$"))
        assert placed.inner_text().endswith(f"over 6 frames (90° of azimuth) (as of frame {idx[1]})")
        # projected labels only: the residual from their confidence; non-numbers shown as "?"
        page.click("#fv-next")
        expect(page.locator("#fv-title")).to_have_text(re.compile(f"frame {idx[3]}$"))
        text = placed.inner_text()
        assert text == ("twin placement: offset (?, +0.50) mm from the axis · yaw ? · tilt bias +0.00° · "
                        "scale 1.000 · residual 0.100 · from the projected labels"), text
        assert page.locator("#injected").count() == 0 and page.title() != "pwned"
        # before the twin had any placement, the nearest later one (frame 1's)
        for _ in range(3):
            page.click("#fv-prev")
        expect(page.locator("#fv-title")).to_have_text(re.compile(f"frame {idx[0]}$"))
        assert placed.inner_text().endswith(f"(as of frame {idx[1]})")
        assert errors == []
