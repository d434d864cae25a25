"""Closed-loop realism of a human agent on recorded trials, after the Waymo Open Sim Agents
Challenge (WOSAC; Montali et al., NeurIPS 2023): how likely is the real driving under the agent's
own rollouts?

For every recorded trial and every car in it labelled ``human``, the agent takes that car over
after the first ``MIN_HISTORY`` recorded steps and drives it ``rollouts`` times to the end of the
recording (and on, up to :data:`EXTENSION` steps, until it reaches the cutoff: whether a rollout
swaps lanes before the cutoff is known only there), against the other car replayed as recorded (it
does not react; past the recording it holds its last acceleration). Per-step features, who passed
first and collisions are judged over the recorded steps. Each rollout and the recording give the values of the :data:`FEATURES`, per step (speed, accelerations, jerks, held
controls, lateral position, distance and time to collision) or once per stream (when and where
the lane change starts and crosses the divider, who passed first, collision, off road).

A feature's likelihood is WOSAC's histogram likelihood: the rollouts' values in :data:`BINS` equal
bins over the feature's range (values outside clipped to the end bins; "did not happen", e.g. no
lane change, is a bin of its own), smoothed by :data:`PSEUDOCOUNT`, and the probability of the
bin the real value falls in; per stream the exponent of its mean log over the stream's steps,
then averaged over streams, so each feature scores in [0, 1]. Features average into three groups
(``kinematic``, ``interactive``, ``road``) and the groups, weighted by :data:`GROUP_WEIGHTS`, into
one ``realism`` score in [0, 1]. Rates over the rollouts (lane swap before the cutoff, off road,
collision, collision with the human car at fault) are reported next to the recording's.
docs/realism.md has the table of every agent.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
from tqdm import tqdm

from ..data.behaviour import HOLD_TOLERANCE, lane_change_events
from ..data.stats import swap_step
from ..data.trials import TrialSet, load_trials
from ..errors import InputError
from ..model.crossval import out_of_fold_models
from ..model.device import choose_device
from ..model.exemplars import build_exemplars
from ..scenario import (CUTOFF_X, DT, MIN_HISTORY, ROAD_Y_MAX, ROAD_Y_MIN, across_divider, at_fault_collision, colliding,
                        on_road, swapped_before_cutoff, time_to_collision)
from .humans import HUMAN_SPECS, ModelDriver, ReplayedCar, human_agent
from .world import Agent, run_episodes

ROLLOUTS = 32
"""Rollouts per stream (WOSAC's 32)."""
ROLLOUT_BYTES = 200_000
"""About the memory one rollout of one stream holds while the rollouts run: its states, its feature
values and a model driver's share of the batch (measured with ``model:driver`` on the 30 real
trials; about 30 kB without a model)."""
MAX_ROLLOUTS = 512
"""Most rollouts per stream: all of a group's rollouts run at once, so the 30 real trials' 30
recorded humans need about 30 · 512 · :data:`ROLLOUT_BYTES` = 3 GB at most (16 times WOSAC's 32)."""
BINS = 20
"""Histogram bins over a continuous feature's range."""
PSEUDOCOUNT = 0.1
"""Additive smoothing of each bin's count, so that no real value has probability 0 (the WOSAC
configurations use 0.1)."""
EXTENSION = 30
"""Steps (3 s) a rollout may run past the end of its recording to reach the cutoff."""
TTC_CAP = 5.0
"""Time to collision beyond this (or never: not closing, or not in the same lane) counts as it, s."""


@dataclass(frozen=True)
class Feature:
    """A realism feature: its ``group``, the range ``[low, high]`` its bins cover (``bins`` of them;
    2 for a yes/no feature, whose values are 0 and 1), whether it has a value at every step
    (``per_step``) or once per stream, its unit and what it measures."""

    group: str
    low: float
    high: float
    per_step: bool
    unit: str
    what: str
    bins: int = BINS


def _flag(group: str, per_step: bool, what: str) -> Feature:
    return Feature(group, -0.5, 1.5, per_step, "", what, bins=2)


FEATURES = {
    "speed": Feature("kinematic", 15.0, 40.0, True, "m/s", "longitudinal speed"),
    "accel_x": Feature("kinematic", -5.0, 5.0, True, "m/s²", "longitudinal acceleration"),
    "accel_y": Feature("kinematic", -3.0, 3.0, True, "m/s²", "lateral acceleration"),
    "jerk_x": Feature("kinematic", -20.0, 20.0, True, "m/s³", "longitudinal jerk"),
    "jerk_y": Feature("kinematic", -20.0, 20.0, True, "m/s³", "lateral jerk"),
    "held_x": _flag("kinematic", True, "longitudinal control held (acceleration changed by less than HOLD_TOLERANCE)"),
    "held_y": _flag("kinematic", True, "lateral control held"),
    "distance": Feature("interactive", 0.0, 60.0, True, "m", "distance between the cars' centres"),
    "time_to_collision": Feature("interactive", 0.0, TTC_CAP, True, "s",
                                 "time to collision with the other car in the same lane (capped)"),
    "passed_first": _flag("interactive", False, "ahead of the other car once both have swapped lanes"),
    "collision": _flag("interactive", False, "collides with the other car"),
    "lateral_position": Feature("road", ROAD_Y_MIN, ROAD_Y_MAX, True, "m", "lateral position"),
    "lane_change_start": Feature("road", 0.0, 6.0, False, "s", "when the sideways motion of the lane change starts"),
    "crossing_time": Feature("road", 0.0, 6.0, False, "s", "when the car crosses the lane divider"),
    "crossing_x": Feature("road", -140.0, 20.0, False, "m", "where the car crosses the lane divider"),
    "off_road": _flag("road", False, "leaves the road before the cutoff"),
}
"""The features by name. Times count from the stream's first step."""
GROUP_WEIGHTS = {"kinematic": 0.3, "interactive": 0.4, "road": 0.3}
"""Weights of the groups in ``realism`` (they sum to 1): interaction weighs most, as this task is
about it. Fixed once published, so that scores stay comparable."""


@dataclass
class Streams:
    """Recorded streams to roll out, or their rollouts: ``states [n, 2, T, 6]`` with the other car
    first (car 0) and the human car second (car 1), ``lengths [n]``, ``trial_ids [n]``, the
    trials' start lanes ``start_lanes [n, 2]`` in that order, and ``recorded [n]``: the recorded
    length, over which per-step features are scored (a rollout's ``lengths`` may go beyond it)."""

    states: np.ndarray
    lengths: np.ndarray
    trial_ids: np.ndarray
    start_lanes: np.ndarray
    recorded: np.ndarray

    @staticmethod
    def of(trials: TrialSet) -> "Streams":
        """One stream per agent labelled ``human`` in ``trials`` (both cars of a human–human trial),
        the human model's streams (:func:`~trafficweaving.model.exemplars.build_exemplars`)."""
        trials.require_dt(DT, "the simulation")
        exemplars = build_exemplars(trials)
        rows, agents = exemplars.stream_trial, exemplars.stream_agent
        order = np.stack([1 - agents, agents], axis=1)  # [n, 2]: other car, human
        return Streams(states=exemplars.streams.transpose(0, 2, 1, 3), lengths=exemplars.lengths.copy(),
                       trial_ids=trials.trial_ids[rows], start_lanes=trials.start_lanes[rows[:, None], order],
                       recorded=exemplars.lengths.copy())

    def __len__(self) -> int:
        return len(self.lengths)

    def _apply(self, f: Callable[[np.ndarray], np.ndarray]) -> "Streams":
        return Streams(*(f(a) for a in (self.states, self.lengths, self.trial_ids, self.start_lanes, self.recorded)))

    def repeat(self, r: int) -> "Streams":
        """Each stream ``r`` times in a row (stream-major)."""
        return self._apply(lambda a: np.repeat(a, r, axis=0))

    def select(self, rows: np.ndarray) -> "Streams":
        """The streams ``rows`` (indices or a mask ``[n]``)."""
        return self._apply(lambda a: a[rows])

    def as_trials(self, recorded: bool = False) -> TrialSet:
        """As a :class:`TrialSet` (roles: the other car ``robot``, the human car ``human``), up to
        ``lengths`` or, with ``recorded``, to the recorded lengths."""
        n = len(self)
        return TrialSet(states=self.states, lengths=self.recorded if recorded else self.lengths, trial_ids=self.trial_ids,
                        roles=np.tile(np.array(["robot", "human"]), (n, 1)), start_lanes=self.start_lanes,
                        drivers=np.full((n, 2), -1, dtype=np.int32), ic_dv=np.full(n, np.nan), ic_tco=np.full(n, np.nan),
                        sources=np.full(n, "realism"))


def roll_out(streams: Streams, agent: Agent, rollouts: int, rng: np.random.Generator,
             progress: bool = False) -> Streams:
    """``rollouts`` rollouts of every stream (stream-major, ``[n · rollouts]``): ``agent`` drives
    the human car (car 1) from the stream's first ``MIN_HISTORY`` recorded steps to its recorded
    length and on until it reaches ``CUTOFF_X`` (at most :data:`EXTENSION` steps more), the other
    car replays its recorded accelerations (its last one past the recording)."""
    many = streams.repeat(rollouts)
    t_max = streams.states.shape[2] + EXTENSION
    steps = np.minimum(np.arange(t_max), many.lengths[:, None] - 1)  # [m, T]
    other = ReplayedCar(many.states[np.arange(len(many))[:, None], 0, steps, 4:6])
    world = run_episodes(many.states[:, :, :MIN_HISTORY], [other, agent], rng, max_steps=t_max, progress=progress,
                         until_max_steps=True)
    states = world.states.copy()
    past = states[:, 1, :, 0] >= CUTOFF_X  # [m, T]
    reached = np.where(past.any(axis=1), past.argmax(axis=1) + 1, t_max)
    lengths = np.clip(reached, many.lengths, many.lengths + EXTENSION)
    states[np.broadcast_to(np.arange(t_max)[None, None, :] >= lengths[:, None, None], states.shape[:3])] = np.nan
    return Streams(states, lengths, many.trial_ids, many.start_lanes, many.lengths)


def feature_values(streams: Streams, flags: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Every feature's values for the human car of each stream: ``[n, T]`` per step (NaN outside
    steps ``MIN_HISTORY .. length - 1``, the steps an agent drives), ``[n]`` once (NaN: did not
    happen); ``flags``: the streams' :func:`rates`."""
    s = streams.states
    n, _, t_max, _ = s.shape
    human = s[:, 1]  # [n, T, 6]
    steps = np.arange(t_max)
    driven = (steps[None, :] >= MIN_HISTORY) & (steps[None, :] < streams.recorded[:, None])
    change = np.diff(human[..., 4:6], axis=1, prepend=np.nan)  # [n, T, 2]
    per_step = {
        "speed": human[..., 2], "accel_x": human[..., 4], "accel_y": human[..., 5],
        "jerk_x": change[..., 0] / DT, "jerk_y": change[..., 1] / DT,
        "held_x": (np.abs(change[..., 0]) < HOLD_TOLERANCE).astype(float),
        "held_y": (np.abs(change[..., 1]) < HOLD_TOLERANCE).astype(float),
        "distance": np.hypot(human[..., 0] - s[:, 0, :, 0], human[..., 1] - s[:, 0, :, 1]),
        "time_to_collision": np.minimum(time_to_collision(s[:, 0], human), TTC_CAP), "lateral_position": human[..., 1],
    }
    values = {name: np.where(driven, v, np.nan) for name, v in per_step.items()}

    trials = streams.as_trials()
    events = lane_change_events(trials)  # one per stream, in order
    values["lane_change_start"] = events.start * DT
    values["crossing_time"] = events.crossing * DT
    k = np.floor(np.nan_to_num(events.crossing)).astype(int)
    frac = np.nan_to_num(events.crossing) - k
    x = human[..., 0]
    at_crossing = x[np.arange(n), k] + frac * (x[np.arange(n), np.minimum(k + 1, t_max - 1)] - x[np.arange(n), k])
    values["crossing_x"] = np.where(np.isnan(events.crossing), np.nan, at_crossing)
    both = swap_step(streams.as_trials(recorded=True))
    y_both = s[np.arange(n), :, both, 1]  # [n, 2]
    swapped = across_divider(s[:, :, 0, 1], y_both).all(axis=1)
    ahead = s[np.arange(n), 1, both, 0] > s[np.arange(n), 0, both, 0]
    values["passed_first"] = np.where(swapped, ahead.astype(float), np.nan)
    values["collision"], values["off_road"] = flags["collision"].astype(float), flags["off_road"].astype(float)
    return values


def rates(streams: Streams) -> dict[str, np.ndarray]:
    """Per stream ``[n]`` (bool): the human car's ``swap`` (across the divider before the cutoff,
    :func:`~trafficweaving.scenario.swapped_before_cutoff`, over the whole rollout), ``off_road``
    (off the road at a driven recorded step before it reaches the cutoff), ``collision`` (with
    the other car, at any recorded step: past the recording the other car is no longer real) and
    ``at_fault_collision`` (such a collision with the human car at fault,
    :func:`~trafficweaving.scenario.at_fault_collision`: the replayed car does not react, so it may
    move into a rollout that is where the real car was not)."""
    s, lengths = streams.states, streams.lengths
    steps = np.arange(s.shape[2])[None, :]
    recorded = steps < streams.recorded[:, None]
    before_cutoff = recorded & (steps >= MIN_HISTORY) & (np.fmax.accumulate(np.nan_to_num(s[:, 1, :, 0], nan=-np.inf), axis=1) < CUTOFF_X)
    return {"swap": swapped_before_cutoff(s, lengths)[:, 1],
            "off_road": (~on_road(s[:, 1, :, 1]) & before_cutoff).any(axis=1),
            "collision": (colliding(s[:, 0], s[:, 1]) & recorded).any(axis=1),
            "at_fault_collision": at_fault_collision(s[:, 1], s[:, 0], recorded)}


def bin_index(values: np.ndarray, feature: Feature) -> np.ndarray:
    """Each value's bin (0 .. ``bins - 1``; NaN: ``bins``, "did not happen"), same shape."""
    scaled = (np.nan_to_num(values) - feature.low) / (feature.high - feature.low) * feature.bins
    index = np.clip(np.floor(scaled), 0, feature.bins - 1).astype(int)
    return np.where(np.isnan(values), feature.bins, index)


def feature_likelihood(real: np.ndarray, rolled: np.ndarray, feature: Feature) -> np.ndarray:
    """Per stream ``[n]``: the histogram likelihood (module docstring) of the real values ``real
    [n, T]`` (per step; NaN steps are not scored) or ``[n]`` under the rollouts' ``rolled
    [n, R, T]`` or ``[n, R]``."""
    cells = feature.bins + 1
    real_bin = bin_index(real, feature)  # [n(, T)]
    counts = np.stack([(bin_index(rolled, feature) == b).sum(axis=1) for b in range(cells)], axis=-1)  # [n(, T), cells]
    p = (counts + PSEUDOCOUNT) / (rolled.shape[1] + PSEUDOCOUNT * cells)
    log_p = np.log(np.take_along_axis(p, real_bin[..., None], axis=-1)[..., 0])
    if not feature.per_step:
        return np.exp(log_p)
    scored = ~np.isnan(real)
    return np.exp(np.where(scored, log_p, 0.0).sum(axis=1) / np.maximum(scored.sum(axis=1), 1))


@dataclass
class Realism:
    """Per-stream feature likelihoods ``likelihoods {name: [n]}`` and rates of the rollouts
    ``rolled_rates {swap, off_road, collision, at_fault_collision: [n]}`` (fraction of each stream's
    rollouts) and of the recordings ``real_rates`` (``[n]`` bool), for ``trial_ids [n]``, with
    ``rollouts`` each."""

    likelihoods: dict[str, np.ndarray]
    rolled_rates: dict[str, np.ndarray]
    real_rates: dict[str, np.ndarray]
    trial_ids: np.ndarray
    rollouts: int

    @staticmethod
    def concatenate(parts: list["Realism"]) -> "Realism":
        cat = lambda key: {k: np.concatenate([getattr(p, key)[k] for p in parts]) for k in getattr(parts[0], key)}  # noqa: E731
        return Realism(cat("likelihoods"), cat("rolled_rates"), cat("real_rates"),
                       np.concatenate([p.trial_ids for p in parts]), parts[0].rollouts)

    def summary(self) -> dict:
        """``realism``, ``groups``, ``features`` (means over streams), ``trials``, ``streams``,
        ``rollouts``, the rollouts' ``swap_rate``, ``off_road_rate``, ``collision_rate``,
        ``at_fault_collision_rate`` and the recordings' ``real_swap_rate``, ``real_off_road_rate``,
        ``real_collision_rate``, ``real_at_fault_collision_rate``."""
        features = {name: float(v.mean()) for name, v in self.likelihoods.items()}
        groups = {g: float(np.mean([features[f] for f, spec in FEATURES.items() if spec.group == g])) for g in GROUP_WEIGHTS}
        out = {"realism": float(sum(w * groups[g] for g, w in GROUP_WEIGHTS.items())), "groups": groups,
               "features": features, "trials": int(len(np.unique(self.trial_ids))), "streams": int(len(self.trial_ids)),
               "rollouts": self.rollouts}
        for key in ("swap", "off_road", "collision", "at_fault_collision"):
            out[f"{key}_rate"] = float(self.rolled_rates[key].mean())
            out[f"real_{key}_rate"] = float(self.real_rates[key].mean())
        return out


def score_streams(streams: Streams, rolled: Streams, rollouts: int) -> Realism:
    """The realism of ``rolled`` (:func:`roll_out` of ``streams``) against ``streams``."""
    real_flags, rolled_flags = rates(streams), rates(rolled)
    real, many = feature_values(streams, real_flags), feature_values(rolled, rolled_flags)
    n, t_max = len(streams), streams.states.shape[2]

    def rolled_values(name: str, spec: Feature) -> np.ndarray:  # [n, R, T] on the streams' steps, or [n, R]
        return many[name][:, :t_max].reshape(n, rollouts, t_max) if spec.per_step else many[name].reshape(n, rollouts)

    likelihoods = {name: feature_likelihood(real[name], rolled_values(name, spec), spec) for name, spec in FEATURES.items()}
    rolled_rates = {k: v.reshape(n, rollouts).mean(axis=1) for k, v in rolled_flags.items()}
    return Realism(likelihoods, rolled_rates, real_flags, streams.trial_ids, rollouts)


def realism(trials: TrialSet, agents: Callable[[np.ndarray, str], list[tuple[np.ndarray, Agent]]],
            rollouts: int = ROLLOUTS, seed: int = 0, progress: bool = False) -> Realism:
    """The realism of a human agent on ``trials``' human streams (module docstring).

    ``agents(trial_ids, other)`` splits the trial ids ``[k]`` into groups, each with the agent that
    drives them, facing ``other`` (:func:`~trafficweaving.model.mixture.facing`: ``person`` in
    trials where both cars are labelled human, else ``robot``): one group for a fixed agent, one per
    fold for an agent trained on the trials (out-of-fold). ``rollouts`` per stream; seeded from
    ``seed``."""
    if not (isinstance(rollouts, int) and 2 <= rollouts <= MAX_ROLLOUTS):
        raise ValueError(f"rollouts must be an integer in 2..{MAX_ROLLOUTS}, got {rollouts!r}")
    streams = Streams.of(trials)
    if len(streams) == 0:
        raise ValueError("the trials have no agent labelled human (expected at least one to roll out)")
    short = streams.lengths <= MIN_HISTORY
    if short.any():
        raise ValueError(f"trial {streams.trial_ids[short][0]} has {streams.lengths[short][0]} steps "
                         f"(expected more than the {MIN_HISTORY} recorded steps a rollout starts from)")
    rng = np.random.default_rng(seed)
    parts = []
    trial_ids = np.unique(streams.trial_ids)
    human_human = np.isin(trial_ids, trials.trial_ids[(trials.roles == "human").all(axis=1)])
    by_other = {"robot": trial_ids[~human_human], "person": trial_ids[human_human]}
    groups = [(np.intersect1d(ids, facing_ids), agent) for other, facing_ids in by_other.items() if len(facing_ids)
              for ids, agent in agents(facing_ids, other)]
    for ids, agent in tqdm(groups, desc="realism", unit="group", disable=not progress or len(groups) == 1):
        part = streams.select(np.isin(streams.trial_ids, ids))
        if len(part):
            parts.append(score_streams(part, roll_out(part, agent, rollouts, rng, progress), rollouts))
    return Realism.concatenate(parts)


def realism_of(data: str, human: str | None = None, folds: str | None = None, rollouts: int = ROLLOUTS, seed: int = 0,
               device: str = "cpu", progress: bool = False) -> dict:
    """The realism summary (:meth:`Realism.summary`, with ``human``, ``data`` and ``seed``) of the
    recorded trials in the file ``data``, driven by one of: ``human``, a human agent's spec, or
    ``folds``, the folder of ``crossval --out`` fold models, each driving the trials it did not
    train on (out-of-fold). ``device``: a model agent's device."""
    if (human is None) == (folds is None):
        raise InputError(f"realism needs one of --human SPEC ({HUMAN_SPECS}) or --folds DIR (out-of-fold models)")
    device = choose_device(device)
    if human is not None:
        made = {}

        def agent(other: str):
            """The --human agent facing ``other``, made once."""
            if other not in made:
                try:
                    made[other] = human_agent(human, device, other=other)
                except InputError as exc:
                    raise InputError(f"--human {human}: {exc}") from None
            return made[other]

        agent("robot")  # a bad --human fails before the data is read
        agents = lambda ids, other: [(ids, agent(other))]  # noqa: E731
    trials = load_trials(data)
    if folds is not None:
        models = out_of_fold_models(folds)
        held = np.concatenate([np.asarray(ids) for _, ids in models])
        missing = np.setdiff1d(trials.trial_ids[(trials.roles == "human").any(axis=1)], held)
        if len(missing):
            raise InputError(f"--folds {folds}: trial {missing[0]} of {data} is held out by no fold (expected "
                             f"the folds of `trafficweaving crossval --out` on the same data)")
        agents = lambda ids, other: [(np.asarray(h), ModelDriver(m.to(device), other=other)) for m, h in models]  # noqa: E731
    try:
        result = realism(trials, agents, rollouts=rollouts, seed=seed, progress=progress)
    except InputError:
        raise
    except ValueError as exc:
        raise InputError(f"{data}: {exc}") from None
    return {"human": human or f"out-of-fold:{folds}", "data": str(data), "seed": seed, **result.summary()}
