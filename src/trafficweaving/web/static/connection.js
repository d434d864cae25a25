// trafficweaving drive: the connection. One WebSocket to the server's room (a new one, or with
// ?room=N&token=T from a join link the room that link invites to), the server's messages and
// what the page shows of them: the room, the trial set-up, the queue, the result. Every message
// both ways, its fields and when it is sent: src/trafficweaving/web/protocol.py.
"use strict";

let socket = null;
let phaseBeforeStart = "idle";
let controlsTimer = null;

function connect() {
  const query = new URLSearchParams(location.search);
  const passed = new URLSearchParams();
  for (const name of ["room", "token", "key"]) if (query.has(name)) passed.set(name, query.get(name));
  const suffix = passed.toString() ? `?${passed}` : "";
  socket = new WebSocket(`${location.protocol === "https:" ? "wss" : "ws"}://${location.host}/ws${suffix}`);
  socket.onopen = () => setPill("connection", "connected", "ok");
  socket.onclose = (event) => {
    drive.phase = "closed";
    const last = drive.errors.length ? drive.errors[drive.errors.length - 1].error : "";
    const why = event.code === 1013 ? last || "busy" : drive.welcome ? "disconnected — reload to reconnect"
      : "refused (a room needs its join link)";
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
    const robot = robotMode();
    setPill("mode", robot ? "you vs the robot" : "human–human room", "ok");
    document.querySelectorAll(".robot-only").forEach((e) => e.classList.toggle("hidden", !robot));
    document.querySelectorAll(".room-only").forEach((e) => e.classList.toggle("hidden", robot));
    const select = $("ic");
    select.innerHTML = "";
    select.add(new Option(robot ? "random (one of the study's 18)" : "the protocol's next", ""));
    for (const ic of m.initial_conditions) select.add(new Option(icLabel(ic), String(ic.index)));
    select.onchange = describeChoice;
    $("car").onchange = describeChoice;
    $("driver0").onchange = () => {
      if (!robot) send({ type: "participant", driver: driverId() });
    };
    describeChoice();
    updateStart();
    controlsTimer = controlsTimer || setInterval(sendControls, 1000 * m.control_interval_s);
  },
  room(m) {
    drive.room = m;
    if (m.join) {
      const link = `${location.origin}${m.join}`;
      $("join-link").value = link;
      if (!new URLSearchParams(location.search).has("room")) history.replaceState(null, "", m.join);  // a reload rejoins
    }
    const other = 1 - drive.welcome.seat;
    $("room-text").textContent = `Room ${m.room} (session ${m.session}). You are person ${drive.welcome.seat + 1}; `
      + (m.seats[other] ? "the other driver is here." : "waiting for the other driver: send them the join link.");
    if (m.study) {
      const s = m.study, car = "AB"[s.seats.indexOf(drive.welcome.seat)];
      $("study-text").textContent = `Round ${s.round + 1}, trial ${s.position + 1} of 18 (${s.done} done). `
        + `Next: start ${s.next_initial_condition}; you drive car ${car} (the cars swap every round).`;
    }
    describeChoice();
    updateStart();
  },
  queued(m) {
    drive.queued = m;
    drive.phase = "queued";
    showOverlay("");
    setPill("connection", `waiting for the robot: ${m.position} ahead of you`, "");
  },
  started(m) {
    drive.started = m; drive.ended = null; drive.plan = null; drive.plans = 0; drive.state = null;
    drive.phase = "countdown";
    seq = [0, 0];
    lastState = { step: 0, t: 0, cars: m.states };
    lastStateAt = performance.now();
    setPill("connection", "connected", "ok");
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
    const x = Math.max(...followedCars().map((k) => m.cars[k][0]));
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
    setPill("connection", "connected", "ok");
    $("abort").disabled = true;
    updateStart();
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
function driverId() { return $("driver0").value === "" ? null : Math.floor(Number($("driver0").value)); }

// whether this page may start a trial now (a human-human room needs both drivers)
function updateStart() {
  const ready = ["idle", "ended"].includes(drive.phase)
    && (robotMode() || (drive.room !== null && drive.room.seats.every((taken) => taken)));
  $("start").disabled = !ready;
  $("next").disabled = !ready;
}

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
  if (k === "") {
    $("ic-text").textContent = robotMode() ? "Each trial draws one of the study's 18 starts."
      : "The protocol plays the 18 starts in a random order each round.";
    return;
  }
  const ic = w.initial_conditions[Number(k)];
  const car = $("car").value;
  if (robotMode() && car !== "") {
    const me = Number(car), robot = 1 - me;
    $("ic-text").textContent = `You: ${carText(ic.states, ic.lanes, me, robot)} the robot.`;
  } else {
    $("ic-text").textContent = `A: ${carText(ic.states, ic.lanes, 0, 1)} B.`
      + (robotMode() ? "" : " A start you choose is off the protocol: it does not count towards the rounds.");
  }
}

function describeTrial(m) {
  const mine = m.cars[0];
  const other = robotMode() ? "the robot" : "the other driver";
  $("ic-text").textContent = `You drive car ${"AB"[mine]}: ${carText(m.states, m.initial_condition.lanes, mine, 1 - mine)} `
    + `${other}. Swap lanes before the cutoff.`;
}

function startTrial() {
  if (!drive.welcome || $("start").disabled) return;
  unlockAudio();
  if (document.activeElement instanceof HTMLElement) document.activeElement.blur();  // keys drive, not the form
  const ic = $("ic").value, car = $("car").value;
  const message = { type: "start", initial_condition: ic === "" ? null : Number(ic) };
  if (robotMode()) {
    message.robot_car = car !== "" ? 1 - Number(car) : null;
    message.drivers = [driverId()];
  }
  send(message);
  phaseBeforeStart = drive.phase;
  drive.phase = "starting";
  $("start").disabled = true;
  $("abort").disabled = !robotMode();  // robot mode: Esc leaves the planner's queue
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
  aborted: "The trial was stopped.",
  disconnected: "A page disconnected.",
  server_error: "The server failed (see its log).",
};

function fmt(value, unit, digits = 1) {
  if (value === null || value === undefined) return "—";
  if (typeof value === "boolean") return value ? "yes" : "no";
  return `${Number(value).toFixed(digits)}${unit ? " " + unit : ""}`;
}

function showResult(m) {
  if (m.trial === null) {  // left the planner's queue
    $("outcome").textContent = "Not started";
    $("outcome").style.color = "#ff7b7b";
    $("reason").textContent = m.note;
    $("metrics").innerHTML = "";
    $("file").textContent = "";
    $("result").classList.remove("hidden");
    return;
  }
  const metrics = m.metrics || {};
  const robot = robotMode();
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

$("start").onclick = startTrial;
$("next").onclick = startTrial;
$("abort").onclick = () => send({ type: "abort" });
$("copy-link").onclick = () => { $("join-link").select(); document.execCommand("copy"); };

connect();
showGamepads();
requestAnimationFrame(frame);
