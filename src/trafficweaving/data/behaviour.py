"""Marginal driving-behaviour statistics, used to calibrate simulated drivers against real ones.

:func:`lane_change_events` finds when each car's lane change starts, crosses the divider and ends
(the one definition of lane-change timing in the package); :func:`behaviour_samples` pools 1-D
samples (speeds, accelerations, jerks, control holds, lane-change timing and positions) over every
agent of a role; :func:`compare_behaviour` sets two such pools side by side with the 1-D
Wasserstein distance, and :func:`format_comparison` renders that as Markdown.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.stats import wasserstein_distance

from ..scenario import LANE_CENTRE_Y, LANE_DIVIDER_Y
from .trials import TrialSet

LANE_BAND = 0.4
"""A car is *at* a lane centre while within this lateral distance of it, m."""
SIDEWAYS_SPEED = 0.2
"""A lane change starts at the last step before the divider crossing with at most this lateral
speed towards the target lane, m/s."""
HOLD_TOLERANCE = 0.01
"""An acceleration is *held* between consecutive steps that change it by less than this, m/s²."""
NEAR_CROSSING = (2.5, 0.5)
"""Window around the divider crossing for ``long_accel_abs_near_crossing``: seconds before, after."""

STATISTICS = {
    "speed": "m/s",
    "long_accel": "m/s²",
    "lat_accel": "m/s²",
    "long_jerk": "m/s³",
    "lat_jerk": "m/s³",
    "long_hold": "fraction",
    "lat_hold": "fraction",
    "long_hold_run": "steps",
    "lat_hold_run": "steps",
    "long_accel_abs_near_crossing": "m/s²",
    "lane_change_sideways_time": "s",
    "lane_change_duration": "s",
    "lane_change_x": "m",
}
"""The statistics of :func:`behaviour_samples` and their units, in display order."""

SUMMARY_KEYS = ("count", "mean", "std", "p5", "p50", "p95")


@dataclass(frozen=True)
class LaneChanges:
    """Lane-change timing of ``m`` agents: equal-length 1-D arrays ``[m]``, one entry per agent.

    ``trial``: row index into the :class:`TrialSet`; ``agent``: 0 or 1; ``start``: step where the
    sideways motion towards the other lane starts; ``crossing``: step
    (float, interpolated) where the car crosses ``LANE_DIVIDER_Y``; ``end``: first step after the
    crossing within ``LANE_BAND`` of the target lane's centre. Step indices count from the trial's
    first step (multiply by ``trials.dt`` for seconds). NaN where the event does not happen or is
    not recorded (all three NaN for an agent that never crosses).
    """

    trial: np.ndarray
    agent: np.ndarray
    start: np.ndarray
    crossing: np.ndarray
    end: np.ndarray


def lane_change_events(trials: TrialSet, role: str = "human") -> LaneChanges:
    """Lane-change timing of every agent with ``trials.roles == role`` (row-major order of
    ``(trial, agent)``), over recorded steps only.

    - ``crossing``: the first recorded step on the other side of ``LANE_DIVIDER_Y`` from the start
      lane, interpolated linearly in ``y`` with the step before (NaN if the car never crosses, or
      is already across at step 0);
    - ``start``: the last step before the crossing at which the lateral speed towards the target
      lane (``yd``, signed) is at most ``SIDEWAYS_SPEED``; 0 when the car already moves sideways
      faster at the first step. With this threshold the 30 real human-in-the-loop drivers take a
      median 1.9 s (mean 2.0 s) from ``start`` to ``crossing``;
    - ``end``: the first recorded step at or after the crossing within ``LANE_BAND`` of the target
      lane's centre (NaN if the recording stops before).
    """
    trial_idx, agent_idx = np.nonzero(trials.roles == role)
    s = trials.states[trial_idx, agent_idx]  # [m, T, 6]
    m, t_max = s.shape[:2]
    if m == 0 or t_max == 0:  # no such agent, or no recorded step: no events
        none = np.full(m, np.nan)
        return LaneChanges(trial=trial_idx, agent=agent_idx, start=none, crossing=none.copy(), end=none.copy())
    steps = np.arange(t_max)
    recorded = steps[None, :] < trials.lengths[trial_idx][:, None]  # [m, T]
    y, yd = s[..., 1], s[..., 3]
    starts_left = trials.start_lanes[trial_idx, agent_idx] == "left"
    side = np.where(starts_left, 1.0, -1.0)[:, None]  # +1: the start lane lies at larger y

    d = np.where(recorded, (y - LANE_DIVIDER_Y) * side, np.inf)  # distance to the divider, + on the start side
    across = d <= 0
    k = across.argmax(axis=1)  # first step on the other side
    crosses = across.any(axis=1) & (k > 0)
    rows = np.flatnonzero(crosses)
    k_c = k[rows]
    d0, d1 = d[rows, k_c - 1], d[rows, k_c]
    crossing = np.full(m, np.nan)
    crossing[rows] = k_c - 1 + d0 / (d0 - d1)

    toward = -yd[rows] * side[rows]  # lateral speed towards the target lane, m/s
    slow = (toward <= SIDEWAYS_SPEED) & (steps[None, :] < k_c[:, None])
    last_slow = t_max - 1 - slow[:, ::-1].argmax(axis=1)
    start = np.full(m, np.nan)
    start[rows] = np.where(slow.any(axis=1), last_slow, 0.0)

    y_target = np.where(starts_left, LANE_CENTRE_Y["right"], LANE_CENTRE_Y["left"])[rows, None]
    arrived = (np.abs(y[rows] - y_target) < LANE_BAND) & (steps[None, :] >= k_c[:, None]) & recorded[rows]
    end = np.full(m, np.nan)
    end[rows] = np.where(arrived.any(axis=1), arrived.argmax(axis=1), np.nan)
    return LaneChanges(trial=trial_idx, agent=agent_idx, start=start, crossing=crossing, end=end)


def hold_runs(acc: np.ndarray, recorded: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Where a driver holds an acceleration, and for how long.

    ``acc``: ``[m, T]`` accelerations (m/s²); ``recorded``: ``[m, T]`` bool. Returns ``(held, runs)``:
    ``held`` is 1.0/0.0 for every pair of consecutive recorded steps (whether ``acc`` changed by less
    than ``HOLD_TOLERANCE``), ``runs`` the lengths (in steps) of the maximal runs of consecutive
    held pairs of each agent; both 1-D.
    """
    pairs = recorded[:, 1:]
    held = (np.abs(np.diff(acc, axis=1)) < HOLD_TOLERANCE) & pairs  # [m, T-1]
    padded = np.pad(held, ((0, 0), (1, 1))).astype(np.int8).ravel()  # False between agents
    edges = np.diff(padded)
    runs = np.flatnonzero(edges == -1) - np.flatnonzero(edges == 1)
    return held[pairs].astype(float), runs.astype(float)


