// m2s2hil operator console. Plain JavaScript, no build step, no third-party code.
// Every text from the daemon is put in the page with textContent (never as HTML).
"use strict";

const $ = (id) => document.getElementById(id);
const state = { token: sessionStorage.getItem("m2s2hil-token"), live: null, watched: null, sheetN: 0,
  browserId: null, catalog: null, axes: null, owner: null };

// ------------------------------------------------------------------ HTTP
const TAB_ID = sessionStorage.getItem("m2s2hil-tab") || "console-" + Math.random().toString(36).slice(2, 10);
sessionStorage.setItem("m2s2hil-tab", TAB_ID);
class ApiError extends Error { constructor(status, detail) { super(detail); this.status = status; } }

function headers(json) {
  // the daemon's cross-site guard (see docs/security.md); the tab's id for the activity log's "who"
  const h = { "X-M2S2HIL": "1", "X-M2S2HIL-Client": TAB_ID };
  if (json) h["Content-Type"] = "application/json";
  if (state.token) h["Authorization"] = "Bearer " + state.token;
  return h;
}

async function api(method, path, body) {
  // a failed poll (GET) is cleared by the next good poll, a failed action by the next good action
  const kind = method === "GET" ? "read" : "action";
  let res;
  try {
    res = await fetch(path, { method, headers: headers(body !== undefined),
      body: body === undefined ? undefined : JSON.stringify(body) });
  } catch (e) { throw Object.assign(new ApiError(0, "daemon unreachable: " + e.message), { kind }); }
  if (res.status === 401) { showLogin(); throw new ApiError(401, "token needed"); }
  const type = res.headers.get("content-type") || "";
  const data = type.includes("json") ? await res.json() : await res.text();
  if (!res.ok) {
    let detail = data && data.detail !== undefined ? data.detail : data;
    if (Array.isArray(detail)) detail = detail.map((d) => (d.loc || []).join(".") + ": " + d.msg).join("; ");
    throw Object.assign(new ApiError(res.status, String(detail)), { kind });
  }
  if (state.bannerKind === kind) banner("");
  return data;
}

async function blobUrl(path) {
  const res = await fetch(path, { headers: headers(false) });
  if (!res.ok) throw new ApiError(res.status, "cannot load " + path);
  return URL.createObjectURL(await res.blob());
}

// The banner: "info" goes by itself; "read"/"action" errors until the next success of their kind
// (see api) or the dismiss button; "stop" until the queue is released.
let bannerTimer = null;
function banner(text, kind) {
  const b = $("banner");
  clearTimeout(bannerTimer);
  state.bannerKind = text ? (kind || "action") : null;
  if (!text) { b.hidden = true; return; }
  $("banner-text").textContent = text; b.className = kind || ""; b.hidden = false;
  if (kind !== "info") announce(text);
  if (kind === "info") bannerTimer = setTimeout(() => { b.hidden = true; state.bannerKind = null; }, 6000);
}
$("banner-close").addEventListener("click", () => banner(""));
// The assertive live region: screen readers read the stop and errors at once (emptied first, so
// the same message twice is read twice).
function announce(text) { const a = $("announce"); a.textContent = ""; setTimeout(() => { a.textContent = text; }, 30); }

function report(el, text, ok) { el.textContent = text; el.className = "result " + (ok ? "ok" : "bad"); }

// A long action's button: disabled, with a spinner (class busy, aria-busy) until it ends; a click
// or submit while it runs is ignored (no second export or snapshot on top of the first).
function busyHandler(target, fn) {
  const btn = target.tagName === "FORM" ? target.querySelector("button[type=submit]") : target;
  return async (ev) => {
    if (ev && ev.type === "submit") ev.preventDefault();
    if (btn.classList.contains("busy")) return;
    btn.classList.add("busy"); btn.disabled = true; btn.setAttribute("aria-busy", "true");
    try { return await fn(ev); } finally {
      btn.classList.remove("busy"); btn.removeAttribute("aria-busy");
      btn.disabled = btn.classList.contains("manual") && Boolean(state.owner);
    }
  };
}

async function guarded(fn, el) {
  try { return await fn(); } catch (e) {
    if (el) { report(el, e.message, false); announce(e.message); } else banner(e.message, e.kind);
    return undefined;
  }
}

function showLogin() { $("login").hidden = false; $("token").focus(); }
$("login-form").addEventListener("submit", (ev) => {
  ev.preventDefault();
  state.token = $("token").value.trim();
  sessionStorage.setItem("m2s2hil-token", state.token);
  $("login").hidden = true;
  init();
});

// ------------------------------------------------------------------ tabs and emergency stop
for (const b of document.querySelectorAll("#tabs button")) {
  b.addEventListener("click", () => showView(b.dataset.view));
}
function showView(name) {
  for (const b of document.querySelectorAll("#tabs button")) b.classList.toggle("active", b.dataset.view === name);
  for (const v of document.querySelectorAll(".view")) v.classList.toggle("active", v.id === "view-" + name);
  if (name === "setup") refreshAxes();
  if (name === "browser") loadSessions();
  if (name === "calibration") loadCalibration();
}

