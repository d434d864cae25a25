// trafficweaving drive: the page. It draws what the server simulates and sends the person's raw
// controls; every number about the scenario and the controls comes from the server's welcome
// message (src/trafficweaving/web/session.py), none is restated here. Protocol: web/protocol.py.
"use strict";

const COLOURS = { robot: "#1f77b4", human: "#d62728", human2: "#ff7f0e" };
const VIEW_SPAN_M = 65;          // metres of road across the canvas (more when two cars are far apart)
const FOCUS_AT = 0.38;           // where the followed car sits across the canvas (fraction of the width)
const GAUGE_MAX = 50;            // speedometer full scale, m/s
const DEADZONE = 0.08;           // gamepad axis dead zone
const FUTURES_DRAWN = 16;        // sampled human futures drawn per plan
const KEYS_A = { throttle: ["KeyW"], brake: ["KeyS"], left: ["KeyA"], right: ["KeyD"] };
const KEYS_B = { throttle: ["ArrowUp"], brake: ["ArrowDown"], left: ["ArrowLeft"], right: ["ArrowRight"] };

// state shared with automation (tests read it; the page never reads it back)
const drive = window.drive = {
  welcome: null, started: null, state: null, plan: null, plans: 0, ended: null, errors: [],
  phase: "connecting",   // connecting | idle | countdown | driving | ended | closed
};

const $ = (id) => document.getElementById(id);
const canvas = $("road");
const ctx = canvas.getContext("2d");
const pressed = new Set();
let socket = null;
let seq = [0, 0];
let lastState = null, lastStateAt = 0;
let audio = null, beepOn = false;
let phaseBeforeStart = "idle";

// ------------------------------------------------------------------ connection
function connect() {
  socket = new WebSocket(`${location.protocol === "https:" ? "wss" : "ws"}://${location.host}/ws`);
  socket.onopen = () => setPill("connection", "connected", "ok");
  socket.onclose = (event) => {
    drive.phase = "closed";
    const why = event.code === 1013 ? "another page is driving" : "disconnected — reload to reconnect";
    setPill("connection", why, "bad");
    $("start").disabled = true;
    $("abort").disabled = true;
  };
  socket.onmessage = (event) => {
    const message = JSON.parse(event.data);
    const handler = HANDLERS[message.type];
    if (handler) handler(message);
  };
}

function send(message) {
  if (socket && socket.readyState === WebSocket.OPEN) socket.send(JSON.stringify(message));
}

