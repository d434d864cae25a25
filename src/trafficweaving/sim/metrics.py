"""Closed-loop metrics: what happened in one robot–human episode, and aggregates over many with
95 % confidence intervals.

Per episode (:func:`episode_metrics`, from the record ``states [2, T, 6]``, its ``length`` and the
robot's car index), judged by the scenario's rules
(:func:`~trafficweaving.scenario.check_validity`; paper §II-C, §V-A):

* ``outcome``: the rule a record breaks first, one of ``VALIDITY_REASONS`` (``valid`` when both
  cars swapped lanes before the cutoff without collision, on the road);
* ``robot_swapped`` / ``human_swapped``: the car, at its last step before ``CUTOFF_X`` (its last
  recorded step if it never gets there), on the other side of ``SWAP_THRESHOLD_Y`` from its start;
* ``success``: the robot swapped, no collision, both cars on the road and past the cutoff (the
  outcome is ``valid`` or ``no_lane_swap`` by the human alone);
* ``robot_success``: the robot's own part of ``success``: it swapped, stayed on the road before
  the cutoff, reached it and did not collide (the score's multipliers all 1,
  :func:`~.score.robot_succeeded`), whatever the human did (left the road, did not reach the cutoff);
* ``collision``: the scenario's rule (``|Δx| < COLLISION_DX`` and ``|Δy| < COLLISION_DY`` at a
  recorded step); ``robot_at_fault``: a collision with the robot at fault, by nuPlan's at-fault
  rule (:func:`~trafficweaving.scenario.at_fault_collision`: the car behind in a rear-end
  collision, the one moving sideways into the other in a side collision);
* ``near_collision``: a recorded step where the paper's collision cost ``J_c`` of
  :meth:`PaperCost.terms <trafficweaving.planning.costs.PaperCost.terms>` is positive (``|Δs| <
  8 m`` and ``|Δτ| < 2 m``, §V-C); every collision is also a near collision;
* ``min_gap_m``: the smallest longitudinal distance ``|Δx|`` between the car centres at the
  steps where the cars overlap laterally (``|Δy| < COLLISION_DY``, one car cutting in front of or
  behind the other), m; None if they never do. Below ``COLLISION_DX`` exactly when they collide;
  minus ``CAR_LENGTH`` it is the bumper-to-bumper gap;
* ``min_distance_m``: the smallest Euclidean distance between the car centres, m (side by side
  in adjacent lanes it is about the lane spacing, 4.26 m);
* ``robot_first``: the robot ahead (larger ``x``) at the first step a car reaches ``CUTOFF_X``
  (the last recorded step if none does): it passed first;
* ``accel_rms``, ``jerk_rms``: the robot's root-mean-square acceleration (m/s²) and jerk (m/s³,
  differences of consecutive accelerations over ``DT``), ``longitudinal`` and ``lateral``, over
  the whole record;
* ``time_to_swap_s``: time from the start until the robot is first in the other lane (across
  ``LANE_DIVIDER_Y``, :func:`~trafficweaving.scenario.lane_of`), s; None if it never is;
* ``lane_reversals``: how often the robot's sideways motion turns back towards the lane it
  started in (:func:`lane_reversals`);
* ``lateral_swings``: how often the robot's lateral acceleration changes sign (:func:`lateral_swings`;
  one lane change swings once: towards the other lane, then braking into it);
* ``score``: the closed-loop score and its parts (:func:`~.score.closed_loop_score`; its
  definition, limits and weights: :mod:`trafficweaving.sim.score`).

The planner's latencies (:func:`latency_summary`; seconds per plan, which vary between runs, so
they are kept apart from the metrics above, which a run reproduces exactly) give ``plans``, ``median_s``, ``p99_s`` and
``deadline_misses``: plans slower than the 0.3 s replanning period (paper §V-C).

Aggregates (:func:`aggregate`): rates with the Wilson score interval (correct at 0/n and n/n,
where the normal approximation collapses), means with the Student-t interval
``mean ± t(0.975, n-1)·s/√n`` (None below 2 values); latencies pooled over all plans.
"""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np
import torch
from scipy import stats

from ..planning.costs import PaperCost
from ..scenario import (COLLISION_DY, CUTOFF_X, DT, LANE_CENTRE_Y, LANE_DIVIDER_Y, REPLAN_PERIOD_S, VALIDITY_REASONS,
                        at_fault_collision, check_validity, lane_of, swapped_before_cutoff)
from .score import COMFORT_LIMITS, SCORE_WEIGHTS, closed_loop_score, robot_succeeded

Z95 = float(stats.norm.ppf(0.975))
"""Two-sided 95 % standard normal quantile (1.96)."""