async function emergencyStop() {
  try {
    const r = await api("POST", "/rig/stop");
    banner("EMERGENCY STOP: " + (r.safe ? "rig safe (lamps off, motion stopped)" : "rig NOT confirmed safe: " +
      r.errors.join("; ")) + ". The queue is held until released.", "stop");
  } catch (e) { banner("EMERGENCY STOP FAILED: " + e.message, "stop"); }
  // the watched session too: "running" with Pause and Abort live beside "held" read as a stop not taken
  await Promise.all([refreshStatus(), pollRun()]);
  if (!$("estop-release").hidden) $("estop-release").focus();  // Release is where the stop was pressed
}
$("estop").addEventListener("click", emergencyStop);
// Esc stops the rig except where Esc means "close" or "cancel": in a text field, a drop-down, an
// open dialog or menu (there it does its usual thing). Shift+Esc and F2 stop from anywhere (F2 for
// browsers that keep Shift+Esc for their task manager).
const ESC_CLOSES = "input:not([type=checkbox]):not([type=radio]):not([type=button]):not([type=submit]), " +
  "select, textarea, dialog[open], [role=menu], [role=listbox], [role=dialog], .overlay:not([hidden])";
function escMeansClose(target) {
  if (document.querySelector("dialog[open], [role=dialog]:not([hidden]), .overlay:not([hidden])")) return true;
  return Boolean(target && target.closest && target.closest(ESC_CLOSES));
}
document.addEventListener("keydown", (ev) => {
  const always = ev.key === "F2" || (ev.key === "Escape" && ev.shiftKey);
  if (always || (ev.key === "Escape" && !ev.defaultPrevented && !escMeansClose(ev.target))) {
    ev.preventDefault(); emergencyStop();
  }
});
$("estop-release").addEventListener("click", () => guarded(() => api("POST", "/queue/release"))
  .then((r) => { if (r) banner(""); refreshStatus(); }));

// ------------------------------------------------------------------ rig status chip + axes
async function refreshStatus() {
  const q = await guarded(() => api("GET", "/queue"));
  if (!q) return;
  const chip = $("rig-status");
  if (q.running) { chip.textContent = "session " + q.running; chip.className = "chip busy"; }
  else if (q.held) { chip.textContent = "held: " + q.held; chip.className = "chip bad"; }
  else if (q.items && q.items.length) { chip.textContent = "queued: " + q.items.length; chip.className = "chip busy"; }
  else { chip.textContent = "rig idle"; chip.className = "chip ok"; }
  $("estop-release").hidden = !q.held;
  renderQueue(q);
}

function el(tag, text, cls) { const e = document.createElement(tag); if (text !== undefined) e.textContent = text; if (cls) e.className = cls; return e; }
function button(text, onClick, cls) { const b = el("button", text, cls); b.type = "button"; b.addEventListener("click", onClick); return b; }

async function refreshAxes() {
  // only while they can be seen: an idle console on another view (or tab) costs the daemon nothing
  if ($("axes").dataset.built && (document.hidden || !$("view-setup").classList.contains("active"))) return;
  const a = await guarded(() => api("GET", "/rig/axes"));
  if (!a) return;
  state.axes = a; state.owner = a.owner;
  const note = $("owner-note");
  note.hidden = !a.owner;
  note.textContent = a.owner ? "Session " + a.owner + " owns the rig: manual control is refused until it ends." : "";
  const box = $("axes");
  if (!box.dataset.built) buildAxes(a);
  for (const ax of a.axes) {
    const pos = box.querySelector(`[data-pos="${ax.role}"]`);
    pos.textContent = ax.position_deg === null ? "–" : ax.position_deg.toFixed(2) + "°" + (ax.moving ? " ⟳" : "");
  }
  for (const b of document.querySelectorAll(".manual")) b.disabled = Boolean(a.owner);
  // while a session owns the rig the daemon does not read the lamps: its status says which are on
  let lampsOn = a.lamps_on;
  if (lampsOn == null && a.owner) lampsOn = (await guarded(() => api("GET", "/sessions/" + a.owner)))?.lamps_on;
  const on = new Set(lampsOn || []);
  for (const cb of document.querySelectorAll("#lamps input")) cb.checked = on.has(cb.value);
  for (const b of document.querySelectorAll("#presets button")) {
    const lamps = a.presets[b.dataset.preset] || [];
    b.classList.toggle("on", b.dataset.preset !== "" && lamps.length === on.size && lamps.every((l) => on.has(l)));
  }
}