const HANDLERS = {
  welcome(m) {
    drive.welcome = m;
    drive.phase = "idle";
    setPill("mode", m.mode === "robot" ? "you vs the robot" : "human–human", "ok");
    const robot = m.mode === "robot";
    document.querySelectorAll(".robot-only").forEach((e) => e.classList.toggle("hidden", !robot));
    $("car-choice").classList.toggle("hidden", !robot);
    $("help-robot").classList.toggle("hidden", !robot);
    $("help-hh").classList.toggle("hidden", robot);
    $("driver1-label").classList.toggle("hidden", robot);
    $("driver0").parentElement.firstChild.textContent = robot ? "Driver id " : "Driver id (WASD) ";
    const select = $("ic");
    select.innerHTML = "";
    select.add(new Option("random (one of the study's 18)", ""));
    for (const ic of m.initial_conditions) select.add(new Option(icLabel(ic), String(ic.index)));
    select.onchange = describeChoice;
    $("car").onchange = describeChoice;
    describeChoice();
    $("start").disabled = false;
    setInterval(sendControls, 1000 * m.control_interval_s);
  },
  started(m) {
    drive.started = m; drive.ended = null; drive.plan = null; drive.plans = 0; drive.state = null;
    drive.phase = "countdown";
    seq = [0, 0];
    lastState = { step: 0, t: 0, cars: m.states };
    lastStateAt = performance.now();
    $("result").classList.add("hidden");
    $("start").disabled = true;
    $("abort").disabled = false;
    $("st-trial").textContent = `${m.trial} (start ${m.initial_condition.index})`;
    describeTrial(m);
    if (m.countdown_s === 0) showOverlay("");
  },
  countdown(m) { showOverlay(String(m.seconds)); },
  go() {
    drive.phase = "driving";
    showOverlay("GO");
    setTimeout(() => { if (drive.phase === "driving") showOverlay(""); }, 600);
  },
  state(m) {
    drive.state = m;
    lastState = m;
    lastStateAt = performance.now();
    $("st-time").textContent = `${m.t.toFixed(1)} s`;
    const follow = followedCars();
    const x = Math.max(...follow.map((k) => m.cars[k][0]));
    const cutoff = drive.welcome.scenario.road_end_x - x;
    $("st-cutoff").textContent = cutoff > 0 ? `${cutoff.toFixed(0)} m` : "passed";
    if (m.planner) {
      $("st-plans").textContent = String(m.planner.plans);
      $("st-late").textContent = String(m.planner.late);
      $("st-latency").textContent = m.planner.latency_s == null ? "—" : `${(1000 * m.planner.latency_s).toFixed(0)} ms`;
    }
  },
  plan(m) { drive.plan = m; drive.plans += 1; },
  ended(m) {
    drive.ended = m;
    drive.phase = "ended";
    showOverlay("");
    beep(false);
    $("start").disabled = false;
    $("abort").disabled = true;
    showResult(m);
  },
  error(m) {
    drive.errors.push(m);
    if (m.for === "start" && drive.phase === "starting") drive.phase = phaseBeforeStart;
    console.warn("server refused a message:", m.error);
    const item = document.createElement("li");
    item.textContent = m.error;
    const list = $("errors");
    list.prepend(item);
    while (list.children.length > 5) list.lastChild.remove();
  },
};

// ------------------------------------------------------------------ trial set-up and results
function icLabel(ic) {
  const dv = ic.dv_ab === 0 ? "same speed" : `B ${ic.dv_ab > 0 ? "+" : ""}${ic.dv_ab} m/s`;
  const tco = ic.dv_ab === 0 ? "" : `, crossover ${ic.tco} s`;
  return `${ic.index}: A ${ic.lanes[0]} lane, ${dv}${tco}`;
}

function carText(states, lanes, k, other) {
  const me = states[k], them = states[other];
  const gap = me[0] - them[0];
  const where = Math.abs(gap) < 0.05 ? "level with" : `${Math.abs(gap).toFixed(0)} m ${gap > 0 ? "ahead of" : "behind"}`;
  return `${lanes[k]} lane at ${me[2].toFixed(0)} m/s, ${where}`;
}

function describeChoice() {
  const w = drive.welcome;
  if (!w) return;
  const k = $("ic").value;
  if (k === "") { $("ic-text").textContent = "Each trial draws one of the study's 18 starts."; return; }
  const ic = w.initial_conditions[Number(k)];
  const car = $("car").value;
  if (w.mode === "robot" && car !== "") {
    const me = Number(car), robot = 1 - me;
    $("ic-text").textContent = `You: ${carText(ic.states, ic.lanes, me, robot)} the robot.`;
  } else {
    $("ic-text").textContent = `A: ${carText(ic.states, ic.lanes, 0, 1)} B.`;
  }
}

function describeTrial(m) {
  const w = drive.welcome;
  const human = m.roles.indexOf("human");
  $("ic-text").textContent = w.mode === "robot"
    ? `You drive car ${"AB"[human]}: ${carText(m.states, m.initial_condition.lanes, human, 1 - human)} the robot. `
      + "Swap lanes before the cutoff."
    : `A: ${carText(m.states, m.initial_condition.lanes, 0, 1)} B. Both swap lanes before the cutoff.`;
}

