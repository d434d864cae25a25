"""Driving styles: the rules a planning robot adds to the paper's cost, and when it changes style.

A :class:`DrivingStyle` says how the candidates move the robot (their
:class:`~.candidates.Kinematics`), how a candidate's sampled futures judge it (``risk``), which
rules add to its cost (:func:`rule_costs`: turning back, setting out beside the human, the
stand-off exit, progress in the goal lane) and which style it falls back on
(:meth:`DrivingStyle.fallback_for`). :data:`STYLES` holds the planning robots' styles by their
``--robot`` names; every rule is off in the paper's. Each style, rule and constant, with the reason
for its value: docs/driving.md, Driving styles.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..errors import InputError
from ..scenario import (CAR_WIDTH, CUTOFF_X, DT, HORIZON, LANE_CENTRE_Y, LANES,
                        REPLAN_STEPS, lane_of)
from .candidates import KINEMATICS, Action, Candidates, Kinematics, acceleration_indices

TURN_BACK_COST = 300.0
"""The decisive and comfort styles' cost of turning back from a lane change (cost units of
:class:`~.costs.PaperCost`: about 0.6 m of lane offset held over the horizon)."""
COMMIT_OFFSET = 1.0
"""How far (m) from the other lane's centre the decisive styles' robot is committed to its lane change."""
SET_OUT_GAP = 5.0
"""The decisive styles' smallest longitudinal distance (m, centre to centre) for setting out: a car
length and a little more, so that the cars do not overlap lengthwise while the robot moves across."""
SET_OUT_FROM = 0.6
"""The first time (s from now) the set-out rule checks the gap: half a second or more before a lane
change set out in window 1 brings the robot's side over the divider."""
SETTLED_OFFSET = 0.3
"""How close (m) to its lane's centre the robot is settled in it (:meth:`DrivingStyle.fallback_for`)."""
SETTLED_SPEED = 0.3
"""How slowly (m/s) the robot moves sideways when settled in its lane (:meth:`DrivingStyle.fallback_for`)."""
SET_OUT_COST = 100_000.0
"""Cost of setting out with the human closer than a style's ``set_out_gap``: more than a sampled
future's collision costs can add up to (about 66,000), so it acts as a rule."""
STANDOFF_EXIT_COST = 2000.0
"""The ``planner`` style's cost of a window 1 that does not take the way out of a stand-off: about
what one colliding future in 32 adds to a candidate's mean, so a risk the futures show still wins."""
YIELD_MARGIN = 0.5
"""How much sooner (s) one way out of a stand-off must be than the other for :func:`standoff_exit`
to leave the way it prefers (yielding, or going ahead once it is)."""
YIELD_SPEED_FLOOR = 20.0
"""The slowest (m/s) the stand-off exit brakes the robot to, to drop behind the human: about the
slowest the real drivers of the 30 recorded trials drove (20.7 m/s)."""
BRAKING_ALONG_SLOWED = 1.0
"""How much (m/s) the robot must have slowed in the last :data:`HUMAN_ACCELERATION_HELD` s for
:func:`brakes_along` to judge whether the human braked with it."""
BRAKING_ALONG_LEVEL = 1.0
"""How close (m/s) the cars' speeds are while the human brakes along with the robot
(:func:`brakes_along`): the robot's braking has opened no gap."""
BRAKING_ALONG_SHARE = 0.7
"""The share of the robot's slowing by which the human slows too when it brakes along with it
(:func:`brakes_along`)."""
HUMAN_ACCELERATION_HELD = 0.6
"""How long (s) :func:`standoff_exit` expects the human to hold its present acceleration (then its
speed): to the end of window 1, by when the next plans have seen what it did instead."""
PROGRESS_COST = 500.0
"""The ``planner`` style's cost per m/s by which a candidate ends its horizon slower than
:data:`YIELD_SPEED_FLOOR` while the robot is in its goal lane and slower than that: more than
staying behind a slower human saves, less than a colliding future."""
STANDOFF_WITHIN = 3.0
"""How long (s) before the cutoff a ``planner`` robot that has not set out falls back on the
decisive style in a stand-off that would still hold it :data:`FALLBACK_WITHIN` s before the cutoff."""
FALLBACK_WITHIN = 2.0
"""How long (s) before the cutoff a ``planner`` robot that has not set out falls back on the
decisive style: its quicker lane change still crosses the swap line 0.7 s before the cutoff."""