function buildAxes(a) {
  const box = $("axes"); box.dataset.built = "1";
  for (const ax of a.axes) {
    const d = el("div", undefined, "axis");
    const head = el("div", undefined, "row");
    head.append(el("b", ax.role), el("span", "", "pos"), el("span", `limits ${ax.min_deg}° … ${ax.max_deg}° · ${ax.max_speed_dps}°/s · homing: ${ax.homing}`, "lim"));
    head.children[1].dataset.pos = ax.role;
    const jog = el("div", undefined, "row");
    for (const step of [-10, -1, -0.1, 0.1, 1, 10]) {
      const b = button((step > 0 ? "+" : "") + step, () => manual("jog", ax.role, { delta_deg: step }), "manual");
      b.dataset.jog = ax.role + ":" + step; b.setAttribute("aria-label", `jog ${ax.role} ${b.textContent}°`); jog.append(b);
    }
    const go = el("div", undefined, "row");
    const inp = el("input"); inp.type = "number"; inp.step = "0.1"; inp.min = ax.min_deg; inp.max = ax.max_deg; inp.value = "0";
    inp.dataset.goto = ax.role; inp.setAttribute("aria-label", `${ax.role} target °`);
    go.append(inp, button("Go to", () => manual("goto", ax.role, { position_deg: Number(inp.value) }), "manual"),
      button("Stop", () => manual("stop", ax.role), "manual"));
    go.lastChild.setAttribute("aria-label", `stop the ${ax.role}`);
    if (ax.homing === "switches") go.append(button("Home", () => manual("home", ax.role), "manual"));
    else go.append(button("Set origin here", () => { if (confirm(`Make where the ${ax.role} stands its 0°?`)) manual("origin", ax.role); }, "manual"));
    d.append(head, jog, go); box.append(d);
  }
  const presets = $("presets");
  presets.append(button("all off", () => lamps({ preset: null }), "manual"));
  presets.lastChild.dataset.preset = "";
  for (const name of Object.keys(a.presets)) {
    const b = button(name, () => lamps({ preset: name }), "manual"); b.dataset.preset = name; presets.append(b);
  }
  const box2 = $("lamps");
  for (const [name, kind] of Object.entries(a.lamps)) {
    const lab = el("label"); const cb = el("input"); cb.type = "checkbox"; cb.value = name; cb.className = "manual";
    cb.addEventListener("change", () => {
      const on = [...document.querySelectorAll("#lamps input")].filter((c) => c.checked).map((c) => c.value);
      lamps({ lamps: on });
    });
    lab.append(cb, document.createTextNode(name + " (" + kind.replace("_", " ") + ")")); box2.append(lab);
  }
}

async function manual(action, role, body) {
  await guarded(() => api("POST", `/rig/axes/${role}/${action}`, body));
  refreshAxes();
}
async function lamps(body) { await guarded(() => api("PUT", "/rig/lamps", body)); refreshAxes(); }

// ------------------------------------------------------------------ live view (MJPEG read with fetch)
const BOUNDARY = "--m2s2hil-frame";
function indexOf(buf, len, pat, from) {
  outer: for (let i = from; i <= len - pat.length; i++) {
    for (let j = 0; j < pat.length; j++) if (buf[i + j] !== pat[j]) continue outer;
    return i;
  }
  return -1;
}

async function startLive() {
  if (state.live) return;
  const ctl = new AbortController(); state.live = { ctl, times: [] };
  window.m2s2hilLive = { seq: 0, fps: 0, latency_ms: 0, frames: 0 };  // this stream's own count
  $("live-toggle").textContent = "Stop"; $("live-note").textContent = "connecting…";
  try {
    const res = await fetch("/camera/live.mjpeg", { headers: headers(false), signal: ctl.signal });
    if (res.status === 401) { showLogin(); throw new ApiError(401, "token needed"); }
    if (!res.ok) throw new ApiError(res.status, "live view: HTTP " + res.status);
    const reader = res.body.getReader(); const enc = new TextEncoder();
    const bnd = enc.encode(BOUNDARY); const sep = enc.encode("\r\n\r\n");
    let buf = new Uint8Array(1 << 20); let len = 0;
    for (;;) {
      const { value, done } = await reader.read();
      if (done) break;
      if (len + value.length > buf.length) { const nb = new Uint8Array(Math.max(buf.length * 2, len + value.length)); nb.set(buf.subarray(0, len)); buf = nb; }
      buf.set(value, len); len += value.length;
      for (;;) {
        const start = indexOf(buf, len, bnd, 0); if (start < 0) break;
        const hEnd = indexOf(buf, len, sep, start); if (hEnd < 0) break;
        const head = new TextDecoder().decode(buf.subarray(start + bnd.length, hEnd));
        const fields = {};
        for (const line of head.split("\r\n")) { const k = line.indexOf(":"); if (k > 0) fields[line.slice(0, k).trim().toLowerCase()] = line.slice(k + 1).trim(); }
        const n = Number(fields["content-length"] || -1); const body = hEnd + 4;
        if (n < 0 || len < body + n) break;
        const jpeg = buf.slice(body, body + n);
        buf.copyWithin(0, body + n, len); len -= body + n;
        await showFrame(jpeg, fields);
      }
    }
  } catch (e) { if (e.name !== "AbortError") $("live-note").textContent = e.message; }
  stopLive(false);
}