function startTrial() {
  if (!drive.welcome || !["idle", "ended"].includes(drive.phase)) return;
  unlockAudio();
  if (document.activeElement instanceof HTMLElement) document.activeElement.blur();  // keys drive, not the form
  const ic = $("ic").value, car = $("car").value;
  const robotCar = drive.welcome.mode === "robot" && car !== "" ? 1 - Number(car) : null;
  const people = drive.welcome.mode === "robot" ? ["driver0"] : ["driver0", "driver1"];
  const drivers = people.map((id) => ($(id).value === "" ? null : Math.floor(Number($(id).value))));
  send({ type: "start", initial_condition: ic === "" ? null : Number(ic), robot_car: robotCar, drivers });
  phaseBeforeStart = drive.phase;
  drive.phase = "starting";
}

const OUTCOMES = {
  valid: "Both cars swapped lanes",
  collision: "Collision",
  off_road: "Off the road",
  no_lane_swap: "A car did not swap lanes",
  cutoff_not_reached: "Cutoff not reached",
};
const REASONS = {
  finished: "Both cars passed the end of the recording.",
  time_limit: "The time limit was reached.",
  collision: "The cars collided.",
  off_road: "A car left the road.",
  aborted: "You stopped the trial.",
  disconnected: "The page disconnected.",
  server_error: "The server failed (see its log).",
};

function fmt(value, unit, digits = 1) {
  if (value === null || value === undefined) return "—";
  if (typeof value === "boolean") return value ? "yes" : "no";
  return `${Number(value).toFixed(digits)}${unit ? " " + unit : ""}`;
}

function showResult(m) {
  const metrics = m.metrics || {};
  const robot = drive.welcome.mode === "robot";
  let outcome = OUTCOMES[metrics.outcome] || "Trial ended";
  if (metrics.outcome === "no_lane_swap") {
    const swapped = robot ? [metrics.robot_swapped, metrics.human_swapped] : metrics.swapped;
    const names = robot ? ["The robot", "You"] : ["Car A", "Car B"];
    const stayed = names.filter((_, k) => !swapped[k]);
    outcome = stayed.length === 2 ? "Neither car swapped lanes" : `${stayed[0]} did not swap lanes`;
  }
  $("outcome").textContent = outcome;
  $("outcome").style.color = metrics.outcome === "valid" ? "#7fd67f" : "#ff7b7b";
  $("reason").textContent = `${REASONS[m.reason] || m.reason} ${m.steps} steps (${(m.steps * drive.welcome.scenario.dt).toFixed(1)} s).`;
  const rows = robot ? [
    ["robot succeeded", fmt(metrics.success)],
    ["who passed first", metrics.robot_first === undefined ? "—" : metrics.robot_first ? "the robot" : "you"],
    ["near collision", fmt(metrics.near_collision)],
    ["smallest gap (overlapping)", fmt(metrics.min_gap_m, "m")],
    ["smallest distance", fmt(metrics.min_distance_m, "m")],
    ["robot's lane change at", fmt(metrics.time_to_swap_s, "s")],
  ] : [
    ["swapped (A, B)", metrics.swapped ? metrics.swapped.map((s) => (s ? "yes" : "no")).join(", ") : "—"],
    ["who passed first", metrics.first ? `car ${metrics.first}` : "—"],
    ["near collision", fmt(metrics.near_collision)],
    ["smallest gap (overlapping)", fmt(metrics.min_gap_m, "m")],
    ["smallest distance", fmt(metrics.min_distance_m, "m")],
  ];
  $("metrics").innerHTML = "";
  for (const [name, value] of rows) {
    const row = $("metrics").insertRow();
    row.insertCell().textContent = name;
    row.insertCell().textContent = value;
  }
  $("file").textContent = m.file ? `Recorded: ${m.file}` : m.note;
  $("result").classList.remove("hidden");
}

function showOverlay(text) {
  const overlay = $("overlay");
  overlay.textContent = text;
  overlay.classList.toggle("hidden", !text);
}

function setPill(id, text, kind) {
  const pill = $(id);
  pill.textContent = text;
  pill.className = `pill ${kind || ""}`;
}

// ------------------------------------------------------------------ input
function humanCars() {
  return drive.started ? drive.started.roles.flatMap((role, k) => (role === "human" ? [k] : [])) : [];
}

