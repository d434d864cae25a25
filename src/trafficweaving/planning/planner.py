"""The two-stage exhaustive planner (paper §IV and §V-C) and its real-time (deadline) mode.

Stage 1 scores every candidate robot future with a few sampled human responses each; stage 2
re-scores the best ones with many samples; the best is executed. All counts are configurable.

With a deadline (real-time mode) stage 2 runs anytime, in rounds of samples until the time is
spent. Stage 1 samples every candidate's own human futures where at least two each fit in
:data:`OWN_FUTURES_SHARE` of the deadline (int8 sampling on two cores); where they do not (a CPU
sampling in bfloat16 or float32 would score each candidate against one sample, or only some of
them), it screens: the candidates that share their first free window's action share
:data:`SCREENING_SAMPLES` human futures, sampled conditioned on the candidate that holds that action
(8 conditionings instead of 4096); the finalists are then re-scored against their own futures, as
in the paper. Where stage 1 sampled own futures, the :data:`SHORTLIST` best get more of them before
the finalists are chosen (:data:`SHORTLIST_SHARE` of the time left): with two or three samples per
candidate, the full budget's choice is often not among the finalists. The human is any
:class:`HumanModel` (the CVAE's is :class:`~trafficweaving.model.predictor.HumanPredictor`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from typing import Protocol, runtime_checkable

import numpy as np
import torch

from .. import validate
from ..dynamics import future_states
from ..errors import InputError
from ..scenario import (CAR_WIDTH, COLLISION_DX, COLLISION_DY, CUTOFF_X, DT, HORIZON, LANE_CENTRE_Y, LANES,
                        REPLAN_STEPS, STATE_NAMES, lane_of)
from .candidates import (MOTIONS, N_ACTIONS, N_CANDIDATES, STEPS_PER_WINDOW, WINDOWS, Action, Candidates, Motion,
                         acceleration_indices, robot_candidates)
from .costs import Cost


SCREENING_SAMPLES = 32
"""Real-time mode: human futures per window-1 action shared by stage 1's candidates."""
OWN_FUTURES_SHARE = 0.4
"""Real-time mode: the share of the deadline stage 1 may spend sampling every candidate's own human
futures. Where at least two per candidate fit in it at the measured sampling rate, stage 1 samples
them (the paper's stage 1 with fewer samples), else it screens (docs/planner.md, Real-time mode)."""
SHORTLIST = 256
"""Real-time mode, where stage 1 sampled every candidate's own futures: how many of the best get more
samples of their own before the finalists are chosen from them (docs/planner.md, Shortlist)."""
SHORTLIST_SHARE = 1 / 3
"""Real-time mode: the share of the time left after stage 1 that the :data:`SHORTLIST` samples
may take (the rest goes to stage 2)."""