function stopLive(abort = true) {
  if (state.live && abort) state.live.ctl.abort();
  state.live = null; $("live-toggle").textContent = "Start";
  $("live-canvas").setAttribute("aria-label", "live view: stopped (" + $("live-note").textContent + ")");
}

async function showFrame(jpeg, fields) {
  const img = await createImageBitmap(new Blob([jpeg], { type: "image/jpeg" }));
  // Draw at the canvas's displayed size (the overlay stays crisp whatever the frame's size).
  const cv = $("live-canvas"); const ctx = cv.getContext("2d");
  cv.parentElement.style.aspectRatio = `${img.width} / ${img.height}`;
  const dpr = window.devicePixelRatio || 1;
  const W = Math.round(cv.clientWidth * dpr), H = Math.round(cv.clientHeight * dpr);
  if (cv.width !== W || cv.height !== H) { cv.width = W; cv.height = H; }
  ctx.imageSmoothingEnabled = true; ctx.imageSmoothingQuality = "high";
  ctx.drawImage(img, 0, 0, W, H);
  if (fields["x-live-error"]) { $("live-note").textContent = JSON.parse(fields["x-live-error"]); return; }
  const st = JSON.parse(fields["x-live-stats"] || "{}");
  if ($("live-overlay").checked) overlay(ctx, cv.width, cv.height, st.axis_x ?? 0.5);
  const now = performance.now(); const times = state.live ? state.live.times : [];
  times.push(now); while (times.length > 20) times.shift();
  const fps = times.length > 1 ? (times.length - 1) * 1000 / (times[times.length - 1] - times[0]) : 0;
  const latency = Date.now() / 1000 - st.captured_at;
  window.m2s2hilLive = { seq: st.seq, fps, latency_ms: latency * 1000, frames: (window.m2s2hilLive?.frames || 0) + 1 };
  $("live-note").textContent = `frame ${st.seq} · ${st.sensor?.join("×")} sensor → ${img.width}×${img.height} · ${fmtMs(st.exposure_s)} · gain ${st.gain}`;
  $("st-fps").textContent = fps.toFixed(1);
  $("st-latency").textContent = (latency * 1000).toFixed(0) + " ms";
  $("st-sat").textContent = (100 * st.saturated_fraction).toFixed(3) + " %";
  $("st-sat").style.color = st.saturated_fraction > 0 ? "var(--bad)" : "";
  $("st-p999").textContent = Math.round(st.p999) + " / " + st.full_scale;
  $("st-focus").textContent = st.focus.toExponential(2) + " @" + st.focus_band_nm + " nm";
  $("st-temp").textContent = st.temperature_c.toFixed(1) + " °C";
  histogram(st.histogram || [], st.full_scale);
  // the canvases' text alternatives say what they show (screen readers cannot see the pixels)
  $("live-canvas").setAttribute("aria-label", `live view, ${$("live-view").selectedOptions[0]?.textContent ?? ""}: ` +
    $("live-note").textContent + ($("live-overlay").checked ? ` · crosshair and turntable axis at ${st.axis_x ?? 0.5}` : ""));
  $("histogram").setAttribute("aria-label", `histogram of the live frame (log scale): ${$("st-sat").textContent} ` +
    `saturated, 99.9th percentile ${$("st-p999").textContent}`);
}

function overlay(ctx, w, h, axisX) {
  ctx.save(); ctx.lineWidth = 1.5;
  ctx.strokeStyle = "rgba(255,255,80,.85)"; ctx.setLineDash([8, 6]);
  ctx.beginPath(); ctx.moveTo(w / 2, 0); ctx.lineTo(w / 2, h); ctx.moveTo(0, h / 2); ctx.lineTo(w, h / 2); ctx.stroke();
  ctx.setLineDash([]); ctx.strokeStyle = "rgba(74,163,255,.9)"; ctx.lineWidth = 2;
  ctx.beginPath(); ctx.moveTo(axisX * w, 0); ctx.lineTo(axisX * w, h); ctx.stroke();
  ctx.fillStyle = "rgba(74,163,255,.95)"; ctx.font = `${Math.round(13 * (window.devicePixelRatio || 1))}px sans-serif`;
  ctx.fillText("turntable axis", axisX * w + 6, 18);
  ctx.restore();
}