@dataclass(frozen=True)
class DrivingStyle:
    """How a planning robot drives (docs/driving.md, Driving styles); the defaults are the paper's.

    ``kinematics``: how its candidates move the robot. ``turn_back_cost``: cost per window that
    leaves the goal lane after one that targeted it, once the robot is ``commit_offset`` m or more
    from the other lane's centre. ``risk``: the share α of the worst sampled futures that judge a
    candidate (CVaR_α; 1: the mean). ``set_out_gap`` (m): setting out for the goal lane in window 1
    while the human would be closer than this lengthwise costs :data:`SET_OUT_COST`, checked at
    :attr:`set_out_times` up to ``set_out_until`` s. ``standoff_exit_cost``: cost of a
    window 1 that does not take the way out of a stand-off (:meth:`way_out`). ``progress_cost``:
    cost per m/s by which a candidate ends slower than :data:`YIELD_SPEED_FLOOR` in the goal lane.
    ``fallback``: the style it falls back on (:meth:`fallback_for`), within ``fallback_within`` s
    of the cutoff, or ``standoff_within`` s in a stand-off; ``safety_fallback``: the style a window
    the safety layer brakes in harder than ``kinematics`` can is planned in (:mod:`.safety`).
    ``safety_layer``: every window is checked before it is executed (:mod:`.safety`). All rules
    and the safety layer off are the paper's planner."""

    kinematics: Kinematics = KINEMATICS["paper"]
    turn_back_cost: float = 0.0
    risk: float = 1.0
    commit_offset: float = 0.0
    set_out_gap: float = 0.0
    set_out_until: float = 2.0
    fallback: DrivingStyle | None = None
    safety_fallback: DrivingStyle | None = None
    fallback_within: float = 0.0
    standoff_within: float = 0.0
    standoff_exit_cost: float = 0.0
    progress_cost: float = 0.0
    safety_layer: bool = False

    def __post_init__(self):
        non_negative = (self.turn_back_cost, self.commit_offset, self.set_out_gap, self.fallback_within,
                        self.standoff_within, self.standoff_exit_cost, self.progress_cost)
        if (not all(v >= 0 and np.isfinite(v) for v in non_negative) or not 0 < self.risk <= 1
                or not SET_OUT_FROM < self.set_out_until < np.inf
                or not all(s is None or isinstance(s, DrivingStyle) and s.fallback is None and s.safety_fallback is None
                           for s in (self.fallback, self.safety_fallback))):
            raise InputError(f"a driving style needs turn_back_cost, commit_offset, set_out_gap, fallback_within, "
                             f"standoff_within, standoff_exit_cost and progress_cost finite and >= 0, "
                             f"0 < risk <= 1, set_out_until finite and > {SET_OUT_FROM} and fallbacks that are None or "
                             f"DrivingStyles without fallbacks of their own, got {self.turn_back_cost}, "
                             f"{self.commit_offset}, {self.set_out_gap}, {self.fallback_within}, {self.standoff_within}, "
                             f"{self.standoff_exit_cost}, {self.progress_cost}, {self.risk}, "
                             f"{self.set_out_until}, {self.fallback!r}, {self.safety_fallback!r}")

    def blocks_set_out(self, robot: np.ndarray, human: np.ndarray, after: float = 0.0) -> bool:
        """Whether the set-out rule holds a robot that keeps its speed in its lane (a stand-off),
        from both cars' present states ``robot [6]``, ``human [6]``: the human would be less than
        ``set_out_gap`` ahead or behind at any of :attr:`set_out_times`, both keeping their speeds,
        and is not in the robot's lane; with ``after`` (s), whether it would still hold the robot
        that much later."""
        crossing_gaps = robot[0] - human[0] + (robot[2] - human[2]) * (after + self.set_out_times)
        return bool(self._too_close(crossing_gaps, robot, human))

    def blocks_set_out_along(self, states: np.ndarray, robot: np.ndarray, human: np.ndarray) -> np.ndarray:
        """Per candidate, whether the set-out rule holds it back ``[C]``: as :meth:`blocks_set_out`,
        with the robot moving as the candidate moves it (``states [C, 15, 6]`` at steps t+1..t+15,
        then holding its last speed), so a candidate pulling clear may set out and one braking in
        front of the human may not."""
        steps = DT * np.arange(0, HORIZON + 1)
        x = np.concatenate([np.full((len(states), 1), robot[0]), states[:, :, 0]], axis=1)  # [C, 16]
        times = self.set_out_times
        inside = np.minimum(times, steps[-1])
        index = np.minimum((inside / DT).astype(int), HORIZON - 1)  # linear within each step
        share = (inside - steps[index]) / DT
        robot_x = x[:, index] * (1 - share) + x[:, index + 1] * share + states[:, -1:, 2] * (times - inside)
        return self._too_close(robot_x - human[0] - human[2] * times, robot, human)

    def _too_close(self, crossing_gaps: np.ndarray, robot: np.ndarray, human: np.ndarray) -> np.ndarray:
        """The set-out rule's test on the gaps (m, robot minus human) at :attr:`set_out_times`,
        ``crossing_gaps [..., 15]``, from both cars' present states ``robot [6]``, ``human [6]``:
        any gap shorter than ``set_out_gap`` either way, with the human not in the robot's lane
        ``[...]``."""
        return (np.abs(crossing_gaps).min(-1) < self.set_out_gap) & (abs(robot[1] - human[1]) >= CAR_WIDTH)

    def fallback_for(self, history: np.ndarray, first_action: int, goal_y: float | None) -> DrivingStyle | None:
        """The style a plan from both cars' states ``history [t+1, 2, 6]`` (robot, human; the
        present last), window 0 executing ``first_action``, towards the lane centre ``goal_y`` (m;
        None: no goal lane) falls back on, if any: the ``fallback`` where the robot, settled in the
        lane it has not left, is short of time (:meth:`_short_of_time`); None otherwise."""
        if self.fallback is not None and self._short_of_time(history, first_action, goal_y):
            return self.fallback
        return None

    def _short_of_time(self, history: np.ndarray, first_action: int, goal_y: float | None) -> bool:
        """Whether the robot, settled in the lane it has not left (within :data:`SETTLED_OFFSET` m
        of its centre, slower sideways than :data:`SETTLED_SPEED` m/s), towards a goal lane, falls
        back (:meth:`fallback_for`, with its arguments): it would reach the cutoff at its present
        speed within ``fallback_within`` s; or the set-out rule holds it (:meth:`blocks_set_out`)
        and the human has braked along with it (:meth:`human_yields`), or it is within
        ``standoff_within`` s and the rule would still hold it ``fallback_within`` s before the
        cutoff."""
        robot, human = history[-1]
        lane = Action(first_action).lane
        settled = abs(robot[1] - LANE_CENTRE_Y[lane]) < SETTLED_OFFSET and abs(robot[3]) < SETTLED_SPEED
        if not settled or goal_y is None or lane == lane_of(np.array([goal_y]))[0]:
            return False
        seconds_to_cutoff = (CUTOFF_X - robot[0]) / robot[2] if robot[2] > 0 else np.inf
        if seconds_to_cutoff < self.fallback_within:
            return True
        if not self.blocks_set_out(robot, human):
            return False
        if self.human_yields(history):  # both yielding beside each other
            return True
        return (seconds_to_cutoff < self.standoff_within
                and self.blocks_set_out(robot, human, after=seconds_to_cutoff - self.fallback_within))

    def human_yields(self, history: np.ndarray) -> bool:
        """Whether the human has braked with the robot (:func:`brakes_along`) at a plan time of
        ``history [t+1, 2, 6]`` (robot, human; every ``REPLAN_STEPS`` steps back from the last)
        where the set-out rule held the robot (:meth:`blocks_set_out`): both yielding, so the robot
        goes ahead from then on (:meth:`way_out`)."""
        return any(self.blocks_set_out(*history[end - 1]) and brakes_along(history[:end])
                   for end in range(len(history), 0, -REPLAN_STEPS))

    def way_out(self, history: np.ndarray) -> int:
        """The acceleration index of the ``kinematics`` by which the robot leaves a stand-off, from
        both cars' states ``history [t+1, 2, 6]`` (robot, human): its hardest acceleration once the
        human has braked along with it (:meth:`human_yields`) where it can get clear ahead at all,
        else :func:`standoff_exit` from the present states."""
        robot, human = history[-1]
        ahead_possible = np.isfinite(_time_to_clear_ahead(robot, human, self.kinematics, self.set_out_gap))
        if ahead_possible and self.human_yields(history):
            return int(np.argmax(self.kinematics.accelerations))
        return standoff_exit(robot, human, self.kinematics, self.set_out_gap)

    @property
    def set_out_times(self) -> np.ndarray:
        """When (s from now) the set-out rule checks the gap ``[15]``."""
        return np.linspace(SET_OUT_FROM, self.set_out_until, 15)


