"""A room: the pages that drive one trial together, the protocol's state machine and the
real-time trial loop.

In ``robot`` mode a room is one page against the planner; the server's one planner is shared by
every robot room through the :class:`PlannerQueue` (a trial waits its turn, and the page is told
its place in the queue). In ``human-human`` mode a room has two seats: the page that created it
(seat 0) and the page that joined with its link (seat 1), each driving one car; the study
protocol (:mod:`.study`) picks the initial conditions and swaps the cars every round.

A room answers its pages' messages (:mod:`.protocol`): ``start`` begins a :class:`~.trial.Trial`
(countdown, then one world step every 0.1 s of wall time: the server owns time), ``controls``
update the person's :class:`~.person.PersonAgent` (a late or missing message leaves the car on
its driver's last controls; those that arrive after the trial ended are ignored; before the
first trial they are refused), ``abort`` ends the trial, ``participant`` sets a page's person.
The loop never waits for the robot: its planner runs in a background thread
(:class:`~trafficweaving.planning.mpc.NonBlockingMPCPolicy`); a step that starts late does not
make the next ones hurry (the schedule restarts from it). A page that leaves ends the running
trial (``disconnected``).

When a trial ends its outcome and metrics are sent to every page (``ended``) and, if it lasted at
least ``MIN_TRIAL_STEPS`` steps (the dataset format's shortest trial), it is written atomically by
the :class:`~.recording.Recorder` with the drive's record under the metadata key ``drive``
(:meth:`Room.drive_record`).

Server messages (JSON objects; ``type`` first):

* ``welcome``: ``protocol``, ``mode``, ``scenario`` (geometry, ``dt``, ``speed_alert``),
  ``controls`` (:class:`~.controls.ControlLimits`), ``initial_conditions`` (index, Δv, tco, lanes,
  start states), ``planning`` (period and deadline, or null), ``limits`` (message size, seq),
  ``control_interval_s`` (how often the page sends controls), ``out`` (the folder), ``seat`` (this
  page's);
* ``room`` (human–human rooms, whenever a page comes or goes, a participant id is set or a trial
  ends): ``room`` (its number), ``session``, ``join`` (the join link's path and query, holding
  the room's token), ``seats`` (whether each is taken), ``participants`` (per seat), ``study``
  (:meth:`~.study.StudySchedule.progress`);
* ``queued``: ``position`` (1: next) while a robot room waits for the planner;
* ``started``: ``trial``, ``initial_condition``, ``robot_car``, ``roles``, ``drivers``, ``cars``
  (the cars this page drives), ``round`` and ``position`` (null off the protocol), ``states``
  (start ``[2, 6]``), ``countdown_s``; then ``countdown`` (``seconds`` left) and ``go``;
* ``state``: ``step``, ``t`` (s), ``cars`` (``[2, 6]``: ``[x, y, xd, yd, xdd, ydd]``), ``planner``
  (``plans``, ``late``, ``latency_s``) in robot mode;
* ``plan``: ``step`` (made at), ``actions``, ``robot`` (``[15, 2]`` positions), ``humans``
  (``[k, 15, 2]`` sampled human futures), ``latency_s``, ``futures``;
* ``ended``: ``trial`` (null when the page left the queue before driving), ``reason``, ``steps``,
  ``metrics``, ``file`` (null when not recorded) and ``note``;
* ``error``: ``error`` (one line), ``for`` (the refused message's type when known).
"""

from __future__ import annotations

import asyncio
import json
import logging
import math
import time
from collections import deque
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
from .options import COUNTDOWN_S, MAX_ROOMS, MODES, PLAN_DEADLINE_S
from .person import PersonAgent
from .protocol import (MAX_MESSAGE_BYTES, MAX_SEQ, PROTOCOL_VERSION, Abort, ControlsMessage, Participant,
                       ProtocolError, Start, parse)
from .recording import Recorder
from .study import StudySchedule
from .trial import COMPLETED, Trial, TrialSetup

log = logging.getLogger("trafficweaving.drive")

CONTROL_INTERVAL_S = 0.05
"""How often the page sends each car's controls while a trial runs, s (20 per second)."""
PLAN_FUTURES_SHOWN = 16
"""Sampled human futures of each plan sent to the page."""
OUTBOX_STATE_BACKLOG = 8
"""``state`` messages are dropped while this many messages wait to be sent to a page (a page that
does not read must not make the server queue without bound)."""
OUTBOX_LIMIT = 256
"""Most messages waiting to be sent to a page; one more drops the page (it does not read what it
is sent, e.g. while it floods the server with refused messages)."""