def near_collision_steps(robot: np.ndarray, human: np.ndarray) -> np.ndarray:
    """Steps ``[T]`` (bool) where the paper's collision cost ``J_c`` is positive, for the robot's
    and the human's states ``[T, 6]`` (``PaperCost.terms``; its goal lane does not enter ``J_c``)."""
    cost = PaperCost(goal_y=LANE_CENTRE_Y["left"])
    terms = cost.terms(torch.from_numpy(np.ascontiguousarray(robot)), torch.from_numpy(np.ascontiguousarray(human)))
    return (terms["collision"] > 0).numpy()


def latency_summary(latencies: Sequence[float]) -> dict:
    """``plans``, ``median_s``, ``p99_s`` (None without plans) and ``deadline_misses`` (plans
    longer than :data:`REPLAN_PERIOD_S`) of planner latencies in seconds."""
    values = np.asarray(latencies, dtype=float)
    if not len(values):
        return {"plans": 0, "median_s": None, "p99_s": None, "deadline_misses": 0}
    return {"plans": len(values), "median_s": float(np.median(values)), "p99_s": float(np.percentile(values, 99)),
            "deadline_misses": int((values > REPLAN_PERIOD_S).sum())}


def _rms(values: np.ndarray) -> float:
    return float(np.sqrt(np.mean(values**2))) if len(values) else 0.0


def episode_metrics(states: np.ndarray, length: int, robot: int, dt: float = DT) -> dict:
    """The metrics of one episode (module docstring) from ``states [2, T, 6]`` (car, step,
    ``STATE_NAMES``; steps from ``length`` on ignored), the robot's car index ``robot`` (0 or 1)
    and the time step ``dt`` (s). Values are JSON-ready (bool, float, str, None)."""
    states = np.asarray(states, dtype=float)[:, :length]
    human = 1 - robot
    reason, _ = check_validity(states[None], np.array([length]))
    outcome = VALIDITY_REASONS[int(reason[0])]
    swapped = swapped_before_cutoff(states[None], np.array([length]))[0]
    robot_swapped, human_swapped = bool(swapped[robot]), bool(swapped[human])

    x, y = states[:, :, 0], states[:, :, 1]
    reached = (x >= CUTOFF_X).any(axis=0)
    at_cutoff = int(reached.argmax()) if reached.any() else length - 1
    dx, dy = np.abs(x[0] - x[1]), np.abs(y[0] - y[1])
    overlap = dy < COLLISION_DY

    acc = states[robot, :, 4:6]
    jerk = np.diff(acc, axis=0) / dt
    lanes = lane_of(y[robot])
    crossed = np.flatnonzero(lanes != lanes[0])
    score = closed_loop_score(states, robot, outcome, robot_swapped, int(crossed[0]) if len(crossed) else None, dt)
    return {
        "outcome": outcome,
        "success": robot_swapped and outcome in ("valid", "no_lane_swap"),
        "robot_success": robot_succeeded(score),
        "robot_swapped": robot_swapped,
        "human_swapped": human_swapped,
        "collision": outcome == "collision",
        "robot_at_fault": bool(at_fault_collision(states[robot][None], states[human][None])[0]),
        "near_collision": bool(near_collision_steps(states[robot], states[human]).any()),
        "min_gap_m": float(dx[overlap].min()) if overlap.any() else None,
        "min_distance_m": float(np.hypot(dx, dy).min()),
        "robot_first": bool(x[robot, at_cutoff] > x[human, at_cutoff]),
        "accel_rms": {"longitudinal": _rms(acc[:, 0]), "lateral": _rms(acc[:, 1])},
        "jerk_rms": {"longitudinal": _rms(jerk[:, 0]), "lateral": _rms(jerk[:, 1])},
        "time_to_swap_s": float(crossed[0] * dt) if len(crossed) else None,
        "lane_reversals": lane_reversals(y[robot], states[robot, :, 3]),
        "lateral_swings": lateral_swings(acc[:, 1]),
        "score": score,
    }


REVERSAL_SPEED = 0.2
"""Lateral speed (m/s) above which the robot counts as moving sideways for :func:`lane_reversals`."""


def lane_reversals(y: np.ndarray, yd: np.ndarray) -> int:
    """How often a car with lateral positions ``y [T]`` and speeds ``yd [T]`` (m, m/s) turns back
    towards the lane it started in: spells of sideways motion faster than :data:`REVERSAL_SPEED`
    towards that lane that follow a spell towards the other lane."""
    towards_target = -np.sign(LANE_DIVIDER_Y - y[0])  # +1: the target lane lies at larger y
    moving = np.sign(yd * towards_target) * (np.abs(yd) > REVERSAL_SPEED)  # +1 towards the target, -1 back
    spells = moving[moving != 0]
    changes = spells[1:][spells[1:] != spells[:-1]]
    return int((changes < 0).sum())


