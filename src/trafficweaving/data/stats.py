"""Dataset statistics: who passed whom and the paper's Table I.

Table I (Schmerling et al., ICRA 2018, §V-A "Data Collection") is the fraction of human–human
trials in which the car that started in the **left** lane passes in front, per initial condition
``(Δv = v_left - v_right, tco)``. Every number returned is finite or None (JSON null) where it is
undefined, so results serialise as strict JSON.
"""

from __future__ import annotations

import numpy as np
from scipy import stats as scipy_stats

from ..scenario import STUDY_TRIALS, TCO_VALUES, across_divider
from .behaviour import behaviour_samples, compare_behaviour, summarise
from .trials import TrialSet

TABLE1_PAPER = {
    "-2": {"1": 0.072, "2": 0.131, "3": 0.236},
    "0": {"all": 0.382},
    "2": {"1": 0.857, "2": 0.762, "3": 0.667},
}
"""Table I of the paper: fraction of human–human trials where the left-lane car passes in front."""
TABLE1_PAPER_TRIALS = {dv: {k: STUDY_TRIALS / (3 if dv == "0" else 9) for k in cells} for dv, cells in TABLE1_PAPER.items()}
"""Trials behind each cell of the paper's Table I. The paper gives only the total (1105 valid
human–human trials over the 18 initial conditions); taken as spread evenly (each published
percentage is a whole number of trials out of 119–125, or 369 for Δv = 0)."""


def swap_step(trials: TrialSet) -> np.ndarray:
    """Per trial, the first step at which both cars are across ``SWAP_THRESHOLD_Y`` from where they
    started (``[n]``); the last recorded step when that never happens."""
    y = trials.states[..., 1]  # [n, 2, T]
    across = across_divider(y[:, :, :1], y)
    both = across.all(axis=1)  # [n, T]
    both &= np.arange(y.shape[2])[None, :] < trials.lengths[:, None]
    if both.size == 0:  # no trials (or no steps): nothing to find
        return np.zeros(len(trials), dtype=int)
    return np.where(both.any(axis=1), both.argmax(axis=1), trials.lengths - 1)


def left_car_in_front(trials: TrialSet) -> np.ndarray:
    """Per trial, whether the car that started in the left lane is ahead (larger ``x``) at the
    moment both cars have swapped lanes (``[n]`` bool)."""
    k = swap_step(trials)
    x_at = trials.states[np.arange(len(trials)), :, k, 0]  # [n, 2]
    left_agent = (trials.start_lanes[:, 1] == "left").astype(int)
    right_agent = 1 - left_agent
    idx = np.arange(len(trials))
    return x_at[idx, left_agent] > x_at[idx, right_agent]


def table1(trials: TrialSet) -> dict:
    """Table I of ``trials``: ``{"-2": {"1": f, "2": f, "3": f}, "0": {"all": f}, "2": {...}}`` with the
    fraction ``f`` of trials where the left-lane car passes in front (None where a cell is empty),
    and the trial count of each cell under the same keys in ``counts``."""
    front = left_car_in_front(trials)
    dv = np.round(trials.ic_dv)
    tco = np.round(trials.ic_tco)
    fractions: dict = {}
    counts: dict = {}
    for dv_key in ("-2", "0", "2"):
        in_dv = dv == float(dv_key)
        cells = {"all": in_dv} if dv_key == "0" else {
            str(int(c)): in_dv & (tco == c) for c in TCO_VALUES
        }
        fractions[dv_key] = {k: (float(front[m].mean()) if m.any() else None) for k, m in cells.items()}
        counts[dv_key] = {k: int(m.sum()) for k, m in cells.items()}
    return {"table1": fractions, "counts": counts}


def table1_max_deviation(table: dict, reference: dict = TABLE1_PAPER) -> float | None:
    """Largest absolute difference (fraction, not pp) between two Table I dicts over the cells
    filled in both; None when no cell is."""
    diffs = [
        abs(table[dv][k] - reference[dv][k])
        for dv in reference
        for k in reference[dv]
        if table.get(dv, {}).get(k) is not None and reference[dv][k] is not None
    ]
    return max(diffs) if diffs else None


