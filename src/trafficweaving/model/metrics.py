"""Evaluation beyond the mean NLL, per prediction instance: the NLLs of :mod:`.evaluate`, the
instance's lane-change phase, and metrics of sampled human futures (positions).

* **Positions.** Sampled accelerations become positions by the trapezoid rule from the recorded
  present state (:func:`~trafficweaving.dynamics.future_states`). The true positions are
  integrated the same way from the *recorded* accelerations (:func:`true_positions`), so the
  sampled metrics judge the action model alone: on the synthetic data this is the recording
  exactly; on the 30 real trials the recorded positions differ from it by 1.4 cm (x) and 3.5 cm
  (y) on average at 1.5 s (p99 11 cm), residue of the driving simulator's own integration.
* **Coverage.** For each direction (x longitudinal, y lateral) and horizon (0.5, 1.0, 1.5 s =
  steps 5, 10, 15 ahead): whether the true position lies within the central interval of the
  sampled positions at a level (50 %: between their 25th and 75th percentiles, linearly
  interpolated). A calibrated model covers the truth in 50 % and 90 % of instances.
* **minADE / minFDE.** Over the first ``ade_samples`` samples: the smallest mean (ADE) and final
  (FDE, 1.5 s) Euclidean position error, m.
* **Holds.** The fraction of the 15 steps whose acceleration changes by less than
  :data:`~trafficweaving.data.behaviour.HOLD_TOLERANCE` from the step before (the present action
  for the first), per direction, in the sampled futures (mean over samples) and in the truth: a
  model that learned drivers' intermittent control samples holds as often as they happen; no
  narrow density component can fake that.
* **Phase** of an instance at present step ``t`` relative to its human's lane change
  (:func:`~trafficweaving.data.behaviour.lane_change_events`): ``before`` if ``t < start``,
  ``during`` if ``start <= t < end`` (``end`` not recorded: the crossing plus
  :data:`DURING_WITHOUT_END` steps), ``after`` otherwise; ``none`` for a human that never crosses
  the lane divider (reported as its own phase).

Samples come from ``p(z|x)`` and :meth:`CVAE.sample_actions` with one seeded generator on the
model's device, so results are deterministic for given options and device.

:func:`evaluate_file` is the ``evaluate`` command's workflow: a model spec and a dataset file in,
the ``--json`` payload out.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import torch

from ..atomic import atomic_write, check_output_file
from ..data.behaviour import HOLD_TOLERANCE, lane_change_events
from ..data.trials import TrialSet, load_trials
from ..dynamics import future_states
from ..errors import InputError
from ..scenario import DT, HORIZON, MIN_TRIAL_STEPS
from .cvae import ACCEL, CVAE
from .device import choose_device
from .evaluate import Evaluation, evaluate_tensors
from .exemplars import ExemplarSet, ExemplarTensors, build_exemplars
from .mixture import Mixture, describe
from .registry import load_model

DIRECTIONS = ("x", "y")
HORIZON_STEPS = (5, 10, HORIZON)
"""Horizons of the coverage, steps ahead (0.5, 1.0, 1.5 s: the last is the full horizon)."""
LEVELS = (0.5, 0.9)
"""Central-interval levels reported by default."""
PHASES = ("before", "during", "after", "none")
DURING_WITHOUT_END = 10
"""Steps after the crossing that count as ``during`` when the lane change's end is not recorded."""
ROLLOUTS_PER_BATCH = 25_600
"""Sampled futures decoded together (instances per batch × samples)."""
MAX_SAMPLES = ROLLOUTS_PER_BATCH
"""Most futures sampled per instance (``evaluate --coverage-samples`` and ``--ade-samples``,
``calibrate --samples``, ``predict --samples``): one instance's futures are decoded in one batch."""


def horizon_key(step: int) -> str:
    """``"0.5"``, ``"1.0"``, ``"1.5"``: a horizon in seconds, as used in JSON keys."""
    return f"{step * DT:.1f}"


def level_key(level: float) -> str:
    """``"50"``, ``"90"``: a level in percent, as used in JSON keys."""
    return f"{100 * level:g}"


