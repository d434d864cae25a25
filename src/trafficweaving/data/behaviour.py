"""Marginal driving-behaviour statistics, used to calibrate simulated drivers against real ones.

:func:`behaviour_samples` pools 1-D samples (speeds, accelerations, jerks, lane-change durations
and positions) over every agent of a role; :func:`compare_behaviour` sets two such pools side by
side with the 1-D Wasserstein distance, and :func:`format_comparison` renders that as Markdown.
"""

from __future__ import annotations

import numpy as np
from scipy.stats import wasserstein_distance

from ..scenario import LANE_CENTRE_Y, LANE_DIVIDER_Y
from .trials import TrialSet

LANE_BAND = 0.4
"""A car is *at* a lane centre while within this lateral distance of it, m."""

STATISTICS = {
    "speed": "m/s",
    "long_accel": "m/s²",
    "lat_accel": "m/s²",
    "long_jerk": "m/s³",
    "lat_jerk": "m/s³",
    "lane_change_duration": "s",
    "lane_change_lead_time": "s",
    "lane_change_x": "m",
}
"""The statistics of :func:`behaviour_samples` and their units, in display order."""

SUMMARY_KEYS = ("count", "mean", "std", "p5", "p50", "p95")


def behaviour_samples(trials: TrialSet, role: str = "human") -> dict[str, np.ndarray]:
    """Pooled samples of every agent with ``roles == role``, over recorded steps only.

    Returns a dict keyed like :data:`STATISTICS`, each a 1-D float array:

    - ``speed`` (m/s), ``long_accel`` / ``lat_accel`` (m/s²): ``xd``, ``xdd``, ``ydd`` at every step;
    - ``long_jerk`` / ``lat_jerk`` (m/s³): change of ``xdd`` / ``ydd`` between consecutive steps
      divided by ``trials.dt``;
    - ``lane_change_duration`` (s): one per agent whose lane change is fully recorded, from the last
      step within ``LANE_BAND`` of its start lane's centre before it first crosses
      ``LANE_DIVIDER_Y`` to the first step within ``LANE_BAND`` of the other lane's centre after;
    - ``lane_change_lead_time`` (s): one per agent that crosses the divider, from the last step within
      ``LANE_BAND`` of its start lane's centre to the (interpolated) crossing — the first half of a
      lane change, observed for every crossing agent, so unlike ``lane_change_duration`` it does not
      favour quick lane changes when recordings stop soon after the cutoff;
    - ``lane_change_x`` (m): one per agent that crosses the divider, ``x`` where ``y`` first crosses
      it, interpolated linearly between the two steps either side.
    """
    trial_idx, agent_idx = np.nonzero(trials.roles == role)
    s = trials.states[trial_idx, agent_idx]  # [m, T, 6]
    lengths = trials.lengths[trial_idx]
    t_max = s.shape[1]
    steps = np.arange(t_max)
    recorded = steps[None, :] < lengths[:, None]  # [m, T]
    pair_recorded = recorded[:, 1:]  # both steps k and k+1 recorded
    x, y, xd, xdd, ydd = s[..., 0], s[..., 1], s[..., 2], s[..., 4], s[..., 5]

    # Lane change: signed distance to the divider, positive on the start lane's side.
    starts_left = trials.start_lanes[trial_idx, agent_idx] == "left"
    side = np.where(starts_left, 1.0, -1.0)[:, None]
    d = np.where(recorded, (y - LANE_DIVIDER_Y) * side, np.inf)  # [m, T]
    crossed = d <= 0
    k = crossed.argmax(axis=1)  # first step on the other side
    crosses = crossed.any(axis=1) & (k > 0)
    rows = np.flatnonzero(crosses)
    k_c = k[rows]
    d0, d1 = d[rows, k_c - 1], d[rows, k_c]
    frac = d0 / (d0 - d1)
    lane_change_x = x[rows, k_c - 1] + frac * (x[rows, k_c] - x[rows, k_c - 1])

    y_start = np.where(starts_left, LANE_CENTRE_Y["left"], LANE_CENTRE_Y["right"])[rows, None]
    y_target = np.where(starts_left, LANE_CENTRE_Y["right"], LANE_CENTRE_Y["left"])[rows, None]
    y_c, rec_c = y[rows], recorded[rows]
    before = steps[None, :] < k_c[:, None]
    at_start = (np.abs(y_c - y_start) < LANE_BAND) & before
    at_target = (np.abs(y_c - y_target) < LANE_BAND) & ~before & rec_c
    complete = at_start.any(axis=1) & at_target.any(axis=1)
    leave = t_max - 1 - at_start[:, ::-1].argmax(axis=1)
    arrive = at_target.argmax(axis=1)
    duration = (arrive - leave)[complete] * trials.dt
    left_start = at_start.any(axis=1)
    lead_time = ((k_c - 1 + frac) - leave)[left_start] * trials.dt

    return {
        "speed": xd[recorded],
        "long_accel": xdd[recorded],
        "lat_accel": ydd[recorded],
        "long_jerk": (np.diff(xdd, axis=1) / trials.dt)[pair_recorded],
        "lat_jerk": (np.diff(ydd, axis=1) / trials.dt)[pair_recorded],
        "lane_change_duration": duration.astype(float),
        "lane_change_lead_time": lead_time.astype(float),
        "lane_change_x": lane_change_x,
    }


def summarise(sample: np.ndarray) -> dict:
    """Count, mean, std (ddof 0) and 5/50/95th percentiles of a 1-D sample; None when empty."""
    if sample.size == 0:
        return {"count": 0, **{key: None for key in SUMMARY_KEYS[1:]}}
    p5, p50, p95 = np.percentile(sample, [5, 50, 95])
    return {"count": int(sample.size), "mean": float(sample.mean()), "std": float(sample.std()),
            "p5": float(p5), "p50": float(p50), "p95": float(p95)}


def compare_behaviour(sim: dict, real: dict) -> dict[str, dict]:
    """Compare two dicts of :func:`behaviour_samples`, statistic by statistic (those in both).

    Each entry: ``{"unit", "sim": summary, "real": summary, "wasserstein", "wasserstein_over_std"}``
    where a summary has ``count, mean, std, p5, p50, p95`` (the statistic's unit), ``wasserstein``
    is the 1-D Wasserstein distance of the two samples (same unit) and ``wasserstein_over_std`` that
    divided by the real sample's std. Undefined numbers (an empty sample, a zero std) are None, so the
    result is JSON-ready.
    """
    table = {}
    for name in [n for n in sim if n in real]:
        a, b = np.asarray(sim[name], float), np.asarray(real[name], float)
        w = float(wasserstein_distance(a, b)) if a.size and b.size else None
        sd = float(b.std()) if b.size else 0.0
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