@dataclass(frozen=True)
class Mode:
    """How the planner drives (docs/closed_loop.md). ``motion``: how its candidates move the robot
    (:data:`~.candidates.MOTIONS`). ``turn_back_cost``: added to a candidate's cost for every window
    that leaves the goal lane (a cost's ``goal_y``) after the window before it targeted it, window 0
    (the one being executed) included (:func:`turn_backs`), once the robot is ``commit_offset`` m
    or more from the other lane's centre: once a lane change is under way, the plan keeps to it
    unless turning back is better by more than that; setting out, and turning back from a first
    probe, are free (0: the paper's).
    ``risk``: the share α of a candidate's sampled human futures whose costs judge it, the worst
    ones (CVaR_α, :func:`risk_cost`; 1: the expected cost, the paper's).
    ``set_out_gap``: while the human would be beside the robot as it moves across (less than this
    many m ahead or behind at any of 15 times from :data:`SET_OUT_FROM` to ``set_out_until`` s from
    now, the robot moving as the candidate moves it, the human keeping its speed; and not in the
    robot's lane: their centres a car's width or more apart sideways; :meth:`blocks_set_out_along`),
    a candidate that sets out for the goal lane in window 1 (:func:`set_outs`) costs
    :data:`SET_OUT_COST`: the robot does not start a lane change beside the human (0: it may, the
    paper's). The robot "held in its lane" by the set-out rule, in what follows, is one that would
    be held keeping its speed (:meth:`blocks_set_out`): the stand-off. ``set_out_until``: about
    half a second after the ``motion``'s lane change, set out in window 1, takes the robot's body
    clear of the divider.
    ``follow_braking``: the following rule (:func:`stopping_shortfall`): while the human is ahead
    and in the robot's way (within :data:`FOLLOW_LATERAL` m sideways of where the candidate takes
    the robot), a candidate costs :data:`FOLLOW_COST` per metre by which the robot, braking as hard
    as its ``motion`` can from the end of window 1 (when the next plan can first brake) and steering
    as the candidate does, would come short of stopping behind the human braking at
    ``follow_braking`` m/s² from now (or as hard as it brakes now, if harder): the robot keeps a gap
    it can stop in, or steers out of the way (0: no rule, the paper's).
    ``standoff_exit_cost``: the stand-off exit: while the set-out rule holds the robot in the lane
    it has not yet left (window 0 keeps to it), a candidate whose window 1 does not take the way
    out of the stand-off (:meth:`way_out`: its ``motion``'s hardest braking, to drop behind
    the human, or its hardest acceleration where that gets it clear ahead clearly sooner, where
    it cannot drop behind without slowing below :data:`YIELD_SPEED_FLOOR`, or once the human has
    braked along with it) costs this much: the robot makes room instead of waiting beside the human
    for room (0: it may wait, the paper's).
    ``progress_cost``: while the robot is in its goal lane (across the divider) and slower than
    :data:`YIELD_SPEED_FLOOR`, a candidate costs this much per m/s by which its speed at the
    horizon's end falls short of that: a robot that has slowed or stopped for the human gets
    going again as soon as the following rule and the sampled futures let it (0: no such cost,
    the paper's, whose separation reward pays a robot for staying behind a slower human, however
    slow).
    ``fallback``: the mode a receding-horizon policy plans in (None: none) from the first plan where
    the robot has not set out for the goal lane and would reach the cutoff within
    ``fallback_within`` s at its present speed, or within ``standoff_within`` s in a stand-off, or
    is in a stand-off with a human that has braked along with it, or where the human ahead brakes
    harder than the ``motion`` can, in a lane change too (:meth:`fallback_for`), to the end of the
    episode (:class:`~.mpc.MPCPolicy`): a comfortable mode that falls back on a quicker one when
    time runs short or safety needs harder braking. ``safety_fallback``: where braking for safety is
    the only reason, the mode planned in instead (None: ``fallback``) until another reason asks for
    ``fallback``: one that brakes as hard as ``fallback`` and steers as comfortably as this mode."""

    motion: Motion = MOTIONS["paper"]
    turn_back_cost: float = 0.0
    risk: float = 1.0
    commit_offset: float = 0.0
    set_out_gap: float = 0.0
    set_out_until: float = 2.0
    fallback: Mode | None = None
    safety_fallback: Mode | None = None
    fallback_within: float = 0.0
    standoff_within: float = 0.0
    follow_braking: float = 0.0
    standoff_exit_cost: float = 0.0
    progress_cost: float = 0.0

    def __post_init__(self):
        non_negative = (self.turn_back_cost, self.commit_offset, self.set_out_gap, self.fallback_within,
                        self.standoff_within, self.follow_braking, self.standoff_exit_cost, self.progress_cost)
        if (not all(v >= 0 and np.isfinite(v) for v in non_negative) or not 0 < self.risk <= 1
                or not SET_OUT_FROM < self.set_out_until < np.inf
                or not all(m is None or isinstance(m, Mode) and m.fallback is None and m.safety_fallback is None
                           for m in (self.fallback, self.safety_fallback))):
            raise InputError(f"a planner mode needs turn_back_cost, commit_offset, set_out_gap, fallback_within, "
                             f"standoff_within, follow_braking, standoff_exit_cost and progress_cost finite and >= 0, "
                             f"0 < risk <= 1, set_out_until finite and > {SET_OUT_FROM} and fallbacks that are None or "
                             f"Modes without fallbacks of their own, got {self.turn_back_cost}, {self.commit_offset}, "
                             f"{self.set_out_gap}, {self.fallback_within}, {self.standoff_within}, {self.follow_braking}, "
                             f"{self.standoff_exit_cost}, {self.progress_cost}, {self.risk}, {self.set_out_until}, "
                             f"{self.fallback!r}, {self.safety_fallback!r}")

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
        then holding its last speed) instead of keeping its present speed, so that a candidate
        pulling clear of the human may set out as soon as its own motion takes it clear, and one
        braking in front of the human may not."""
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

    def fallback_for(self, history: np.ndarray, first_action: int, goal_y: float | None) -> Mode | None:
        """The mode a plan from both cars' states ``history [t+1, 2, 6]`` (robot, human; the present
        last), the robot executing the action ``first_action`` (window 0), towards the lane centre
        ``goal_y`` (m; None: no goal lane) falls back on, if any. The ``fallback`` where the robot
        has not set out (window 0 keeps to its lane, and it is within :data:`SETTLED_OFFSET` m of its
        centre and moving sideways slower than :data:`SETTLED_SPEED` m/s) and would reach
        :data:`~trafficweaving.scenario.CUTOFF_X` at its present speed (standing still: never)
        within ``fallback_within`` s; or within ``standoff_within`` s while the set-out rule holds
        it (:meth:`blocks_set_out`) and, both cars keeping their speeds, would still hold it when
        ``fallback_within`` s are left: a stand-off the comfortable mode does not get out of in
        time; or while the set-out rule holds it and the human has braked along with it
        (:meth:`human_yields`): the comfortable motion's acceleration is too gentle to get ahead
        of a human that answers it (these three need a goal lane). The ``safety_fallback`` (or,
        without one, the ``fallback``) where none of these holds and, in either lane or moving
        between them, the human is ahead in its way (within :data:`FOLLOW_LATERAL` m sideways of
        the robot or of the lane centre window 0 steers it to) braking harder than this mode's
        ``motion`` can: braking for safety is not held to comfort, nor put off until a lane change
        is done. None otherwise: a lane change under way is not switched over for time, the two
        motions' rollouts of it differ."""
        if self.fallback is None:
            return None
        robot, human = history[-1]
        if self._short_of_time(history, first_action, goal_y):
            return self.fallback
        lateral_gap = min(abs(human[1] - robot[1]), abs(human[1] - LANE_CENTRE_Y[Action(first_action).lane]))
        in_way_ahead = human[0] > robot[0] and lateral_gap < FOLLOW_LATERAL
        if in_way_ahead and -human[4] > self.motion.hardest_braking:
            return self.safety_fallback or self.fallback
        return None

    def _short_of_time(self, history: np.ndarray, first_action: int, goal_y: float | None) -> bool:
        """Whether the robot, settled in the lane it has not left, falls back for time or a
        stand-off (:meth:`fallback_for`, with its arguments)."""
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
        where the set-out rule held the robot (:meth:`blocks_set_out`): both yielding, neither
        makes room, so the robot goes ahead from then on (:meth:`way_out`)."""
        return any(self.blocks_set_out(*history[end - 1]) and brakes_along(history[:end])
                   for end in range(len(history), 0, -REPLAN_STEPS))

    def way_out(self, history: np.ndarray) -> int:
        """The acceleration index of the ``motion`` by which the robot leaves a stand-off, from both
        cars' states ``history [t+1, 2, 6]`` (robot, human): its hardest acceleration once the human
        has braked along with it (:meth:`human_yields`) where it can get clear ahead at all, else
        :func:`standoff_exit` from the present states."""
        robot, human = history[-1]
        ahead_possible = np.isfinite(_time_to_clear_ahead(robot, human, self.motion, self.set_out_gap))
        if ahead_possible and self.human_yields(history):
            return int(np.argmax(self.motion.accelerations))
        return standoff_exit(robot, human, self.motion, self.set_out_gap)

    @property
    def set_out_times(self) -> np.ndarray:
        """When (s from now) the set-out rule checks the gap ``[15]``."""
        return np.linspace(SET_OUT_FROM, self.set_out_until, 15)


TURN_BACK_COST = 300.0
"""The decisive modes' cost of turning back from a lane change (cost units of
:class:`~.costs.PaperCost`: about 0.6 m of lane offset held over the horizon)."""
COMMIT_OFFSET = 1.0
"""How far (m) from the other lane's centre the decisive modes' robot is committed to its lane change."""
SET_OUT_GAP = 5.0
"""The decisive modes' smallest longitudinal distance (m, centre to centre) between the cars for
setting out: a car length (:data:`~trafficweaving.scenario.CAR_LENGTH`, 4.22 m) and a little more,
so that the cars do not overlap lengthwise while the robot moves across."""
SET_OUT_FROM = 0.6
"""The first time (s from now) the set-out rule checks the gap: a lane change set out in window 1
(0.3 s from now, at rest sideways) brings the robot's side over the divider about 1.1 s from now
with the settled motion (1.55 s with the comfort motion), so this leaves half a second or more to
spare."""
SETTLED_OFFSET = 0.3
"""How close (m) to its lane's centre the robot is settled in it (:meth:`Mode.fallback_for`)."""
SETTLED_SPEED = 0.3
"""How slowly (m/s) the robot moves sideways when settled in its lane (:meth:`Mode.fallback_for`)."""
SET_OUT_COST = 100_000.0
"""Cost of setting out with the human closer than a mode's ``set_out_gap``: more than a sampled
future's collision costs can add up to (1000 · 9.25 at each of 15 steps discounted by 0.9: about
66,000), so it acts as a rule."""
FOLLOW_COST = 100_000.0
"""Cost per metre by which a candidate would come short of stopping behind the human
(:func:`stopping_shortfall`): a rule, as :data:`SET_OUT_COST`; where every candidate comes short,
the one short by least (braking hardest, or steering clear) is best."""
STANDOFF_EXIT_COST = 2000.0
"""The ``comfort-first`` mode's cost of a window 1 that does not take the way out of a stand-off
(``Mode.standoff_exit_cost``): about what one colliding future in the 32 of a real-time screening
adds to a candidate's mean (66,000 / 32), so the way out gives way to a risk of collision that
the sampled futures show, not to their small preferences."""
YIELD_MARGIN = 0.5
"""How much sooner (s) getting clear ahead must be than dropping behind for a stand-off exit
(:func:`standoff_exit`) to accelerate, and dropping behind than getting ahead for an accelerating
robot to turn: in doubt the robot yields, or keeps going ahead once it is."""
YIELD_SPEED_FLOOR = 20.0
"""The slowest (m/s) the stand-off exit brakes the robot to, to drop behind the human
(:func:`standoff_exit`): about the slowest the real drivers of the 30 recorded trials drove (20.7 m/s,
docs/closed_loop.md). A human that slows with it to there is yielding; slower, the robot would be a
hazard on the highway and might not reach the cutoff at all."""
BRAKING_ALONG_SLOWED = 1.0
"""How much (m/s) the robot must have slowed in the last :data:`HUMAN_ACCELERATION_HELD` s for
:func:`brakes_along` to judge whether the human braked with it."""
BRAKING_ALONG_LEVEL = 1.0
"""How close (m/s) the cars' speeds are while the human brakes along with the robot
(:func:`brakes_along`): the robot's braking has opened no gap; where the human brakes harder, the
way ahead opens by itself."""
BRAKING_ALONG_SHARE = 0.7
"""The share of the robot's slowing by which the human slows too when it brakes along with it
(:func:`brakes_along`): the robot's braking opens less than a third of the speed difference it
would open against a human keeping its speed."""
HUMAN_ACCELERATION_HELD = 0.6
"""How long (s) :func:`standoff_exit` expects the human to hold its present acceleration (then its
speed): to the end of window 1, by when the next plans have seen what it did instead."""
PROGRESS_COST = 500.0
"""The ``comfort-first`` mode's cost per m/s by which a candidate ends its horizon slower than
:data:`YIELD_SPEED_FLOOR` while the robot is in its goal lane and slower than that
(``Mode.progress_cost``): the comfort motion's 2 m/s² from window 1 on (ramped up at 4 m/s³) ends
the horizon 1.9 m/s faster than holding a standstill (950 less), more than staying behind a slower
human saves: the paper's separation reward (at most 100 a step, 715 over the horizon) and the
effort of accelerating (about 20); a colliding sampled future (up to 66,000) and the following
rule still outweigh it (docs/closed_loop.md)."""
FOLLOW_LATERAL = COLLISION_DY + 0.5
"""How close sideways (m, centre to centre) the human, held where it is, is in the robot's way
(:func:`stopping_shortfall`): the collision rule's 1.8 m and half a metre for the human's sideways
motion in the next 0.6 s."""
STANDOFF_WITHIN = 3.0
"""How long (s) before the cutoff a ``comfort-first`` robot that has not set out falls back on the
decisive mode in a stand-off: while the set-out rule holds it in its lane and, both cars keeping
their speeds, would still hold it :data:`FALLBACK_WITHIN` s before the cutoff
(:meth:`Mode.fallback_for`; docs/closed_loop.md)."""
FALLBACK_WITHIN = 2.0
"""How long (s) before the cutoff a ``comfort-first`` robot that has not set out falls back on the
decisive mode (:meth:`Mode.fallback_for`). Set out a window later, the comfort motion's lane
change would take the robot across the swap line (1.4 s from rest) 0.3 s before the cutoff, the
decisive one's (1.0 s) 0.7 s before it: a little time for the decisive robot to get clear of the
human first (docs/closed_loop.md)."""
_DECISIVE = Mode(MOTIONS["settled"], TURN_BACK_COST, commit_offset=COMMIT_OFFSET, set_out_gap=SET_OUT_GAP,
                 follow_braking=MOTIONS["settled"].hardest_braking)
