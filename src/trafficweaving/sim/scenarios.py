"""The edge-case library: scripted humans that each test one hard situation for the robot (after
nuPlan's interPlan and scenario-based testing), ``simulate --human scenario:NAME``.

A :class:`Scenario` is a scripted, partly reactive human car (a :class:`ScriptedHuman`), how its
episodes start, and what the robot must achieve: ``avoidable`` (a collision is the robot's to
avoid) and ``acceptable`` (``no collision``, or ``swap``: no collision and the robot gets across).
:data:`SCENARIOS` lists them; docs/closed_loop.md has their table.

An episode starts from :meth:`Scenario.draw` (the episode's first draws, so every robot meets the
same start): the robot as car 0, in a lane drawn uniformly, at ``x`` uniform in the scenario's
``robot_x`` and a speed uniform in :data:`ROBOT_SPEED`; the human in the other lane at the
scenario's offsets ``dx`` and ``dv`` from the robot; both on their lane centres without lateral
motion; then the scenario's own parameters (where it cuts in, how long it brakes, ...).

The human's actions: a longitudinal acceleration (its speed kept within :data:`SPEED_RANGE`) and
lane changes as minimum-jerk lateral profiles (:func:`~trafficweaving.dynamics.minimum_jerk_from`,
:data:`LANE_CHANGE_S` unless a scenario says otherwise). Outside ``simulate`` (the environment,
``generate --drivers``, ``realism``) a scripted human drives from whatever start it is given,
drawing its parameters at reset; the other car is "the robot" to it.
"""

from __future__ import annotations

import copy
from abc import ABC, abstractmethod
from dataclasses import dataclass

import numpy as np

from ..dynamics import minimum_jerk_from
from ..scenario import CAR_LENGTH, DT, LANE_CENTRE_Y, LANE_DIVIDER_Y, LANES, STATE_NAMES, lane_centre_y, lane_of

ROBOT_X = (-125.0, -110.0)
"""Where the robot starts (uniform), m: about a second later than the study's start (-145 m)."""
EARLY_ROBOT_X = (-190.0, -175.0)
"""Where the robot starts in the scenarios whose script needs more road before the cutoff, m."""
ROBOT_SPEED = (27.0, 31.0)
"""The robot's start speed (uniform), m/s, around the study's 29 m/s."""
SPEED_RANGE = (10.0, 38.0)
"""The scripted human's speed stays within this range, m/s (38: the study's speed alert)."""
LANE_CHANGE_S = 2.5
"""Duration of a scripted lane change, s (peak lateral acceleration 3.9 m/s²)."""


class LaneChanges:
    """The lateral motion of ``m`` scripted cars: each at rest or in one minimum-jerk move from
    its state when the move began to rest at a target ``y``; a new move replaces the present one."""

    def __init__(self, m: int):
        self.moving = np.zeros(m, dtype=bool)
        self.step = np.zeros(m, dtype=np.int64)  # step at which the move began
        self.y0, self.yd0, self.ydd0 = np.zeros(m), np.zeros(m), np.zeros(m)  # m, m/s, m/s²
        self.target, self.duration = np.zeros(m), np.ones(m)  # m, s

    def begin(self, which: np.ndarray, t: int, car: np.ndarray, target: np.ndarray, duration: float) -> None:
        """Start a move at step ``t`` in the episodes ``which [m]`` (bool) from the cars' states
        ``car [m, 6]`` to lateral position ``target`` (m) over ``duration`` (s)."""
        self.moving |= which
        self.step = np.where(which, t, self.step)
        for name, value in (("y0", car[:, 1]), ("yd0", car[:, 3]), ("ydd0", car[:, 5]), ("target", target),
                            ("duration", duration)):
            setattr(self, name, np.where(which, value, getattr(self, name)))

    def acceleration(self, t: int) -> np.ndarray:
        """The lateral accelerations ``[m]`` (m/s²) at step ``t + 1``."""
        s = np.clip((t + 1 - self.step) * DT / self.duration, 0.0, 1.0)
        moving = minimum_jerk_from(self.target - self.y0, s, self.duration, self.yd0, self.ydd0)
        return np.where(self.moving, moving, 0.0)


