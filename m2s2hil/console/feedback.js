// Feedback the operator does not have to look for: a notice (system notification when allowed,
// else a toast in the page, and the tab's title) when the watched session ends or fails; the
// log (faults, retries, state changes, operator actions: GET /activity) opened from the fault
// count; a note when another client has changed something on the rig lately. Loaded after
// console.js and uses its helpers ($, el, button, api, guarded, announce, state).
"use strict";

const ENDED = { completed: "✔", completed_with_gaps: "⚠", failed: "✖", aborted: "■", cancelled: "■", estopped: "⛔" };
const BASE_TITLE = document.title;

function toast(text, bad) {
  let box = $("toasts");
  if (!box) { box = el("div"); box.id = "toasts"; document.body.append(box); }
  const t = el("div", undefined, "toast" + (bad ? " bad" : ""));
  t.setAttribute("role", "status");
  t.append(el("span", text), document.createTextNode(" "));
  const drop = () => { t.remove(); toastRoom(box); };
  t.append(button("×", drop, "linkish"));
  t.lastChild.setAttribute("aria-label", "dismiss the notice");
  box.append(t);
  toastRoom(box);
  setTimeout(drop, 15000);
}

// Room below the page and the frame viewer for the toasts (console.css --toast-room): on a phone a
// toast spans the screen and would hide the bottom of what is open (the viewer's spectrum chart);
// with the room, that part scrolls up from under it.
function toastRoom(box) {
  const h = box.childElementCount ? box.getBoundingClientRect().height + 24 : 0;
  document.documentElement.style.setProperty("--toast-room", `${Math.ceil(h)}px`);
}

function notifyEnd(sid, st) {
  const bad = !["completed"].includes(st);
  const text = `session ${sid} ${st.replaceAll("_", " ")}`;
  document.title = `${ENDED[st] ?? "•"} ${st} — ${BASE_TITLE}`;
  announce(text);
  chime(bad);
  if ("Notification" in window && Notification.permission === "granted" && document.hidden) {
    new Notification("m2s2hil: " + text);  // (a background tab; in view, the toast says it)
  } else toast(text, bad);
}
// the title comes back once the operator is looking again
document.addEventListener("visibilitychange", () => { if (!document.hidden) setTimeout(() => { document.title = BASE_TITLE; }, 5000); });
$("session-form").addEventListener("submit", () => {
  // asked on a click (browsers allow the question only then); refusing leaves toasts and the title
  if ("Notification" in window && Notification.permission === "default") Notification.requestPermission().catch(() => {});
  document.title = BASE_TITLE;
});

// The watched session's state as console.js writes it: a change to an end state is the notice.
let lastRun = { id: null, state: null };
new MutationObserver(() => {
  const sid = $("run-id").textContent, st = $("run-state").textContent;
  if (sid === lastRun.id && st !== lastRun.state && lastRun.state && !ENDED[lastRun.state] && ENDED[st]) notifyEnd(sid, st);
  lastRun = { id: sid, state: st };
}).observe($("run-state"), { childList: true, characterData: true, subtree: true });

// ------------------------------------------------------------------ sound
// A short tone with the session-end notice (WebAudio, no file to fetch). Browsers let a page make
// sound only after a user gesture (autoplay policy): the audio context is made, or resumed, on the
// operator's first click or key in the page; until then, or with "sound" unchecked, no tone.
// The checkbox sits under "Running" (Sessions view), on by default, remembered (localStorage).
const sound = { ctx: null, played: 0 };
{
  const lab = el("label"); lab.title = "a short tone when the watched session ends or fails";
  const cb = el("input"); cb.type = "checkbox"; cb.id = "sound-on";
  cb.checked = localStorage.getItem("m2s2hil.sound") !== "0";
  cb.addEventListener("change", () => localStorage.setItem("m2s2hil.sound", cb.checked ? "1" : "0"));
  lab.append(cb, document.createTextNode(" sound"));
  lab.id = "sound-label"; lab.className = "sound-toggle";
  $("run-none").before(lab);  // under "Running": set before a session is watched, too
}
function unlockAudio() {
  const AC = window.AudioContext || window.webkitAudioContext;
  if (!AC || !$("sound-on").checked) return;
  try {
    if (!sound.ctx) sound.ctx = new AC();
    if (sound.ctx.state === "suspended") sound.ctx.resume().catch(() => {});
  } catch (e) { sound.ctx = null; }  // no audio device: the notice stays silent
}
document.addEventListener("pointerdown", unlockAudio, true);
document.addEventListener("keydown", unlockAudio, true);
// Two notes, rising when the session completed, falling otherwise; 0.4 s, quiet. True if played.
function chime(bad) {
  const c = sound.ctx;
  if (!$("sound-on").checked || !c || c.state !== "running") return false;
  const t = c.currentTime, o = c.createOscillator(), g = c.createGain();
  o.type = "sine";
  o.frequency.setValueAtTime(bad ? 660 : 880, t); o.frequency.setValueAtTime(bad ? 440 : 1320, t + 0.15);
  g.gain.setValueAtTime(0.0001, t); g.gain.exponentialRampToValueAtTime(0.15, t + 0.02);
  g.gain.exponentialRampToValueAtTime(0.0001, t + 0.38);
  o.connect(g).connect(c.destination); o.start(t); o.stop(t + 0.4);
  sound.played += 1;
  return true;
}
window.m2s2hilSound = sound;