def behaviour_samples(trials: TrialSet, role: str = "human") -> dict[str, np.ndarray]:
    """Pooled samples of every agent with ``roles == role``, over recorded steps only.

    Returns a dict keyed like :data:`STATISTICS`, each a 1-D float array:

    - ``speed`` (m/s), ``long_accel`` / ``lat_accel`` (m/s²): ``xd``, ``xdd``, ``ydd`` at every step;
    - ``long_jerk`` / ``lat_jerk`` (m/s³): change of ``xdd`` / ``ydd`` between consecutive steps
      divided by ``trials.dt``;
    - ``long_hold`` / ``lat_hold``: 1 or 0 per pair of consecutive steps, whether ``xdd`` / ``ydd`` is
      held (changes by less than ``HOLD_TOLERANCE``); the mean is the fraction of held steps;
    - ``long_hold_run`` / ``lat_hold_run`` (steps): lengths of the runs of consecutive held steps;
    - ``long_accel_abs_near_crossing`` (m/s²): one per agent that crosses the divider, the mean of
      ``|xdd|`` over the recorded steps from ``NEAR_CROSSING[0]`` s before to ``NEAR_CROSSING[1]`` s
      after the crossing (how hard a driver presses the pedals around its lane change);
    - ``lane_change_sideways_time`` (s): one per agent that crosses, from ``start`` to ``crossing``
      of :func:`lane_change_events`, observed for every crossing agent (so, unlike the duration, it
      does not favour quick lane changes when recordings stop soon after the cutoff);
    - ``lane_change_duration`` (s): one per agent whose lane change is recorded to its ``end``, from
      ``start`` to ``end``;
    - ``lane_change_x`` (m): one per agent that crosses, ``x`` at the crossing (interpolated linearly
      between the two steps either side).
    """
    trial_idx, agent_idx = np.nonzero(trials.roles == role)
    s = trials.states[trial_idx, agent_idx]  # [m, T, 6]
    steps = np.arange(s.shape[1])
    recorded = steps[None, :] < trials.lengths[trial_idx][:, None]  # [m, T]
    pair_recorded = recorded[:, 1:]  # both steps k and k+1 recorded
    x, xd, xdd, ydd = s[..., 0], s[..., 2], s[..., 4], s[..., 5]
    long_hold, long_runs = hold_runs(xdd, recorded)
    lat_hold, lat_runs = hold_runs(ydd, recorded)

    events = lane_change_events(trials, role)
    rows = np.flatnonzero(np.isfinite(events.crossing))
    crossing, start, end = events.crossing[rows], events.start[rows], events.end[rows]
    k = np.maximum(np.ceil(crossing) - 1, 0).astype(int)  # crossing in (k, k + 1]: both steps recorded
    frac = crossing - k
    lane_change_x = x[rows, k] + frac * (x[rows, k + 1] - x[rows, k])
    before, after = (w / trials.dt for w in NEAR_CROSSING)
    window = ((steps[None, :] >= crossing[:, None] - before - 1e-9)
              & (steps[None, :] <= crossing[:, None] + after + 1e-9) & recorded[rows])
    in_window = window.sum(axis=1)  # 0 only for a time step above NEAR_CROSSING's window
    near = (np.where(window, np.abs(xdd[rows]), 0.0).sum(axis=1) / np.maximum(in_window, 1))[in_window > 0]
    complete = np.isfinite(end)

    return {
        "speed": xd[recorded],
        "long_accel": xdd[recorded],
        "lat_accel": ydd[recorded],
        "long_jerk": (np.diff(xdd, axis=1) / trials.dt)[pair_recorded],
        "lat_jerk": (np.diff(ydd, axis=1) / trials.dt)[pair_recorded],
        "long_hold": long_hold,
        "lat_hold": lat_hold,
        "long_hold_run": long_runs,
        "lat_hold_run": lat_runs,
        "long_accel_abs_near_crossing": near,
        "lane_change_sideways_time": (crossing - start) * trials.dt,
        "lane_change_duration": (end - start)[complete] * trials.dt,
        "lane_change_x": lane_change_x,
    }