function histogram(bins, full) {
  const cv = $("histogram"); const ctx = cv.getContext("2d"); const w = cv.width, h = cv.height;
  ctx.clearRect(0, 0, w, h);
  if (!bins.length) return;
  const logs = bins.map((v) => Math.log10(1 + v)); const max = Math.max(...logs, 1); const bw = w / bins.length;
  const css = getComputedStyle(document.documentElement);  // the theme's colours (light or dark)
  const color = (name) => css.getPropertyValue(name).trim();
  for (let i = 0; i < bins.length; i++) {
    ctx.fillStyle = i === bins.length - 1 && bins[i] > 0 ? color("--bad") : color("--accent");
    const bh = (logs[i] / max) * (h - 14); ctx.fillRect(i * bw, h - bh, Math.max(1, bw - 1), bh);
  }
  ctx.fillStyle = color("--muted"); ctx.font = "11px sans-serif"; ctx.fillText("0", 2, 11); ctx.fillText(String(full), w - 30, 11);
}

$("live-toggle").addEventListener("click", () => (state.live ? stopLive() : startLive()));
async function liveSettings() {
  const v = $("live-view").value;
  await guarded(() => api("PUT", "/camera/live", { exposure_s: Number($("live-exposure").value) / 1000,
    gain: Number($("live-gain").value), view: v === "rgb" ? "rgb" : Number(v), axis_x: Number($("live-axis").value) }));
}
for (const id of ["live-view", "live-exposure", "live-gain", "live-axis"]) $(id).addEventListener("change", liveSettings);

// ------------------------------------------------------------------ snapshots
$("snap").addEventListener("click", busyHandler($("snap"), async () => {
  const r = await guarded(() => api("POST", "/snapshots", { note: $("snap-note").value }));
  if (r) { banner("snapshot " + r.id + " stored", "info"); loadSnapshots(); }
}));
async function loadSnapshots() {
  const r = await guarded(() => api("GET", "/snapshots?limit=10"));
  if (!r) return;
  const ul = $("snapshots"); ul.replaceChildren();
  for (const s of r.items) {
    const li = el("li"); li.append(el("span", s.id), el("span", s.note || "", "muted"));
    for (const f of ["raw.tiff", "meta.json", "preview.png"]) li.append(button(f, () => download(`/snapshots/${s.id}/${f}`, `${s.id}-${f}`)));
    ul.append(li);
  }
}
async function download(path, name) {
  const url = await guarded(() => blobUrl(path)); if (!url) return;
  const a = el("a"); a.href = url; a.download = name; document.body.append(a); a.click(); a.remove();
  setTimeout(() => URL.revokeObjectURL(url), 10000);
}

// ------------------------------------------------------------------ sessions: form + estimate
function sweepFromForm() {
  const checked = (id) => [...document.querySelectorAll(`#${id} input:checked`)].map((c) => c.value);
  const sweep = { satellite: $("f-sat").value, build: $("f-build").value, lighting: checked("f-light"),
    tilts: checked("f-tilts"), azimuth_step_deg: Number($("f-step").value), mode: $("f-mode").value };
  // the spotlight's bracket (Sweep.bracket): sent as typed, so the daemon's 422 names a bad factor
  const bracket = $("f-bracket").value.trim();
  if (bracket !== "" && sweep.lighting.includes("directional")) sweep.bracket = { directional: [Number(bracket)] };
  return sweep;
}

function buildForm(cat) {
  const sat = $("f-sat");
  for (const [k, s] of Object.entries(cat.satellites)) { const o = el("option", s.name); o.value = k; sat.append(o); }
  const builds = () => {
    $("f-build").replaceChildren();
    for (const b of Object.keys(cat.satellites[sat.value].builds)) { const o = el("option", b); o.value = b; $("f-build").append(o); }
  };
  sat.addEventListener("change", () => { builds(); estimate(); }); builds();
  for (const [k, lt] of Object.entries(cat.lighting)) {
    const lab = el("label"); const cb = el("input"); cb.type = "checkbox"; cb.value = k; cb.checked = k === "weak";
    lab.append(cb, document.createTextNode(lt.name)); $("f-light").append(lab);
    const o = el("option", lt.name); o.value = k; $("w-light").append(o);
  }
  // a white panel wants even light: a diffuse preset (not the first, the directional spotlight)
  if (cat.lighting.strong) $("w-light").value = "strong";
  for (const e of cat.elevations) {
    const lab = el("label"); const cb = el("input"); cb.type = "checkbox"; cb.value = e; cb.checked = true;
    lab.append(cb, document.createTextNode(e)); $("f-tilts").append(lab);
  }
  $("session-form").addEventListener("change", estimate);
  estimate();
}

// Exposures in ms without float noise (0.2 s -> "200 ms", not "199.99999999999997 ms").
function msOf(s) { return Number((s * 1000).toPrecision(6)); }
function fmtMs(s) { return s == null || !isFinite(s) ? "–" : `${Number((s * 1000).toPrecision(4))} ms`; }
function fmtS(s) { if (!isFinite(s)) return "–"; const m = Math.floor(s / 60); return m ? `${m} min ${Math.round(s % 60)} s` : `${s.toFixed(1)} s`; }