_DECISIVE = DrivingStyle(KINEMATICS["settled"], TURN_BACK_COST, commit_offset=COMMIT_OFFSET, set_out_gap=SET_OUT_GAP, safety_layer=True)
_COMFORT = DrivingStyle(KINEMATICS["comfort"], TURN_BACK_COST, commit_offset=COMMIT_OFFSET, set_out_gap=SET_OUT_GAP,
                        set_out_until=2.5, safety_layer=True)
_COMFORT_FIRST_RULES = {"standoff_exit_cost": STANDOFF_EXIT_COST, "progress_cost": PROGRESS_COST, "turn_back_cost": 0.0}
"""What the ``planner`` style and its fallbacks change in the comfort and decisive styles: the
stand-off exit, and getting going again in the goal lane, added; the turning-back cost dropped
(with the safety layer and the stand-off exit it changes no outcome: docs/driving.md, Ablation)."""
STYLES = {
    "planner": replace(_COMFORT, **_COMFORT_FIRST_RULES,
                       fallback=replace(_DECISIVE, kinematics=KINEMATICS["safety"], **_COMFORT_FIRST_RULES),
                       safety_fallback=replace(_COMFORT, kinematics=KINEMATICS["safety"], **_COMFORT_FIRST_RULES),
                       fallback_within=FALLBACK_WITHIN, standoff_within=STANDOFF_WITHIN),
    "planner-decisive": _DECISIVE,
    "planner-paper": DrivingStyle(),
    "planner-comfort": _COMFORT,
    "planner-cautious": replace(_DECISIVE, risk=0.2),
}
"""The planning robots' driving styles by their ``--robot`` names (docs/driving.md, Driving
styles): ``planner`` comfort first (comfortable until time runs short or a stand-off needs
a way out: then it falls back on the decisive style's shorter set-out check and its accelerations,
with comfortable steering, as it brakes where its safety layer needs to; making room beside the
human), ``planner-decisive``, ``planner-paper`` (the paper's exactly), ``planner-comfort``
(decisive within nuPlan's comfort limits) and ``planner-cautious`` (decisive, judged by CVaR_0.2)."""