SWING_ACCEL = 0.3
"""Lateral acceleration (m/s²) above which its sign counts for :func:`lateral_swings`."""


def lateral_swings(ydd: np.ndarray) -> int:
    """Sign changes of the lateral accelerations ``ydd [T]`` (m/s²) among the steps where
    ``|ydd| > SWING_ACCEL``: a steady lane change has one; dithering and chatter many."""
    signs = np.sign(ydd[np.abs(ydd) > SWING_ACCEL])
    return int((signs[1:] != signs[:-1]).sum())


# ---------------------------------------------------------------- aggregates
def wilson_interval(successes: int, n: int, z: float = Z95) -> list[float] | None:
    """Wilson score interval ``[low, high]`` of a rate ``successes / n`` (None for ``n = 0``):
    ``(k + z²/2)/(n + z²) ± z/(n + z²)·√(k(n−k)/n + z²/4)``; exactly 0 (1) at the ends."""
    if n == 0:
        return None
    centre = (successes + z * z / 2) / (n + z * z)
    half = z / (n + z * z) * math.sqrt(successes * (n - successes) / n + z * z / 4)
    low = 0.0 if successes == 0 else max(0.0, centre - half)
    high = 1.0 if successes == n else min(1.0, centre + half)
    return [low, high]


def rate(flags: Sequence[bool]) -> dict:
    """``count``, ``rate`` (None without episodes) and the Wilson ``ci95`` of booleans."""
    n, k = len(flags), int(sum(bool(f) for f in flags))
    return {"count": k, "rate": k / n if n else None, "ci95": wilson_interval(k, n)}


def mean_interval(values: Sequence[float]) -> dict:
    """``n``, ``mean`` and the Student-t 95 % interval ``ci95`` of ``values`` (None-valued entries
    are left out; mean None without values, interval None below 2)."""
    data = np.array([v for v in values if v is not None], dtype=float)
    n = len(data)
    if n == 0:
        return {"n": 0, "mean": None, "ci95": None}
    mean = float(data.mean())
    if n < 2:
        return {"n": 1, "mean": mean, "ci95": None}
    half = float(stats.t.ppf(0.975, n - 1) * data.std(ddof=1) / math.sqrt(n))
    return {"n": n, "mean": mean, "ci95": [mean - half, mean + half]}


def initial_condition_key(ic: dict) -> tuple:
    """The breakdown key ``(dv, tco, robot_lane)`` of an episode's initial condition: ``dv`` =
    ``v_left − v_right`` (m/s), ``tco`` (s; None for ``dv = 0``, where the crossover time is
    undefined, as in Table I), the lane the robot starts in."""
    return ic["dv"], (None if ic["dv"] == 0 else ic["tco"]), ic["robot_lane"]


def _at_fault_count(metrics: Sequence[dict]) -> int | None:
    """Collisions with the robot at fault; None when a colliding episode was logged before the
    metric existed (a resumed old run), rather than counting it as not at fault."""
    faults = [m.get("robot_at_fault") for m in metrics if m["collision"]]
    return None if None in faults else sum(faults)


def _group(records: Sequence[dict]) -> dict:
    """The aggregate of episode records (see :func:`aggregate`) without the breakdown."""
    metrics = [r["metrics"] for r in records]
    column = lambda name: [m[name] for m in metrics]  # noqa: E731
    gaps = [g for g in column("min_gap_m") if g is not None]
    return {
        "episodes": len(records),
        "success_rate": rate(column("success")),
        "robot_success_rate": rate([robot_succeeded(m["score"]) for m in metrics]),
        "collisions": sum(column("collision")),
        "collision_rate": rate(column("collision")),
        "robot_at_fault_collisions": _at_fault_count(metrics),
        "near_collisions": sum(column("near_collision")),
        "near_collision_rate": rate(column("near_collision")),
        "robot_first_rate": rate(column("robot_first")),
        "human_swap_rate": rate(column("human_swapped")),
        "min_gap_m": {"min": min(gaps) if gaps else None, **mean_interval(gaps)},
        "min_distance_m": mean_interval(column("min_distance_m")),
        "time_to_swap_s": mean_interval(column("time_to_swap_s")),
        "score": mean_interval([m["score"]["score"] for m in metrics]),
        "score_parts": {**{k: rate([m["score"]["multipliers"][k] for m in metrics]) for k in ("no_collision", "on_road", "lane_swap", "reaches_cutoff")},
                        **{k: mean_interval([m["score"][k] for m in metrics]) for k in SCORE_WEIGHTS}},
        "lane_reversals": {**mean_interval(column("lane_reversals")),
                           "at_most_one": rate([r <= 1 for r in column("lane_reversals")])},
        "lateral_swings": mean_interval([m.get("lateral_swings") for m in metrics]),
        "comfort_violation_steps": {"count": sum(m["score"]["comfort_violations"] for m in metrics),
                                    "steps": sum(m["score"]["steps"] for m in metrics),
                                    "by_limit": _violations_by_limit(metrics)},
    }


