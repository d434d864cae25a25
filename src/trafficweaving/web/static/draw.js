// trafficweaving drive: drawing. The road, the cars (extrapolated between the server's 0.1 s
// steps), the robot's plan, the speedometers and the study's over-speed alert, on one canvas.
"use strict";

const VIEW_SPAN_M = 65;          // metres of road across the canvas (more when two cars are far apart)
const FOCUS_AT = 0.38;           // where the followed car sits across the canvas (fraction of the width)
const GAUGE_MAX = 50;            // speedometer full scale, m/s
const FUTURES_DRAWN = 16;        // sampled human futures drawn per plan
const canvas = $("road");
const ctx = canvas.getContext("2d");
let lastState = null, lastStateAt = 0;   // the latest state and when it arrived (performance.now())
let audio = null, beepOn = false;

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
  const mine = myCars().includes(k);
  const colour = role === "robot" ? COLOURS.robot : mine || !drive.started ? COLOURS.human : COLOURS.human2;
  const name = role === "robot" ? "ROBOT" : robotMode() ? "YOU" : `${"AB"[k]} · ${mine ? "YOU" : "OTHER DRIVER"}`;
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
  let over = false;   // the alert sounds for this page's own car
  follow.forEach((k, slot) => {
    const fromRight = follow.length - 1 - slot;  // car A's gauge left of car B's
    const speed = cars[k][2];
    const mine = myCars().includes(k);
    over = over || (mine && speed > alert);
    const colour = mine ? COLOURS.human : COLOURS.human2;
    const name = robotMode() ? "you" : `${mine ? "you" : "other"} (${"AB"[k]})`;
    gauge(v.width - 100 - fromRight * 180, v.height - 88, 58, speed, alert, name, colour);
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