def rule_costs(style: DrivingStyle, candidates: Candidates, history: np.ndarray, goal_y: float | None) -> np.ndarray:
    """``style``'s rule costs of each candidate ``[C]`` from both cars' states ``history [t+1, 2,
    6]`` (robot, human) towards the lane centre ``goal_y`` (m; None: no goal lane, no rule):
    turning back (:func:`turn_backs`, once the robot is ``commit_offset`` from the
    other lane's centre), setting out beside the human (:func:`set_outs`,
    :meth:`~DrivingStyle.blocks_set_out_along`), not taking the way out of a stand-off before it
    has set out (:meth:`~DrivingStyle.way_out`) and ending the horizon below
    :data:`YIELD_SPEED_FLOOR` in the goal lane. Safety (following, braking for the human) is the
    safety layer's (:mod:`.safety`), which checks every window before it is executed."""
    rules = np.zeros(len(candidates))
    if goal_y is not None:
        goal = str(lane_of(np.array([goal_y]))[0])
        other = next(lane for lane in LANES if lane != goal)
        robot, human = history[-1]
        if abs(robot[1] - LANE_CENTRE_Y[other]) >= style.commit_offset:
            rules += style.turn_back_cost * turn_backs(candidates.actions, goal)
        if style.set_out_gap:
            blocked = style.blocks_set_out_along(candidates.states, robot, human)
            rules += SET_OUT_COST * (set_outs(candidates.actions, goal) & blocked)
        not_set_out = Action(int(candidates.actions[0, 0])).lane != goal
        if style.standoff_exit_cost and not_set_out and style.blocks_set_out(robot, human):
            way = style.way_out(history)
            rules += style.standoff_exit_cost * (acceleration_indices(candidates.actions[:, 1]) != way)
        if style.progress_cost and lane_of(robot[1:2])[0] == goal and robot[2] < YIELD_SPEED_FLOOR:
            rules += style.progress_cost * np.maximum(YIELD_SPEED_FLOOR - candidates.states[:, -1, 2], 0.0)
    return rules


