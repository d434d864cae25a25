"""One page's driving session: the protocol's state machine and the real-time trial loop.

A session answers the page's messages (:mod:`.protocol`): ``start`` begins a
:class:`~.trial.Trial` (countdown, then one world step every 0.1 s of wall time), ``controls``
update the person's :class:`~.person.PersonAgent` (those that arrive after the trial ended, sent
before the page learnt it, are ignored; before the first trial they are refused), ``abort`` ends
the trial. The loop never waits for the robot: its planner runs in a background thread
(:class:`~trafficweaving.planning.mpc.NonBlockingMPCPolicy`); a step that starts late does not
make the next ones hurry (the schedule restarts from it).

When a trial ends — for any reason, including the page going away (:meth:`DriveSession.close`) —
its outcome and metrics are sent (``ended``) and, if it lasted at least ``MIN_TRIAL_STEPS``
steps (the dataset format's shortest trial), it is written by the :class:`~.recording.Recorder`
with the drive's record under the metadata key ``drive`` (:meth:`DriveSession.drive_record`).

Server messages (JSON objects; ``type`` first):

* ``welcome``: ``protocol``, ``mode``, ``scenario`` (geometry, ``dt``, ``speed_alert``),
  ``controls`` (:class:`~.controls.ControlLimits`), ``initial_conditions`` (index, Δv, tco, lanes,
  start states), ``planning`` (period and deadline, or null), ``limits`` (message size, seq),
  ``control_interval_s`` (how often the page sends controls), ``out`` (the folder);
* ``started``: ``trial``, ``initial_condition``, ``robot_car``, ``roles``, ``drivers``,
  ``states`` (start ``[2, 6]``), ``countdown_s``; then ``countdown`` (``seconds`` left) and ``go``;
* ``state``: ``step``, ``t`` (s), ``cars`` (``[2, 6]``: ``[x, y, xd, yd, xdd, ydd]``), ``planner``
  (``plans``, ``late``, ``latency_s``) in robot mode;
* ``plan``: ``step`` (made at), ``actions``, ``robot`` (``[15, 2]`` positions), ``humans``
  (``[k, 15, 2]`` sampled human futures), ``latency_s``, ``futures``;
* ``ended``: ``trial``, ``reason``, ``steps``, ``metrics``, ``file`` (null when not recorded) and
  ``note``;
* ``error``: ``error`` (one line), ``for`` (the refused message's type when known).
"""

from __future__ import annotations

import asyncio
import json
import logging
import math
import time
from dataclasses import dataclass, field
from datetime import datetime, timezone
from typing import Awaitable, Callable

import numpy as np

from .. import __version__
from ..planning.mpc import NonBlockingMPCPolicy
from ..scenario import (CAR_LENGTH, CAR_WIDTH, COLLISION_DX, COLLISION_DY, CUTOFF_X, DT, LANE_CENTRE_Y,
                        LANE_DIVIDER_Y, MIN_TRIAL_STEPS, RECORD_END_X, REPLAN_PERIOD_S, ROAD_END_X, ROAD_Y_MAX,
                        ROAD_Y_MIN, SPEED_ALERT, START_X, study_initial_conditions)
from ..sim.metrics import latency_summary
from .controls import ControlLimits
from .options import COUNTDOWN_S, MODES, PLAN_DEADLINE_S
from .person import PersonAgent
from .protocol import (MAX_MESSAGE_BYTES, MAX_SEQ, PROTOCOL_VERSION, Abort, ControlsMessage, ProtocolError, Start,
                       parse)
from .recording import Recorder
from .trial import Trial, TrialSetup

log = logging.getLogger("trafficweaving.drive")

CONTROL_INTERVAL_S = 0.05
"""How often the page sends each car's controls while a trial runs, s (20 per second)."""
PLAN_FUTURES_SHOWN = 16
"""Sampled human futures of each plan sent to the page."""
OUTBOX_STATE_BACKLOG = 8
"""``state`` messages are dropped while this many messages wait to be sent (a page that does not
read must not make the server queue without bound; other messages are never dropped)."""


@dataclass(frozen=True)
class DriveConfig:
    """A drive server's settings: ``mode`` (:data:`~.options.MODES`), the countdown before a trial
    (whole seconds, 0 for none), the person's control ``limits``, and the robot's human ``model``
    spec, its planning ``deadline`` (s) and torch ``threads`` (None: the server's choice)."""

    mode: str = "robot"
    countdown_s: int = COUNTDOWN_S
    limits: ControlLimits = field(default_factory=ControlLimits)
    model: str = "default"
    deadline: float = PLAN_DEADLINE_S
    threads: int | None = None

    def __post_init__(self):
        if self.mode not in MODES:
            raise ValueError(f"mode must be one of {', '.join(MODES)}, got {self.mode!r}")


