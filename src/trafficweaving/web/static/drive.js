// trafficweaving drive: the page's shared state. The page draws what the server simulates
// (draw.js), sends the person's raw controls (input.js) and talks to the server (connection.js);
// every number about the scenario and the controls comes from the server's welcome message
// (src/trafficweaving/web/room.py), none is restated here. Protocol: web/protocol.py.
"use strict";

const COLOURS = { robot: "#1f77b4", human: "#d62728", human2: "#ff7f0e" };

// state shared with automation (tests read it; the page never reads it back)
const drive = window.drive = {
  welcome: null, room: null, queued: null, started: null, state: null, plan: null, plans: 0, ended: null, errors: [],
  phase: "connecting",   // connecting | idle | starting | queued | countdown | driving | ended | closed
};

const $ = (id) => document.getElementById(id);

function robotMode() { return drive.welcome.mode === "robot"; }

// the cars this page drives in the present trial
function myCars() { return drive.started ? drive.started.cars : []; }

// the cars the view and the speedometers follow: yours against the robot, both in a human-human room
function followedCars() {
  if (drive.welcome && !robotMode()) return [0, 1];
  return myCars().length ? myCars() : [0, 1];
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
