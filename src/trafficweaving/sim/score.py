"""The closed-loop score of one episode: nuPlan's closed-loop score (Caesar et al., 2021) adapted
to the traffic-weaving task, with its limits and weights.

``score`` = (product of the multipliers) × (the :data:`SCORE_WEIGHTS` mean of the averaged
parts), in [0, 1]; :func:`closed_loop_score` computes it from an episode's recorded states.

Multipliers (each 0 or 1; any 0 makes the score 0):

* ``no_collision``: the episode's outcome is not ``collision`` (``|Δx| < COLLISION_DX`` and
  ``|Δy| < COLLISION_DY`` at a recorded step, :func:`~trafficweaving.scenario.check_validity`).
* ``on_road``: the robot's centre is on the road (:func:`~trafficweaving.scenario.on_road`) at
  every step before it first reaches ``CUTOFF_X``.
* ``lane_swap``: the robot is across ``SWAP_THRESHOLD_Y`` from its start at its last step before
  the cutoff.
* ``reaches_cutoff``: the robot reaches ``CUTOFF_X`` before the episode ends (nuPlan's "making
  progress").

Averaged parts, weighted by :data:`SCORE_WEIGHTS` (``ttc`` 5, ``progress`` 5, ``comfort`` 2, as
nuPlan weighs time to collision, progress and comfort):

* ``ttc``: 1 when the time to collision (:func:`~trafficweaving.scenario.time_to_collision`: the
  bumper gap over the closing speed while the cars overlap laterally) is at least
  :data:`TTC_LIMIT_S` (0.95 s, nuPlan's ego TTC bound) at every recorded step, else 0.
* ``progress``: the mean of the share of the road to the cutoff still ahead when the robot is
  first in the other lane (0 if never) and of its mean speed before the cutoff over its start
  speed (at most 1).
* ``comfort``: 1 when no step of the robot breaks :data:`COMFORT_LIMITS` (nuPlan's: longitudinal
  acceleration in −4.05…2.40 m/s², lateral acceleration within ±4.89 m/s², longitudinal jerk
  within ±4.13 m/s³, jerk vector norm at most 8.37 m/s³; jerk as differences of consecutive
  accelerations over ``DT``, none at the first step), else 0.

Alongside: ``comfort_violations`` (the robot's steps over any limit),
``comfort_violations_by_limit`` (its steps over each) and ``steps``. The robot did its part
(:func:`robot_succeeded`) when every multiplier is 1. The weights and limits are fixed, so that
scores stay comparable between runs.
"""

from __future__ import annotations

import numpy as np

from ..scenario import CUTOFF_X, DT, on_road, time_to_collision

TTC_LIMIT_S = 0.95
"""Time to collision a robot must keep at every step (nuPlan's ego TTC bound), s."""

COMFORT_LIMITS = {"longitudinal_accel": (-4.05, 2.40), "lateral_accel": 4.89, "longitudinal_jerk": 4.13, "jerk": 8.37}
"""nuPlan's comfort limits: longitudinal acceleration range and largest lateral acceleration
(m/s²), largest longitudinal and total (vector norm) jerk (m/s³)."""

SCORE_WEIGHTS = {"ttc": 5.0, "progress": 5.0, "comfort": 2.0}
"""Weights of the score's averaged parts (nuPlan's closed-loop score weighs TTC and progress 5,
comfort 2)."""


def comfort_violations_by_limit(accelerations: np.ndarray, dt: float = DT) -> dict[str, np.ndarray]:
    """Per limit of :data:`COMFORT_LIMITS` (its key), the steps ``[T]`` (bool) at which
    accelerations ``[T, 2]`` (m/s², ``[xdd, ydd]``) or their jerk (differences over ``dt``; none at
    the first step) break it."""
    low, high = COMFORT_LIMITS["longitudinal_accel"]
    jerk = np.vstack([np.zeros((1, 2)), np.diff(accelerations, axis=0) / dt])
    return {"longitudinal_accel": (accelerations[:, 0] < low) | (accelerations[:, 0] > high),
            "lateral_accel": np.abs(accelerations[:, 1]) > COMFORT_LIMITS["lateral_accel"],
            "longitudinal_jerk": np.abs(jerk[:, 0]) > COMFORT_LIMITS["longitudinal_jerk"],
            "jerk": np.hypot(jerk[:, 0], jerk[:, 1]) > COMFORT_LIMITS["jerk"]}


def comfort_violations(accelerations: np.ndarray, dt: float = DT) -> np.ndarray:
    """Steps ``[T]`` (bool) at which accelerations ``[T, 2]`` (m/s², ``[xdd, ydd]``) or their jerk
    break any of :data:`COMFORT_LIMITS` (:func:`comfort_violations_by_limit`)."""
    return _any_limit(comfort_violations_by_limit(accelerations, dt))


def _any_limit(by_limit: dict[str, np.ndarray]) -> np.ndarray:
    """The steps ``[T]`` over any limit, from :func:`comfort_violations_by_limit`'s steps per limit."""
    return np.logical_or.reduce(list(by_limit.values()))


def robot_succeeded(score: dict) -> bool:
    """Whether the robot did its part of an episode whose :func:`closed_loop_score` is ``score``:
    every multiplier 1 (it swapped lanes before the cutoff, stayed on the road, reached the cutoff,
    no collision)."""
    return all(score["multipliers"].values())


def closed_loop_score(states: np.ndarray, robot: int, outcome: str, robot_swapped: bool, crossed: int | None,
                      dt: float = DT) -> dict:
    """The closed-loop score (module docstring) of one episode ``states [2, T, 6]`` (recorded
    steps only) for the robot car ``robot``, whose ``outcome`` (one of ``VALIDITY_REASONS``) and
    lane swap ``robot_swapped`` are known, ``crossed`` the first step the robot is in the other
    lane (None: never): ``score``, ``multipliers``, the parts ``ttc``, ``progress``, ``comfort``,
    ``comfort_violations``, ``comfort_violations_by_limit`` and ``steps``."""
    me, x = states[robot], states[robot, :, 0]
    before_cutoff = np.maximum.accumulate(x) < CUTOFF_X
    multipliers = {"no_collision": outcome != "collision",
                   "on_road": bool(on_road(me[before_cutoff, 1]).all()), "lane_swap": robot_swapped,
                   "reaches_cutoff": bool(x.max() >= CUTOFF_X)}
    ttc = time_to_collision(states[0], states[1])
    road = CUTOFF_X - x[0]
    swap_left = float(np.clip((CUTOFF_X - x[crossed]) / road, 0.0, 1.0)) if crossed is not None and road > 0 else 0.0
    speed_kept = float(min(1.0, me[before_cutoff, 2].mean() / me[0, 2])) if me[0, 2] > 0 else 1.0
    by_limit = comfort_violations_by_limit(me[:, 4:6], dt)
    violations = _any_limit(by_limit)
    parts = {"ttc": float(ttc.min() >= TTC_LIMIT_S), "progress": 0.5 * (swap_left + speed_kept),
             "comfort": float(not violations.any())}
    mean = sum(SCORE_WEIGHTS[k] * v for k, v in parts.items()) / sum(SCORE_WEIGHTS.values())
    return {"score": float(all(multipliers.values())) * mean, "multipliers": multipliers, **parts,
            "comfort_violations": int(violations.sum()),
            "comfort_violations_by_limit": {k: int(v.sum()) for k, v in by_limit.items()}, "steps": len(violations)}