def welcome(config: DriveConfig, out: str) -> dict:
    """The ``welcome`` message: everything the page draws and checks comes from here."""
    ics = study_initial_conditions()
    return {
        "type": "welcome",
        "protocol": PROTOCOL_VERSION,
        "mode": config.mode,
        "scenario": {"dt": DT, "lane_centre_y": LANE_CENTRE_Y, "lane_divider_y": LANE_DIVIDER_Y,
                     "road_y_min": ROAD_Y_MIN, "road_y_max": ROAD_Y_MAX, "car_length": CAR_LENGTH,
                     "car_width": CAR_WIDTH, "road_end_x": ROAD_END_X, "cutoff_x": CUTOFF_X,
                     "record_end_x": RECORD_END_X, "start_x": START_X, "speed_alert": SPEED_ALERT,
                     "collision_dx": COLLISION_DX, "collision_dy": COLLISION_DY},
        "controls": config.limits.as_dict(),
        "initial_conditions": [{"index": k, "dv_ab": ic.dv_ab, "dv": ic.dv_left_minus_right + 0.0, "tco": ic.tco,
                                "lanes": [ic.lane_a, ic.lane_b], "states": ic.start_states().tolist()}
                               for k, ic in enumerate(ics)],
        "planning": None if config.mode != "robot" else {"period_s": REPLAN_PERIOD_S,
                                                         "deadline_s": config.deadline},
        "limits": {"max_message_bytes": MAX_MESSAGE_BYTES, "max_seq": MAX_SEQ},
        "control_interval_s": CONTROL_INTERVAL_S,
        "out": out,
    }


def period_summary(starts: list[float]) -> dict:
    """``steps``, ``mean_s``, ``p99_s``, ``max_s`` of the periods between consecutive step starts
    ``starts`` (s; None without two steps)."""
    periods = np.diff(np.asarray(starts, dtype=float))
    if not len(periods):
        return {"steps": len(starts), "mean_s": None, "p99_s": None, "max_s": None}
    return {"steps": len(starts), "mean_s": float(periods.mean()), "p99_s": float(np.percentile(periods, 99)),
            "max_s": float(periods.max())}