let estimateSeq = 0;
async function estimate() {
  const box = $("estimate");
  // answers can arrive out of order as the form changes: only the latest request's is shown
  const mine = ++estimateSeq;
  try {
    const r = await api("POST", "/plans/estimate", sweepFromForm());
    if (mine !== estimateSeq) return;
    const size = r.bytes >= 1e9 ? (r.bytes / 1e9).toFixed(2) + " GB" : (r.bytes / 1e6).toFixed(0) + " MB";
    box.textContent = `${r.frames + r.darks} captures: ${r.frames} frames + ${r.darks} dark${r.darks === 1 ? "" : "s"} · estimate ${fmtS(r.estimate_s)} (lower bound ${fmtS(r.lower_bound_s)}) · ${size}`;
    box.className = "estimate";
  } catch (e) { if (mine === estimateSeq) { box.textContent = e.message; box.className = "estimate bad"; } }
}

$("session-form").addEventListener("submit", async (ev) => {
  ev.preventDefault();
  const r = await guarded(() => api("POST", "/sessions", sweepFromForm()));
  if (r) { watch(r.session_id); banner("session " + r.session_id + " submitted (" + r.state + ")", "info"); }
});

// ------------------------------------------------------------------ sessions: progress, contact sheet, queue
function watch(id) {
  state.watched = id; state.sheetN = 0;
  $("run-none").hidden = true; $("run").hidden = false; $("run-id").textContent = id; $("run-sheet").replaceChildren();
  pollRun();
}

async function pollRun() {
  const id = state.watched; if (!id) return;
  const s = await guarded(() => api("GET", "/sessions/" + id));
  if (!s) return;
  const shownState = s.state === "queued" && s.queue_position ? `queued (#${s.queue_position})` : s.state;
  const changed = $("run-state").textContent !== shownState;
  $("run-state").textContent = shownState;  // written every poll: feedback.js observes it per session
  // the pictures (coverage map) and the rig chip redraw at once, not at their next tick:
  // "completed" beside poses still drawn pending, or beside "session …" in the chip, read as a fault
  if (changed) { document.dispatchEvent(new CustomEvent("run-state")); refreshStatus(); }
  $("run-progress").max = Math.max(1, s.total);
  $("run-progress").value = s.done;
  // captures = lit frames + darks, the unit of done/total (the estimate says the same)
  $("run-frames").textContent = `${s.done} / ${s.total}` + (s.skipped ? ` (${s.skipped} skipped)` : "");
  $("run-pose").textContent = s.azimuth_deg == null ? "–" : `az ${s.azimuth_deg.toFixed(1)}° tilt ${(s.tilt_deg ?? 0).toFixed(1)}°`;
  $("run-light").textContent = s.lighting ? `${s.lighting} ${s.elevation ?? ""}` : "–";
  $("run-eta").textContent = s.eta_s == null ? "–" : fmtS(s.eta_s);
  $("run-faults").textContent = String(s.fault_count);  // every fault met: `faults` lists the last 50
  const ended = ["completed", "completed_with_gaps", "failed", "aborted", "cancelled", "estopped"].includes(s.state);
  $("run-pause").disabled = ended || s.state !== "running";
  const lens = lensWait(s);
  $("run-reason").textContent = s.pause_reason ? "paused: " + s.pause_reason : "";
  $("run-reason").hidden = !s.pause_reason;
  $("run-lens").hidden = lens === null;
  $("run-lens").textContent = lens === null ? "" : (lens ? "Lens cap is on — continue" : "Lens cap is off — continue");
  $("run-lens").dataset.capped = String(lens);
  // resume: a paused session, or one the daemon says can be queued again (interrupted, e-stopped, gaps)
  $("run-resume").disabled = !(s.state === "paused" || s.resumable) || lens !== null;
  $("run-abort").disabled = ended;
  await fillSheet(id, $("run-sheet"), "sheetN");
  $("run-qc").textContent = String($("run-sheet").querySelectorAll("figure.flagged").length);
}

async function fillSheet(id, box, key) {
  const r = await guarded(() => api("GET", `/sessions/${id}/frames?offset=${state[key]}&limit=50`));
  if (!r) return;
  for (const f of r.items) {
    const fig = el("figure"); const img = el("img"); img.alt = f.event_id;
    const qc = (f.meta && f.meta.qc) || {};
    if (qc.flags && qc.flags.length) fig.classList.add("flagged");
    const ev = (f.meta && f.meta.event) || {};
    const bracket = ev.exposure_factor != null && ev.exposure_factor !== 1 ? ` ×${ev.exposure_factor} (bracket, not QC-checked)` : "";
    const caption = `${ev.lighting ?? ""} ${ev.elevation ?? ""} ${ev.azimuth_deg ?? "?"}°${bracket}` +
      (qc.score != null ? ` · QC ${qc.score.toFixed(2)}` : "") + (qc.flags && qc.flags.length ? " ⚑ " + qc.flags.join(", ") : "");
    fig.append(img, el("figcaption", caption));
    box.append(fig);
    if (f.preview_url) loadThumb(img, fig, f.preview_url);
  }
  state[key] += r.items.length;
}

