"""The traffic-weaving scenario: road, cars, time step, the study's initial conditions and the
validity rules of a trial.

Every number that describes the scenario lives here (paper §II-C "Traffic Weaving Scenario" and
§V-A "Data Collection"); other modules import them.
Coordinates: ``x`` longitudinal in m (0 at the cutoff, negative before it), ``y`` lateral in m
(0 at the left edge of the left lane, negative to the right).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

DT = 0.1
"""Time step of every trajectory, s."""

STATE_NAMES = ("x", "y", "xd", "yd", "xdd", "ydd")
"""Order of the 6 state components of a car: position, velocity, acceleration (m, m/s, m/s²)."""

LANE_CENTRE_Y = {"left": -1.83, "right": -6.09}
"""Lateral coordinate of each lane centre, m."""
LANES = tuple(LANE_CENTRE_Y)
"""Lane names, left first: ``("left", "right")``."""
LANE_DIVIDER_Y = -3.96
"""Lane divider, m (used for drawing and for deciding which lane a car is in)."""
SWAP_THRESHOLD_Y = -4.0
"""A car has changed lane once it is on the other side of this ``y`` (authors' sanitising), m."""
ROAD_Y_MIN, ROAD_Y_MAX = -8.0, -1.0
"""A trial is valid only while both cars keep ``ROAD_Y_MIN <= y <= ROAD_Y_MAX``, m."""

CAR_LENGTH = 4.22
CAR_WIDTH = 1.76
COLLISION_DX, COLLISION_DY = 4.5, 1.8
"""Two cars collide when ``|Δx| < COLLISION_DX`` and ``|Δy| < COLLISION_DY`` at the same step, m."""

ROAD_END_X = 0.0
"""The cutoff: where the two lanes end (the origin of ``x``), m."""
CUTOFF_X = 2.0
"""The validity line of the authors' sanitising, just past :data:`ROAD_END_X`: both cars must have
swapped lanes before reaching this ``x``; valid trials are cut at the step before the first car
reaches it, m."""
RECORD_START_X = -100.0
"""Recordings start at the first step where both cars are behind this ``x`` (bag sanitising), m."""
RECORD_END_X = 20.0
"""Recordings end once both cars are past this ``x`` (bag sanitising), m."""

START_X = -145.0
"""Longitudinal start of the car that starts ahead, m."""
BASE_SPEED = 29.0
"""Speed of car A at the start (65 mph), m/s."""
SPEED_ALERT = 38.0
"""The simulator sounded a high-pitched alert above this speed (85 mph), m/s."""

DELTA_V_VALUES = (-2.0, 0.0, 2.0)
"""Speed difference of car B relative to car A at the start, m/s."""
TCO_VALUES = (1.0, 2.0, 3.0)
"""Crossover times: seconds until the cars would be side by side with no control, s."""
STUDY_TRIALS = 1105
"""Valid human–human trials of the paper's study (§V-A; 19 pairs of drivers)."""

HORIZON = 15
"""Steps of the future the human model predicts and the planner plans (1.5 s; paper §IV-A)."""
REPLAN_STEPS = 3
"""The robot replans every 3 steps and holds each action for as long (paper §V-C)."""
REPLAN_PERIOD_S = round(REPLAN_STEPS * DT, 9)
"""The replanning period, s (0.3 s, rounded so that it equals ``--deadline 0.3``): a plan that takes
longer misses its deadline."""
MIN_HISTORY = 5
"""Fewest history steps a prediction is made from (steps 0..t with ``t >= 4``), as in the paper."""
MIN_TRIAL_STEPS = MIN_HISTORY + HORIZON
"""Shortest usable trial: a 5-step history plus a 15-step future (``4 <= t <= T-16``)."""


@dataclass(frozen=True)
class InitialCondition:
    """One of the study's 18 initial configurations.

    ``dv_ab``: speed of car B minus car A (m/s); ``tco``: crossover time (s); ``swap``: False puts
    car A in the left lane, True in the right lane. Car A starts at ``BASE_SPEED``.
    """

    dv_ab: float
    tco: float
    swap: bool

    @property
    def lane_a(self) -> str:
        return "right" if self.swap else "left"

    @property
    def lane_b(self) -> str:
        return "left" if self.swap else "right"

    @property
    def dv_left_minus_right(self) -> float:
        """Table I's ``Δv = v_left - v_right``, m/s."""
        return self.dv_ab if self.swap else -self.dv_ab

    def start_states(self) -> np.ndarray:
        """Initial states of car A and car B, ``[2, 6]`` (rows: A, B; columns: ``STATE_NAMES``)."""
        v_a, v_b = BASE_SPEED, BASE_SPEED + self.dv_ab
        gap = abs(self.dv_ab) * self.tco  # the faster car starts this far behind, m
        x_a = START_X - (gap if v_a > v_b else 0.0)
        x_b = START_X - (gap if v_b > v_a else 0.0)
        return np.array(
            [
                [x_a, LANE_CENTRE_Y[self.lane_a], v_a, 0.0, 0.0, 0.0],
                [x_b, LANE_CENTRE_Y[self.lane_b], v_b, 0.0, 0.0, 0.0],
            ]
        )


def study_initial_conditions() -> list[InitialCondition]:
    """The 18 configurations of the data collection: Δv × tco × swap (Δv = 0 repeated per tco,
    as in the study, where each round played all 18 shuffled)."""
    return [
        InitialCondition(dv, tco, swap)
        for dv, tco, swap in itertools.product(DELTA_V_VALUES, TCO_VALUES, (False, True))
    ]


VALIDITY_REASONS = ("valid", "collision", "off_road", "no_lane_swap", "cutoff_not_reached")
"""Outcome codes of :func:`check_validity`, indexed by the integer it returns."""


def check_validity(states: np.ndarray, lengths: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Apply the authors' sanitising rules to a batch of two-car recordings.

    ``states``: ``[n, 2, T, 6]`` (trial, car, step, ``STATE_NAMES``), steps past ``lengths`` ignored.
    ``lengths``: ``[n]`` recorded steps per trial. A recording must run until both cars reach
    ``CUTOFF_X``. Rules (the authors' sanitising of their recordings): no collision at any
    recorded step; both cars on the road up to the step where the first reaches ``CUTOFF_X``;
    each car, at its last step before ``CUTOFF_X``, on the other side of ``SWAP_THRESHOLD_Y``
    from its start.

    Returns ``(reason, cut)``: ``reason[n]`` indexes ``VALIDITY_REASONS`` (0 = valid) and ``cut[n]``
    is the number of steps a valid trial keeps (the steps before the first car reaches
    ``CUTOFF_X``).
    """
    states = np.asarray(states, dtype=float)
    lengths = np.asarray(lengths)
    n, _, t_max, _ = states.shape
    steps = np.arange(t_max)
    recorded = steps[None, :] < lengths[:, None]  # [n, T]
    x, y = states[..., 0], states[..., 1]  # [n, 2, T]

    collide = colliding(states[:, 0], states[:, 1])
    collision = (collide & recorded).any(axis=1)

    past = (x >= CUTOFF_X) & recorded[:, None, :]  # [n, 2, T]
    reached = past.any(axis=2)  # [n, 2]
    first_past = np.where(reached, past.argmax(axis=2), t_max)  # [n, 2]
    cut = first_past.min(axis=1)  # [n]

    upto_cut = steps[None, :] <= np.minimum(cut, lengths - 1)[:, None]  # [n, T]
    off_road = (~on_road(y) & upto_cut[:, None, :]).any(axis=(1, 2))

    swapped = swapped_before_cutoff(states, lengths)  # [n, 2]

    reason = np.zeros(n, dtype=np.int8)
    reason[~swapped.all(axis=1)] = VALIDITY_REASONS.index("no_lane_swap")
    reason[off_road] = VALIDITY_REASONS.index("off_road")
    reason[~reached.all(axis=1)] = VALIDITY_REASONS.index("cutoff_not_reached")
    reason[collision] = VALIDITY_REASONS.index("collision")
    return reason, np.where(reason == 0, cut, 0)


def swapped_before_cutoff(states: np.ndarray, lengths: np.ndarray) -> np.ndarray:
    """Per trial and car ``[n, 2]`` (bool): on the other side of ``SWAP_THRESHOLD_Y`` from its
    start at its last recorded step before ``CUTOFF_X`` (its last recorded step if it never reaches
    it), the lane-swap rule of :func:`check_validity`. ``states [n, 2, T, 6]``, ``lengths [n]``."""
    states = np.asarray(states, dtype=float)
    lengths = np.asarray(lengths)
    recorded = np.arange(states.shape[2])[None, None, :] < lengths[:, None, None]  # [n, 1, T]
    past = (states[..., 0] >= CUTOFF_X) & recorded  # [n, 2, T]
    last = np.where(past.any(axis=2), np.maximum(past.argmax(axis=2) - 1, 0), lengths[:, None] - 1)  # [n, 2]
    y = states[..., 1]
    y_end = np.take_along_axis(y, last[..., None], axis=2)[..., 0]
    return across_divider(y[:, :, 0], y_end)


def colliding(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Whether two cars collide, for their states ``a``, ``b`` ``[..., 6]`` at the same steps:
    ``|Δx| < COLLISION_DX`` and ``|Δy| < COLLISION_DY``; shape ``[...]``."""
    return (np.abs(a[..., 0] - b[..., 0]) < COLLISION_DX) & (np.abs(a[..., 1] - b[..., 1]) < COLLISION_DY)


def at_fault_collision(a: np.ndarray, b: np.ndarray, steps: np.ndarray | None = None) -> np.ndarray:
    """Whether car ``a`` collides with car ``b`` and is at fault, for their trajectories ``a``,
    ``b`` ``[n, T, 6]`` (at the steps where ``steps [n, T]`` is true; all when None), after
    nuPlan's at-fault rule adapted to two cars that both change lanes. At the first colliding step:
    when the cars already overlapped laterally one step before (|Δy| < ``COLLISION_DY``) and only
    the longitudinal gap closed, the car behind is at fault (a rear-end collision); otherwise (a
    side collision) the car moving sideways towards the other at least as fast as the other moves
    towards it is. Shape ``[n]`` (bool); a collision at the first step is both cars' fault."""
    hit = colliding(a, b) if steps is None else colliding(a, b) & steps
    rows = np.arange(len(a))
    k = hit.argmax(axis=1)
    before = np.maximum(k - 1, 0)
    rear_end = (k > 0) & (np.abs(a[rows, before, 1] - b[rows, before, 1]) < COLLISION_DY) & ~(
        np.abs(a[rows, before, 0] - b[rows, before, 0]) < COLLISION_DX)
    towards = np.sign(b[rows, k, 1] - a[rows, k, 1])  # +1: b is to a's left
    a_sideways, b_sideways = a[rows, k, 3] * towards, -b[rows, k, 3] * towards  # m/s towards the other
    fault = np.where(rear_end, a[rows, k, 0] < b[rows, k, 0], a_sideways >= b_sideways) | (k == 0)
    return hit.any(axis=1) & fault


def time_to_collision(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Time until two cars touch bumpers at their present speeds, for their states ``a``, ``b``
    ``[..., 6]`` at the same steps: the gap ``|Δx| - CAR_LENGTH`` (0 when overlapping) over the
    closing speed, while they overlap laterally (``|Δy| < COLLISION_DY``) and close in; ``inf``
    otherwise. Seconds, shape ``[...]``."""
    dx = b[..., 0] - a[..., 0]
    closing = -np.sign(dx) * (b[..., 2] - a[..., 2])  # m/s, > 0: the gap shrinks
    same_lane = np.abs(b[..., 1] - a[..., 1]) < COLLISION_DY
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(same_lane & (closing > 0), np.maximum(np.abs(dx) - CAR_LENGTH, 0.0) / closing, np.inf)


def on_road(y: np.ndarray) -> np.ndarray:
    """Whether lateral positions ``y`` (m, any shape) are on the road, ``ROAD_Y_MIN <= y <= ROAD_Y_MAX``."""
    return (y >= ROAD_Y_MIN) & (y <= ROAD_Y_MAX)


def across_divider(y_start: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Whether a car at ``y`` is on the other side of ``SWAP_THRESHOLD_Y`` from where it started,
    ``y_start`` (m; broadcasting): it has swapped lanes."""
    return (SWAP_THRESHOLD_Y - y_start) * (SWAP_THRESHOLD_Y - y) < 0


def lane_of(y: np.ndarray) -> np.ndarray:
    """Lane name (``"left"``/``"right"``) for lateral positions ``y`` (m), any shape."""
    return np.where(np.asarray(y) > LANE_DIVIDER_Y, "left", "right")


def lane_centre_y(y: np.ndarray) -> np.ndarray:
    """The centre line (m) of the lane each lateral position ``y`` (m, any shape) is in (:func:`lane_of`)."""
    return np.where(np.asarray(y) > LANE_DIVIDER_Y, LANE_CENTRE_Y["left"], LANE_CENTRE_Y["right"])