def _targets(actions: np.ndarray, goal: str) -> np.ndarray:
    """Which windows of the action sequences ``actions [C, W]`` steer to the ``goal`` lane ``[C, W]``."""
    return np.asarray(actions) % len(LANES) == LANES.index(goal)


def turn_backs(actions: np.ndarray, goal: str) -> np.ndarray:
    """Per action sequence of ``actions [C, W]``, the windows that leave the ``goal`` lane after a
    window that targeted it ``[C]``."""
    targets = _targets(actions, goal)
    return (targets[:, :-1] & ~targets[:, 1:]).sum(1)


def set_outs(actions: np.ndarray, goal: str) -> np.ndarray:
    """Per action sequence of ``actions [C, W]``, whether window 1 targets the ``goal`` lane while
    window 0 (the one being executed) does not ``[C]``: the plan starts a lane change now."""
    targets = _targets(actions, goal)
    return ~targets[:, 0] & targets[:, 1]


def standoff_exit(robot: np.ndarray, human: np.ndarray, kinematics: Kinematics, gap: float) -> int:
    """The acceleration index of ``kinematics`` by which the robot leaves a stand-off, from the cars'
    present states ``robot [6]``, ``human [6]``: its hardest acceleration, if that gets it ``gap`` m
    ahead of the human more than :data:`YIELD_MARGIN` s sooner than its hardest braking, down to
    :data:`YIELD_SPEED_FLOOR` and no slower, gets it ``gap`` m behind (both held from now; the human
    holding its present acceleration for :data:`HUMAN_ACCELERATION_HELD` s, then its speed); else
    that braking. A robot already accelerating keeps going ahead unless braking is that much
    sooner, so that the way out does not turn at every plan."""
    dx, dv = robot[0] - human[0], robot[2] - human[2]
    braking_for = max(robot[2] - YIELD_SPEED_FLOOR, 0.0) / kinematics.hardest_braking  # s until the floor
    behind = _time_to_gain(gap + dx, -dv, kinematics.hardest_braking, human[4], braking_for)
    ahead = _time_to_clear_ahead(robot, human, kinematics, gap)
    go_ahead = not behind + YIELD_MARGIN < ahead if robot[4] > 0 else ahead + YIELD_MARGIN < behind
    return int(np.argmax(kinematics.accelerations) if go_ahead else np.argmin(kinematics.accelerations))