// A thumbnail whose fetch fails (a daemon busy or restarting) is tried again a few times, then
// says so in its figure rather than staying blank.
function loadThumb(img, fig, url, tries = 0) {
  blobUrl(url).then((u) => { img.src = u; fig.classList.remove("missing"); }).catch((e) => {
    if (tries < 3) { setTimeout(() => loadThumb(img, fig, url, tries + 1), 500 * 2 ** tries); return; }
    fig.classList.add("missing");
    img.title = "preview not available: " + (e && e.message ? e.message : "the request failed");
  });
}

// A real rig's darks: the session waits for the operator's word on the lens cap (the pause
// reasons of m2s2hil/engine/darks.py); null when it waits for nothing of the kind.
const LENS_WAITS = { "lens_cap: put the lens cap on": true, "lens_cap: take the lens cap off": false };
function lensWait(s) {
  return s.state === "paused" && Object.hasOwn(LENS_WAITS, s.pause_reason ?? "") ? LENS_WAITS[s.pause_reason] : null;
}
$("run-lens").addEventListener("click", async () => {
  const capped = $("run-lens").dataset.capped === "true";
  if (state.watched) await guarded(() => api("POST", `/sessions/${state.watched}/lens`, { capped }));
  pollRun();
});
$("run-pause").addEventListener("click", () => control("pause"));
$("run-resume").addEventListener("click", () => control("resume"));
$("run-abort").addEventListener("click", () => { if (confirm("Abort the session? What is stored is kept.")) control("abort"); });
async function control(action) { if (state.watched) await guarded(() => api("POST", `/sessions/${state.watched}/${action}`)); pollRun(); }

function renderQueue(q) {
  const box = $("queue"); box.replaceChildren();
  if (!q.items || !q.items.length) { box.append(el("div", "queue empty", "muted")); return; }
  for (const it of q.items) {
    const row = el("div", undefined, "row");
    row.append(el("span", `${it.position ?? ""} ${it.session_id}`), button("Watch", () => watch(it.session_id)),
      button("Cancel", () => guarded(() => api("POST", `/sessions/${it.session_id}/abort`)).then(refreshStatus), "danger"));
    box.append(row);
  }
}
$("queue-hold").addEventListener("click", () => guarded(() => api("POST", "/queue/hold?reason=operator")).then(refreshStatus));
$("queue-release").addEventListener("click", () => guarded(() => api("POST", "/queue/release")).then(() => { banner(""); refreshStatus(); }));

// ------------------------------------------------------------------ browser
async function loadSessions() {
  const r = await guarded(() => api("GET", "/sessions?limit=100"));
  if (!r) return;
  const tb = document.querySelector("#sessions-table tbody"); tb.replaceChildren();
  for (const s of r.items) {
    const tr = el("tr");
    tr.append(el("td", s.session_id), el("td", s.state), el("td", `${s.done} / ${s.total}`),
      el("td", s.created ? new Date(s.created * 1000).toLocaleString() : ""));
    tr.addEventListener("click", () => { for (const o of tb.children) o.classList.remove("sel"); tr.classList.add("sel"); browse(s.session_id); });
    tb.append(tr);
  }
}
function browse(id) {
  state.browserId = id; state.browserN = 0; $("b-title").textContent = id; $("b-sheet").replaceChildren(); $("b-result").textContent = "";
  fillSheet(id, $("b-sheet"), "browserN");
}
$("b-report").addEventListener("click", async () => {
  if (!state.browserId) return;
  const path = `/sessions/${state.browserId}/report.html`;
  if (!state.token) { window.open(path, "_blank", "noopener"); return; }
  const url = await guarded(() => blobUrl(path), $("b-result")); if (url) window.open(url, "_blank", "noopener");
});
$("b-verify").addEventListener("click", busyHandler($("b-verify"), async () => {
  if (!state.browserId) return;
  report($("b-result"), "verifying…", true);
  const r = await guarded(() => api("GET", `/sessions/${state.browserId}/verify`), $("b-result"));
  if (r) report($("b-result"), r.ok ? `verified: ${r.frames} frames, every checksum matches` : "PROBLEMS:\n" + r.problems.join("\n"), r.ok);
}));
// Export as a daemon job (POST …/export/jobs), followed until done; the result is a download (a zip).
$("b-export").addEventListener("click", busyHandler($("b-export"), async () => {
  if (!state.browserId) return;
  const sid = state.browserId, layout = $("b-layout").value, out = $("b-result");
  let job = await guarded(() => api("POST", `/sessions/${sid}/export/jobs`, { layout, overwrite: true }), out);
  while (job && job.state === "running") {
    report(out, `exporting ${layout}: ${job.phase} · ${fmtS(job.elapsed_s)}`, true);
    if (typeof exportProgress === "function") exportProgress(out, job);  // the bar (feedback.js)
    await new Promise((ok) => setTimeout(ok, 1000));
    job = await guarded(() => api("GET", `/exports/jobs/${job.job_id}`), out);
  }
  if (!job) return;
  if (job.state !== "done") { report(out, `export failed: ${job.error ?? job.phase}`, false); announce("export failed"); return; }
  const r = job.result || {};
  report(out, `exported ${r.images} images (${r.files} files) in ${fmtS(job.elapsed_s)} to ${r.folder}`, true);
  if (job.download_url && state.browserId === sid) {
    out.append(document.createTextNode("\n"), button(`Download ${sid}-${layout}.zip`, () => download(job.download_url, `${sid}-${layout}.zip`)));
  }
}));