def true_actions(exemplars: ExemplarSet, index: np.ndarray) -> np.ndarray:
    """The human's recorded accelerations ``[len(index), 15, 2]`` (m/s²) at steps t+1..t+15 of
    exemplars ``index``."""
    s, t = exemplars.stream[index], exemplars.t[index]
    return exemplars.streams[s[:, None], t[:, None] + np.arange(1, HORIZON + 1), 1, ACCEL]


def true_positions(exemplars: ExemplarSet, index: np.ndarray) -> np.ndarray:
    """The human's positions ``[len(index), 15, 2]`` (m) at steps t+1..t+15 of exemplars ``index``,
    integrated by the trapezoid rule from its recorded present state and recorded accelerations."""
    present = exemplars.streams[exemplars.stream[index], exemplars.t[index], 1]  # [E, 6]
    return future_states(torch.as_tensor(present), torch.as_tensor(true_actions(exemplars, index)))[..., :2].numpy()


@dataclass
class SampledMetrics:
    """Metrics of sampled futures for ``E'`` instances: ``covered [E', 2, 3, L]`` (direction,
    horizon of :data:`HORIZON_STEPS`, level) whether the truth lies in the central interval;
    ``min_ade``, ``min_fde`` ``[E']`` (m); ``held [E', 2, 2]`` (sampled, true; direction) the
    fraction of held steps."""

    covered: np.ndarray
    min_ade: np.ndarray
    min_fde: np.ndarray
    held: np.ndarray