@dataclass(frozen=True)
class DriveConfig:
    """A drive server's settings: ``mode`` (:data:`~.options.MODES`), the countdown before a trial
    (whole seconds, 0 for none), the person's control ``limits``, the robot's human ``model``
    spec, its planning ``deadline`` (s) and torch ``threads`` (None: the server's choice), and the
    most rooms open at once (``max_rooms``)."""

    mode: str = "robot"
    countdown_s: int = COUNTDOWN_S
    limits: ControlLimits = field(default_factory=ControlLimits)
    model: str = "default"
    deadline: float = PLAN_DEADLINE_S
    threads: int | None = None
    max_rooms: int = MAX_ROOMS

    def __post_init__(self):
        if self.mode not in MODES:
            raise ValueError(f"mode must be one of {', '.join(MODES)}, got {self.mode!r}")


def welcome(config: DriveConfig, out: str, seat: int) -> dict:
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
        "seat": seat,
    }


def period_summary(starts: list[float]) -> dict:
    """``steps``, ``mean_s``, ``p99_s``, ``max_s`` of the periods between consecutive step starts
    ``starts`` (s; None without two steps)."""
    periods = np.diff(np.asarray(starts, dtype=float))
    if not len(periods):
        return {"steps": len(starts), "mean_s": None, "p99_s": None, "max_s": None}
    return {"steps": len(starts), "mean_s": float(periods.mean()), "p99_s": float(np.percentile(periods, 99)),
            "max_s": float(periods.max())}


class Member:
    """A page in a room: its ``seat`` and the texts waiting to be sent to it (``send`` delivers
    one; a coroutine that may raise once the page is gone). A page with :data:`OUTBOX_LIMIT`
    texts waiting is dropped: its queue emptied, ``drop`` called (it closes the connection, so
    that the page leaves its room), and nothing more queued."""

    def __init__(self, send: Callable[[str], Awaitable[None]], drop: Callable[[], None] | None = None):
        self.send, self.drop = send, drop
        self.seat = -1
        self.outbox: asyncio.Queue[str] = asyncio.Queue()
        self.sender: asyncio.Task | None = None
        self.dropped = False

    def open(self) -> None:
        self.sender = asyncio.create_task(self._send_loop())

    def post(self, text: str, droppable: bool = False) -> None:
        """Queue ``text`` (``droppable``: skipped while the page lags behind)."""
        if self.dropped or (droppable and self.outbox.qsize() >= OUTBOX_STATE_BACKLOG):
            return
        if self.outbox.qsize() >= OUTBOX_LIMIT:
            self.dropped = True
            self.outbox = asyncio.Queue()
            if self.sender is not None:
                self.sender.cancel()
            if self.drop is not None:
                self.drop()
            return
        self.outbox.put_nowait(text)

    async def _send_loop(self) -> None:
        while True:
            text = await self.outbox.get()
            try:
                await self.send(text)
            except Exception:  # the page is gone: the receive side makes it leave
                return

    async def close(self) -> None:
        """Send what is queued (while the page takes it), then stop."""
        if self.sender is not None:
            while not self.outbox.empty() and not self.sender.done():
                await asyncio.sleep(0.01)
            self.sender.cancel()


class PlannerQueue:
    """The server's one planner, lent to one robot room at a time, first come first served; the
    rooms waiting are told their place (``queued``) whenever it changes."""

    def __init__(self):
        self.holder: Room | None = None
        self.waiting: deque[tuple[Room, asyncio.Future]] = deque()

    async def acquire(self, room: "Room", stop: asyncio.Event) -> bool:
        """Wait for the planner; False (and not holding it) when ``stop`` is set first."""
        if self.holder is None and not self.waiting:
            self.holder = room
            return True
        turn = asyncio.get_running_loop().create_future()
        self.waiting.append((room, turn))
        self._tell_places()
        stopped = asyncio.ensure_future(stop.wait())
        try:
            await asyncio.wait({turn, stopped}, return_when=asyncio.FIRST_COMPLETED)
        except asyncio.CancelledError:
            self._withdraw(room, turn)
            raise
        finally:
            stopped.cancel()
        if stop.is_set():
            self._withdraw(room, turn)
            return False
        return True

    def _withdraw(self, room: "Room", turn: asyncio.Future) -> None:
        if turn.done() and not turn.cancelled():  # it had become this room's turn
            self.release(room)
            return
        turn.cancel()
        self.waiting = deque(entry for entry in self.waiting if entry[1] is not turn)
        self._tell_places()

    def release(self, room: "Room") -> None:
        """``room`` is done with the planner: the next room waiting gets it."""
        if self.holder is not room:
            return
        self.holder = None
        while self.waiting:
            next_room, turn = self.waiting.popleft()
            if not turn.done():
                self.holder = next_room
                turn.set_result(None)
                break
        self._tell_places()

    def _tell_places(self) -> None:
        for place, (room, _) in enumerate(self.waiting, start=1):
            room.broadcast({"type": "queued", "position": place})


