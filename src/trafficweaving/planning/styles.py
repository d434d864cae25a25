"""Driving styles: the rules a planning robot adds to the paper's cost, and when it changes style.

A :class:`DrivingStyle` says how the candidates move the robot (their
:class:`~.candidates.Kinematics`), how a candidate's sampled futures judge it (``risk``), which
rules add to its cost (:func:`rule_costs`: turning back, setting out beside the human, the
stand-off exit, progress in the goal lane, following) and which style it falls back on
(:meth:`DrivingStyle.fallback_for`). :data:`STYLES` holds the planning robots' styles by their
``--robot`` names; every rule is off in the paper's. Each style, rule and constant, with the reason
for its value: docs/planner.md, Driving styles.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..errors import InputError
from ..scenario import (CAR_WIDTH, COLLISION_DX, COLLISION_DY, CUTOFF_X, DT, HORIZON, LANE_CENTRE_Y, LANES,
                        REPLAN_STEPS, lane_of)
from .candidates import KINEMATICS, STEPS_PER_WINDOW, Action, Candidates, Kinematics, acceleration_indices

TURN_BACK_COST = 300.0
"""The decisive styles' cost of turning back from a lane change (cost units of
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
FOLLOW_COST = 100_000.0
"""Cost per metre by which a candidate would come short of stopping behind the human
(:func:`stopping_shortfall`): a rule, as :data:`SET_OUT_COST`."""
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
staying behind a slower human saves, less than a colliding future or the following rule."""
FOLLOW_LATERAL = COLLISION_DY + 0.5
"""How close sideways (m, centre to centre) the human is in the robot's way
(:func:`stopping_shortfall`): the collision rule's 1.8 m and half a metre for its sideways motion."""
STANDOFF_WITHIN = 3.0
"""How long (s) before the cutoff a ``planner`` robot that has not set out falls back on the
decisive style in a stand-off that would still hold it :data:`FALLBACK_WITHIN` s before the cutoff."""
FALLBACK_WITHIN = 2.0
"""How long (s) before the cutoff a ``planner`` robot that has not set out falls back on the
decisive style: its quicker lane change still crosses the swap line 0.7 s before the cutoff."""


@dataclass(frozen=True)
class DrivingStyle:
    """How a planning robot drives (docs/planner.md, Driving styles); the defaults are the paper's.

    ``kinematics``: how its candidates move the robot. ``turn_back_cost``: cost per window that
    leaves the goal lane after one that targeted it, once the robot is ``commit_offset`` m or more
    from the other lane's centre. ``risk``: the share α of the worst sampled futures that judge a
    candidate (CVaR_α; 1: the mean). ``set_out_gap`` (m): setting out for the goal lane in window 1
    while the human would be closer than this lengthwise costs :data:`SET_OUT_COST`, checked at
    :attr:`set_out_times` up to ``set_out_until`` s. ``follow_braking`` (m/s²): the human's braking
    the following rule (:func:`stopping_shortfall`) expects. ``standoff_exit_cost``: cost of a
    window 1 that does not take the way out of a stand-off (:meth:`way_out`). ``progress_cost``:
    cost per m/s by which a candidate ends slower than :data:`YIELD_SPEED_FLOOR` in the goal lane.
    ``fallback``, ``safety_fallback``: the styles it falls back on (:meth:`fallback_for`), within
    ``fallback_within`` s of the cutoff, or ``standoff_within`` s in a stand-off.
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
    follow_braking: float = 0.0
    standoff_exit_cost: float = 0.0
    progress_cost: float = 0.0
    safety_layer: bool = False

    def __post_init__(self):
        non_negative = (self.turn_back_cost, self.commit_offset, self.set_out_gap, self.fallback_within,
                        self.standoff_within, self.follow_braking, self.standoff_exit_cost, self.progress_cost)
        if (not all(v >= 0 and np.isfinite(v) for v in non_negative) or not 0 < self.risk <= 1
                or not SET_OUT_FROM < self.set_out_until < np.inf
                or not all(s is None or isinstance(s, DrivingStyle) and s.fallback is None and s.safety_fallback is None
                           for s in (self.fallback, self.safety_fallback))):
            raise InputError(f"a driving style needs turn_back_cost, commit_offset, set_out_gap, fallback_within, "
                             f"standoff_within, follow_braking, standoff_exit_cost and progress_cost finite and >= 0, "
                             f"0 < risk <= 1, set_out_until finite and > {SET_OUT_FROM} and fallbacks that are None or "
                             f"DrivingStyles without fallbacks of their own, got {self.turn_back_cost}, "
                             f"{self.commit_offset}, {self.set_out_gap}, {self.fallback_within}, {self.standoff_within}, "
                             f"{self.follow_braking}, {self.standoff_exit_cost}, {self.progress_cost}, {self.risk}, "
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
        lane it has not left, is short of time (:meth:`_short_of_time`); else the
        ``safety_fallback`` (without one, the ``fallback``) where the human ahead in its way (within
        :data:`FOLLOW_LATERAL` m sideways of the robot or of window 0's lane centre) brakes harder
        than this style's ``kinematics`` can. None otherwise."""
        if self.fallback is None:
            return None
        robot, human = history[-1]
        if self._short_of_time(history, first_action, goal_y):
            return self.fallback
        lateral_gap = min(abs(human[1] - robot[1]), abs(human[1] - LANE_CENTRE_Y[Action(first_action).lane]))
        in_way_ahead = human[0] > robot[0] and lateral_gap < FOLLOW_LATERAL
        if in_way_ahead and -human[4] > self.kinematics.hardest_braking:
            return self.safety_fallback or self.fallback
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


