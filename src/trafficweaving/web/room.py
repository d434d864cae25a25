"""A room: the pages that drive one trial together, the protocol's state machine and the
real-time trial loop.

A ``robot`` room is one page against the planner; the server's one planner is shared by
every robot room through the :class:`PlannerQueue` (a trial waits its turn, and the page is told
its place in the queue). A ``human-human`` room has two seats: the page that created it
(seat 0) and the page that joined with its link (seat 1), each driving one car; the study
protocol (:mod:`.study`) picks the initial conditions and swaps the cars every round.

A room answers its pages' messages: ``start`` begins a :class:`~.trial.Trial`
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

The messages both ways, their fields and when each is sent: :mod:`.protocol`.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections import deque
from dataclasses import dataclass, field
from datetime import datetime, timezone
from typing import Awaitable, Callable

import numpy as np

from .. import __version__
from ..planning.mpc import NonBlockingMPCPolicy
from ..scenario import DT, MIN_TRIAL_STEPS, study_initial_conditions
from ..sim.metrics import latency_summary
from . import protocol
from .controls import ControlLimits
from .options import COUNTDOWN_S, MAX_ROOMS, PLAN_DEADLINE_S, ROOM_KINDS
from .person import PersonAgent
from .protocol import Abort, ControlsMessage, Participant, ProtocolError, Start
from .recording import Recorder
from .study import StudySchedule
from .trial import COMPLETED, Trial, TrialSetup

log = logging.getLogger("trafficweaving.drive")

OUTBOX_STATE_BACKLOG = 8
"""``state`` messages are dropped while this many messages wait to be sent to a page (a page that
does not read must not make the server queue without bound)."""
OUTBOX_LIMIT = 256
"""Most messages waiting to be sent to a page; one more drops the page (it does not read what it
is sent, e.g. while it floods the server with refused messages)."""


@dataclass(frozen=True)
class DriveConfig:
    """A drive server's settings: ``mode``, the kind of its rooms (:data:`~.options.ROOM_KINDS`),
    the countdown before a trial (whole seconds, 0 for none), the person's control ``limits``, the
    robot's human ``model`` spec, its planner's real-time ``deadline`` (s) and torch ``threads``
    (None: the server's choice), and the most rooms open at once (``max_rooms``)."""

    mode: str = "robot"
    countdown_s: int = COUNTDOWN_S
    limits: ControlLimits = field(default_factory=ControlLimits)
    model: str = "default"
    deadline: float = PLAN_DEADLINE_S
    threads: int | None = None
    max_rooms: int = MAX_ROOMS

    def __post_init__(self):
        if self.mode not in ROOM_KINDS:
            raise ValueError(f"mode must be one of {', '.join(ROOM_KINDS)}, got {self.mode!r}")


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
            room.broadcast(protocol.queued(place))


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
        config = self.config
        member.post(protocol.encode(protocol.welcome(config.mode, config.limits.as_dict(), config.deadline,
                                                     str(self.recorder.folder), member.seat)))
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
        text = protocol.encode(message)
        for member in self.seats:
            if member is not None:
                member.post(text, droppable)

    def _post_room(self) -> None:
        """The ``room`` message (human–human rooms: a robot room's one page needs none)."""
        if self.study is None:
            return
        self.broadcast(protocol.room(self.number, self.session, self.join_path,
                                     [member is not None for member in self.seats], self.participants,
                                     self.study.progress()))

    # ------------------------------------------------------------------ messages from a page
    async def receive(self, member: Member, text: str | bytes | None) -> None:
        """Handle one message from ``member``'s page; a refused one is answered with an ``error``."""
        try:
            message = protocol.parse(text)
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
            member.post(protocol.encode(protocol.error(str(exc), exc.kind)))

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
            self.broadcast(protocol.ended(None, "aborted", 0, None, None, "left the planner's queue before driving"))
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
        ic, states = setup.initial_condition_record(), trial.start.tolist()
        round_ = self.study.round if self.on_schedule else None
        position = self.study.position if self.on_schedule else None
        for member in self.seats:
            if member is not None:
                cars = [car for car in (0, 1) if self.car_seats[car] == member.seat]
                member.post(protocol.encode(protocol.started(
                    trial.number, ic, setup.robot_car, list(setup.roles), list(setup.drivers), round_, position,
                    states, self.config.countdown_s, cars)))

    async def _drive(self, trial: Trial) -> None:
        try:
            for left in range(self.config.countdown_s, 0, -1):
                if trial.end_reason is not None:
                    break
                self.broadcast(protocol.countdown(left))
                await self._pause(1.0)
            if trial.end_reason is None:
                self.broadcast(protocol.go())
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
        robot, counts = self.robot, None
        if robot is not None:
            counts = protocol.planner_counts(len(robot.plans), len(robot.late_steps),
                                             robot.latencies[-1] if robot.latencies else None)
            for made, plan in zip(robot.plan_steps[self.plans_sent:], robot.plans[self.plans_sent:]):
                self.broadcast(protocol.plan(made, plan.actions, plan.robot, plan.human, plan.seconds, plan.futures))
            self.plans_sent = len(robot.plans)
        self.broadcast(protocol.state(trial.step_index, trial.states[:, -1], counts), droppable=True)

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
        self.broadcast(protocol.ended(trial.number, trial.end_reason, steps, metrics,
                                      None if path is None else str(path), note))

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
        return protocol.finite(record)