_COMFORT = Mode(MOTIONS["comfort"], TURN_BACK_COST, commit_offset=COMMIT_OFFSET, set_out_gap=SET_OUT_GAP, set_out_until=2.5,
                follow_braking=MOTIONS["comfort"].hardest_braking)
_COMFORT_FIRST_RULES = {"standoff_exit_cost": STANDOFF_EXIT_COST, "progress_cost": PROGRESS_COST}
"""What ``comfort-first`` and both its fallbacks add to their motions' modes: the stand-off exit,
and getting going again in the goal lane."""
MODES = {
    "paper": Mode(),
    "decisive": _DECISIVE,
    "comfort": _COMFORT,
    "cautious": replace(_DECISIVE, risk=0.2),
    "comfort-first": replace(_COMFORT, **_COMFORT_FIRST_RULES, fallback=replace(_DECISIVE, **_COMFORT_FIRST_RULES),
                             safety_fallback=replace(_COMFORT, motion=MOTIONS["safety"], **_COMFORT_FIRST_RULES,
                                                     follow_braking=MOTIONS["safety"].hardest_braking),
                             fallback_within=FALLBACK_WITHIN, standoff_within=STANDOFF_WITHIN),
}
"""The planner's modes: the paper's exactly; ``decisive`` (it keeps to a lane change once under way,
does not start one beside the human, settles on the lane centre, keeps a gap it can stop in behind
a human braking as hard as it can itself, :attr:`~.candidates.Motion.hardest_braking`); ``comfort`` (the same within
nuPlan's comfort limits, with longer lane changes and so a longer look at the gap before setting
out); ``cautious`` (decisive, judged by the worst 20 % of its sampled futures: CVaR_0.2);
``comfort-first`` (comfort, falling back on decisive when the robot has not set out
:data:`FALLBACK_WITHIN` s before the cutoff, or :data:`STANDOFF_WITHIN` s before it in a
stand-off, or in a stand-off once the human has braked along with it; and on comfort braking as
hard as decisive, steering as comfortably as before (``safety_fallback``), when the human ahead
brakes harder than comfort allows; in each, beside the human it makes room: the stand-off exit,
:data:`STANDOFF_EXIT_COST`, and once in its goal lane it does not stay slower than
:data:`YIELD_SPEED_FLOOR` where it need not, :data:`PROGRESS_COST`; docs/closed_loop.md)."""