class ScriptedHuman(ABC):
    """A scenario's human for ``m`` episodes at once (the agent protocol of
    :class:`~trafficweaving.sim.world.Agent`). Subclasses script :meth:`drive`; this class keeps
    the lane changes and the speed range. Its parameters (:attr:`Scenario.parameters`, ``[m]``
    each) are bound by :meth:`start` (``simulate``) or drawn from the rng at :meth:`reset`."""

    def __init__(self, scenario: "Scenario"):
        self.scenario = scenario
        self.bound: dict[str, np.ndarray] | None = None
        self.me = 1

    def start(self, rng: np.random.Generator) -> tuple[np.ndarray, "ScriptedHuman"]:
        """One episode's start ``[2, 6]`` (:meth:`Scenario.draw`, the robot in car 0) and a copy of
        this human bound to the parameters drawn with it."""
        start, parameters = self.scenario.draw(rng, 1)
        bound = copy.copy(self)
        bound.bound = parameters
        return start[0], bound

    def reset(self, rng: np.random.Generator, start: np.ndarray, me: int) -> None:
        start = np.asarray(start, dtype=float)
        m = len(start)
        if self.bound is not None and any(len(values) != m for values in self.bound.values()):
            raise RuntimeError(f"this scripted human is bound to other episodes than the {m} it is reset with")
        self.parameters = self.bound if self.bound is not None else self.scenario.draw_parameters(rng, m)
        self.me = me
        own = start[:, me]
        self.home_y = lane_centre_y(own[:, 1])  # the lane it starts in, m
        self.away_y = np.where(lane_of(own[:, 1]) == LANES[0], LANE_CENTRE_Y[LANES[1]], LANE_CENTRE_Y[LANES[0]])
        self.lateral = LaneChanges(m)
        self.setup(m)

    def setup(self, m: int) -> None:
        """The script's own state for ``m`` episodes (none by default)."""

    def act(self, history: np.ndarray) -> np.ndarray:
        t = history.shape[2] - 1
        own, robot = history[:, self.me, -1], history[:, 1 - self.me, -1]
        xdd = self.drive(t, history, own, robot)
        low, high = SPEED_RANGE
        xdd = np.clip(xdd, (low - own[:, 2]) / DT, (high - own[:, 2]) / DT)
        return np.stack([xdd, self.lateral.acceleration(t)], axis=1)

    @abstractmethod
    def drive(self, t: int, history: np.ndarray, own: np.ndarray, robot: np.ndarray) -> np.ndarray:
        """The longitudinal accelerations ``[m]`` (m/s²) at step ``t + 1`` (lane changes begun
        through :attr:`lateral`), from both cars' ``history [m, 2, t+1, 6]`` and present states
        ``own``, ``robot`` ``[m, 6]``: each scenario's script."""

    def change_lanes(self, which: np.ndarray, t: int, own: np.ndarray, duration: float = LANE_CHANGE_S) -> None:
        """Begin the lane change into the other lane in the episodes ``which`` not changing yet."""
        self.lateral.begin(which & ~self.lateral.moving, t, own, self.away_y, duration)

    def clear(self, own: np.ndarray, robot: np.ndarray, gap: float) -> np.ndarray:
        """Whether the other lane is clear of the robot ``[m]``: more than ``gap`` (m) bumper to
        bumper between the cars, or the robot across the divider into this car's lane."""
        return (np.abs(robot[:, 0] - own[:, 0]) - CAR_LENGTH > gap) | (lane_of(robot[:, 1]) == lane_of(self.home_y))