class Room:
    """The pages and trials of one room (module docstring): number ``number``, joined with
    ``token`` (human–human), recording to ``recorder``; ``robot`` is the planner agent shared by
    the server's robot rooms through ``planner`` (both None in human–human mode). The protocol's
    order is drawn from a fresh seed per room (:class:`~.study.StudySchedule`)."""

    def __init__(self, number: int, token: str, session: str, config: DriveConfig, recorder: Recorder,
                 robot: NonBlockingMPCPolicy | None = None, planner: PlannerQueue | None = None):
        robot_mode = config.mode == "robot"
        if (robot is None or planner is None) == robot_mode:
            raise ValueError("a robot agent and its planner queue are needed in robot mode, and only there")
        self.number, self.token, self.session = number, token, session
        self.config, self.recorder, self.robot, self.planner = config, recorder, robot, planner
        self.seats: list[Member | None] = [None] if robot_mode else [None, None]
        self.participants: list[int | None] = [None] * len(self.seats)
        self.study = None if robot_mode else StudySchedule(int(np.random.SeedSequence().entropy % 2**32))
        self.trial: Trial | None = None
        self.runner: asyncio.Task | None = None
        self.stopping = asyncio.Event()
        self.car_seats: tuple[int | None, int | None] = (None, None)  # the seat driving each car
        self.on_schedule = False
        self.last_seq: dict[int, int] = {}
        self.step_starts: list[float] = []
        self.plans_sent = 0
        self.started_at = ""

    # ------------------------------------------------------------------ pages
    @property
    def empty(self) -> bool:
        return all(member is None for member in self.seats)

    @property
    def join_path(self) -> str | None:
        """The join link's path and query (human–human rooms), holding the room's token."""
        return None if self.study is None else f"/?room={self.number}&token={self.token}"

    def join(self, member: Member) -> bool:
        """Seat ``member`` (False when the room is full), greet it and tell every page."""
        if None not in self.seats:
            return False
        member.seat = self.seats.index(None)
        self.seats[member.seat] = member
        member.open()
        member.post(json.dumps(welcome(self.config, str(self.recorder.folder), member.seat)))
        self._post_room()
        return True

    async def leave(self, member: Member) -> None:
        """``member``'s page went away: a running trial (or a wait for the planner) ends as
        ``disconnected``; the other page is told."""
        if self._running():
            if self.trial is not None:
                self.trial.stop("disconnected")
            self.stopping.set()
            await self.runner
        self.seats[member.seat] = None
        await member.close()
        self._post_room()

    def broadcast(self, message: dict, droppable: bool = False) -> None:
        """Queue ``message`` for every page of the room (its JSON made once)."""
        text = json.dumps(_finite(message), allow_nan=False)
        for member in self.seats:
            if member is not None:
                member.post(text, droppable)

    def _post_room(self) -> None:
        """The ``room`` message (human–human rooms: a robot room's one page needs none)."""
        if self.study is None:
            return
        self.broadcast({"type": "room", "room": self.number, "session": self.session, "join": self.join_path,
                        "seats": [member is not None for member in self.seats], "participants": self.participants,
                        "study": self.study.progress()})

    # ------------------------------------------------------------------ messages from a page
    async def receive(self, member: Member, text: str | bytes | None) -> None:
        """Handle one message from ``member``'s page; a refused one is answered with an ``error``."""
        try:
            message = parse(text)
            if isinstance(message, Start):
                self._start(message)
            elif isinstance(message, ControlsMessage):
                self._controls(member, message)
            elif isinstance(message, Abort):
                if not self._running() or (self.trial is not None and self.trial.end_reason is not None):
                    raise ProtocolError("abort without a running trial (send start first)", "abort")
                if self.trial is not None:
                    self.trial.stop("aborted")
                self.stopping.set()
            elif isinstance(message, Participant):
                self._participant(member, message)
        except ProtocolError as exc:
            member.post(json.dumps({"type": "error", "error": str(exc), "for": exc.kind}))

    def _running(self) -> bool:
        return self.runner is not None and not self.runner.done()

    def _participant(self, member: Member, message: Participant) -> None:
        if self.study is None:
            raise ProtocolError("participant is for human-human rooms (in robot mode, send drivers with start)",
                                "participant")
        if self._running():
            raise ProtocolError("a trial is running (set the participant between trials)", "participant")
        self.participants[member.seat] = message.driver
        self._post_room()

    def _controls(self, member: Member, message: ControlsMessage) -> None:
        if self.trial is None:
            raise ProtocolError("controls without a running trial (send start first)", "controls")
        if self.trial.end_reason is not None:
            return  # sent before the page learnt that the trial had ended: ignored
        agent = self.trial.agents[message.car]
        if not isinstance(agent, PersonAgent):
            raise ProtocolError(f"car {message.car} is the robot's (expected the car a person drives)", "controls")
        if self.car_seats[message.car] != member.seat:
            raise ProtocolError(f"car {message.car} is driven by the other page (expected car "
                                f"{self.car_seats.index(member.seat)})", "controls")
        last = self.last_seq.get(message.car, -1)
        if message.seq <= last:
            raise ProtocolError(f"seq {message.seq} out of order for car {message.car} (expected more than {last})",
                                "controls")
        self.last_seq[message.car] = message.seq
        agent.controls = message.controls

    def _start(self, message: Start) -> None:
        if self._running():
            raise ProtocolError("a trial is running (send abort first, or wait for it to end)", "start")
        seed = int(np.random.SeedSequence().entropy % 2**32)
        rng = np.random.default_rng(seed)
        ic = int(rng.integers(len(study_initial_conditions())))
        if self.study is None:
            robot_car = int(rng.integers(2)) if message.robot_car is None else message.robot_car
            ids = message.drivers if message.drivers is not None else (None,)
            if len(ids) != 1:
                raise ProtocolError(f"drivers must list 1 id(s) in robot mode (one per person driving), got {len(ids)}",
                                    "start")
            self.car_seats = (None, 0) if robot_car == 0 else (0, None)
            drivers = tuple(-1 if car == robot_car or ids[0] is None else ids[0] for car in (0, 1))
            self.on_schedule = False
        else:
            if message.robot_car is not None:
                raise ProtocolError("robot_car must be null in human-human mode (no robot drives)", "start")
            if message.drivers is not None:
                raise ProtocolError("drivers are not sent with start in a human-human room (each page sends its "
                                    "participant id)", "start")
            if None in self.seats:
                raise ProtocolError("the other driver has not joined (share the room's join link)", "start")
            robot_car = None
            self.on_schedule = message.initial_condition is None
            ic = self.study.next_initial_condition() if self.on_schedule else ic
            self.car_seats = self.study.seats()
            drivers = tuple(-1 if (p := self.participants[seat]) is None else p for seat in self.car_seats)
        ic = ic if message.initial_condition is None else message.initial_condition
        setup = TrialSetup(self.config.mode, ic, robot_car, drivers, seed)
        self.trial, self.stopping = None, asyncio.Event()
        self.runner = asyncio.create_task(self._run(setup))

    # ------------------------------------------------------------------ the trial loop
    async def _pause(self, seconds: float) -> None:
        """Sleep ``seconds`` or until the trial is stopped."""
        try:
            await asyncio.wait_for(self.stopping.wait(), max(seconds, 0.0))
        except asyncio.TimeoutError:
            pass

    async def _run(self, setup: TrialSetup) -> None:
        """One trial: the planner's turn (robot mode), the countdown, the steps, the record."""
        if self.planner is not None and not await self.planner.acquire(self, self.stopping):
            self.broadcast({"type": "ended", "trial": None, "reason": "aborted", "steps": 0, "metrics": None,
                            "file": None, "note": "left the planner's queue before driving"})
            return
        try:
            agents = tuple(self.robot if car == setup.robot_car else PersonAgent(self.config.limits) for car in (0, 1))
            trial = self.trial = Trial(self.recorder.reserve(), setup, agents)
            self.last_seq, self.step_starts, self.plans_sent = {}, [], 0
            self.started_at = datetime.now(timezone.utc).isoformat(timespec="seconds")
            self._post_started(trial)
            await self._drive(trial)
        finally:
            if self.planner is not None:
                self.planner.release(self)
            self._post_room()

    def _post_started(self, trial: Trial) -> None:
        setup = trial.setup
        message = {"type": "started", "trial": trial.number, "initial_condition": setup.initial_condition_record(),
                   "robot_car": setup.robot_car, "roles": list(setup.roles), "drivers": list(setup.drivers),
                   "round": self.study.round if self.on_schedule else None,
                   "position": self.study.position if self.on_schedule else None,
                   "states": trial.start.tolist(), "countdown_s": self.config.countdown_s}
        for member in self.seats:
            if member is not None:
                cars = [car for car in (0, 1) if self.car_seats[car] == member.seat]
                member.post(json.dumps({**message, "cars": cars}))

    async def _drive(self, trial: Trial) -> None:
        try:
            for left in range(self.config.countdown_s, 0, -1):
                if trial.end_reason is not None:
                    break
                self.broadcast({"type": "countdown", "seconds": left})
                await self._pause(1.0)
            if trial.end_reason is None:
                self.broadcast({"type": "go"})
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
                self.broadcast({"type": "plan", "step": made, "actions": [int(a) for a in plan.actions],
                                "robot": plan.robot[:, :2].tolist(),
                                "humans": plan.human[:PLAN_FUTURES_SHOWN, :, :2].tolist(),
                                "latency_s": plan.seconds, "futures": plan.futures})
            self.plans_sent = len(self.robot.plans)
        self.broadcast(state, droppable=True)

    async def _finish(self, trial: Trial) -> None:
        """Record the ended trial (when long enough), advance the protocol, and tell the pages."""
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
        if self.on_schedule and path is not None and trial.end_reason in COMPLETED:
            self.study.advance()
        log.info("trial %d ended (%s) after %d steps; %s", trial.number, trial.end_reason, steps, note)
        self.broadcast({"type": "ended", "trial": trial.number, "reason": trial.end_reason, "steps": steps,
                        "metrics": metrics, "file": None if path is None else str(path), "note": note})

    def drive_record(self, trial: Trial, metrics: dict | None) -> dict:
        """The drive's record stored with the trial (metadata key ``drive``): ``trial``,
        ``mode``, ``started_at`` (UTC), ``seed``, ``initial_condition``, ``robot_car``, ``roles``,
        ``drivers``, ``reason`` (why it ended), ``metrics``, ``room`` (``number``, ``session``,
        ``participants`` per seat, ``seats`` (the seat driving each car, null: the robot),
        ``round`` and ``position`` in the protocol, null off it), ``step_period``
        (:func:`period_summary`) and ``step_periods_s`` (the wall-clock seconds between
        consecutive steps), ``controls`` (the limits and each person's controls per step:
        ``[throttle, brake, steer]`` used for the accelerations of step k+1), ``planner`` (robot
        mode: ``model``, ``deadline_s``, ``threads``, ``plans`` (step made at, actions, seconds,
        futures), ``latencies_s`` of every finished plan and their summary, ``late_windows``: the
        window starts whose plan was late) and ``version``."""
        setup = trial.setup
        controls_log = {str(car): [c.as_list() for c in agent.log]
                        for car, agent in enumerate(trial.agents) if isinstance(agent, PersonAgent)}
        record = {
            "trial": trial.number, "mode": setup.mode, "started_at": self.started_at, "seed": setup.seed,
            "initial_condition": setup.initial_condition_record(), "robot_car": setup.robot_car,
            "roles": list(setup.roles), "drivers": list(setup.drivers), "reason": trial.end_reason,
            "metrics": metrics,
            "room": {"number": self.number, "session": self.session, "participants": list(self.participants),
                     "seats": list(self.car_seats), "round": self.study.round if self.on_schedule else None,
                     "position": self.study.position if self.on_schedule else None},
            "step_period": period_summary(self.step_starts), "step_periods_s": np.diff(self.step_starts).tolist(),
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


def _finite(value):
    """``value`` with every non-finite float as None (JSON has no NaN or Infinity)."""
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_finite(v) for v in value]
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value
