// trafficweaving drive: the person's input. Keys (WASD or arrows) and the first gamepad become raw
// controls (throttle, brake in [0, 1], steer in [-1, 1]), sent for this page's car 20 times a
// second while a trial runs; the server turns them into accelerations (web/controls.py).
"use strict";

const DEADZONE = 0.08;           // gamepad axis dead zone
const KEYS = { throttle: ["KeyW", "ArrowUp"], brake: ["KeyS", "ArrowDown"], left: ["KeyA", "ArrowLeft"],
               right: ["KeyD", "ArrowRight"] };
const pressed = new Set();
let seq = [0, 0];

function keyValue(codes) { return codes.some((c) => pressed.has(c)) ? 1 : 0; }

function keyboardControls() {
  return { throttle: keyValue(KEYS.throttle), brake: keyValue(KEYS.brake), steer: keyValue(KEYS.right) - keyValue(KEYS.left) };
}

function axis(v) { return Math.abs(v) < DEADZONE ? 0 : Math.max(-1, Math.min(1, v)); }

function padControls(pad) {
  if (!pad) return null;
  if (pad.mapping === "standard") {
    return { throttle: pad.buttons[7] ? pad.buttons[7].value : 0, brake: pad.buttons[6] ? pad.buttons[6].value : 0,
             steer: axis(pad.axes[0] || 0) };
  }
  const pedal = axis(pad.axes[1] || 0);  // other pads and wheels: stick or pedal axis 1, up = throttle
  return { throttle: Math.max(0, -pedal), brake: Math.max(0, pedal), steer: axis(pad.axes[0] || 0) };
}

function gamepads() {
  return navigator.getGamepads ? Array.from(navigator.getGamepads()).filter((p) => p && p.connected) : [];
}

// for each control, the stronger of keyboard and pad
function strongest(a, b) {
  if (!b) return a;
  const pick = (k) => (Math.abs(b[k]) > Math.abs(a[k]) ? b[k] : a[k]);
  return { throttle: pick("throttle"), brake: pick("brake"), steer: pick("steer") };
}

function sendControls() {
  if (!["countdown", "driving"].includes(drive.phase)) return;
  const c = strongest(keyboardControls(), padControls(gamepads()[0]));
  const round = (v) => Math.round(v * 1000) / 1000;
  for (const car of myCars()) {
    seq[car] += 1;
    send({ type: "controls", seq: seq[car], car, throttle: round(c.throttle), brake: round(c.brake), steer: round(c.steer) });
  }
  showInputs(c);
}

function showInputs(c) {
  const box = $("inputs");
  box.innerHTML = "";
  const bars = document.createElement("div");
  bars.className = "bars";
  const row = (name, from, to) => {
    const label = document.createElement("span");
    label.textContent = name;
    const bar = document.createElement("div");
    bar.className = from === 0 ? "bar centred" : "bar";
    const fill = document.createElement("i");
    fill.style.left = `${50 * (1 + Math.min(from, to))}%`;
    fill.style.width = `${50 * Math.abs(to - from)}%`;
    bar.append(fill);
    bars.append(label, bar);
  };
  row("gas", -1, -1 + 2 * c.throttle);
  row("brake", -1, -1 + 2 * c.brake);
  row("steer", 0, c.steer);
  box.append(bars);
}

function showGamepads() {
  const pads = gamepads();
  $("gamepads").textContent = pads.length ? `gamepad: ${pads[0].id}` : "no gamepad";
}

const GAME_KEYS = new Set(["ArrowUp", "ArrowDown", "ArrowLeft", "ArrowRight", "Space"]);
window.addEventListener("keydown", (event) => {
  const driving = ["countdown", "driving"].includes(drive.phase);
  const form = event.target instanceof HTMLInputElement || event.target instanceof HTMLSelectElement;
  if (form && !driving && event.code !== "Enter") return;  // typing an id, choosing a start
  if (GAME_KEYS.has(event.code) || (driving && form)) event.preventDefault();
  pressed.add(event.code);
  if (event.repeat) return;
  if (event.code === "Enter") startTrial();
  else if (event.code === "Escape" && (driving || drive.phase === "queued")) send({ type: "abort" });
  else if (event.code === "KeyP") $("show-plan").checked = !$("show-plan").checked;
  else if (event.code === "KeyM") { $("sound").checked = !$("sound").checked; if (!$("sound").checked) beep(false); }
});
window.addEventListener("keyup", (event) => pressed.delete(event.code));
window.addEventListener("blur", () => pressed.clear());
window.addEventListener("gamepadconnected", showGamepads);
window.addEventListener("gamepaddisconnected", showGamepads);