def _time_to_clear_ahead(robot: np.ndarray, human: np.ndarray, kinematics: Kinematics, gap: float) -> float:
    """How long (s) the robot ``robot [6]``, at ``kinematics``'s hardest acceleration from now, takes to
    get ``gap`` m ahead of the human ``human [6]`` holding its present acceleration for
    :data:`HUMAN_ACCELERATION_HELD` s, then its speed (inf: never)."""
    return _time_to_gain(gap - (robot[0] - human[0]), robot[2] - human[2], max(kinematics.accelerations), -human[4])


def brakes_along(history: np.ndarray) -> bool:
    """Whether the human brakes with the robot, from both cars' states ``history [t+1, 2, 6]``:
    over the last :data:`HUMAN_ACCELERATION_HELD` s the robot slowed by more than
    :data:`BRAKING_ALONG_SLOWED` m/s and the human by at least :data:`BRAKING_ALONG_SHARE` as much,
    and their speeds now differ by less than :data:`BRAKING_ALONG_LEVEL` m/s."""
    steps = round(HUMAN_ACCELERATION_HELD / DT)
    if len(history) <= steps:
        return False
    robot_slowed, human_slowed = history[-1 - steps, :, 2] - history[-1, :, 2]
    level = abs(history[-1, 0, 2] - history[-1, 1, 2]) < BRAKING_ALONG_LEVEL
    return bool(robot_slowed > BRAKING_ALONG_SLOWED and human_slowed >= BRAKING_ALONG_SHARE * robot_slowed and level)


def _time_to_gain(distance: float, speed: float, acceleration: float, human_part: float,
                  robot_for: float = np.inf) -> float:
    """How long (s) the robot takes to gain ``distance`` (m) on the human from their relative
    ``speed`` (m/s) at the relative ``acceleration`` (m/s²) for the first ``robot_for`` s (then
    holding its speed), plus the human's ``human_part`` (m/s²) for the first
    :data:`HUMAN_ACCELERATION_HELD` s: 0 where ``distance`` is 0 or less, inf where it never does."""
    def relative(t: float) -> float:  # the relative acceleration from time t (s) on
        return (acceleration if t < robot_for else 0.0) + (human_part if t < HUMAN_ACCELERATION_HELD else 0.0)

    start = 0.0
    for end in sorted(b for b in {HUMAN_ACCELERATION_HELD, robot_for} if 0.0 < b < np.inf):
        held = relative(start)
        t = _uniform_time_to_gain(distance, speed, held)
        if t <= end - start:
            return start + t
        span = end - start
        distance -= speed * span + 0.5 * held * span * span
        speed += held * span
        start = end
    return start + _uniform_time_to_gain(distance, speed, relative(start))


def _uniform_time_to_gain(distance: float, speed: float, acceleration: float) -> float:
    """:func:`_time_to_gain` at one relative ``acceleration`` (m/s²) throughout."""
    if distance <= 0:
        return 0.0
    if abs(acceleration) < 1e-9:
        return distance / speed if speed > 1e-9 else np.inf
    discriminant = speed * speed + 2 * acceleration * distance
    if discriminant < 0 or acceleration < 0 and speed <= 0:
        return np.inf  # decelerating, it stops gaining first
    if acceleration > 0:
        return (np.sqrt(discriminant) - speed) / acceleration
    return (speed - np.sqrt(discriminant)) / -acceleration