def table1_test(table: dict, counts: dict) -> dict | None:
    """Whether a Table I (``table`` and ``counts`` of :func:`table1`) is consistent with the
    paper's, as a two-sample comparison of proportions: each filled cell's ``difference``
    (fraction, ours minus the paper's), its standard error ``se`` (both samples' binomial errors;
    the paper's cell sizes :data:`TABLE1_PAPER_TRIALS`) and the pooled two-proportion ``z``; over
    the cells ``chi2`` = Σ z² with ``dof`` = the number of cells and its ``p_value`` (small: the
    tables differ by more than sampling error). None when no cell is filled.

    Both tables are samples: with the paper's cell sizes, a simulator that plays exactly the
    study's rates gets every cell within 5 pp of the paper in only about one run of 1105 trials
    in nine (about one in three with ten times more trials), so a largest difference alone cannot
    say whether a table fits."""
    cells: dict = {}
    for dv, reference in TABLE1_PAPER.items():
        for k, q in reference.items():
            p, n, m = table.get(dv, {}).get(k), counts.get(dv, {}).get(k, 0), TABLE1_PAPER_TRIALS[dv][k]
            if p is None or n == 0:
                continue
            pooled = (p * n + q * m) / (n + m)
            spread = np.sqrt(pooled * (1 - pooled) * (1 / n + 1 / m))
            cells.setdefault(dv, {})[k] = {
                "difference": float(p - q), "se": float(np.sqrt(p * (1 - p) / n + q * (1 - q) / m)),
                "z": float((p - q) / spread) if spread > 0 else 0.0}
    if not cells:
        return None
    chi2 = float(sum(c["z"] ** 2 for row in cells.values() for c in row.values()))
    dof = sum(len(row) for row in cells.values())
    return {"cells": cells, "chi2": chi2, "dof": dof, "p_value": float(scipy_stats.chi2.sf(chi2, dof))}


def dataset_stats(trials: TrialSet, reference: TrialSet | None = None) -> dict:
    """The summary of a dataset (``trafficweaving stats``): ``trials``, trial lengths in steps,
    Table I with its counts and its test against the paper's, and the humans' driving behaviour
    (:func:`~trafficweaving.data.behaviour.summarise`); with ``reference``, the humans' behaviour
    compared with the reference's (``behaviour_vs_reference``)."""
    t1 = table1(trials)
    humans = behaviour_samples(trials, role="human")
    payload = {
        "trials": len(trials),
        "steps": {"min": int(trials.lengths.min()), "mean": float(trials.lengths.mean()),
                  "max": int(trials.lengths.max())},
        "table1": t1["table1"],
        "table1_counts": t1["counts"],
        "table1_vs_paper": table1_test(t1["table1"], t1["counts"]),
        "behaviour": {name: summarise(values) for name, values in humans.items()},
    }
    if reference is not None:
        payload["behaviour_vs_reference"] = compare_behaviour(humans, behaviour_samples(reference, role="human"))
    return payload


def format_table1_test(test: dict | None) -> str:
    """One line: the largest difference from the paper's Table I and the χ² test of
    :func:`table1_test`."""
    if test is None:
        return "vs the paper's Table I: no filled cell"
    dv, k, cell = max(((dv, k, c) for dv, row in test["cells"].items() for k, c in row.items()),
                      key=lambda item: abs(item[2]["difference"]))
    where = "Δv = 0" if k == "all" else f"Δv = {int(dv):+d} m/s, tco = {k} s"
    verdict = "consistent with" if test["p_value"] >= 0.05 else "differs from"
    return (f"vs the paper's Table I: largest difference {100 * cell['difference']:+.1f} pp ({where}, z {cell['z']:+.1f}); "
            f"χ²({test['dof']}) = {test['chi2']:.1f}, p = {test['p_value']:.3f}: {verdict} the study at the 5 % level")


def format_table1(table: dict, counts: dict) -> str:
    """Table I as text, each cell beside the paper's value and its trial count."""
    def cell(dv, k):
        value = table[dv][k]
        ours = "   -  " if value is None else f"{100 * value:5.1f}%"
        return f"{ours} (paper {100 * TABLE1_PAPER[dv][k]:4.1f}%, n={counts[dv][k]})"

    lines = ["Table I: fraction of trials where the car starting in the left lane passes in front",
             f"{'tco':>5} | {'Δv = -2 m/s':^30} | {'Δv = +2 m/s':^30}"]
    for k in ("1", "2", "3"):
        lines.append(f"{k + ' s':>5} | {cell('-2', k):^30} | {cell('2', k):^30}")
    lines.append(f"Δv = 0 (all tco): {cell('0', 'all')}")
    return "\n".join(lines)
