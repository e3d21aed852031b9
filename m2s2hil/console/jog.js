// Keyboard jog for the Setup view, with a step picker (0.1°, 1°, 10°). Loaded after console.js
// and uses its helpers ($, el, button, manual, announce, state).
// Keys, on the Setup view when focus is not in a field: ←/→ or [/] the turntable −/+ one step,
// ↑/↓ the tilt +/−, 1/2/3 pick the step. A held key jogs once (key repeat is ignored), so a key
// stuck down cannot queue moves; the daemon runs jogs one after the other (none is lost).
"use strict";

const JOG_STEPS = [0.1, 1, 10];
const JOG_KEYS = { ArrowLeft: ["turntable", -1], ArrowRight: ["turntable", 1], "[": ["turntable", -1],
  "]": ["turntable", 1], ArrowUp: ["tilt", 1], ArrowDown: ["tilt", -1] };
let jogStep = 1;

function pickJogStep(step) {
  jogStep = step;
  for (const b of document.querySelectorAll("#jog-steps button")) {
    b.setAttribute("aria-pressed", String(Number(b.dataset.step) === step));
  }
}

function buildJogPicker() {
  const box = el("div", undefined, "row jog-keys"); box.id = "jog-steps";
  box.setAttribute("role", "group"); box.setAttribute("aria-label", "keyboard jog step");
  box.append(el("span", "key step", "muted"));
  JOG_STEPS.forEach((step, i) => {
    const b = button(step + "°", () => pickJogStep(step), "step");
    b.dataset.step = String(step); b.setAttribute("aria-label", `keyboard jog step ${step}° (key ${i + 1})`);
    box.append(b);
  });
  box.append(el("span", "keys: ←/→ or [/] turntable, ↑/↓ tilt, 1/2/3 step", "muted hint"));
  $("axes").before(box);
  pickJogStep(jogStep);
}

// Keys jog only on the Setup view, and never from a field (a number field uses ↑/↓ itself) or
// while a dialog is open.
function jogTarget(target) {
  if (!$("view-setup").classList.contains("active")) return false;
  if (document.querySelector("dialog[open], .overlay:not([hidden])")) return false;
  return !(target && target.closest && target.closest("input, select, textarea, [contenteditable], [role=slider]"));
}

document.addEventListener("keydown", (ev) => {
  if (ev.altKey || ev.ctrlKey || ev.metaKey || ev.defaultPrevented || !jogTarget(ev.target)) return;
  const pick = { 1: 0.1, 2: 1, 3: 10 }[ev.key];
  if (pick !== undefined) { ev.preventDefault(); pickJogStep(pick); announce(`jog step ${pick}°`); return; }
  const jog = JOG_KEYS[ev.key];
  if (!jog) return;
  ev.preventDefault();  // (no page scroll)
  if (ev.repeat) return;
  if (state.owner) { announce(`session ${state.owner} owns the rig: no jog`); return; }
  const [role, sign] = jog;
  manual("jog", role, { delta_deg: sign * jogStep });
});

buildJogPicker();