class Mirror(ScriptedHuman):
    """Starts beside the robot at its speed and copies its longitudinal acceleration 0.3 s later
    (:attr:`DELAY_STEPS`) until ``x`` > :attr:`UNTIL_X`, then keeps its speed; it changes lanes
    once the robot has opened a :attr:`GAP` or left the lane it wants. Tests a robot whose
    every longitudinal choice is copied: it gets across only by a large change of speed (the
    copy lags), and staying in its lane is acceptable."""

    DELAY_STEPS = 3
    UNTIL_X = -50.0
    GAP = 5.0
    """Bumper-to-bumper gap at which it changes lanes beside the robot, m."""

    def drive(self, t, history, own, robot):
        copied = history[:, 1 - self.me, max(t + 1 - self.DELAY_STEPS, 0), 4]
        self.change_lanes(self.clear(own, robot, self.GAP), t, own)
        return np.where(own[:, 0] <= self.UNTIL_X, copied, 0.0)


class LateCutIn(ScriptedHuman):
    """Starts ahead in the other lane at the robot's speed, keeps its lane and speed until ``x`` ≥
    ``cut_x`` (about -55 m) and then cuts into the robot's lane in :attr:`CUT_IN_S` without
    looking. Tests braking for a car that cuts in late ahead, and taking the lane it left."""

    CUT_IN_S = 2.0
    """The cut-in's duration, s: peak lateral acceleration 6.1 m/s², a hard swerve."""

    def drive(self, t, history, own, robot):
        self.change_lanes(own[:, 0] >= self.parameters["cut_x"], t, own, self.CUT_IN_S)
        return np.zeros(len(own))


class BrakeAfterMerge(ScriptedHuman):
    """Starts ahead in the robot's goal lane and keeps it; once the robot has merged behind it
    (within :attr:`MERGED_DY` of that lane's centre, behind, before ``x`` = :attr:`ARMED_UNTIL_X`)
    it brakes at :attr:`BRAKE` for ``brake_s`` (1.0-1.5 s; not below :attr:`FLOOR`), then keeps
    its speed and changes into the other lane; a robot that never merges sees it change at
    ``fallback_x`` (-50 to -45 m, late enough to swap lanes before the cutoff). Tests the following
    distance the robot keeps after merging. Its episodes start about 65 m earlier than the others:
    the robot's lane change, the braking and the human's own lane change take about 5 s."""

    BRAKE = 8.0
    """Braking, m/s²."""
    FLOOR = 12.0
    """Speed it does not brake below, m/s."""
    MERGED_DY = 0.5
    """The robot has merged within this distance of the lane centre, m."""
    ARMED_UNTIL_X = -65.0
    """It brakes only for a robot merged before it reaches this ``x`` (m), so that it still
    changes lanes before the cutoff."""

    def setup(self, m):
        self.brake_until = np.full(m, -1)  # it brakes while t < brake_until; -1: not braked yet

    def drive(self, t, history, own, robot):
        armed = (self.brake_until < 0) & ~self.lateral.moving & (own[:, 0] < self.ARMED_UNTIL_X)
        merged = (np.abs(robot[:, 1] - self.home_y) < self.MERGED_DY) & (robot[:, 0] < own[:, 0])
        steps = np.round(self.parameters["brake_s"] / DT).astype(int)
        self.brake_until = np.where(armed & merged, t + steps, self.brake_until)
        braking = t < self.brake_until
        done = (self.brake_until >= 0) & ~braking
        self.change_lanes(done | (own[:, 0] >= self.parameters["fallback_x"]), t, own)
        return np.where(braking, np.maximum(-self.BRAKE, (self.FLOOR - own[:, 2]) / DT), 0.0)


class NeverYield(ScriptedHuman):
    """Starts beside the robot, keeps its speed and changes lanes at ``x`` ≥ ``change_x`` (uniform
    in [-85, -65] m) whatever the robot does, never braking for it. Tests a robot that must open
    a gap itself: the human overlaps the robot's lane no sooner than 2.2 s after the start."""

    def drive(self, t, history, own, robot):
        self.change_lanes(own[:, 0] >= self.parameters["change_x"], t, own)
        return np.zeros(len(own))