def held_fraction(present: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
    """Fraction ``[..., 2]`` of the steps of ``actions [..., 15, 2]`` (m/s²) that change by less
    than ``HOLD_TOLERANCE`` from the step before, the first from ``present [..., 2]``."""
    previous = torch.cat([present.unsqueeze(-2).expand(*actions.shape[:-2], 1, 2), actions[..., :-1, :]], dim=-2)
    return ((actions - previous).abs() < HOLD_TOLERANCE).double().mean(-2)


@torch.no_grad()
def sampled_metrics(model: CVAE | Mixture, exemplars: ExemplarSet, index: np.ndarray, samples: int = 100,
                    ade_samples: int = 20, levels: tuple[float, ...] = LEVELS, seed: int = 0,
                    data: ExemplarTensors | None = None) -> SampledMetrics:
    """Coverage at ``levels`` over ``samples`` sampled futures and minADE/minFDE over the first
    ``ade_samples`` of them, for exemplars ``index [E']`` (``data``: the exemplars already
    standardised for ``model``, to reuse)."""
    model.eval()
    device = next(model.parameters()).device
    if data is None:
        data = exemplars.standardised(model)
    draws = max(samples, ade_samples)
    generator = torch.Generator(device=device).manual_seed(seed)
    truth = torch.as_tensor(true_positions(exemplars, index), device=device)  # [E', 15, 2]
    truth_actions = torch.as_tensor(true_actions(exemplars, index), device=device)  # [E', 15, 2]
    s, t = exemplars.stream[index], exemplars.t[index]
    present = torch.as_tensor(exemplars.streams[s, t, 1], device=device)  # [E', 6]
    bounds = torch.tensor([q for level in levels for q in (0.5 - level / 2, 0.5 + level / 2)],
                          dtype=torch.float64, device=device)
    steps = torch.tensor(HORIZON_STEPS, device=device) - 1
    covered, ade, fde, held = [], [], [], []
    batch_size = max(1, ROLLOUTS_PER_BATCH // draws)
    for start in range(0, len(index), batch_size):
        rows = slice(start, start + batch_size)
        batch = data.batch(torch.as_tensor(index[rows], device=device))
        actions = model.actions_to_physical(model.sample_futures(batch, draws, generator).double())
        positions = future_states(present[rows], actions)[..., :2]  # [S, B, 15, 2]
        true = truth[rows]
        # coverage: [2L, B, 3, 2] quantiles of the first `samples` draws at the horizons
        q = torch.quantile(positions[:samples, :, steps], bounds, dim=0).view(len(levels), 2, *true[:, steps].shape)
        inside = (q[:, 0] <= true[:, steps]) & (true[:, steps] <= q[:, 1])  # [L, B, 3, 2]
        covered.append(inside.permute(1, 3, 2, 0))
        error = torch.linalg.vector_norm(positions[:ade_samples] - true, dim=-1)  # [k, B, 15]
        ade.append(error.mean(-1).min(0).values)
        fde.append(error[..., -1].min(0).values)
        present_action = present[rows, ACCEL]
        held.append(torch.stack([held_fraction(present_action, actions).mean(0),
                                 held_fraction(present_action, truth_actions[rows])], 1))
    cat = lambda parts: torch.cat(parts).cpu().numpy()  # noqa: E731
    return SampledMetrics(cat(covered), cat(ade), cat(fde), cat(held))


def instance_phases(trials: TrialSet, exemplars: ExemplarSet) -> np.ndarray:
    """The lane-change phase (one of :data:`PHASES`) of each exemplar ``[E]`` of
    ``exemplars = build_exemplars(trials)`` (module docstring)."""
    events = lane_change_events(trials, role="human")
    row = {(int(i), int(a)): k for k, (i, a) in enumerate(zip(events.trial, events.agent))}
    k = np.array([row[int(i), int(a)] for i, a in zip(exemplars.stream_trial, exemplars.stream_agent)], dtype=np.int64)
    per_exemplar = lambda values: np.asarray(values, dtype=float)[k][exemplars.stream]  # noqa: E731
    start, crossing, end = per_exemplar(events.start), per_exemplar(events.crossing), per_exemplar(events.end)
    end = np.where(np.isnan(end), crossing + DURING_WITHOUT_END, end)
    t = exemplars.t
    return np.select([np.isnan(crossing), t < start, t < end], ["none", "before", "during"], "after")


@dataclass
class InstanceMetrics:
    """Everything measured per instance ``[E]``: identification (``trial_id``, ``source``,
    ``agent`` the human, ``t`` the present step, ``phase``), the NLLs (``evaluation``), and the
    sampled metrics of the instances ``sampled [E]`` (bool; ``covered [E, 2, 3, L]``, ``min_ade``,
    ``min_fde`` in m, ``held [E, 2, 2]`` as in :class:`SampledMetrics`; NaN / False where not
    sampled) over ``samples`` futures (``ade_samples`` for minADE/minFDE) at ``levels``."""

    trial_id: np.ndarray
    source: np.ndarray
    agent: np.ndarray
    t: np.ndarray
    phase: np.ndarray
    evaluation: Evaluation
    sampled: np.ndarray
    covered: np.ndarray
    min_ade: np.ndarray
    min_fde: np.ndarray
    held: np.ndarray
    samples: int
    ade_samples: int
    levels: tuple[float, ...]

    def __len__(self) -> int:
        return len(self.t)

    @staticmethod
    def concatenate(parts: list["InstanceMetrics"]) -> "InstanceMetrics":
        """The instances of several evaluations with the same options (e.g. the held-out folds of a
        cross-validation, each scored by the model that did not train on it) as one."""
        first = parts[0]
        cat = lambda name: np.concatenate([getattr(p, name) for p in parts])  # noqa: E731
        ev = [p.evaluation for p in parts]
        evaluation = Evaluation(np.concatenate([e.nll_exact for e in ev]),
                                None if any(e.nll_is is None for e in ev) else np.concatenate([e.nll_is for e in ev]),
                                np.concatenate([e.nll_naive for e in ev]), np.concatenate([e.nll_direction for e in ev]))
        return InstanceMetrics(*(cat(n) for n in ("trial_id", "source", "agent", "t", "phase")), evaluation,
                               *(cat(n) for n in ("sampled", "covered", "min_ade", "min_fde", "held")),
                               first.samples, first.ade_samples, first.levels)

    def coverage(self) -> dict:
        """``{direction: {horizon s: {level %: fraction covered}}}`` over the sampled instances
        (fractions None when none was sampled)."""
        covered = self.covered[self.sampled]
        fraction = lambda d, h, k: float(covered[:, d, h, k].mean()) if len(covered) else None  # noqa: E731
        return {name: {horizon_key(step): {level_key(level): fraction(d, h, k) for k, level in enumerate(self.levels)}
                       for h, step in enumerate(HORIZON_STEPS)} for d, name in enumerate(DIRECTIONS)}

    def summary(self) -> dict:
        """JSON-ready means: :meth:`Evaluation.summary`'s keys, then ``nll_exact_by_direction``
        (``{"x", "y"}``), ``nll_exact_by_phase`` (``{phase: {"instances", "nll_exact"}}``),
        ``sampled_instances``, ``samples``, ``ade_samples``, ``coverage`` (:meth:`coverage`),
        ``min_ade_m``, ``min_fde_m`` and ``held_fraction`` (``{"x"|"y": {"sampled", "true"}}``;
        None when no instance was sampled)."""
        mean = lambda a: float(np.mean(a)) if len(a) else None  # noqa: E731
        nll = self.evaluation.nll_exact
        return {
            **self.evaluation.summary(),
            "nll_exact_by_direction": {name: mean(self.evaluation.nll_direction[:, d]) for d, name in enumerate(DIRECTIONS)},
            "nll_exact_by_phase": {p: {"instances": int((self.phase == p).sum()), "nll_exact": mean(nll[self.phase == p])}
                                   for p in PHASES},
            "sampled_instances": int(self.sampled.sum()),
            "samples": self.samples,
            "ade_samples": self.ade_samples,
            "coverage": self.coverage(),
            "min_ade_m": mean(self.min_ade[self.sampled]),
            "min_fde_m": mean(self.min_fde[self.sampled]),
            "held_fraction": {name: {"sampled": mean(self.held[self.sampled, 0, d]), "true": mean(self.held[self.sampled, 1, d])}
                              for d, name in enumerate(DIRECTIONS)},
        }

    def to_table(self, metadata: dict | None = None) -> pa.Table:
        """One row per instance: ``trial``, ``source``, ``agent``, ``t``, ``phase``, ``nll_exact``,
        ``nll_is`` (null without q), ``nll_naive``, ``nll_exact_x``, ``nll_exact_y`` (nats),
        ``sampled``, ``min_ade_m``, ``min_fde_m`` and ``covered_<x|y>_<0.5|1.0|1.5>s_<level %>``
        (null where not sampled). ``metadata`` (with the options) goes to the schema key
        ``trafficweaving`` as JSON."""
        ev, missing = self.evaluation, ~self.sampled
        columns = {
            "trial": pa.array(self.trial_id, pa.int32()), "source": pa.array(self.source.astype(str)),
            "agent": pa.array(self.agent, pa.int8()), "t": pa.array(self.t, pa.int32()), "phase": pa.array(self.phase.astype(str)),
            "nll_exact": ev.nll_exact, "nll_is": pa.nulls(len(self), pa.float64()) if ev.nll_is is None else ev.nll_is,
            "nll_naive": ev.nll_naive, "nll_exact_x": ev.nll_direction[:, 0], "nll_exact_y": ev.nll_direction[:, 1],
            "sampled": self.sampled,
            "min_ade_m": pa.array(self.min_ade, mask=missing), "min_fde_m": pa.array(self.min_fde, mask=missing),
        }
        for d, name in enumerate(DIRECTIONS):
            columns[f"held_{name}_sampled"] = pa.array(self.held[:, 0, d], mask=missing)
            columns[f"held_{name}_true"] = pa.array(self.held[:, 1, d], mask=missing)
        for d, name in enumerate(DIRECTIONS):
            for h, step in enumerate(HORIZON_STEPS):
                for k, level in enumerate(self.levels):
                    columns[f"covered_{name}_{horizon_key(step)}s_{level_key(level)}"] = pa.array(self.covered[:, d, h, k], mask=missing)
        table = pa.table(columns)
        return table.replace_schema_metadata({"trafficweaving": json.dumps(metadata or {})})

    def write_parquet(self, path: str | os.PathLike, metadata: dict | None = None) -> None:
        """Write :meth:`to_table` to ``path`` atomically."""
        with atomic_write(path) as f:
            pq.write_table(self.to_table(metadata), f, compression="zstd")


def evaluate_instances(model: CVAE | Mixture, trials: TrialSet, exemplars: ExemplarSet, samples: int = 100,
                       ade_samples: int = 20, levels: tuple[float, ...] = LEVELS, max_sampled: int | None = None,
                       nll_samples: int = 50, seed: int = 0) -> InstanceMetrics:
    """Every metric of every exemplar of ``exemplars = build_exemplars(trials)``: the NLLs
    (``nll_samples`` latent samples for the sampled estimators) and, on all exemplars or on
    ``max_sampled`` of them chosen at random (``seed``), the sampled metrics."""
    data = exemplars.standardised(model)
    evaluation = evaluate_tensors(model, data, nll_samples, seed)
    n = len(exemplars)
    index = np.arange(n)
    if max_sampled is not None and max_sampled < n:
        index = np.sort(np.random.default_rng(seed).choice(n, max_sampled, replace=False))
    sampled = np.zeros(n, dtype=bool)
    sampled[index] = True
    covered = np.zeros((n, len(DIRECTIONS), len(HORIZON_STEPS), len(levels)), dtype=bool)
    min_ade, min_fde = np.full(n, np.nan), np.full(n, np.nan)
    held = np.full((n, 2, len(DIRECTIONS)), np.nan)
    if len(index):
        metrics = sampled_metrics(model, exemplars, index, samples, ade_samples, levels, seed, data)
        covered[index], min_ade[index], min_fde[index], held[index] = metrics.covered, metrics.min_ade, metrics.min_fde, metrics.held
    return InstanceMetrics(
        trial_id=trials.trial_ids[exemplars.stream_trial[exemplars.stream]],
        source=exemplars.sources[exemplars.stream],
        agent=exemplars.stream_agent[exemplars.stream],
        t=exemplars.t,
        phase=instance_phases(trials, exemplars),
        evaluation=evaluation, sampled=sampled, covered=covered, min_ade=min_ade, min_fde=min_fde, held=held,
        samples=samples, ade_samples=ade_samples, levels=tuple(levels),
    )


def evaluate_file(model: str, data: str | os.PathLike, samples: int = 50, coverage_samples: int = 100,
                  ade_samples: int = 20, max_sampled: int | None = 5000, seed: int = 0, device: str = "auto",
                  per_instance: str | os.PathLike | None = None) -> tuple[dict, str]:
    """``evaluate``: every metric of ``model`` (a model spec) on every prediction instance of the
    dataset file ``data`` (:func:`evaluate_instances`; ``samples`` latent samples for the sampled
    NLLs, ``coverage_samples`` and ``ade_samples`` futures on at most ``max_sampled`` instances),
    each instance's values also written to ``per_instance`` (Parquet) when given; the output path is
    checked before anything is loaded. Returns the ``--json`` payload (:meth:`InstanceMetrics.summary`'s
    keys, then ``model``, ``variant``, ``data``, ``seed``) and the model described for people
    (:func:`~.mixture.describe`)."""
    per_instance = check_output_file(per_instance, "--per-instance") if per_instance is not None else None
    loaded = load_model(model, choose_device(device))
    trials = load_trials(data)
    exemplars = build_exemplars(trials)
    if len(exemplars) == 0:
        raise InputError(f"{data}: no prediction instances (expected human agents in trials of at least "
                         f"{MIN_TRIAL_STEPS} steps)")
    metrics = evaluate_instances(loaded, trials, exemplars, samples=coverage_samples, ade_samples=ade_samples,
                                 max_sampled=max_sampled, nll_samples=samples, seed=seed)
    result = metrics.summary()
    if per_instance is not None:
        metrics.write_parquet(per_instance, {"model": model, "data": str(data), "seed": seed, "samples": samples,
                                             "coverage_samples": coverage_samples, "ade_samples": ade_samples})
    payload = {**result, "model": model, "variant": loaded.config.name, "data": str(data), "seed": seed}
    return payload, describe(loaded)