def _violations_by_limit(metrics: Sequence[dict]) -> dict | None:
    """Per limit of :data:`~.score.COMFORT_LIMITS`, the robot's ``steps`` over it and the ``episodes`` with
    any; None when an episode's log predates the breakdown."""
    counts = [m["score"].get("comfort_violations_by_limit") for m in metrics]
    if any(c is None for c in counts):
        return None
    return {k: {"steps": sum(c[k] for c in counts), "episodes": sum(c[k] > 0 for c in counts)} for k in COMFORT_LIMITS}


def _safety_overrides(records: Sequence[dict]) -> dict | None:
    """The windows the robot's safety layer changed (``windows``), of them those where no action
    was safe (``unresolved``), and the ``episodes`` with any; None when a log predates them."""
    logs = [r.get("safety_overrides") for r in records]
    if any(log is None for log in logs):
        return None
    return {"windows": sum(map(len, logs)), "unresolved": sum(not o["any_safe"] for log in logs for o in log),
            "episodes": sum(bool(log) for log in logs)}


def aggregate(records: Sequence[dict]) -> dict:
    """Aggregate episode records (each a dict with ``metrics`` of :func:`episode_metrics`,
    ``latencies_s`` and ``initial_condition`` with ``dv``, ``tco``, ``robot_lane``).

    Returns ``episodes``, ``outcomes`` (count per ``VALIDITY_REASONS``), rates with Wilson
    intervals (``success_rate``, ``robot_success_rate``, ``collision_rate``, ``near_collision_rate``,
    ``robot_first_rate``, ``human_swap_rate``: ``count``, ``rate``, ``ci95``), counts ``collisions`` (and of them
    ``robot_at_fault_collisions``, :func:`~trafficweaving.scenario.at_fault_collision`; None when
    a colliding episode's log predates it) and
    ``near_collisions``, means with t-intervals (``min_gap_m`` over the episodes where it is defined,
    also with its ``min``; ``min_distance_m``;
    ``time_to_swap_s`` over episodes where the robot changed lane, ``accel_rms`` and ``jerk_rms``
    by direction), ``planner_latency_s`` (``median``, ``p99``, ``plans``) and ``deadline_misses``
    (plans longer than ``planning_period_s``) over all plans pooled, and ``by_initial_condition``:
    the same rates and means per :func:`initial_condition_key`, sorted (unknown ``dv`` last); also
    ``score`` (t-interval), ``score_parts`` (the multipliers as rates, the averaged parts as means),
    ``lane_reversals`` (mean, and the rate of episodes with ``at_most_one``), ``lateral_swings`` and
    ``comfort_violation_steps`` (``count`` of the robot's steps over the limits, of ``steps``, and
    ``by_limit``: per limit of :data:`~.score.COMFORT_LIMITS` the ``steps`` over it and the ``episodes``
    with any), ``safety_overrides`` (:func:`_safety_overrides`). Undefined values are None (strict JSON).
    """
    summary = _group(records)
    outcomes = [r["metrics"]["outcome"] for r in records]
    summary["outcomes"] = {name: outcomes.count(name) for name in VALIDITY_REASONS}
    for name in ("accel_rms", "jerk_rms"):
        summary[name] = {d: mean_interval([r["metrics"][name][d] for r in records]) for d in ("longitudinal", "lateral")}
    latency = latency_summary([s for r in records for s in r["latencies_s"]])
    summary["planner_latency_s"] = {"median": latency["median_s"], "p99": latency["p99_s"], "plans": latency["plans"]}
    summary["deadline_misses"] = latency["deadline_misses"]
    summary["planning_period_s"] = REPLAN_PERIOD_S
    summary["safety_overrides"] = _safety_overrides(records)

    groups: dict[tuple, list[dict]] = {}
    for record in records:
        groups.setdefault(initial_condition_key(record["initial_condition"]), []).append(record)
    order = lambda key: (key[0] is None, key[0] or 0.0, key[1] is not None, key[1] or 0.0, key[2])  # noqa: E731
    summary["by_initial_condition"] = [{"dv": dv, "tco": tco, "robot_lane": lane, **_group(groups[dv, tco, lane])}
                                       for dv, tco, lane in sorted(groups, key=order)]
    return summary