def risk_cost(scores: torch.Tensor, risk: float) -> torch.Tensor:
    """Each candidate's cost ``[k]`` from its sampled futures' costs ``scores [n, k]``: the mean of
    the worst ``ceil(risk · n)`` (CVaR; ``risk`` 1: the mean)."""
    if risk >= 1.0:
        return scores.mean(0)
    return torch.topk(scores, max(1, int(np.ceil(risk * scores.shape[0]))), dim=0).values.mean(0)


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


def standoff_exit(robot: np.ndarray, human: np.ndarray, motion: Motion, gap: float) -> int:
    """The acceleration index of ``motion`` by which the robot leaves a stand-off, from the cars'
    present states ``robot [6]``, ``human [6]``: its hardest acceleration, if that gets it ``gap`` m
    ahead of the human more than :data:`YIELD_MARGIN` s sooner than its hardest braking, down to
    :data:`YIELD_SPEED_FLOOR` and no slower, gets it ``gap`` m behind (both held from now; the human
    holding its present acceleration for :data:`HUMAN_ACCELERATION_HELD` s, then its speed); else
    that braking. A robot already accelerating (the way out the last plan chose) keeps going ahead
    unless braking is that much sooner: each window it executes changes the cars' speeds, and
    without that the way out could turn at every plan. A human that brakes or accelerates with the
    robot makes the other way out the sooner; one that slows with the robot to the floor leaves it
    only the way ahead."""
    dx, dv = robot[0] - human[0], robot[2] - human[2]
    braking_for = max(robot[2] - YIELD_SPEED_FLOOR, 0.0) / motion.hardest_braking  # s until the floor
    behind = _time_to_gain(gap + dx, -dv, motion.hardest_braking, human[4], braking_for)
    ahead = _time_to_clear_ahead(robot, human, motion, gap)
    go_ahead = not behind + YIELD_MARGIN < ahead if robot[4] > 0 else ahead + YIELD_MARGIN < behind
    return int(np.argmax(motion.accelerations) if go_ahead else np.argmin(motion.accelerations))