// ------------------------------------------------------------------ calibration
async function loadCalibration() {
  const r = await guarded(() => api("GET", "/calibration"));
  if (!r) return;
  const wr = r.white_reference;
  report($("c-file"), `${r.file}${r.exists ? "" : " (not written yet)"}\n` +
    (wr ? `white reference: ${wr.file}, captured ${wr.provenance?.captured_at ?? "?"} at ${fmtMs(wr.provenance?.exposure_s)}` : "no white reference") +
    `\ndarks in library: ${(r.darks || []).length}` + (r.named_in_rig_file ? "" : "\nthe rig file names no calibration file"), true);
}
$("darks-form").addEventListener("submit", busyHandler($("darks-form"), async (ev) => {
  ev.preventDefault(); report($("d-result"), "taking darks…", true);
  const r = await guarded(() => api("POST", "/calibration/darks", { plan: sweepFromForm(), n_frames: Number($("d-frames").value), lens_capped: $("d-capped").checked }), $("d-result"));
  if (r) { report($("d-result"), r.darks.map((d) => `${fmtMs(d.exposure_s)} gain ${d.gain}: ${d.n_frames} frames, ${d.temperature_c.toFixed(1)} °C → ${d.file}`).join("\n"), true); loadCalibration(); }
}));
$("white-form").addEventListener("submit", busyHandler($("white-form"), async (ev) => {
  ev.preventDefault(); report($("w-result"), "capturing…", true);
  const r = await guarded(() => api("POST", "/calibration/white", { exposure_s: Number($("w-exposure").value) / 1000, gain: Number($("w-gain").value),
    n_frames: Number($("w-frames").value), reflectance: Number($("w-refl").value), lighting: $("w-light").value, panel_in_place: $("w-panel").checked }), $("w-result"));
  if (r) {
    const c = r.provenance.checks;
    report($("w-result"), `written to ${r.file}\nsaturated ${(100 * c.saturated_fraction).toFixed(3)} % · level ${(100 * c.level_fraction).toFixed(0)} % of full scale · worst uniformity ${(100 * Math.min(...c.uniformity)).toFixed(0)} %` + (r.hint ? "\n" + r.hint : ""), true);
    loadCalibration();
  }
}));
$("phase-form").addEventListener("submit", busyHandler($("phase-form"), async (ev) => {
  ev.preventDefault();
  const r = await guarded(() => api("POST", "/calibration/phase", { exposure_s: Number($("p-exposure").value) / 1000 }), $("p-result"));
  // green only for a conclusive match: "inconclusive" is no confirmation
  if (r) report($("p-result"), `${r.message}\noffset (${r.offset.join(", ")}) · cost at origin ${(100 * r.cost_nominal).toFixed(2)} % · best ${(100 * r.cost_best).toFixed(2)} %`, r.conclusive && !r.suspect);
}));

// ------------------------------------------------------------------ start
let timers = [];
async function init() {
  for (const t of timers) clearInterval(t);
  const cat = await guarded(() => api("GET", "/catalog"));
  if (!cat) return;
  if (!state.catalog) { state.catalog = cat; buildForm(cat); }
  const live = await guarded(() => api("GET", "/camera/live"));
  if (live) {
    $("live-exposure").value = String(msOf(live.settings.exposure_s));
    $("live-gain").value = String(live.settings.gain);
    $("live-axis").value = String(live.settings.axis_x);
  }
  if (live && $("live-view").options.length === 1) {
    live.bands_nm.forEach((nm, i) => { const o = el("option", nm + " nm"); o.value = String(i); $("live-view").append(o); });
  }
  refreshStatus(); refreshAxes(); loadSnapshots();
  timers = [setInterval(refreshStatus, 2000), setInterval(refreshAxes, 700), setInterval(pollRun, 1000)];
}
init();