def _number(value) -> float | None:
    """``value`` as a float, or None when it is NaN or infinite (JSON has no such numbers)."""
    value = float(value)
    return value if np.isfinite(value) else None


def summarise(sample: np.ndarray) -> dict:
    """Count, mean, std (ddof 0) and 5/50/95th percentiles of a 1-D sample; each None where
    undefined (an empty sample, or NaN/inf values in it), so the result is strict JSON."""
    sample = np.asarray(sample, dtype=float)
    if sample.size == 0:
        return {"count": 0, **{key: None for key in SUMMARY_KEYS[1:]}}
    with np.errstate(invalid="ignore", over="ignore"):
        p5, p50, p95 = np.percentile(sample, [5, 50, 95])
        mean, std = sample.mean(), sample.std()
    return {"count": int(sample.size), "mean": _number(mean), "std": _number(std),
            "p5": _number(p5), "p50": _number(p50), "p95": _number(p95)}


def compare_behaviour(sim: dict, real: dict) -> dict[str, dict]:
    """Compare two dicts of :func:`behaviour_samples`, statistic by statistic (those in both).

    Each entry: ``{"unit", "sim": summary, "real": summary, "wasserstein", "wasserstein_over_std"}``
    where a summary has ``count, mean, std, p5, p50, p95`` (the statistic's unit), ``wasserstein``
    is the 1-D Wasserstein distance of the two samples (same unit) and ``wasserstein_over_std`` that
    divided by the real sample's std. Undefined numbers (an empty sample, a zero std, NaN/inf in a
    sample) are None, so the result is strict JSON.
    """
    table = {}
    for name in [n for n in sim if n in real]:
        a, b = np.asarray(sim[name], float), np.asarray(real[name], float)
        finite = a.size and b.size and np.isfinite(a).all() and np.isfinite(b).all()
        w = _number(wasserstein_distance(a, b)) if finite else None
        sd = float(b.std()) if finite else 0.0
        table[name] = {
            "unit": STATISTICS.get(name, ""),
            "sim": summarise(a),
            "real": summarise(b),
            "wasserstein": w,
            "wasserstein_over_std": w / sd if w is not None and sd > 0 else None,
        }
    return table


def _fmt(value, digits: int = 3) -> str:
    return "–" if value is None else f"{value:.{digits}g}"


def format_comparison(table: dict, labels: tuple[str, str] = ("sim", "real")) -> str:
    """A Markdown table of :func:`compare_behaviour`'s result, one row per statistic: counts, mean ±
    std and the 5/50/95th percentiles of both samples, the Wasserstein distance and it over the
    real std."""
    a, b = labels
    header = (f"| statistic | unit | n {a} | n {b} | mean ± std {a} | mean ± std {b} "
              f"| p5 / p50 / p95 {a} | p5 / p50 / p95 {b} | W | W / std {b} |")
    lines = [header, "|" + "---|" * 10]
    for name, row in table.items():
        cells = [name, row["unit"]]
        cells += [str(row[k]["count"]) for k in ("sim", "real")]
        cells += [f"{_fmt(row[k]['mean'])} ± {_fmt(row[k]['std'])}" for k in ("sim", "real")]
        cells += [" / ".join(_fmt(row[k][p]) for p in ("p5", "p50", "p95")) for k in ("sim", "real")]
        cells += [_fmt(row["wasserstein"]), _fmt(row["wasserstein_over_std"], 2)]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)