def _time_to_clear_ahead(robot: np.ndarray, human: np.ndarray, motion: Motion, gap: float) -> float:
    """How long (s) the robot ``robot [6]``, at ``motion``'s hardest acceleration from now, takes to
    get ``gap`` m ahead of the human ``human [6]`` holding its present acceleration for
    :data:`HUMAN_ACCELERATION_HELD` s, then its speed (inf: never)."""
    return _time_to_gain(gap - (robot[0] - human[0]), robot[2] - human[2], max(motion.accelerations), -human[4])


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
                       motion: Motion) -> np.ndarray:
    """Per candidate, how far (m) the robot would come short of stopping behind the human ``[C]``
    (0: it can stop), from the cars' present states ``robot [6]``, ``human [6]`` and the
    candidates' robot states ``states [C, 15, 6]``. The human brakes from now at ``human_braking``
    m/s² (or as hard as it brakes now, if harder) to a stop, keeping its lateral position; the
    robot follows the candidate to the end of window 1 (0.6 s: a plan made next can first brake
    after it) and then brakes at ``motion``'s hardest (reached at its jerk limit: a delay of half
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
    b_r = motion.hardest_braking
    v_h = max(human[2], 0.0)

    def human_x(t):
        moving = np.minimum(t, v_h / b_h)
        return human[0] + v_h * moving - 0.5 * b_h * moving ** 2

    in_way = np.abs(states[..., 1] - human[1]) < FOLLOW_LATERAL  # [C, 15]
    steps = DT * np.arange(1, end + 1)
    gaps_before = np.where(in_way[:, :end], human_x(steps) - states[:, :end, 0] - COLLISION_DX, np.inf)

    x, v, a = states[:, end - 1, 0], np.maximum(states[:, end - 1, 2], 0.0), states[:, end - 1, 4]
    delay = np.zeros_like(v) if motion.jerk is None else np.maximum(a + b_r, 0.0) / (2 * motion.jerk)

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


@runtime_checkable
class HumanModel(Protocol):
    """A model of the human the planner can sample from (the distribution of the human's future
    actions given the history and the robot's future, paper §II-A), in physical units.

    ``prepare`` is called with the ``history [t+1, 2, 6]`` (robot, human states at steps 0..t) and
    the robot futures a stage samples for, ``robot_futures [C, 15, 6]``; ``sample`` then returns
    human accelerations ``[n, len(candidates), 15, 2]`` (m/s², ``[xdd, ydd]`` at steps
    t+1..t+15) for indices ``candidates [k]`` into them (a tensor on :attr:`device`), drawn with
    ``generator``.
    The planner's tensors live on :attr:`device` in :attr:`dtype`.
    """

    device: torch.device
    dtype: torch.dtype

    def prepare(self, history: np.ndarray, robot_futures: np.ndarray) -> None: ...

    def sample(self, candidates: torch.Tensor, n: int, generator: torch.Generator) -> torch.Tensor: ...


@dataclass(frozen=True)
class Budget:
    """Sample counts of the two stages (the paper's, §V-C: 16 per candidate, best 32, 1024 each):
    positive integers, at most :data:`~.candidates.N_CANDIDATES` finalists."""

    first_stage_samples: int = 16
    finalists: int = 32
    second_stage_samples: int = 1024

    def __post_init__(self):
        validate.integer("first_stage_samples", self.first_stage_samples, 1)
        validate.integer("finalists", self.finalists, 1, N_CANDIDATES)
        validate.integer("second_stage_samples", self.second_stage_samples, 1)

    @property
    def futures(self) -> int:
        """Simulated human futures per plan (all :data:`~.candidates.N_CANDIDATES` candidates scored)."""
        return N_CANDIDATES * self.first_stage_samples + self.finalists * self.second_stage_samples


def plan_options(budget: Budget | None, deadline: float | None) -> tuple[Budget | None, float | None]:
    """``budget`` and ``deadline`` (s) of :meth:`Planner.plan`, checked: a :class:`Budget` or
    None, and None or a finite number of seconds > 0."""
    if budget is not None and not isinstance(budget, Budget):
        raise InputError(f"budget must be a Budget(first_stage_samples, finalists, second_stage_samples) or None, got {budget!r}")
    return budget, None if deadline is None else validate.positive_seconds("deadline", deadline)


def check_cost(cost) -> Cost:
    """``cost``, checked to be callable (see :mod:`.costs`)."""
    if not callable(cost):
        raise InputError(f"cost must be a callable (robot [..., 15, 6], human [..., 15, 6]) -> [...], got {cost!r}")
    return cost


@dataclass
class Plan:
    """A planning result. ``actions [5]`` the chosen action sequence (window 0 = the fixed one),
    ``index`` its candidate index, ``robot [15, 6]`` its robot states; diagnostics:
    ``candidates`` (all robot futures), ``first_stage_cost [C]`` (the mode's cost, :class:`Mode`),
    ``finalists [k]`` and ``second_stage_cost [k]``, ``human [n, 15, 6]`` sampled human futures
    for the chosen candidate, ``futures`` (human futures simulated), ``seconds``, and
    ``first_stage_samples`` / ``shortlist_samples`` (real time: the more samples each of the
    :data:`SHORTLIST` got; 0: none) / ``second_stage_samples`` actually used, and the ``mode`` it
    planned in (the planner's, or the one :meth:`Planner.plan` was given)."""

    actions: np.ndarray
    index: int
    robot: np.ndarray
    candidates: Candidates
    first_stage_cost: np.ndarray
    finalists: np.ndarray
    second_stage_cost: np.ndarray
    human: np.ndarray
    futures: int
    seconds: float
    first_stage_samples: int
    shortlist_samples: int
    second_stage_samples: int
    mode: Mode
    timings: dict = field(default_factory=dict)


class Planner:
    """Plans robot action sequences against a :class:`HumanModel`, on its device, drawing its
    random numbers from one generator seeded with ``seed`` (the same seed, model and calls give
    the same plans). ``budget``: the default sample counts of :meth:`plan` (None: the paper's);
    ``mode``: how it drives (:class:`Mode`; default: the paper's)."""

    def __init__(self, human_model: HumanModel, budget: Budget | None = Budget(), seed: int = 0,
                 mode: Mode = Mode()):
        if not isinstance(human_model, HumanModel):
            raise InputError(f"human_model must be a HumanModel (prepare, sample, device, dtype; for a CVAE: "
                             f"HumanPredictor(cvae)), got {type(human_model).__name__}")
        self.human_model = human_model
        if not isinstance(mode, Mode):
            raise InputError(f"mode must be a planner Mode, got {mode!r}")
        self.mode = mode
        self.budget = plan_options(budget, None)[0] or Budget()
        self.device, self.dtype = torch.device(human_model.device), human_model.dtype
        self.generator = torch.Generator(device=self.device).manual_seed(validate.integer("seed", seed, 0))
        self.rows_per_second: float | None = None  # measured futures sampled and scored per second

    @property
    def motion(self) -> Motion:
        """How the candidates move the robot (the mode's; a plan in another mode moves as its
        :attr:`Plan.mode`)."""
        return self.mode.motion

    def _situation(self, history, first_action, mode: Mode | None) -> tuple[np.ndarray, Mode, Candidates,
                                                                             torch.Tensor, torch.Tensor]:
        """The checked ``history [t+1, 2, 6]``, the checked ``mode`` (None: the planner's), the
        candidates from the history moving as that mode with window 0 fixed to the checked
        ``first_action``, their states ``[C, 15, 6]`` and the human's present state ``[6]`` as
        tensors."""
        history = validate.history(history)
        mode = self.mode if mode is None else mode
        if not isinstance(mode, Mode):
            raise InputError(f"mode must be a planner Mode or None, got {mode!r}")
        candidates = robot_candidates(history[-1, 0], validate.integer("first_action", first_action, 0, N_ACTIONS - 1),
                                      mode.motion)
        robot = torch.as_tensor(candidates.states, dtype=self.dtype, device=self.device)
        human_present = torch.as_tensor(history[-1, 1], dtype=self.dtype, device=self.device)
        return history, mode, candidates, robot, human_present

    def _rules(self, mode: Mode, candidates: Candidates, history: np.ndarray, cost: Cost) -> torch.Tensor:
        """``mode``'s rule costs of each candidate ``[C]`` towards the goal lane of ``cost`` (its
        ``goal_y``; none for a cost without one): turning back (:func:`turn_backs`, once the robot,
        at the last step of ``history``, is ``commit_offset`` from the other lane's centre) and
        setting out beside the human (:func:`set_outs`, while the human would be less than
        ``set_out_gap`` ahead or behind as the candidate moves the robot across, and is not in the
        robot's lane: :meth:`Mode.blocks_set_out_along`), and then, in a stand-off
        (:meth:`Mode.blocks_set_out`) before it has set out, not taking the way out of the stand-off
        (:meth:`Mode.way_out`, with ``standoff_exit_cost``); in the goal lane below
        :data:`YIELD_SPEED_FLOOR`, ending the horizon short of it (``progress_cost`` per m/s); and
        coming short of stopping behind it (:func:`stopping_shortfall`, with ``follow_braking``)."""
        goal_y = getattr(cost, "goal_y", None)
        rules = np.zeros(len(candidates))
        if goal_y is not None:
            goal = str(lane_of(np.array([goal_y]))[0])
            other = next(lane for lane in LANES if lane != goal)
            robot, human = history[-1]
            if abs(robot[1] - LANE_CENTRE_Y[other]) >= mode.commit_offset:
                rules += mode.turn_back_cost * turn_backs(candidates.actions, goal)
            if mode.set_out_gap:
                blocked = mode.blocks_set_out_along(candidates.states, robot, human)
                rules += SET_OUT_COST * (set_outs(candidates.actions, goal) & blocked)
            not_set_out = Action(int(candidates.actions[0, 0])).lane != goal
            if mode.standoff_exit_cost and not_set_out and mode.blocks_set_out(robot, human):
                way = mode.way_out(history)
                rules += mode.standoff_exit_cost * (acceleration_indices(candidates.actions[:, 1]) != way)
            if mode.progress_cost and lane_of(robot[1:2])[0] == goal and robot[2] < YIELD_SPEED_FLOOR:
                rules += mode.progress_cost * np.maximum(YIELD_SPEED_FLOOR - candidates.states[:, -1, 2], 0.0)
        if mode.follow_braking:
            rules += FOLLOW_COST * stopping_shortfall(history[-1, 0], candidates.states, history[-1, 1],
                                                      mode.follow_braking, mode.motion)
        return torch.as_tensor(rules, dtype=self.dtype, device=self.device)

    def _sample(self, prepared: torch.Tensor, n: int, human_present: torch.Tensor) -> torch.Tensor:
        """``n`` sampled human futures ``[n, k, 15, 6]`` for the prepared robot futures ``prepared [k]``
        (indices into the last ``prepare``)."""
        actions = self.human_model.sample(prepared, n, self.generator)
        return future_states(human_present, actions.to(self.dtype))

    def _scores(self, prepared: torch.Tensor, robot: torch.Tensor, n: int, human_present: torch.Tensor,
                cost: Cost) -> tuple[torch.Tensor, torch.Tensor]:
        """Costs ``[n, k]`` of ``n`` sampled human futures for each of the robot futures ``robot [k,
        15, 6]`` (prepared as ``prepared [k]``), and those futures; updates the measured rate."""
        start = time.perf_counter()
        human = self._sample(prepared, n, human_present)
        scores = cost(robot.unsqueeze(0), human)
        rate = n * len(prepared) / max(time.perf_counter() - start, 1e-6)
        self.rows_per_second = rate if self.rows_per_second is None else 0.7 * self.rows_per_second + 0.3 * rate
        return scores, human

    def _screen(self, history: np.ndarray, candidates: Candidates, robot: torch.Tensor, human_present: torch.Tensor,
                cost: Cost, risk: float) -> torch.Tensor:
        """Real-time stage 1: costs ``[C]`` (judged with ``risk``, :func:`risk_cost`) of every
        candidate against :data:`SCREENING_SAMPLES` human futures shared by the candidates with the
        same window-1 action, sampled conditioned on the candidate that holds that action to the
        horizon."""
        holding = np.arange(N_ACTIONS) * sum(N_ACTIONS ** w for w in range(WINDOWS - 1))  # [a, a, a, a] (action_sequences)
        self.human_model.prepare(history, candidates.states[holding])
        human = self._sample(torch.arange(N_ACTIONS, device=self.device), SCREENING_SAMPLES, human_present)
        # action_sequences orders the candidates by their window-1 action: [N_ACTIONS, C / N_ACTIONS] groups
        grouped = cost(robot.reshape(N_ACTIONS, -1, *robot.shape[1:]).unsqueeze(0), human.unsqueeze(2))
        return risk_cost(grouped.reshape(len(grouped), -1), risk)

    @torch.no_grad()
    def plan(self, history: np.ndarray, first_action: int, cost: Cost, budget: Budget | None = None,
             deadline: float | None = None, keep_samples: int = 64, mode: Mode | None = None) -> Plan:
        """Plan from ``history [t+1, 2, 6]`` (robot, human states at steps 0..t, physical units)
        with window 0 fixed to ``first_action``.

        Without ``deadline``, ``budget`` (default: the planner's) is spent in full, as in the
        paper: stage 1 scores every candidate against its own sampled human futures. With
        ``deadline`` (s), the plan returns within it (once stage 1 is done): stage 1 samples each
        candidate's own futures where two or more fit in :data:`OWN_FUTURES_SHARE` of the deadline at
        the measured rate (at most the budget's), else it screens every candidate (:meth:`_screen`);
        after own futures, the :data:`SHORTLIST` best get more samples of their own
        (:data:`SHORTLIST_SHARE` of the time left) and the finalists are the best of them by all their
        samples; then stage 2 samples the finalists' own human futures in rounds until the time is
        spent (at most the budget's). ``keep_samples``: how many of the
        chosen candidate's human futures the plan keeps; ``mode``: plan in this :class:`Mode`
        instead of the planner's (its fallback, say). Bad arguments raise
        :class:`~trafficweaving.errors.InputError`: ``history`` must be finite with at least
        ``MIN_HISTORY`` steps, ``first_action`` an integer in ``0..N_ACTIONS-1``, ``deadline`` None
        or finite > 0.
        """
        clock = time.perf_counter()
        check_cost(cost)
        budget, deadline = plan_options(budget, deadline)
        budget = budget or self.budget
        keep_samples = validate.integer("keep_samples", keep_samples, 0)
        left = (lambda: deadline - (time.perf_counter() - clock)) if deadline is not None else (lambda: np.inf)  # noqa: E731
        timings = {}
        history, mode, candidates, robot, human_present = self._situation(history, first_action, mode)
        rules = self._rules(mode, candidates, history, cost)
        timings["candidates"] = time.perf_counter() - clock
        count = len(candidates)

        # stage 1: every candidate with n1 samples of its own each (paper; real time: as many as fit) or screened
        n1 = budget.first_stage_samples
        if deadline is not None:
            n1 = min(n1, int(self._rate() * OWN_FUTURES_SHARE * deadline) // count)
        screening = deadline is not None and n1 < 2
        if screening:
            first_cost, n1 = self._screen(history, candidates, robot, human_present, cost, mode.risk), SCREENING_SAMPLES
        else:
            self.human_model.prepare(history, candidates.states)
            scores = self._scores(torch.arange(count, device=self.device), robot, n1, human_present, cost)[0]
            first_cost = risk_cost(scores, mode.risk)
        first_cost = first_cost + rules
        timings["first_stage"] = time.perf_counter() - clock - sum(timings.values())

        # the finalists; in real time after own futures, the best of a shortlist given more samples
        k, n_short = budget.finalists, 0
        finalists = torch.topk(first_cost, k, largest=False).indices
        if deadline is not None and not screening and k < SHORTLIST < count:
            n_short = max(int(self._rate() * SHORTLIST_SHARE * left()) // SHORTLIST, 0)
            if n_short:
                shortlist = torch.topk(first_cost, SHORTLIST, largest=False).indices
                more = self._scores(shortlist, robot[shortlist], n_short, human_present, cost)[0]
                shortlist_cost = risk_cost(torch.cat([scores[:, shortlist], more]), mode.risk) + rules[shortlist]
                finalists = shortlist[torch.topk(shortlist_cost, k, largest=False).indices]
            timings["shortlist"] = time.perf_counter() - clock - sum(timings.values())

        # stage 2: the finalists, n2 samples of their own each, in rounds while time allows (one at least)
        if screening:
            self.human_model.prepare(history, candidates.states[finalists.cpu().numpy()])
            prepared = torch.arange(k, device=self.device)
        else:
            prepared = finalists
        n2 = budget.second_stage_samples
        rounds, used, kept = [], 0, []
        round_size = n2 if deadline is None else min(n2, 16)
        while used < n2:
            n = min(round_size, n2 - used)
            if used and 1.5 * n * k / self._rate() > left() - 0.01:
                break
            scores, human = self._scores(prepared, robot[finalists], n, human_present, cost)
            rounds.append(scores)
            used += n
            kept.append(human)
        second_cost = (risk_cost(torch.cat(rounds), mode.risk) + rules[finalists] if used
                       else first_cost[finalists])
        best = int(torch.argmin(second_cost))
        index = int(finalists[best])
        human = torch.cat(kept, 0)[:keep_samples, best] if kept else torch.zeros((0, HORIZON, len(STATE_NAMES)))
        timings["second_stage"] = time.perf_counter() - clock - sum(timings.values())
        futures = (N_ACTIONS if screening else count) * n1 + n_short * SHORTLIST + used * k
        return Plan(
            actions=candidates.actions[index], index=index, robot=candidates.states[index], candidates=candidates,
            first_stage_cost=first_cost.cpu().numpy(), finalists=finalists.cpu().numpy(),
            second_stage_cost=second_cost.cpu().numpy(), human=human.cpu().double().numpy(),
            futures=futures, seconds=time.perf_counter() - clock,
            first_stage_samples=n1, shortlist_samples=n_short, second_stage_samples=used, mode=mode, timings=timings)

    @torch.no_grad()
    def score(self, history: np.ndarray, first_action: int, cost: Cost, indices, samples: int) -> tuple[np.ndarray, np.ndarray]:
        """The mode's costs ``[k]`` (:class:`Mode`: risk over the futures, its rules) of candidates
        ``indices [k]`` (of :func:`robot_candidates` with window 0 fixed to ``first_action``) from
        ``samples`` fresh human futures each, and those
        futures ``[samples, k, 15, 6]`` (for re-scoring a choice and for figures). Arguments are
        checked as by :meth:`plan`."""
        check_cost(cost)
        indices = validate.indices("indices", indices, N_CANDIDATES)
        samples = validate.integer("samples", samples, 1)
        history, mode, candidates, robot, human_present = self._situation(history, first_action, None)
        self.human_model.prepare(history, candidates.states[indices])
        chosen = torch.as_tensor(indices, device=self.device)
        scores, human = self._scores(torch.arange(len(chosen), device=self.device), robot[chosen], samples,
                                     human_present, cost)
        total = risk_cost(scores, mode.risk) + self._rules(mode, candidates, history, cost)[chosen]
        return total.cpu().double().numpy(), human.cpu().double().numpy()

    def _rate(self) -> float:
        """Measured human futures sampled and scored per second (a conservative guess before any)."""
        return self.rows_per_second or 20_000.0


def example_history(steps: int = 10, gap: float = 2.0) -> np.ndarray:
    """A contested situation ``[steps, 2, 6]`` for benchmarks and figures: the robot in the right
    lane and the human in the left lane ``gap`` m ahead, both at 29 m/s, at constant speed for
    ``steps`` steps ending about 90 m before the cutoff (both must swap lanes)."""
    t = DT * np.arange(steps)[:, None]
    robot = np.array([-90.0 - 29.0 * DT * (steps - 1), LANE_CENTRE_Y["right"], 29.0, 0.0, 0.0, 0.0])
    human = robot + [gap, LANE_CENTRE_Y["left"] - LANE_CENTRE_Y["right"], 0.0, 0.0, 0.0, 0.0]
    motion = t * np.array([29.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    return np.stack([robot + motion, human + motion], axis=1)