_DECISIVE = DrivingStyle(KINEMATICS["settled"], TURN_BACK_COST, commit_offset=COMMIT_OFFSET, set_out_gap=SET_OUT_GAP,
                         follow_braking=KINEMATICS["settled"].hardest_braking, safety_layer=True)
_COMFORT = DrivingStyle(KINEMATICS["comfort"], TURN_BACK_COST, commit_offset=COMMIT_OFFSET, set_out_gap=SET_OUT_GAP,
                        set_out_until=2.5, follow_braking=KINEMATICS["comfort"].hardest_braking, safety_layer=True)
_COMFORT_FIRST_RULES = {"standoff_exit_cost": STANDOFF_EXIT_COST, "progress_cost": PROGRESS_COST}
"""What the ``planner`` style and both its fallbacks add to their kinematics' styles: the stand-off
exit, and getting going again in the goal lane."""
STYLES = {
    "planner": replace(_COMFORT, **_COMFORT_FIRST_RULES, fallback=replace(_DECISIVE, **_COMFORT_FIRST_RULES),
                       safety_fallback=replace(_COMFORT, kinematics=KINEMATICS["safety"], **_COMFORT_FIRST_RULES,
                                               follow_braking=KINEMATICS["safety"].hardest_braking),
                       fallback_within=FALLBACK_WITHIN, standoff_within=STANDOFF_WITHIN),
    "planner-decisive": _DECISIVE,
    "planner-paper": DrivingStyle(),
    "planner-comfort": _COMFORT,
    "planner-cautious": replace(_DECISIVE, risk=0.2),
}
"""The planning robots' driving styles by their ``--robot`` names (docs/planner.md, Driving
styles): ``planner`` comfort first (comfortable, falling back on decisive when time runs short or
in a stand-off, on decisive braking with comfortable steering for safety; making room beside the
human), ``planner-decisive``, ``planner-paper`` (the paper's exactly), ``planner-comfort``
(decisive within nuPlan's comfort limits) and ``planner-cautious`` (decisive, judged by CVaR_0.2)."""


def rule_costs(style: DrivingStyle, candidates: Candidates, history: np.ndarray, goal_y: float | None) -> np.ndarray:
    """``style``'s rule costs of each candidate ``[C]`` from both cars' states ``history [t+1, 2,
    6]`` (robot, human) towards the lane centre ``goal_y`` (m; None: no goal lane, only the
    following rule): turning back (:func:`turn_backs`, once the robot is ``commit_offset`` from the
    other lane's centre), setting out beside the human (:func:`set_outs`,
    :meth:`~DrivingStyle.blocks_set_out_along`), not taking the way out of a stand-off before it
    has set out (:meth:`~DrivingStyle.way_out`), ending the horizon below
    :data:`YIELD_SPEED_FLOOR` in the goal lane, and coming short of stopping behind the human
    (:func:`stopping_shortfall`)."""
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
    if style.follow_braking:
        rules += FOLLOW_COST * stopping_shortfall(history[-1, 0], candidates.states, history[-1, 1],
                                                  style.follow_braking, style.kinematics)
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


