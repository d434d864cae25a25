"""The robot's candidate futures (paper §V-C): 8 actions per 0.3 s window, 5 windows over the
15-step horizon, the first one fixed, so ``8^4 = 4096`` sequences of 15 robot states.

An action is a longitudinal acceleration held for the window and a lateral target lane, steered
to by :mod:`.steering`. How an action moves the robot is the candidates' :class:`Kinematics`
(:data:`KINEMATICS`): the paper's, or ``"comfort"``, within the closed-loop score's comfort
limits (:data:`trafficweaving.sim.score.COMFORT_LIMITS`). State convention (as in the authors'
recordings of their robot): the ``xdd`` stored at step ``k`` is the acceleration applied from
``k`` to ``k+1``; ``xd`` is integrated with Euler and ``x`` with the trapezoid rule.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..dynamics import robot_longitudinal
from ..scenario import DT, HORIZON, LANE_CENTRE_Y, LANES, REPLAN_STEPS
from .steering import JERK_WEIGHT, jerk_limited_steer, steer

ACCELERATIONS = (0.0, 4.0, -3.0, -6.0)
"""The longitudinal actions, m/s²; the lateral ones are the :data:`~trafficweaving.scenario.LANES`
(steering to the lane centre)."""
STEPS_PER_WINDOW = REPLAN_STEPS
"""Steps an action is held (0.3 s): the replanning period."""
if HORIZON % STEPS_PER_WINDOW:
    raise ImportError(f"the horizon of {HORIZON} steps is not a whole number of {STEPS_PER_WINDOW}-step windows")
WINDOWS = HORIZON // STEPS_PER_WINDOW
"""Action windows per candidate (5), the first one fixed."""


def acceleration_indices(actions: np.ndarray | int) -> np.ndarray | int:
    """The acceleration index (into a :class:`Kinematics`' ``accelerations``) of action indices ``actions``."""
    return actions // len(LANES)


@dataclass(frozen=True)
class Action:
    """One window's action: index ``0..N_ACTIONS-1`` = ``len(LANES) · acceleration index + lane index``."""

    index: int

    @property
    def acceleration(self) -> float:
        return ACCELERATIONS[acceleration_indices(self.index)]

    @property
    def lane(self) -> str:
        return LANES[self.index % len(LANES)]

    @staticmethod
    def of(acceleration: float, lane: str) -> "Action":
        return Action(len(LANES) * ACCELERATIONS.index(acceleration) + LANES.index(lane))


@dataclass(frozen=True)
class Kinematics:
    """How the candidates' actions move the robot: the longitudinal ``accelerations`` (m/s², one
    per acceleration index of :class:`Action`; the first is 0, holding the speed), reached from the
    present acceleration at most ``jerk`` m/s³ (None: at once, and held through the window, as in
    the paper), the lateral steering's jerk weight ``steering_weight`` (ρ of :mod:`.steering`) and
    its shortest final time ``min_steering_time`` (s; :func:`~.steering.steer`: 0 as in the paper,
    0.6 s settles on the lane centre without chatter); or, with ``lateral_limits`` (largest
    lateral acceleration, m/s², and jerk, m/s³), the time-optimal steering within them and
    ``min_steering_time`` instead (:func:`~.steering.jerk_limited_steer`)."""

    accelerations: tuple[float, ...]
    jerk: float | None
    steering_weight: float = JERK_WEIGHT
    min_steering_time: float = 0.0
    lateral_limits: tuple[float, float] | None = None

    @property
    def hardest_braking(self) -> float:
        """The hardest braking, m/s² (positive)."""
        return -min(self.accelerations)

    def steer(self, state: np.ndarray, target: np.ndarray, times: np.ndarray) -> np.ndarray:
        """Lateral states ``[..., len(times), 3]`` (y, yd, ydd) at ``times`` (s) from ``state [..., 3]``
        steering to the lane centre ``target [...]`` (m) as these kinematics do."""
        if self.lateral_limits is not None:
            return jerk_limited_steer(state, target, times, *self.lateral_limits, self.min_steering_time)
        return steer(state, target, times, self.steering_weight, self.min_steering_time)[..., :3]


SETTLING_TIME = 0.6
"""Shortest lateral manoeuvre (s) of the settled kinematics: two windows, six executed steps."""
_COMFORT_KINEMATICS = Kinematics((0.0, 2.0, -2.0, -4.0), 4.0, min_steering_time=SETTLING_TIME, lateral_limits=(4.5, 7.0))
KINEMATICS = {
    "paper": Kinematics(ACCELERATIONS, None, JERK_WEIGHT),
    "settled": Kinematics(ACCELERATIONS, None, JERK_WEIGHT, SETTLING_TIME),
    "comfort": _COMFORT_KINEMATICS,
    "safety": replace(_COMFORT_KINEMATICS, accelerations=ACCELERATIONS, jerk=None),
}
"""The candidates' kinematics: ``paper`` (a lane change from rest takes 2.0 s, peaking at
6.1 m/s² and 31 m/s³ sideways); ``settled``, the same with lateral manoeuvres of at least
:data:`SETTLING_TIME` (no chatter on the lane centre); ``comfort``, within the comfort limits of
:data:`trafficweaving.sim.score.COMFORT_LIMITS` from any state: accelerations 0, +2, −2, −4 m/s²
ramped at 4 m/s³, time-optimal lateral manoeuvres within 4.5 m/s² and 7.0 m/s³ (a lane change
from rest takes 2.7 s); ``safety``, the settled accelerations with the comfort steering, to brake
as hard as ``settled`` while keeping to the comfort limits sideways (docs/driving.md)."""

N_ACTIONS = len(ACCELERATIONS) * len(LANES)
"""Actions per window (8)."""
N_CANDIDATES = N_ACTIONS ** (WINDOWS - 1)
"""Candidate action sequences per plan (4096): every choice for the free windows."""


@dataclass
class Candidates:
    """``states [C, 15, 6]`` robot states at steps t+1..t+15 for each candidate; ``actions [C, 5]``
    action index per window (window 0 is the fixed one, the same for all)."""

    states: np.ndarray
    actions: np.ndarray

    def __len__(self) -> int:
        return len(self.actions)


def action_sequences(first: int, windows: int = WINDOWS) -> np.ndarray:
    """All ``[N_ACTIONS^(windows-1), windows]`` action sequences starting with ``first``; the
    earliest free window varies slowest."""
    free = np.stack(np.meshgrid(*[np.arange(N_ACTIONS)] * (windows - 1), indexing="ij"), -1).reshape(-1, windows - 1)
    return np.concatenate([np.full((len(free), 1), first), free], axis=1)


def rollout(present: np.ndarray, actions: np.ndarray, kinematics: Kinematics = KINEMATICS["paper"]) -> np.ndarray:
    """Robot states ``[C, 3·W, 6]`` after ``present [6]`` under action sequences ``actions [C, W]``
    moving as ``kinematics``.

    The lateral boundary-value problem is solved once per distinct prefix of lane choices (at most
    ``len(LANES)^W`` solves), not once per candidate.
    """
    present = np.asarray(present, dtype=float)
    actions = np.asarray(actions)
    c, w = actions.shape
    steps = STEPS_PER_WINDOW * w
    # longitudinal: acceleration applied from each step (acc [C, steps], from t+k), Euler velocity, trapezoid position
    acc = np.repeat(np.asarray(kinematics.accelerations)[acceleration_indices(actions)], STEPS_PER_WINDOW, axis=1)
    acc = applied_accelerations(np.full(c, present[4]), acc, kinematics.jerk)
    x, xd = robot_longitudinal(np.full(c, present[0]), np.full(c, present[2]), acc)  # at t+1..t+steps
    xdd = np.concatenate([acc[:, 1:], acc[:, -1:]], axis=1)  # stored at t+k: applied from t+k (last: held)

    # lateral: walk the tree of lane choices, one steering solve per distinct prefix
    base = len(LANES)  # a prefix of lane choices is coded as a number in this base
    lanes = actions % base  # [C, W]
    lateral = np.empty((c, steps, 3))
    times = DT * np.arange(1, STEPS_PER_WINDOW + 1)
    targets = np.array([LANE_CENTRE_Y[lane] for lane in LANES])
    starts, parent = present[None, [1, 3, 5]], np.zeros(c, dtype=np.int64)  # start state of each prefix
    for k in range(w):
        codes = parent * base + lanes[:, k]  # prefix code after window k
        unique, inverse = np.unique(codes, return_inverse=True)
        path = kinematics.steer(starts[unique // base], targets[unique % base], times)  # [P, 3, 3]
        lateral[:, STEPS_PER_WINDOW * k: STEPS_PER_WINDOW * (k + 1)] = path[inverse]
        starts = np.zeros((base * (unique.max() + 1), 3))
        starts[unique] = path[:, -1]
        parent = codes
    return np.stack([x, lateral[..., 0], xd, lateral[..., 1], xdd, lateral[..., 2]], axis=-1)


def applied_accelerations(present: np.ndarray, targets: np.ndarray, jerk: float | None) -> np.ndarray:
    """The longitudinal accelerations ``[C, steps]`` (m/s²) applied from steps t..t+steps-1
    towards ``targets [C, steps]`` from the present accelerations ``present [C]``: the targets
    themselves (``jerk`` None), else from the present one towards each step's target by at most
    ``jerk``·DT a step."""
    acc = np.array(targets, dtype=float)
    if jerk is not None:
        acc[:, 0] = present
        for k in range(1, acc.shape[1]):
            acc[:, k] = acc[:, k - 1] + np.clip(acc[:, k] - acc[:, k - 1], -jerk * DT, jerk * DT)
    return acc


def robot_candidates(present: np.ndarray, first: int, kinematics: Kinematics = KINEMATICS["paper"]) -> Candidates:
    """The :data:`N_CANDIDATES` candidates from the robot's ``present [6]`` state with window 0
    fixed to ``first``, moving as ``kinematics``."""
    actions = action_sequences(first)
    return Candidates(rollout(present, actions, kinematics), actions)