function followedCars() {
  const humans = humanCars();
  return humans.length ? humans : [0, 1];
}

function keyValue(codes) { return codes.some((c) => pressed.has(c)) ? 1 : 0; }

function keyboardControls(sets) {
  const value = (name) => Math.max(...sets.map((s) => keyValue(s[name])));
  return { throttle: value("throttle"), brake: value("brake"), steer: value("right") - value("left") };
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

function strongest(a, b) {
  if (!b) return a;
  const pick = (k) => (Math.abs(b[k]) > Math.abs(a[k]) ? b[k] : a[k]);
  return { throttle: pick("throttle"), brake: pick("brake"), steer: pick("steer") };
}

function controlsOf(car, slot, pads) {
  const twoPeople = drive.welcome.mode !== "robot";
  const keys = twoPeople ? [slot === 0 ? KEYS_A : KEYS_B] : [KEYS_A, KEYS_B];
  return strongest(keyboardControls(keys), padControls(pads[slot]));
}

function sendControls() {
  if (!["countdown", "driving"].includes(drive.phase)) return;
  const pads = gamepads();
  const shown = [];
  humanCars().forEach((car, slot) => {
    const c = controlsOf(car, slot, pads);
    const round = (v) => Math.round(v * 1000) / 1000;
    seq[car] += 1;
    send({ type: "controls", seq: seq[car], car, throttle: round(c.throttle), brake: round(c.brake), steer: round(c.steer) });
    shown.push([car, c]);
  });
  showInputs(shown);
}

function showInputs(shown) {
  const box = $("inputs");
  box.innerHTML = "";
  for (const [car, c] of shown) {
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
    const who = drive.welcome.mode === "robot" ? "you" : `car ${"AB"[car]}`;
    row(`${who}: gas`, -1, -1 + 2 * c.throttle);
    row("brake", -1, -1 + 2 * c.brake);
    row("steer", 0, c.steer);
    box.append(bars);
  }
}

const GAME_KEYS = new Set(["ArrowUp", "ArrowDown", "ArrowLeft", "ArrowRight", "Space"]);
window.addEventListener("keydown", (event) => {
  const driving = ["countdown", "driving"].includes(drive.phase);
  const form = event.target instanceof HTMLInputElement || event.target instanceof HTMLSelectElement;
  if (form && !driving && event.code !== "Enter") return;  // typing a driver id, choosing a start
  if (GAME_KEYS.has(event.code) || (driving && form)) event.preventDefault();
  pressed.add(event.code);
  if (event.repeat) return;
  if (event.code === "Enter") startTrial();
  else if (event.code === "Escape" && driving) send({ type: "abort" });
  else if (event.code === "KeyP") $("show-plan").checked = !$("show-plan").checked;
  else if (event.code === "KeyM") { $("sound").checked = !$("sound").checked; if (!$("sound").checked) beep(false); }
});
window.addEventListener("keyup", (event) => pressed.delete(event.code));
window.addEventListener("blur", () => pressed.clear());
window.addEventListener("gamepadconnected", showGamepads);
window.addEventListener("gamepaddisconnected", showGamepads);
$("start").onclick = startTrial;
$("next").onclick = startTrial;
$("abort").onclick = () => send({ type: "abort" });

function showGamepads() {
  const pads = gamepads();
  $("gamepads").textContent = pads.length ? pads.map((p, k) => `gamepad ${k + 1}: ${p.id}`).join("; ") : "no gamepad";
}

// ------------------------------------------------------------------ sound: the study's over-speed alert
function unlockAudio() {
  if (audio || !(window.AudioContext || window.webkitAudioContext)) return;
  try {
    audio = new (window.AudioContext || window.webkitAudioContext)();
    const osc = audio.createOscillator();
    const gain = audio.createGain();
    osc.type = "square";
    osc.frequency.value = 2400;     // high-pitched, as in the study
    gain.gain.value = 0;
    osc.connect(gain).connect(audio.destination);
    osc.start();
    audio.gain = gain;
  } catch (error) {
    audio = null;
  }
}

function beep(on) {
  if (!audio || on === beepOn) return;
  beepOn = on;
  audio.gain.gain.setTargetAtTime(on ? 0.04 : 0, audio.currentTime, 0.01);
}

// ------------------------------------------------------------------ drawing
function extrapolated() {
  // states between server steps: each car moves on with its velocity and acceleration (at most 0.15 s)
  if (!lastState) return null;
  const tau = drive.phase === "driving" ? Math.min((performance.now() - lastStateAt) / 1000, 0.15) : 0;
  return lastState.cars.map((s) => [s[0] + s[2] * tau + 0.5 * s[4] * tau * tau, s[1] + s[3] * tau + 0.5 * s[5] * tau * tau,
                                    s[2] + s[4] * tau, s[3] + s[5] * tau, s[4], s[5]]);
}

function resize() {
  const ratio = window.devicePixelRatio || 1;
  const width = Math.round(canvas.clientWidth * ratio), height = Math.round(canvas.clientHeight * ratio);
  if (canvas.width !== width || canvas.height !== height) { canvas.width = width; canvas.height = height; }
  return ratio;
}

function frame() {
  const ratio = resize();
  const w = drive.welcome;
  ctx.setTransform(1, 0, 0, 1, 0, 0);
  ctx.fillStyle = "#2f5f2f";
  ctx.fillRect(0, 0, canvas.width, canvas.height);
  if (w) {
    const cars = extrapolated();
    const view = camera(cars, ratio);
    drawRoad(view);
    if (cars && $("show-plan").checked && drive.plan && ["driving", "ended"].includes(drive.phase)) drawPlan(view, drive.plan);
    if (cars) cars.forEach((state, k) => drawCar(view, state, k));
    drawHud(view, cars);
  }
  requestAnimationFrame(frame);
}

function camera(cars, ratio) {
  const s = drive.welcome.scenario;
  const width = canvas.width / ratio, height = canvas.height / ratio;
  let focus = s.start_x, span = VIEW_SPAN_M;
  if (cars) {
    const follow = followedCars();
    const xs = follow.map((k) => cars[k][0]);
    focus = xs.reduce((a, b) => a + b, 0) / xs.length;
    if (follow.length > 1) span = Math.max(VIEW_SPAN_M, Math.max(...xs) - Math.min(...xs) + 30);
  }
  const scale = width / span;                               // px per metre, both directions
  const roadTop = s.road_y_max + s.car_width / 2;           // pavement: a car's body on it <=> its centre is on the road
  const roadBottom = s.road_y_min - s.car_width / 2;
  const top = Math.max(24, (height * 0.6 - (roadTop - roadBottom) * scale) / 2);
  return {
    ratio, width, height, scale, s, roadTop, roadBottom,
    x: (x) => (x - focus) * scale + width * FOCUS_AT,
    y: (y) => top + (roadTop - y) * scale,
    x0: focus - width * FOCUS_AT / scale, x1: focus + width * (1 - FOCUS_AT) / scale,
  };
}

function drawRoad(v) {
  const s = v.s;
  ctx.setTransform(v.ratio, 0, 0, v.ratio, 0, 0);
  const yTop = v.y(v.roadTop), yBottom = v.y(v.roadBottom), yDivider = v.y(s.lane_divider_y);
  ctx.fillStyle = "#3b3f45";
  ctx.fillRect(0, yTop, v.width, yBottom - yTop);
  ctx.strokeStyle = "#f2f2f2";
  ctx.lineWidth = 2;
  line(0, yTop, v.width, yTop);
  line(0, yBottom, v.width, yBottom);
  // the lane divider: dashes fixed to the road (3 m painted, 9 m gap) up to the cutoff
  const cutoff = v.x(s.road_end_x);
  ctx.lineWidth = 2;
  for (let x = Math.floor(v.x0 / 12) * 12; x < Math.min(v.x1, s.road_end_x); x += 12) {
    line(v.x(x), yDivider, v.x(Math.min(x + 3, s.road_end_x)), yDivider);
  }
  // past the cutoff the lanes part: a gore area between them
  if (cutoff < v.width) {
    ctx.fillStyle = "#2f5f2f";
    ctx.beginPath();
    const wedge = 0.05 * v.scale;
    ctx.moveTo(cutoff, yDivider);
    ctx.lineTo(v.width + 10, yDivider - wedge * (v.width + 10 - cutoff) / v.scale);
    ctx.lineTo(v.width + 10, yDivider + wedge * (v.width + 10 - cutoff) / v.scale);
    ctx.closePath();
    ctx.fill();
    ctx.strokeStyle = "#ffd84d";
    ctx.lineWidth = 3;
    line(cutoff, yTop, cutoff, yBottom);
    label("CUTOFF", cutoff + 4, yTop - 6, "#ffd84d", "left");
  }
  const end = v.x(s.record_end_x);
  if (end < v.width) {
    ctx.setLineDash([6, 6]);
    ctx.strokeStyle = "#cccccc";
    ctx.lineWidth = 2;
    line(end, yTop, end, yBottom);
    ctx.setLineDash([]);
    label("end", end + 4, yBottom + 14, "#cccccc", "left");
  }
  // distance signs every 25 m before the cutoff
  for (let x = Math.ceil(v.x0 / 25) * 25; x < Math.min(v.x1, s.road_end_x); x += 25) {
    if (x === 0) continue;
    label(`${-x} m`, v.x(x), yTop - 6, "#d8e6d8", "center");
  }
}

function drawCar(v, state, k) {
  const s = v.s;
  const role = drive.started ? drive.started.roles[k] : "human";
  const twoPeople = drive.welcome.mode !== "robot";
  const colour = role === "robot" ? COLOURS.robot : twoPeople && k === 1 ? COLOURS.human2 : COLOURS.human;
  const name = role === "robot" ? "ROBOT" : twoPeople ? `${"AB"[k]} · ${k === 0 ? "WASD" : "ARROWS"}` : "YOU";
  const heading = -Math.atan2(state[3], Math.max(state[2], 1));
  ctx.save();
  ctx.setTransform(v.ratio, 0, 0, v.ratio, 0, 0);
  ctx.translate(v.x(state[0]), v.y(state[1]));
  ctx.rotate(heading);
  const length = s.car_length * v.scale, width = s.car_width * v.scale;
  ctx.fillStyle = colour;
  roundRect(-length / 2, -width / 2, length, width, Math.min(6, width / 3));
  ctx.fill();
  ctx.fillStyle = "rgba(255,255,255,0.55)";        // windscreen: the front of the car
  ctx.fillRect(length * 0.12, -width * 0.38, length * 0.14, width * 0.76);
  ctx.restore();
  ctx.setTransform(v.ratio, 0, 0, v.ratio, 0, 0);
  label(name, v.x(state[0]), v.y(state[1]) - width / 2 - 6, "#ffffff", "center");
}

function drawPlan(v, plan) {
  // a plan made at step s holds positions at steps s+1..s+15: drawn from the present step on
  const now = drive.state ? drive.state.step : 0;
  const ahead = (points) => points.slice(Math.max(0, now - plan.step - 1));
  ctx.setTransform(v.ratio, 0, 0, v.ratio, 0, 0);
  ctx.lineWidth = 1.2;
  ctx.strokeStyle = "rgba(255, 90, 90, 0.45)";
  for (const future of plan.humans.slice(0, FUTURES_DRAWN)) polyline(v, ahead(future));
  ctx.setLineDash([7, 5]);
  ctx.lineWidth = 2.5;
  ctx.strokeStyle = "rgba(90, 170, 255, 0.95)";
  const robot = ahead(plan.robot);
  polyline(v, robot);
  ctx.setLineDash([]);
  ctx.fillStyle = "rgba(90, 170, 255, 0.95)";
  for (const [x, y] of robot) { ctx.beginPath(); ctx.arc(v.x(x), v.y(y), 2.2, 0, 2 * Math.PI); ctx.fill(); }
}

function drawHud(v, cars) {
  ctx.setTransform(v.ratio, 0, 0, v.ratio, 0, 0);
  const alert = v.s.speed_alert;
  const follow = cars ? followedCars() : [];
  let over = false;
  follow.forEach((k, slot) => {
    const fromRight = follow.length - 1 - slot;  // car A's gauge left of car B's
    const speed = cars[k][2];
    over = over || speed > alert;
    const twoPeople = drive.welcome.mode !== "robot";
    const colour = twoPeople && k === 1 ? COLOURS.human2 : COLOURS.human;
    gauge(v.width - 100 - fromRight * 180, v.height - 88, 58, speed, alert, twoPeople ? `car ${"AB"[k]}` : "you", colour);
  });
  beep(over && $("sound").checked && drive.phase === "driving");
  if (drive.state) {
    label(`t = ${drive.state.t.toFixed(1)} s`, 14, v.height - 20, "#ffffff", "left", "16px");
  }
  if ($("show-plan").checked && drive.welcome.mode === "robot") {
    label("dashed blue: the robot's chosen plan; red: the human futures it sampled", 14, v.height - 44, "#d8e6d8", "left");
  }
}

function gauge(cx, cy, r, speed, alert, name, colour) {
  const start = Math.PI * 0.8, sweep = Math.PI * 1.4;
  const angle = (value) => start + sweep * Math.min(Math.max(value, 0), GAUGE_MAX) / GAUGE_MAX;
  const over = speed > alert;
  const flash = over && Math.floor(performance.now() / 250) % 2 === 0;
  ctx.fillStyle = flash ? "rgba(200, 30, 30, 0.85)" : "rgba(15, 18, 22, 0.8)";
  ctx.beginPath(); ctx.arc(cx, cy, r + 12, 0, 2 * Math.PI); ctx.fill();
  ctx.lineWidth = 6;
  ctx.strokeStyle = "#5a626c";
  ctx.beginPath(); ctx.arc(cx, cy, r, start, angle(alert)); ctx.stroke();
  ctx.strokeStyle = "#ff4d4d";
  ctx.beginPath(); ctx.arc(cx, cy, r, angle(alert), start + sweep); ctx.stroke();
  ctx.strokeStyle = colour;
  ctx.lineWidth = 3;
  const a = angle(speed);
  line(cx, cy, cx + Math.cos(a) * (r - 8), cy + Math.sin(a) * (r - 8));
  label(`${speed.toFixed(1)}`, cx, cy + 22, "#ffffff", "center", "bold 18px");
  label(`m/s · ${(speed * 3.6).toFixed(0)} km/h`, cx, cy + 36, "#c8ccd0", "center", "10px");
  label(over ? "SLOW DOWN" : name, cx, cy - r - 16, over ? "#ff7b7b" : "#ffffff", "center", "bold 12px");
}

function polyline(v, points) {
  ctx.beginPath();
  points.forEach(([x, y], k) => (k ? ctx.lineTo(v.x(x), v.y(y)) : ctx.moveTo(v.x(x), v.y(y))));
  ctx.stroke();
}

function line(x0, y0, x1, y1) { ctx.beginPath(); ctx.moveTo(x0, y0); ctx.lineTo(x1, y1); ctx.stroke(); }

function roundRect(x, y, w, h, r) {
  ctx.beginPath();
  ctx.moveTo(x + r, y); ctx.arcTo(x + w, y, x + w, y + h, r); ctx.arcTo(x + w, y + h, x, y + h, r);
  ctx.arcTo(x, y + h, x, y, r); ctx.arcTo(x, y, x + w, y, r); ctx.closePath();
}

function label(text, x, y, colour, align, font = "12px") {
  ctx.font = `${font} system-ui, sans-serif`;
  ctx.fillStyle = colour;
  ctx.textAlign = align;
  ctx.fillText(text, x, y);
}

connect();
showGamepads();
requestAnimationFrame(frame);