def stopping_shortfall(robot: np.ndarray, states: np.ndarray, human: np.ndarray, human_braking: float,
                       kinematics: Kinematics) -> np.ndarray:
    """Per candidate, how far (m) the robot would come short of stopping behind the human ``[C]``
    (0: it can stop), from the cars' present states ``robot [6]``, ``human [6]`` and the
    candidates' robot states ``states [C, 15, 6]``. The human brakes from now at ``human_braking``
    m/s² (or as hard as it brakes now, if harder) to a stop, keeping its lateral position; the
    robot follows the candidate to the end of window 1 (0.6 s: a plan made next can first brake
    after it) and then brakes at ``kinematics``'s hardest (reached at its jerk limit: a delay of half
    the ramp) to a stop, moving sideways as the candidate does. Short: the least bumper gap
    (``|Δx| - COLLISION_DX``), negated where below 0, while the human is ahead now and the robot
    within :data:`FOLLOW_LATERAL` of it sideways (at the horizon's steps, and after the horizon if
    the robot still is at its end): a candidate may also steer out of the human's way. An
    RSS-style check (Shalev-Shwartz et al. 2017) with the replanning period as the response time."""
    if human[0] <= robot[0]:
        return np.zeros(len(states))
    end = 2 * STEPS_PER_WINDOW  # steps to the end of window 1
    t_end = end * DT
    b_h = max(human_braking, -human[4], 1e-6)
    b_r = kinematics.hardest_braking
    v_h = max(human[2], 0.0)

    def human_x(t):
        moving = np.minimum(t, v_h / b_h)
        return human[0] + v_h * moving - 0.5 * b_h * moving ** 2

    in_way = np.abs(states[..., 1] - human[1]) < FOLLOW_LATERAL  # [C, 15]
    steps = DT * np.arange(1, end + 1)
    gaps_before = np.where(in_way[:, :end], human_x(steps) - states[:, :end, 0] - COLLISION_DX, np.inf)

    x, v, a = states[:, end - 1, 0], np.maximum(states[:, end - 1, 2], 0.0), states[:, end - 1, 4]
    delay = np.zeros_like(v) if kinematics.jerk is None else np.maximum(a + b_r, 0.0) / (2 * kinematics.jerk)

    def robot_x(t):
        s = t - t_end
        braking = np.clip(s - delay, 0.0, v / b_r)
        return x + v * np.minimum(s, delay) + v * braking - 0.5 * b_r * braking ** 2

    # braking: at each step of the horizon where the candidate keeps the robot in the human's way, and after the
    # horizon, if it still does, at the least gap: an end of a piece of the speeds or where they are equal
    braking_steps = DT * np.arange(end, HORIZON + 1)[:, None]  # [10, 1] s
    gaps_braking = np.where(in_way[:, end - 1:].T, human_x(braking_steps) - robot_x(braking_steps), np.inf).min(0)
    t_horizon = HORIZON * DT
    with np.errstate(divide="ignore", invalid="ignore"):
        times = np.stack([t_end + delay, np.full_like(v, v_h / b_h), t_end + delay + v / b_r, (v_h - v) / b_h,
                          (v - v_h + b_r * (t_end + delay)) / (b_r - b_h)])
    times = np.maximum(np.nan_to_num(times, nan=0.0, posinf=0.0, neginf=0.0), t_horizon)  # [5, C]
    gaps_beyond = np.where(in_way[:, -1], (human_x(times) - robot_x(times)).min(0), np.inf)
    gaps_after = np.minimum(gaps_braking, gaps_beyond) - COLLISION_DX
    return np.maximum(-np.minimum(gaps_before.min(1), gaps_after), 0.0)

