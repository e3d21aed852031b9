// m2s2hil console pictures: the spectrum at a clicked pixel or dragged region (live view and stored
// frames), the frame viewer (zoom, pan, the ten band images), the sweep's coverage map and the
// calibration pictures. Plain JavaScript, loaded after console.js, whose api(), blobUrl() and
// state it uses. Every text from the daemon goes in with textContent; canvases carry role=img
// and an aria-label saying what they show.
"use strict";

const pictures = (() => {
  const SVG = "http://www.w3.org/2000/svg";
  const byId = (id) => document.getElementById(id);
  function mk(tag, props = {}, text) {
    const e = document.createElement(tag);
    for (const [k, v] of Object.entries(props)) {
      if (k === "class") e.className = v; else if (k in e && typeof v !== "string") e[k] = v; else e.setAttribute(k, v);
    }
    if (text !== undefined) e.textContent = text;
    return e;
  }
  function css(name, fallback) {
    const v = getComputedStyle(document.documentElement).getPropertyValue(name).trim();
    return v || fallback;
  }
  const fmt = (v, d = 1) => (v == null || !isFinite(v) ? "–" : Number(v).toFixed(d));

  // ------------------------------------------------------------------ spectrum chart
  // DN (left axis, blue) and, when there is a white reference, reflectance (right axis, orange),
  // against wavelength. A <details> table under it holds the same numbers as text.
  function spectrumPanel(box, title) {
    const head = mk("div", { class: "row pic-spec-head" });
    const caption = mk("span", { class: "muted pic-spec-caption" }, "click the image for a spectrum; drag for a region");
    head.append(mk("b", {}, title), caption);
    const canvas = mk("canvas", { class: "pic-spec", role: "img", "aria-label": title + ": no spectrum yet" });
    const notes = mk("div", { class: "muted pic-notes" });
    const details = mk("details", { class: "pic-values" });
    details.append(mk("summary", {}, "values"));
    const table = mk("table"); details.append(table);
    box.append(head, canvas, notes, details);
    let last = null;
    const panel = {
      show(s) { last = s; draw(); },
      clear(msg) { last = null; caption.textContent = msg; notes.textContent = ""; table.replaceChildren(); draw(); },
      get spectrum() { return last; },
      canvas,
    };
    function draw() {
      const dpr = window.devicePixelRatio || 1;
      const W = Math.max(200, Math.round(canvas.clientWidth * dpr)), H = Math.round((canvas.clientHeight || 200) * dpr);
      if (canvas.width !== W || canvas.height !== H) { canvas.width = W; canvas.height = H; }
      const ctx = canvas.getContext("2d");
      ctx.clearRect(0, 0, W, H);
      const fg = css("--fg", "#e6e9ec"), muted = css("--muted", "#8d98a3"), line = css("--line", "#323941");
      const blue = css("--accent", "#4aa3ff"), orange = css("--pic-refl", "#ff9f43");
      const s = last;
      const refl = s && s.reflectance ? s.reflectance : null;
      const L = 58 * dpr, R = (refl ? 50 : 14) * dpr, T = 12 * dpr, B = 36 * dpr;
      const pw = W - L - R, ph = H - T - B;
      ctx.font = `${11 * dpr}px system-ui, sans-serif`; ctx.lineWidth = dpr;
      const bands = s ? s.bands_nm : [431, 877];
      const x0 = Math.floor((Math.min(...bands) - 30) / 50) * 50, x1 = Math.ceil((Math.max(...bands) + 30) / 50) * 50;
      const X = (nm) => L + (nm - x0) / (x1 - x0) * pw;
      const dnMax = niceCeil(s ? Math.max(1, ...s.dn) * 1.1 : 1000);
      const rMax = refl ? Math.max(1, niceCeil(Math.max(0, ...refl.filter((v) => v != null)) * 1.1)) : 1;
      const Y = (v, top) => T + ph - (v / top) * ph;
      // axes and grid
      ctx.strokeStyle = line; ctx.fillStyle = muted; ctx.textAlign = "center"; ctx.textBaseline = "top";
      for (let nm = Math.ceil(x0 / 100) * 100; nm <= x1; nm += 100) {
        ctx.beginPath(); ctx.moveTo(X(nm), T); ctx.lineTo(X(nm), T + ph); ctx.stroke();
        ctx.fillText(String(nm), X(nm), T + ph + 4 * dpr);
      }
      ctx.fillText("wavelength (nm)", L + pw / 2, T + ph + 19 * dpr);
      ctx.textAlign = "right"; ctx.textBaseline = "middle";
      for (let i = 0; i <= 4; i++) {
        const v = dnMax * i / 4;
        ctx.beginPath(); ctx.moveTo(L, Y(v, dnMax)); ctx.lineTo(L + pw, Y(v, dnMax)); ctx.stroke();
        ctx.fillStyle = blue; ctx.fillText(shortNum(v), L - 6 * dpr, Y(v, dnMax));
        if (refl) { ctx.fillStyle = orange; ctx.textAlign = "left"; ctx.fillText((rMax * i / 4).toFixed(2), L + pw + 6 * dpr, Y(v, dnMax)); ctx.textAlign = "right"; }
      }
      ctx.save(); ctx.translate(12 * dpr, T + ph / 2); ctx.rotate(-Math.PI / 2); ctx.textAlign = "center";
      ctx.fillStyle = blue; ctx.fillText(s && s.dark ? "DN (dark subtracted)" : "DN", 0, 0); ctx.restore();
      if (refl) {
        ctx.save(); ctx.translate(W - 6 * dpr, T + ph / 2); ctx.rotate(Math.PI / 2); ctx.textAlign = "center";
        ctx.fillStyle = orange; ctx.fillText("reflectance", 0, 0); ctx.restore();
      }
      if (!s) return;
      series(ctx, s.bands_nm.map((nm, i) => [X(nm), Y(s.dn[i], dnMax)]), blue, dpr);
      if (refl) series(ctx, s.bands_nm.map((nm, i) => (refl[i] == null ? null : [X(nm), Y(refl[i], rMax)])), orange, dpr);
      ctx.fillStyle = fg;
      const r = s.region;
      caption.textContent = `${s.source} · x ${r.x} y ${r.y} · ${r.w}×${r.h} px · ${fmt(s.exposure_s * 1000, 2)} ms gain ${s.gain}` +
        (s.dark ? " · dark " + s.dark : "");
      notes.textContent = (s.notes || []).join("; ");
      canvas.setAttribute("aria-label", `${title}, region x ${r.x} y ${r.y} ${r.w}×${r.h} pixels: ` +
        s.bands_nm.map((nm, i) => `${nm} nm ${fmt(s.dn[i])} DN` + (refl && refl[i] != null ? ` reflectance ${fmt(refl[i], 3)}` : "")).join(", "));
      const rows = [mk("tr")]; rows[0].append(mk("th", {}, "nm"), mk("th", {}, "DN"), ...(refl ? [mk("th", {}, "reflectance")] : []));
      s.bands_nm.forEach((nm, i) => {
        const tr = mk("tr"); tr.append(mk("td", {}, String(nm)), mk("td", {}, fmt(s.dn[i])), ...(refl ? [mk("td", {}, fmt(refl[i], 3))] : []));
        rows.push(tr);
      });
      table.replaceChildren(...rows);
    }
    new ResizeObserver(() => draw()).observe(canvas);
    return panel;
  }
  function series(ctx, pts, colour, dpr) {
    ctx.strokeStyle = colour; ctx.fillStyle = colour; ctx.lineWidth = 2 * dpr;
    ctx.beginPath(); let pen = false;
    for (const p of pts) { if (!p) { pen = false; continue; } if (pen) ctx.lineTo(p[0], p[1]); else ctx.moveTo(p[0], p[1]); pen = true; }
    ctx.stroke();
    for (const p of pts) if (p) { ctx.beginPath(); ctx.arc(p[0], p[1], 3.5 * dpr, 0, 2 * Math.PI); ctx.fill(); }
  }
  function niceCeil(v) {
    if (!(v > 0)) return 1;
    const e = Math.pow(10, Math.floor(Math.log10(v))); const m = v / e;
    return (m <= 1 ? 1 : m <= 2 ? 2 : m <= 2.5 ? 2.5 : m <= 3 ? 3 : m <= 4 ? 4 : m <= 5 ? 5 : m <= 8 ? 8 : 10) * e;
  }
  function shortNum(v) { return v >= 1e4 ? (v / 1e3).toFixed(0) + "k" : v >= 100 ? v.toFixed(0) : v.toFixed(1); }

  // ------------------------------------------------------------------ region picking on a canvas
  // A click (no movement) asks for one mosaic cell; a drag draws a rectangle and asks for it.
  // ``toSensor(clientX, clientY)`` maps a pointer to sensor pixels (null outside the image).
  function regionPicker(canvas, toSensor, onRegion, enabled = () => true, dragSelects = () => true) {
    let start = null;
    canvas.addEventListener("pointerdown", (ev) => {
      if (!enabled() || ev.button !== 0) return;
      const p = toSensor(ev.clientX, ev.clientY); if (!p) return;
      start = { p, cx: ev.clientX, cy: ev.clientY, id: ev.pointerId };
      canvas.setPointerCapture(ev.pointerId);
    });
    canvas.addEventListener("pointerup", (ev) => {
      if (!start || ev.pointerId !== start.id) return;
      const moved = Math.hypot(ev.clientX - start.cx, ev.clientY - start.cy) > 4;
      const q = toSensor(ev.clientX, ev.clientY, true) || start.p;
      const a = start.p; start = null;
      if (!moved) { onRegion({ x: a.x, y: a.y, w: 1, h: 1 }); return; }
      if (!dragSelects()) return;  // that drag panned
      const x = Math.min(a.x, q.x), y = Math.min(a.y, q.y);
      onRegion({ x, y, w: Math.abs(q.x - a.x) + 1, h: Math.abs(q.y - a.y) + 1 });
    });
    canvas.addEventListener("pointercancel", () => { start = null; });
  }

  // ------------------------------------------------------------------ live view spectrum
  const live = { sensor: null, panel: null, region: null };
  function liveSetup() {
    const box = byId("live-spectrum"); const cv = byId("live-canvas");
    if (!box || !cv) return;
    live.panel = spectrumPanel(box, "Spectrum (live)");
    live.panel.clear("click the live image for the spectrum at a point; drag for a region");
    regionPicker(cv, (cx, cy, clamp) => {
      const r = cv.getBoundingClientRect(); const s = live.sensor;
      let fx = (cx - r.left) / r.width, fy = (cy - r.top) / r.height;
      if (clamp) { fx = Math.min(Math.max(fx, 0), 0.9999); fy = Math.min(Math.max(fy, 0), 0.9999); }
      if (!s || fx < 0 || fy < 0 || fx >= 1 || fy >= 1) return null;
      return { x: Math.floor(fx * s[0]), y: Math.floor(fy * s[1]) };
    }, async (reg) => { live.region = reg; liveMark(); await liveSpectrum(); }, () => live.sensor !== null);
    live.mark = mk("div", { class: "pic-live-mark", "aria-hidden": "true" }); live.mark.hidden = true;
    cv.parentElement.append(live.mark);
    // the sensor size travels with the live frames' statistics
    setInterval(async () => {
      if (!window.m2s2hilLive || !window.m2s2hilLive.frames) return;
      if (!live.sensor) {
        const r = await api("GET", "/camera/live").catch(() => null);
        if (r && r.stats && r.stats.sensor) live.sensor = r.stats.sensor;
      }
      if (live.region && byId("live-spectrum-follow") && byId("live-spectrum-follow").checked) liveSpectrum();
    }, 1000);
    const follow = mk("label", {}, ""); const cb = mk("input", { type: "checkbox", id: "live-spectrum-follow" });
    follow.append(cb, document.createTextNode(" follow the live frames"));
    box.querySelector(".pic-spec-head").append(follow);
  }
  function liveMark() {  // where the spectrum comes from, over the live image (percentages of it)
    const g = live.region, s = live.sensor, m = live.mark; if (!m || !g || !s) return;
    m.hidden = false;
    m.style.left = (100 * g.x / s[0]) + "%"; m.style.top = (100 * g.y / s[1]) + "%";
    m.style.width = `max(6px, ${100 * g.w / s[0]}%)`; m.style.height = `max(6px, ${100 * g.h / s[1]}%)`;
  }
  async function liveSpectrum() {
    const g = live.region; if (!g) return;
    try {
      live.panel.show(await api("GET", `/camera/live/spectrum?x=${g.x}&y=${g.y}&w=${g.w}&h=${g.h}`));
    } catch (e) { live.panel.clear(e.message); }
  }

  // ------------------------------------------------------------------ frame viewer (stored frames)
  // One overlay for every view: the frame's preview or its ten band images, zoom (wheel, pinch,
  // buttons) and pan (drag), a click or a drag for the spectrum beside it.
  const fv = { sid: null, n: null, items: [], img: null, mode: "preview", scale: 1, tx: 0, ty: 0, sensor: null,
    region: null, pointers: new Map(), panel: null, bandsGeom: null, labels: null, bandsNm: null, bandLabels: [] };
  function viewerSetup() {
    const ov = mk("div", { id: "frame-viewer", class: "overlay pic-overlay", role: "dialog", "aria-modal": "true", "aria-labelledby": "fv-title" });
    ov.hidden = true;
    const card = mk("div", { class: "card pic-viewer" });
    const bar = mk("div", { class: "row" });
    const title = mk("h2", { id: "fv-title" }, "frame");
    const mode = mk("select", { id: "fv-mode", "aria-label": "what to show" });
    mode.append(new Option("false colour", "preview"), new Option("10 bands", "bands"));
    const drag = mk("select", { id: "fv-drag", "aria-label": "what a drag does" });
    drag.append(new Option("drag pans", "pan"), new Option("drag selects a region", "region"));
    const btn = (id, text, label, fn) => { const b = mk("button", { id, type: "button", "aria-label": label }, text); b.addEventListener("click", fn); return b; };
    bar.append(title,
      btn("fv-prev", "◀", "previous frame", () => step(-1)), btn("fv-next", "▶", "next frame", () => step(1)),
      mode, drag, labelsToggle(),
      btn("fv-zoom-in", "+", "zoom in", () => zoomAt(1.5)), btn("fv-zoom-out", "−", "zoom out", () => zoomAt(1 / 1.5)),
      btn("fv-reset", "Reset zoom", "reset zoom and pan", () => { resetView(); draw(); }),
      btn("fv-close", "Close", "close the frame viewer", close));
    const body = mk("div", { class: "pic-body" });
    const stage = mk("div", { class: "pic-stage" });
    const cv = mk("canvas", { id: "fv-canvas", role: "img", "aria-label": "frame: loading" });
    stage.append(cv);
    const side = mk("div", { class: "pic-side", id: "fv-spectrum" });
    body.append(stage, side);
    const info = mk("div", { class: "muted", id: "fv-info" });
    const twin = mk("div", { class: "row muted pic-legend", id: "fv-twin", "aria-live": "polite" });
    twin.style.minHeight = "1.5em";  // (CSSOM: the page's CSP refuses style attributes)
    const placed = mk("div", { class: "muted", id: "fv-placement", title: PLACEMENT_HELP });
    card.append(bar, info, twin, placed, body); ov.append(card); document.body.append(ov);
    fv.panel = spectrumPanel(side, "Spectrum");
    mode.addEventListener("change", () => { fv.mode = mode.value; loadImage(); });
    // zoom at the pointer with the wheel; pan by dragging; pinch with two fingers
    cv.addEventListener("wheel", (ev) => {
      ev.preventDefault();
      const r = cv.getBoundingClientRect();
      zoomAt(Math.exp(-ev.deltaY * 0.0015), ev.clientX - r.left, ev.clientY - r.top);
    }, { passive: false });
    cv.addEventListener("pointerdown", (ev) => {
      fv.pointers.set(ev.pointerId, { x: ev.clientX, y: ev.clientY });
      if (fv.pointers.size === 2) fv.pinch = pinchState();
    });
    cv.addEventListener("pointermove", (ev) => {
      const p = fv.pointers.get(ev.pointerId); if (!p) return;
      if (fv.pointers.size === 2 && fv.pinch) {
        p.x = ev.clientX; p.y = ev.clientY;
        const now = pinchState(); const r = cv.getBoundingClientRect();
        zoomAt(now.d / fv.pinch.d, now.cx - r.left, now.cy - r.top);
        fv.tx += now.cx - fv.pinch.cx; fv.ty += now.cy - fv.pinch.cy; fv.pinch = now; draw(); return;
      }
      if (byId("fv-drag").value === "pan" && fv.pointers.size === 1) {
        fv.tx += ev.clientX - p.x; fv.ty += ev.clientY - p.y; draw();
      }
      p.x = ev.clientX; p.y = ev.clientY;
    });
    const up = (ev) => { fv.pointers.delete(ev.pointerId); if (fv.pointers.size < 2) fv.pinch = null; };
    cv.addEventListener("pointerup", up); cv.addEventListener("pointercancel", up);
    regionPicker(cv, (cx, cy, clamp) => viewToSensor(cx, cy, clamp), (reg) => { fv.region = reg; frameSpectrum(); },
      () => fv.sensor !== null && fv.pointers.size <= 1, () => byId("fv-drag").value === "region");
    // a resized stage (a phone turned, the window narrowed) keeps what was in its centre there:
    // unzoomed, the picture is fitted and centred again; zoomed, the pan follows half the change
    let size = [cv.clientWidth, cv.clientHeight];
    new ResizeObserver(() => {
      const now = [cv.clientWidth, cv.clientHeight];
      if (fv.img && now[0] && now[1]) {
        if (fv.scale === 1 || !size[0] || !size[1]) resetView();
        else { fv.tx += (now[0] - size[0]) / 2; fv.ty += (now[1] - size[1]) / 2; }
      }
      size = now; draw();
    }).observe(cv);
    // thumbnails of the contact sheets open the viewer
    for (const [boxId, sid] of [["b-sheet", () => state.browserId], ["run-sheet", () => state.watched]]) {
      const box = byId(boxId); if (!box) continue;
      box.addEventListener("click", (ev) => {
        const img = ev.target.closest("img"); if (!img || !sid()) return;
        open(sid(), { eventId: img.alt });
      });
    }
  }
  // The twin's projected labels over the frame (GET …/labels.png, RGBA), toggled; off while the
  // frame has none. Remembered across frames and visits (localStorage).
  function labelsToggle() {
    const lab = mk("label", { title: "the registered twin's label map at this frame's pose" });
    const cb = mk("input", { type: "checkbox", id: "fv-labels" });
    cb.checked = localStorage.getItem("m2s2hil.fv.labels") !== "0"; cb.disabled = true;
    cb.addEventListener("change", () => { localStorage.setItem("m2s2hil.fv.labels", cb.checked ? "1" : "0"); draw(); });
    lab.append(cb, document.createTextNode(" twin labels"));
    return lab;
  }
  // How the twin placed the mockup, from the frames' metadata (GET /sessions/{id}/frames): the
  // sweep's registration as it stood when a frame was checked (qc.twin.registration), else the
  // placement a frame's projected labels were drawn with (qc.projected_labels, whose confidence
  // is 1 − the residual). This frame's own, else the nearest frame's before it, else after it.
  const PLACEMENT_HELP = "the registered twin: the mockup's centre off the turntable axis (x right, y away " +
    "from the camera at azimuth 0), its yaw at azimuth 0, the tilt stage's bias, the scale, and the residual " +
    "(1 − the mean IoU of the twin's silhouettes with the frames' masks; docs/twin.md)";
  const finite = (v) => (typeof v === "number" && Number.isFinite(v) ? v : null);
  const isObj = (v) => v !== null && typeof v === "object" && !Array.isArray(v);
  function placementOf(meta) {
    const qc = isObj(meta) && isObj(meta.qc) ? meta.qc : {};
    const reg = isObj(qc.twin) ? qc.twin.registration : null;
    if (isObj(reg) && isObj(reg.placement)) {
      return { p: reg.placement, residual: finite(reg.residual), frames: finite(reg.frames),
        span: finite(reg.azimuth_span_deg), via: "registration" };
    }
    const lab = isObj(qc.projected_labels) ? qc.projected_labels : null;
    if (lab && isObj(lab.placement)) {
      const c = finite(lab.confidence);
      return { p: lab.placement, residual: c === null ? null : 1 - c, frames: null, span: null, via: "labels" };
    }
    return null;
  }
  function placementText(pl) {
    const f = (v, digits, unit = "", signed = true) => {
      const x = finite(v); return x === null ? "?" : (signed && x >= 0 ? "+" : "") + x.toFixed(digits) + unit;
    };
    const p = pl.p;
    let t = `twin placement: offset (${f(p.dx_mm, 2)}, ${f(p.dy_mm, 2)}) mm from the axis · yaw ${f(p.yaw_deg, 2, "°")}` +
      ` · tilt bias ${f(p.tilt_bias_deg, 2, "°")} · scale ${f(p.scale, 3, "", false)}` +
      ` · residual ${pl.residual === null ? "?" : pl.residual.toFixed(3)}`;
    if (pl.frames !== null) t += ` over ${pl.frames} frames` + (pl.span !== null ? ` (${pl.span.toFixed(0)}° of azimuth)` : "");
    return t;
  }
  function showPlacement(it) {
    const box = byId("fv-placement"); if (!box) return;
    const i = fv.items.indexOf(it);
    let at = placementOf(it.meta) ? it : null;
    for (let k = i - 1; !at && k >= 0; k--) if (placementOf(fv.items[k].meta)) at = fv.items[k];
    for (let k = i + 1; !at && k < fv.items.length; k++) if (placementOf(fv.items[k].meta)) at = fv.items[k];
    if (!at) { box.textContent = ""; box.hidden = true; return; }
    const pl = placementOf(at.meta);
    box.hidden = false;
    box.textContent = placementText(pl) + (at === it ? "" : ` (as of frame ${at.n})`) +
      (pl.via === "labels" ? " · from the projected labels" : "");
  }
  async function loadTwin() {
    const want = [fv.sid, fv.n].join("/"); const box = byId("fv-twin"); const cb = byId("fv-labels");
    if (fv.labels) { URL.revokeObjectURL(fv.labels.src); fv.labels = null; }
    cb.disabled = true; box.replaceChildren();
    let t;
    try { t = await api("GET", `/sessions/${fv.sid}/frames/${fv.n}/twin`); } catch (e) { return; }
    if (want !== [fv.sid, fv.n].join("/")) return;
    const parts = [];
    if (t.checked) parts.push(mk("span", { class: t.flags.length ? "bad" : "" }, t.flags.length ? "twin ⚑ " + t.flags.join(", ")
      : "twin: no flag" + (t.frame_flags.length ? ` (this frame alone: ${t.frame_flags.join(", ")})` : "")));
    if (t.labels_url) {
      parts.push(mk("span", {}, "labels" + (t.confidence != null ? ` (confidence ${t.confidence.toFixed(2)})` : "") + ":"));
      for (const it of t.legend) {
        const sw = mk("span", { class: "cov-swatch", "aria-hidden": "true" }); sw.style.background = it.colour;
        const item = mk("span", { class: "fv-legend-item", "data-index": String(it.index) }); item.append(sw, document.createTextNode("\u00a0" + it.name + " "));
        parts.push(item);
      }
      try {
        const img = new Image(); img.src = await blobUrl(t.labels_url); await img.decode();
        if (want !== [fv.sid, fv.n].join("/")) { URL.revokeObjectURL(img.src); return; }
        fv.labels = img; cb.disabled = false; draw();
      } catch (e) { parts.push(mk("span", { class: "bad" }, "labels: " + e.message)); }
    } else if (t.checked) {
      const placed = byId("fv-placement");  // shown already when the twin has a placement (showPlacement)
      parts.push(mk("span", {}, placed && !placed.hidden ? "· no projected labels on this frame"
        : "· no projected labels (the twin is not registered yet)"));
    }
    box.replaceChildren(...parts);
  }
  function pinchState() {
    const [a, b] = [...fv.pointers.values()];
    return { d: Math.max(1, Math.hypot(a.x - b.x, a.y - b.y)), cx: (a.x + b.x) / 2, cy: (a.y + b.y) / 2 };
  }
  async function open(sid, { n = null, eventId = null } = {}) {
    const ov = byId("frame-viewer"); ov.hidden = false;
    if (fv.sid !== sid) { fv.sid = sid; fv.items = []; fv.sensor = null; }
    if (!fv.items.length) {
      for (let off = 0; ; off += 500) {
        const r = await api("GET", `/sessions/${sid}/frames?offset=${off}&limit=500`).catch((e) => { fv.panel.clear(e.message); return null; });
        if (!r) return;
        fv.items.push(...r.items.map((f) => ({ n: f.n, event_id: f.event_id, meta: f.meta || {} })));
        if (fv.items.length >= r.total || !r.items.length) break;
      }
    }
    const it = fv.items.find((f) => (n !== null ? f.n === n : f.event_id === eventId)) || fv.items[0];
    if (!it) { fv.panel.clear("this session has no frames yet"); return; }
    show(it);
    byId("fv-close").focus();
  }
  function close() { byId("frame-viewer").hidden = true; }
  function step(d) {
    const i = fv.items.findIndex((f) => f.n === fv.n); const it = fv.items[i + d];
    if (it) show(it);
  }
  function show(it) {
    fv.n = it.n; const ev = it.meta.event || {}; const qc = it.meta.qc || {};
    byId("fv-title").textContent = `${fv.sid} · frame ${it.n}`;
    byId("fv-info").textContent = `${it.event_id} · ${ev.lighting ?? ""} ${ev.elevation ?? ""} az ${ev.nominal_azimuth_deg ?? ev.azimuth_deg ?? "?"}°` +
      (qc.score != null ? ` · QC ${Number(qc.score).toFixed(3)}` : "") + (qc.flags && qc.flags.length ? " ⚑ " + qc.flags.join(", ") : "");
    byId("fv-prev").disabled = fv.items[0].n === it.n; byId("fv-next").disabled = fv.items[fv.items.length - 1].n === it.n;
    loadImage(); showPlacement(it); loadTwin();
    // the centre cell's spectrum at once (it also tells the sensor's size), or the last region
    fv.region = fv.region && fv.sensor ? fv.region : null;
    frameSpectrum();
  }
  async function loadImage() {
    const path = fv.mode === "bands" ? `/sessions/${fv.sid}/frames/${fv.n}/bands.png` : `/sessions/${fv.sid}/frames/${fv.n}/preview`;
    const want = [fv.sid, fv.n, fv.mode].join("/");
    try {
      const url = await blobUrl(path);
      const img = new Image(); img.src = url; await img.decode();
      if (want !== [fv.sid, fv.n, fv.mode].join("/")) return;
      if (fv.img) URL.revokeObjectURL(fv.img.src);
      const changed = !fv.img || fv.img.naturalWidth !== img.naturalWidth || fv.img.naturalHeight !== img.naturalHeight;
      fv.img = img;
      // on a phone the stage takes the picture's shape (pictures.css): no black bands over the ten bands
      document.querySelector(".pic-stage").style.setProperty("--pic-aspect", `${img.naturalWidth} / ${img.naturalHeight}`);
      fv.bandsGeom = fv.mode === "bands" ? bandsGeometry(img) : null;
      if (changed) resetView();
      draw();
      byId("fv-canvas").setAttribute("aria-label", fv.mode === "bands"
        ? `frame ${fv.n}: its ten band images, five to a row, each labelled with its wavelength`
        : `frame ${fv.n}: false-colour preview; click for the spectrum at a point`);
    } catch (e) { fv.panel.clear("cannot show the frame: " + e.message); }
  }
  // bands.png: 5 tiles to a row, each a 22-px label bar over the image, 2 px of padding around
  function bandsGeometry(img) {
    const s = fv.spectrumSensor || fv.sensor; const cols = 5, rows = 2;
    const tw = img.naturalWidth / cols, th = img.naturalHeight / rows;
    return { cols, tw, th, pad: 2, bar: 22, sensor: s };
  }
  function fit() {
    const cv = byId("fv-canvas"); if (!fv.img) return 1;
    return Math.min(cv.clientWidth / fv.img.naturalWidth, cv.clientHeight / fv.img.naturalHeight);
  }
  function resetView() {
    const cv = byId("fv-canvas"); fv.scale = 1; const f = fit();
    fv.tx = fv.img ? (cv.clientWidth - fv.img.naturalWidth * f) / 2 : 0;
    fv.ty = fv.img ? (cv.clientHeight - fv.img.naturalHeight * f) / 2 : 0;
  }
  function zoomAt(k, px, py) {
    const cv = byId("fv-canvas");
    if (px === undefined) { px = cv.clientWidth / 2; py = cv.clientHeight / 2; }
    const s = Math.min(64, Math.max(1, fv.scale * k)); k = s / fv.scale; fv.scale = s;
    fv.tx = px - (px - fv.tx) * k; fv.ty = py - (py - fv.ty) * k;
    if (s === 1) resetView();
    draw();
  }
  function draw() {
    const cv = byId("fv-canvas"); if (!cv || byId("frame-viewer").hidden) return;
    const dpr = window.devicePixelRatio || 1;
    const W = Math.round(cv.clientWidth * dpr), H = Math.round(cv.clientHeight * dpr);
    if (cv.width !== W || cv.height !== H) { cv.width = W; cv.height = H; }
    const ctx = cv.getContext("2d"); ctx.setTransform(1, 0, 0, 1, 0, 0); ctx.clearRect(0, 0, W, H);
    if (!fv.img) return;
    const k = fit() * fv.scale;
    ctx.setTransform(dpr * k, 0, 0, dpr * k, dpr * fv.tx, dpr * fv.ty);
    ctx.imageSmoothingEnabled = fv.scale < 4;  // zoomed in: show the pixels as they are
    ctx.drawImage(fv.img, 0, 0);
    if (fv.labels && byId("fv-labels").checked) {  // over the image, or over every band's tile
      ctx.globalAlpha = 0.45; ctx.imageSmoothingEnabled = false;
      for (const [ox, oy, bw, bh] of imageBoxes()) ctx.drawImage(fv.labels, ox, oy, bw, bh);
      ctx.globalAlpha = 1;
    }
    bandLabels(ctx, k, dpr);  // in screen pixels, under the region's outline
    ctx.setTransform(dpr * k, 0, 0, dpr * k, dpr * fv.tx, dpr * fv.ty);
    const g = fv.region, s = fv.sensor;
    if (g && s) {  // the spectrum's region: on the image, or on every band's tile
      ctx.strokeStyle = "#ffe066"; ctx.lineWidth = 2 / k;
      for (const [ox, oy, bw, bh] of imageBoxes()) {
        const sx = bw / s[0], sy = bh / s[1];
        ctx.strokeRect(ox + g.x * sx, oy + g.y * sy, Math.max(g.w * sx, 2 / k), Math.max(g.h * sy, 2 / k));
      }
    }
    ctx.setTransform(1, 0, 0, 1, 0, 0);
    ctx.fillStyle = "rgba(0,0,0,.55)"; ctx.fillRect(0, H - 20 * dpr, 92 * dpr, 20 * dpr);
    ctx.fillStyle = "#fff"; ctx.font = `${11 * dpr}px system-ui, sans-serif`; ctx.textBaseline = "middle";
    ctx.fillText(`zoom ×${fv.scale.toFixed(fv.scale < 10 ? 1 : 0)}`, 6 * dpr, H - 10 * dpr);
  }
  // bands.png's own labels are 11 px at full size: fitted to a phone they shrink to 3-6 px. While a
  // label bar shows smaller than the text needs, each tile's wavelength is drawn again over its bar
  // in screen pixels (fv.bandLabels: what was drawn, for the browser test)
  const BAND_LABEL_PX = 12;
  function bandLabels(ctx, k, dpr) {
    fv.bandLabels = [];
    const t = fv.bandsGeom, nm = fv.bandsNm;
    if (fv.mode !== "bands" || !t || !nm || t.bar * k >= BAND_LABEL_PX + 4) return;
    ctx.setTransform(1, 0, 0, 1, 0, 0);
    ctx.font = `${BAND_LABEL_PX * dpr}px system-ui, sans-serif`; ctx.textBaseline = "top"; ctx.textAlign = "left";
    imageBoxes().forEach(([ox, oy, bw], b) => {
      if (nm[b] == null) return;
      const x = fv.tx + ox * k, y = fv.ty + (oy - t.bar) * k, text = `${nm[b]} nm`;
      const w = Math.min(ctx.measureText(text).width / dpr + 6, bw * k);
      ctx.fillStyle = "rgba(0,0,0,.75)"; ctx.fillRect(x * dpr, y * dpr, w * dpr, (BAND_LABEL_PX + 4) * dpr);
      ctx.fillStyle = "#fff"; ctx.fillText(text, (x + 3) * dpr, (y + 2) * dpr, (w - 4) * dpr);
      fv.bandLabels.push({ text, x, y, w, px: BAND_LABEL_PX });
    });
  }
  // where the sensor's image is on the drawn picture: the whole preview, or each band's tile
  function imageBoxes() {
    const boxes = [];
    if (fv.mode === "preview") boxes.push([0, 0, fv.img.naturalWidth, fv.img.naturalHeight]);
    else if (fv.bandsGeom) {
      const t = fv.bandsGeom;
      for (let b = 0; b < 10; b++) {
        boxes.push([(b % t.cols) * t.tw + t.pad, Math.floor(b / t.cols) * t.th + t.pad + t.bar, t.tw - 2 * t.pad, t.th - 2 * t.pad - t.bar]);
      }
    }
    return boxes;
  }
  // canvas pixel → image pixel → sensor pixel (in the band view: within the tile under the pointer)
  function viewToSensor(cx, cy, clamp) {
    const cv = byId("fv-canvas"); const s = fv.sensor; if (!fv.img || !s) return null;
    if (byId("fv-drag").value === "pan" && !clamp && fv.pointers.size > 1) return null;
    const r = cv.getBoundingClientRect(); const k = fit() * fv.scale;
    let ix = (cx - r.left - fv.tx) / k, iy = (cy - r.top - fv.ty) / k;
    let fx, fy;
    if (fv.mode === "bands") {
      const g = fv.bandsGeom; const col = Math.floor(ix / g.tw), row = Math.floor(iy / g.th);
      if (col < 0 || col >= g.cols || row < 0 || row > 1) return null;
      fx = (ix - col * g.tw - g.pad) / (g.tw - 2 * g.pad); fy = (iy - row * g.th - g.pad - g.bar) / (g.th - 2 * g.pad - g.bar);
    } else { fx = ix / fv.img.naturalWidth; fy = iy / fv.img.naturalHeight; }
    if (clamp) { fx = Math.min(Math.max(fx, 0), 0.9999); fy = Math.min(Math.max(fy, 0), 0.9999); }
    if (!(fx >= 0 && fx < 1 && fy >= 0 && fy < 1)) return null;
    return { x: Math.floor(fx * s[0]), y: Math.floor(fy * s[1]) };
  }
  async function frameSpectrum() {
    const want = [fv.sid, fv.n].join("/");
    let g = fv.region;
    try {
      if (!g) {  // first look at a frame: its centre cell (and the sensor size comes back with it)
        const s0 = fv.sensor || (await api("GET", `/sessions/${fv.sid}/frames/${fv.n}/spectrum?x=0&y=0`)).sensor;
        fv.sensor = s0;
        g = { x: Math.floor(s0[0] / 2), y: Math.floor(s0[1] / 2), w: 1, h: 1 };
      }
      const s = await api("GET", `/sessions/${fv.sid}/frames/${fv.n}/spectrum?x=${g.x}&y=${g.y}&w=${g.w}&h=${g.h}`);
      if (want !== [fv.sid, fv.n].join("/")) return;
      fv.sensor = s.sensor; fv.region = s.region; fv.bandsNm = s.bands_nm;
      fv.panel.show(s); draw();
    } catch (e) { fv.panel.clear(e.message); }
  }

  // ------------------------------------------------------------------ coverage map (console)
  const STATE_TEXT = { captured: "captured", flagged: "captured, QC flagged", skipped: "skipped (fault)", failed: "failed", pending: "pending" };
  async function coverageInto(box, sid) {
    if (!box || !sid) return;
    // only the latest request draws: an earlier one answered late (taken while the session still
    // ran) would put its pending cells back over the final map
    const ticket = String(Number(box.dataset.ticket || 0) + 1);
    box.dataset.ticket = ticket;
    let cov;
    try { cov = await api("GET", `/sessions/${sid}/coverage`); } catch (e) {
      if (box.dataset.ticket === ticket) box.replaceChildren(mk("div", { class: "muted" }, e.message));
      return;
    }
    if (box.dataset.ticket !== ticket) return;
    const cell = 20, left = 40, top = 16;
    const frag = [];
    for (const lt of cov.lightings) {
      const w = left + cell * cov.azimuths_deg.length + 6, h = top + cell * cov.elevations.length + 16;
      const svg = document.createElementNS(SVG, "svg");
      svg.setAttribute("viewBox", `0 0 ${w} ${h}`); svg.setAttribute("width", String(w)); svg.setAttribute("class", "pic-coverage");
      svg.setAttribute("role", "group");
      const name = cov.lighting_names[lt] || lt;
      svg.setAttribute("aria-label", `coverage under ${name}: tilts down, azimuths across`);
      const text = (x, y, t, anchor = "start") => { const e = document.createElementNS(SVG, "text"); e.setAttribute("x", x); e.setAttribute("y", y); e.setAttribute("text-anchor", anchor); e.textContent = t; svg.append(e); };
      text(0, 11, name);
      cov.elevations.forEach((el, r) => text(left - 5, top + r * cell + cell * 0.7, el, "end"));
      // labels where they fit: every azimuth when there are few, else the multiples of 90°
      const few = cov.azimuths_deg.length <= 6 || !cov.azimuths_deg.some((a) => a % 90 === 0);
      const every = Math.ceil(30 / cell);
      cov.azimuths_deg.forEach((a, k) => {
        if (few ? k % every === 0 : a % 90 === 0) text(left + k * cell + cell / 2, top + cov.elevations.length * cell + 12, a + "°", "middle");
      });
      for (const c of cov.cells.filter((c) => c.lighting === lt)) {
        const r = cov.elevations.indexOf(c.elevation), k = cov.azimuths_deg.indexOf(c.azimuth_deg);
        const rect = document.createElementNS(SVG, "rect");
        rect.setAttribute("x", left + k * cell); rect.setAttribute("y", top + r * cell);
        rect.setAttribute("width", cell - 2); rect.setAttribute("height", cell - 2); rect.setAttribute("rx", 2);
        rect.setAttribute("class", "cov-" + c.state);
        const tip = `${c.event_id}: ${STATE_TEXT[c.state]}` + (c.score != null ? `, QC ${Number(c.score).toFixed(3)}` : "") +
          (c.flags.length ? " ⚑ " + c.flags.join(", ") : "") + (c.reason ? ` (${c.reason})` : "") +
          (c.twin_flags && c.twin_flags.length ? ` · twin ⚑ ${c.twin_flags.join(", ")}` : "") + (c.labels ? " · projected labels" : "");
        const t = document.createElementNS(SVG, "title"); t.textContent = tip; rect.append(t);
        rect.setAttribute("aria-label", tip);
        if (c.n != null) {
          rect.setAttribute("tabindex", "0"); rect.setAttribute("role", "button"); rect.dataset.n = String(c.n);
          const go = () => open(sid, { n: c.n });
          rect.addEventListener("click", go);
          rect.addEventListener("keydown", (ev) => { if (ev.key === "Enter" || ev.key === " ") { ev.preventDefault(); go(); } });
        }
        svg.append(rect);
        if (c.twin_flags && c.twin_flags.length) {  // the twin's flag: a magenta corner on the cell
          const m = document.createElementNS(SVG, "path"); const x = left + k * cell + cell - 2, y = top + r * cell;
          m.setAttribute("d", `M${x - 8} ${y}H${x}V${y + 8}Z`); m.setAttribute("fill", "#e0249a");
          m.setAttribute("class", "cov-twin"); m.setAttribute("pointer-events", "none"); svg.append(m);
        }
      }
      frag.push(svg);
    }
    const legend = mk("div", { class: "row pic-legend" });
    for (const s of ["captured", "flagged", "skipped", "failed", "pending"]) {
      const sw = mk("span", { class: "cov-swatch cov-" + s }); legend.append(mk("span", {}, ""), sw, document.createTextNode(`${STATE_TEXT[s]} ${cov.counts[s]}`));
    }
    if (cov.twin && cov.twin.checked) {
      const sw = mk("span", { class: "cov-swatch" }); sw.style.background = "#e0249a";
      legend.append(mk("span", {}, ""), sw, document.createTextNode(`twin flagged ${cov.twin.flagged} · labelled ${cov.twin.labelled}`));
    }
    box.replaceChildren(...frag, legend);
    box.dataset.session = sid;
  }
  // follow the session the views show (console.js keeps them in state.watched / state.browserId)
  const shown = { run: null, browser: null, runAt: 0, sawActive: false };
  const ENDED = ["completed", "completed_with_gaps", "failed", "aborted", "cancelled", "estopped"];
  function coverageTick() {
    const run = byId("run-coverage"), br = byId("b-coverage");
    const now = Date.now();
    // once more when the watched session ends (pollRun writes its state into #run-state): a short
    // session can finish between the 3 s refreshes and would otherwise keep showing frames pending
    const ended = ENDED.includes((byId("run-state") || {}).textContent);
    if (shown.run !== state.watched) shown.sawActive = false;
    const justEnded = ended && shown.sawActive;
    if (!ended && shown.run === state.watched) shown.sawActive = true;
    if (run && state.watched && (shown.run !== state.watched || justEnded || (now - shown.runAt > 3000 && isActive("view-sessions")))) {
      if (shown.run !== state.watched && !ended) shown.sawActive = true;
      if (justEnded) shown.sawActive = false;
      shown.run = state.watched; shown.runAt = now; coverageInto(run, state.watched);
    }
    if (br && state.browserId && shown.browser !== state.browserId) { shown.browser = state.browserId; coverageInto(br, state.browserId); }
  }
  const isActive = (id) => { const v = byId(id); return v && v.classList.contains("active"); };

  // ------------------------------------------------------------------ calibration pictures
  async function calibrationPictures() {
    const box = byId("calib-pictures"); if (!box) return;
    const list = byId("calib-pictures-list"); if (!list) return;
    let r;
    try { r = await api("GET", "/calibration/pictures"); } catch (e) { list.replaceChildren(mk("div", { class: "muted" }, e.message)); return; }
    const figs = [];
    for (const p of r.items) {
      const fig = mk("figure", { class: "pic-figure" });
      const img = mk("img", { alt: p.alt });
      fig.append(img, mk("figcaption", {}, p.title));
      figs.push(fig);
      blobUrl(p.url).then((u) => { img.src = u; }).catch(() => { fig.append(mk("div", { class: "muted" }, "cannot load " + p.url)); });
    }
    list.replaceChildren(...(figs.length ? figs : [mk("div", { class: "muted" }, r.empty || "nothing to show yet")]));
  }
  async function phaseMap() {
    const out = byId("calib-phase-map"); if (!out) return;
    const exp = Number((byId("p-exposure") || {}).value || 10) / 1000;
    out.replaceChildren(mk("div", { class: "muted" }, "taking one frame…"));
    try {
      const res = await fetch("/calibration/phase.png", { method: "POST", headers: headers(true), body: JSON.stringify({ exposure_s: exp }) });
      if (!res.ok) { const d = await res.json().catch(() => ({})); throw new Error(d.detail || "HTTP " + res.status); }
      const img = mk("img", { alt: res.headers.get("X-Phase-Summary") || "mosaic phase cost map" });
      img.src = URL.createObjectURL(await res.blob());
      out.replaceChildren(img, mk("div", { class: "muted" }, res.headers.get("X-Phase-Summary") || ""));
    } catch (e) { out.replaceChildren(mk("div", { class: "result bad" }, e.message)); }
  }

  function init() {
    live.panel || liveSetup();
    viewerSetup();
    setInterval(coverageTick, 1000);
    document.addEventListener("run-state", coverageTick);
    const cal = document.querySelector("#tabs button[data-view='calibration']");
    if (cal) cal.addEventListener("click", calibrationPictures);
    const refresh = byId("calib-pictures-refresh"); if (refresh) refresh.addEventListener("click", calibrationPictures);
    const ph = byId("calib-phase-button"); if (ph) ph.addEventListener("click", phaseMap);
  }
  init();
  return { open, coverageInto, calibrationPictures, fv, live };
})();
window.m2s2hilPictures = pictures;