class DriveSession:
    """The trials of one page (module docstring). ``send`` delivers a message's JSON text to the
    page (a coroutine; it may raise once the page is gone); ``robot`` is the planner agent shared by the
    server's sessions (one session drives at a time), None in human–human mode."""

    def __init__(self, send: Callable[[str], Awaitable[None]], config: DriveConfig, recorder: Recorder,
                 robot: NonBlockingMPCPolicy | None):
        if (robot is None) != (config.mode != "robot"):
            raise ValueError("a robot agent is needed in robot mode, and only there")
        self.send, self.config, self.recorder, self.robot = send, config, recorder, robot
        self.outbox: asyncio.Queue[dict] = asyncio.Queue()
        self.sender: asyncio.Task | None = None
        self.trial: Trial | None = None
        self.runner: asyncio.Task | None = None
        self.stopping = asyncio.Event()
        self.last_seq: dict[int, int] = {}
        self.last_number = 0
        self.step_starts: list[float] = []
        self.plans_sent = 0
        self.started_at = ""

    # ------------------------------------------------------------------ messages to the page
    async def open(self) -> None:
        """Start sending; greet the page."""
        self.sender = asyncio.create_task(self._send_loop())
        self.post(welcome(self.config, str(self.recorder.folder)))

    def post(self, message: dict, droppable: bool = False) -> None:
        """Queue ``message`` for the page (``droppable``: skipped while the page lags behind)."""
        if droppable and self.outbox.qsize() >= OUTBOX_STATE_BACKLOG:
            return
        self.outbox.put_nowait(message)

    async def _send_loop(self) -> None:
        while True:
            text = json.dumps(_finite(await self.outbox.get()), allow_nan=False)
            try:
                await self.send(text)
            except Exception:  # the page is gone: the receive side ends the session
                return

    # ------------------------------------------------------------------ messages from the page
    async def receive(self, text: str | bytes | None) -> None:
        """Handle one message from the page; a refused one is answered with an ``error``."""
        try:
            message = parse(text)
            if isinstance(message, Start):
                self._start(message)
            elif isinstance(message, ControlsMessage):
                self._controls(message)
            elif isinstance(message, Abort):
                if not self._running() or self.trial.end_reason is not None:
                    raise ProtocolError("abort without a running trial (send start first)", "abort")
                self.trial.stop("aborted")
                self.stopping.set()
        except ProtocolError as exc:
            self.post({"type": "error", "error": str(exc), "for": exc.kind})

    def _running(self) -> bool:
        return self.runner is not None and not self.runner.done()

    def _controls(self, message: ControlsMessage) -> None:
        if self.trial is None:
            raise ProtocolError("controls without a running trial (send start first)", "controls")
        if self.trial.end_reason is not None:
            return  # sent before the page learnt that the trial had ended: ignored
        agent = self.trial.agents[message.car]
        if not isinstance(agent, PersonAgent):
            raise ProtocolError(f"car {message.car} is the robot's (expected the car a person drives)", "controls")
        last = self.last_seq.get(message.car, -1)
        if message.seq <= last:
            raise ProtocolError(f"seq {message.seq} out of order for car {message.car} (expected more than {last})",
                                "controls")
        self.last_seq[message.car] = message.seq
        agent.controls = message.controls

    def _start(self, message: Start) -> None:
        if self._running():
            raise ProtocolError("a trial is running (send abort first, or wait for it to end)", "start")
        robot_mode = self.config.mode == "robot"
        if not robot_mode and message.robot_car is not None:
            raise ProtocolError("robot_car must be null in human-human mode (no robot drives)", "start")
        seed = int(np.random.SeedSequence().entropy % 2**32)
        rng = np.random.default_rng(seed)
        ic = int(rng.integers(len(study_initial_conditions())))
        robot_car = int(rng.integers(2))
        ic = ic if message.initial_condition is None else message.initial_condition
        robot_car = (robot_car if message.robot_car is None else message.robot_car) if robot_mode else None
        people = [car for car in (0, 1) if car != robot_car]
        ids = message.drivers if message.drivers is not None else (None,) * len(people)
        if len(ids) != len(people):
            raise ProtocolError(f"drivers must list {len(people)} id(s) in {self.config.mode} mode (one per person "
                                f"driving), got {len(ids)}", "start")
        drivers = [-1, -1]
        for car, driver in zip(people, ids):
            drivers[car] = -1 if driver is None else driver
        drivers = tuple(drivers)
        setup = TrialSetup(self.config.mode, ic, robot_car, drivers, seed)
        agents = tuple(self.robot if car == robot_car else PersonAgent(self.config.limits) for car in (0, 1))
        number = max(self.recorder.next_number(), self.last_number + 1)
        self.last_number = number
        self.trial = Trial(number, setup, agents)
        self.last_seq, self.step_starts, self.plans_sent = {}, [], 0
        self.started_at = datetime.now(timezone.utc).isoformat(timespec="seconds")
        self.stopping = asyncio.Event()
        self.post({"type": "started", "trial": number, "initial_condition": setup.initial_condition_record(),
                   "robot_car": robot_car, "roles": list(setup.roles), "drivers": list(drivers),
                   "states": self.trial.start.tolist(), "countdown_s": self.config.countdown_s})
        self.runner = asyncio.create_task(self._run(self.trial))

    # ------------------------------------------------------------------ the trial loop
    async def _pause(self, seconds: float) -> None:
        """Sleep ``seconds`` or until the trial is stopped."""
        try:
            await asyncio.wait_for(self.stopping.wait(), max(seconds, 0.0))
        except asyncio.TimeoutError:
            pass

    async def _run(self, trial: Trial) -> None:
        try:
            for left in range(self.config.countdown_s, 0, -1):
                if trial.end_reason is not None:
                    break
                self.post({"type": "countdown", "seconds": left})
                await self._pause(1.0)
            if trial.end_reason is None:
                self.post({"type": "go"})
            loop = asyncio.get_running_loop()
            next_tick = loop.time()
            while trial.end_reason is None:
                self.step_starts.append(time.perf_counter())
                trial.step()
                self._post_progress(trial)
                next_tick += DT
                delay = next_tick - loop.time()
                if delay < 0:  # late: restart the schedule from now instead of hurrying
                    next_tick, delay = loop.time(), 0.0
                await self._pause(delay)
        except asyncio.CancelledError:  # the server is shutting down
            trial.stop("disconnected")
            raise
        except Exception:
            log.exception("trial %d failed", trial.number)
            trial.stop("server_error")
        finally:
            await asyncio.shield(self._finish(trial))

    def _post_progress(self, trial: Trial) -> None:
        """The new ``state`` and any new ``plan`` messages."""
        state = {"type": "state", "step": trial.step_index, "t": round(trial.step_index * DT, 3),
                 "cars": trial.states[:, -1].tolist()}
        if self.robot is not None:
            latencies = self.robot.latencies
            state["planner"] = {"plans": len(self.robot.plans), "late": len(self.robot.late_steps),
                                "latency_s": latencies[-1] if latencies else None}
            for made, plan in zip(self.robot.plan_steps[self.plans_sent:], self.robot.plans[self.plans_sent:]):
                self.post({"type": "plan", "step": made, "actions": [int(a) for a in plan.actions],
                           "robot": plan.robot[:, :2].tolist(),
                           "humans": plan.human[:PLAN_FUTURES_SHOWN, :, :2].tolist(),
                           "latency_s": plan.seconds, "futures": plan.futures})
            self.plans_sent = len(self.robot.plans)
        self.post(state, droppable=True)

    async def _finish(self, trial: Trial) -> None:
        """Record the ended trial (when long enough) and tell the page."""
        steps = trial.step_index + 1
        metrics = trial.metrics() if steps > 1 else None
        path, note = None, ""
        if trial.recordable:
            try:
                record = trial.trial_set({"drive": self.drive_record(trial, metrics)})
                path = await asyncio.to_thread(self.recorder.write, record, trial.number)
                note = f"recorded in {path}"
            except Exception as exc:
                log.exception("trial %d could not be written", trial.number)
                note = f"not recorded: {exc}"
        else:
            note = (f"not recorded: {steps} steps (the dataset format needs at least {MIN_TRIAL_STEPS}, "
                    f"{MIN_TRIAL_STEPS * DT:g} s)")
        log.info("trial %d ended (%s) after %d steps; %s", trial.number, trial.end_reason, steps, note)
        self.post({"type": "ended", "trial": trial.number, "reason": trial.end_reason, "steps": steps,
                   "metrics": metrics, "file": None if path is None else str(path), "note": note})

    def drive_record(self, trial: Trial, metrics: dict | None) -> dict:
        """The drive's record stored with the trial (metadata key ``drive``): ``trial``,
        ``mode``, ``started_at`` (UTC), ``seed``, ``initial_condition``, ``robot_car``, ``roles``,
        ``drivers``, ``reason`` (why it ended), ``metrics``, ``step_period`` (:func:`period_summary`)
        and ``step_periods_s`` (the wall-clock seconds between consecutive steps),
        ``controls`` (the limits and each person's controls per step: ``[throttle, brake, steer]``
        used for the accelerations of step k+1), ``planner`` (robot mode: ``model``,
        ``deadline_s``, ``threads``, ``plans`` (step made at, actions, seconds, futures),
        ``latencies_s`` of every finished plan and their summary, ``late_windows``: the window
        starts whose plan was late) and ``version``."""
        setup = trial.setup
        controls_log = {str(car): [c.as_list() for c in agent.log]
                        for car, agent in enumerate(trial.agents) if isinstance(agent, PersonAgent)}
        record = {
            "trial": trial.number, "mode": setup.mode, "started_at": self.started_at, "seed": setup.seed,
            "initial_condition": setup.initial_condition_record(), "robot_car": setup.robot_car,
            "roles": list(setup.roles), "drivers": list(setup.drivers), "reason": trial.end_reason,
            "metrics": metrics, "step_period": period_summary(self.step_starts),
            "step_periods_s": np.diff(self.step_starts).tolist(),
            "controls": {"limits": self.config.limits.as_dict(), "log": controls_log},
            "version": __version__,
        }
        if self.robot is not None:
            robot = self.robot
            record["planner"] = {
                "model": self.config.model, "deadline_s": self.config.deadline, "threads": self.config.threads,
                "plans": [{"step": made, "actions": [int(a) for a in plan.actions], "seconds": plan.seconds,
                           "futures": plan.futures} for made, plan in zip(robot.plan_steps, robot.plans)],
                "latencies_s": list(robot.latencies), "latency": latency_summary(robot.latencies),
                "late_windows": list(robot.late_steps),
            }
        return _finite(record)

    # ------------------------------------------------------------------ the end
    async def close(self, reason: str = "disconnected") -> None:
        """End the session: a running trial ends for ``reason`` and is recorded; then stop sending."""
        if self._running():
            self.trial.stop(reason)
            self.stopping.set()
            await self.runner
        if self.sender is not None:
            while not self.outbox.empty() and not self.sender.done():
                await asyncio.sleep(0.01)
            self.sender.cancel()


def _finite(value):
    """``value`` with every non-finite float as None (JSON has no NaN or Infinity)."""
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_finite(v) for v in value]
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value