// ------------------------------------------------------------------ export progress
// console.js's export loop calls this with each job it polls (GET /exports/jobs/{id}: done, total,
// fraction): a bar and the percentage under the phase line.
function exportProgress(out, job) {
  const f = Math.max(0, Math.min(1, job.fraction ?? 0));
  const bar = el("progress"); bar.id = "export-progress"; bar.max = 1; bar.value = f;
  bar.setAttribute("aria-label", "export progress");
  out.append(document.createTextNode("\n"), bar,
    el("span", ` ${Math.round(100 * f)}% · ${job.done ?? 0} of ${job.total ?? job.frames ?? "?"} frames`));
}

// ------------------------------------------------------------------ the log dialog
function buildLog() {
  const d = el("dialog"); d.id = "log-dialog"; d.setAttribute("aria-labelledby", "log-title");
  const head = el("div", undefined, "row"); const h = el("h2", "Log"); h.id = "log-title";
  const only = el("label"); const cb = el("input"); cb.type = "checkbox"; cb.id = "log-session-only"; cb.checked = true;
  only.append(cb, document.createTextNode("watched session only"));
  const kinds = el("label"); const sel = el("select"); sel.id = "log-kind";
  for (const [v, t] of [["", "everything"], ["fault,retry", "faults and retries"], ["action", "operator actions"], ["state,session,queue", "states"]]) {
    const o = el("option", t); o.value = v; sel.append(o);
  }
  kinds.append(document.createTextNode("show"), sel);
  head.append(h, only, kinds, button("Refresh", fillLog), button("Close", () => d.close()));
  const note = el("div", "", "muted"); note.id = "log-note";
  const ul = el("ul"); ul.id = "log-list"; ul.setAttribute("aria-live", "polite");
  d.append(head, note, ul); document.body.append(d);
  cb.addEventListener("change", fillLog); sel.addEventListener("change", fillLog);
}

function entryLine(time, kind, level, message, who) {
  const li = el("li", undefined, level);
  const t = el("time", new Date(time * 1000).toLocaleTimeString()); li.append(t, el("b", kind + " "), el("span", message));
  if (who) li.append(el("span", " · " + who, "muted"));
  return li;
}

async function fillLog() {
  const ul = $("log-list"), note = $("log-note"); const sid = $("log-session-only").checked ? state.watched : null;
  const q = new URLSearchParams({ limit: "200" });
  for (const k of $("log-kind").value.split(",").filter(Boolean)) q.append("kind", k);
  if (sid) q.set("session_id", sid);
  try {
    const r = await api("GET", "/activity?" + q);
    ul.replaceChildren(...r.items.reverse().map((a) => entryLine(a.wall, a.kind, a.level, a.message,
      a.actor ? (a.actor.client || a.actor.address || "") + (a.actor.origin ? " " + a.actor.origin : "") : "")));
    note.textContent = (r.gap ? "older entries are gone from the daemon's log · " : "") + `${r.items.length} entries, newest first`;
  } catch (e) {
    // a daemon without the activity log: the session's own fault list (the last 50)
    const s = sid ? await guarded(() => api("GET", "/sessions/" + sid)) : null;
    const faults = (s && s.faults) || [];
    ul.replaceChildren(...faults.slice().reverse().map((f) => entryLine((s.created || 0) + (f.time_s || 0), "fault", "warning",
      `${f.fault_class}: ${f.message} → ${f.action}` + (f.attempt > 1 ? ` (attempt ${f.attempt})` : ""), f.device || "")));
    note.textContent = `no activity log (${e.message}): the session's faults` + (s ? ` (${s.fault_count} in all)` : "");
  }
  if (!ul.children.length) ul.append(el("li", "nothing logged", "muted"));
}

function openLog() { const d = $("log-dialog"); if (!d.open) d.showModal(); fillLog(); }

buildLog();
// the fault count becomes the button that opens the log
{
  const count = $("run-faults"); const b = button("", openLog, "linkish"); b.id = "run-faults-open";
  b.setAttribute("aria-label", "faults: open the log"); b.title = "open the log (faults, retries, actions)";
  count.replaceWith(b); b.append(count);
}

// ------------------------------------------------------------------ other clients
async function otherClients() {
  const r = await api("GET", "/activity/clients?window_s=60").catch(() => null);
  let chip = $("others");
  if (!r) { if (chip) chip.hidden = true; return; }
  if (!chip) { chip = el("span", "", "chip busy"); chip.id = "others"; $("rig-status").after(chip); }
  const ctl = r.clients.filter((c) => c.controlling && !c.you);
  chip.hidden = !ctl.length;
  chip.textContent = ctl.length ? `another client acts on the rig: ${ctl[0].last_action ?? ""}` : "";
  chip.title = ctl.map((c) => `${c.client ?? c.address ?? "?"} ${c.origin ?? ""}: ${c.last_action ?? ""}`).join("\n");
}
setInterval(otherClients, 5000);