class Block(ScriptedHuman):
    """Starts behind in the robot's goal lane. While the robot is at most :attr:`LEAD` ahead and
    is ahead or moves towards this lane (faster than :attr:`TOWARDS` sideways), it drives (at up
    to :attr:`ACCEL` either way) to come alongside the robot; otherwise it matches the robot's
    speed. From ``x`` > :attr:`UNTIL_X` on it keeps its speed and changes lanes once clear
    (:attr:`GAP`). Tests a robot whose gap is closed on purpose: merging behind it, or
    staying, is the way."""

    LEAD = 10.0
    """A robot ahead by more than this is let go, m."""
    TOWARDS = 0.2
    """Lateral speed towards this lane that counts as moving into it, m/s."""
    ACCEL = 3.0
    """Hardest acceleration and braking while it blocks or matches the robot's speed, m/s²."""
    UNTIL_X = -40.0
    """From here on it stops blocking and changes lanes once clear, m."""
    GAP = 3.0
    """Bumper-to-bumper gap at which it changes lanes beside the robot, m."""
    GAINS = (0.5, 1.0)
    """Coming alongside: acceleration per m of gap and per m/s of speed difference (1/s², 1/s)."""

    def drive(self, t, history, own, robot):
        ahead = robot[:, 0] - own[:, 0]
        towards = robot[:, 3] * np.sign(self.home_y - self.away_y) > self.TOWARDS
        blocking = (ahead <= self.LEAD) & ((ahead > 0) | towards)
        closing = robot[:, 2] - own[:, 2]
        wanted = np.where(blocking, self.GAINS[0] * ahead + self.GAINS[1] * closing, closing)
        xdd = np.clip(wanted, -self.ACCEL, self.ACCEL)
        late = own[:, 0] > self.UNTIL_X
        self.change_lanes(late & self.clear(own, robot, self.GAP), t, own)
        return np.where(late, 0.0, xdd)


class AbortedChange(ScriptedHuman):
    """Starts ahead in the other lane; at ``x`` ≥ ``abort_x`` it begins a slow lane change into the
    robot's lane (:attr:`ABORT_S`), turns back when its centre reaches the divider (a swerve back
    over :attr:`ABORT_S`, up to 4.9 m/s² lateral), and changes lanes for good at ``x`` ≥
    ``final_x`` (-50 to -44 m) whatever the robot does, from wherever the swerve has brought it
    (up to 6.4 m/s² lateral, reversing the swerve). Tests a robot that must not take a human's
    first move for its last. Its episodes start about 65 m earlier than the others: the aborted
    change takes about 3 s to be back across the divider and 3.8 s to be back in its lane."""

    ABORT_S = 3.0
    """Duration of the aborted change and of the swerve back, s."""

    def setup(self, m):
        self.phase = np.zeros(m, dtype=int)  # 0 in lane, 1 aborting, 2 back, 3 for good

    def drive(self, t, history, own, robot):
        begin = (self.phase == 0) & (own[:, 0] >= self.parameters["abort_x"])
        self.lateral.begin(begin, t, own, self.away_y, self.ABORT_S)
        at_divider = (self.phase == 1) & ((own[:, 1] - LANE_DIVIDER_Y) * (self.home_y - LANE_DIVIDER_Y) <= 0)
        self.lateral.begin(at_divider, t, own, self.home_y, self.ABORT_S)
        final = (self.phase == 2) & (own[:, 0] >= self.parameters["final_x"])
        self.lateral.begin(final, t, own, self.away_y, LANE_CHANGE_S)
        self.phase += begin | at_divider | final
        return np.zeros(len(own))


@dataclass(frozen=True)
class Scenario:
    """One scenario of the library: its ``name``, a one-line ``summary``, whether a collision is
    ``avoidable`` for the robot, the ``acceptable`` outcome (``no collision`` or ``swap``), the
    scripted ``human`` (a :class:`ScriptedHuman` subclass), the start: the robot's ``robot_x``
    range (m), the human's offsets from the robot ``dx`` (m, + ahead) and ``dv`` (m/s), uniform
    ranges; and its ``parameters``: ``(name, low, high)`` drawn uniformly per episode."""

    name: str
    summary: str
    avoidable: bool
    acceptable: str
    human: type
    dx: tuple[float, float]
    dv: tuple[float, float] = (-1.0, 1.0)
    parameters: tuple[tuple[str, float, float], ...] = ()
    robot_x: tuple[float, float] = ROBOT_X

    def agent(self) -> ScriptedHuman:
        """A new human agent of this scenario."""
        return self.human(self)

    def draw_parameters(self, rng: np.random.Generator, m: int) -> dict[str, np.ndarray]:
        """The scenario's parameters of ``m`` episodes, ``{name: [m]}``, drawn in order."""
        return {name: rng.uniform(low, high, m) for name, low, high in self.parameters}

    def draw(self, rng: np.random.Generator, m: int) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        """The starts ``[m, 2, 6]`` (robot car 0, human car 1) of ``m`` episodes and their
        parameters, drawn in this order: the robot's lane, ``x`` and speed, the human's ``dx``
        and ``dv``, then :meth:`draw_parameters`."""
        robot_left = rng.integers(2, size=m) == 0
        x, v = rng.uniform(*self.robot_x, m), rng.uniform(*ROBOT_SPEED, m)
        dx, dv = rng.uniform(*self.dx, m), rng.uniform(*self.dv, m)
        left, right = LANE_CENTRE_Y[LANES[0]], LANE_CENTRE_Y[LANES[1]]
        start = np.zeros((m, 2, len(STATE_NAMES)))
        start[:, 0, :3] = np.stack([x, np.where(robot_left, left, right), v], axis=1)
        start[:, 1, :3] = np.stack([x + dx, np.where(robot_left, right, left), v + dv], axis=1)
        return start, self.draw_parameters(rng, m)


SCENARIOS: dict[str, Scenario] = {s.name: s for s in (
    Scenario("mirror", "beside the robot, copies its longitudinal acceleration 0.3 s later until x = -50 m; "
             "changes lanes once 5 m clear", True, "no collision", Mirror, dx=(-1.5, 1.5), dv=(0.0, 0.0)),
    Scenario("late-cut-in", "8-14 m ahead in the other lane; at x ≈ -55 m cuts into the robot's lane in 2 s "
             "without looking", True, "swap", LateCutIn, dx=(8.0, 14.0), dv=(0.0, 0.0),
             parameters=(("cut_x", -58.0, -52.0),)),
    Scenario("brake-after-merge", "10-16 m ahead in the robot's goal lane; brakes at 8 m/s² for 1-1.5 s once the "
             "robot has merged behind, then changes lanes", True, "swap", BrakeAfterMerge, dx=(10.0, 16.0),
             parameters=(("brake_s", 1.0, 1.5), ("fallback_x", -50.0, -45.0)), robot_x=EARLY_ROBOT_X),
    Scenario("never-yield", "beside the robot; keeps its speed and changes lanes at x in [-85, -65] m whatever the "
             "robot does", True, "swap", NeverYield, dx=(-3.0, 3.0), parameters=(("change_x", -85.0, -65.0),)),
    Scenario("block", "3-8 m behind in the robot's goal lane; drives alongside the robot while it moves over or is "
             "ahead", True, "no collision", Block, dx=(-8.0, -3.0)),
    Scenario("aborted-change", "6-12 m ahead in the other lane; starts a lane change, swerves back at the divider, "
             "changes for good at x ≈ -47 m", True, "swap", AbortedChange, dx=(6.0, 12.0),
             parameters=(("abort_x", -162.0, -156.0), ("final_x", -50.0, -44.0)), robot_x=EARLY_ROBOT_X),
)}
"""The library, by name, in the order docs/closed_loop.md lists it."""
