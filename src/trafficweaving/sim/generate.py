"""The synthetic human–human trial generator: the study's protocol played by simulated drivers.

As in the authors' data collection, pairs of drivers play rounds of the 18 initial conditions in
shuffled order; car A starts at ``BASE_SPEED``, car B at ``BASE_SPEED + Δv``, the faster one
``|Δv|·tco`` metres behind. Every trial of a batch is simulated at once (arrays over trials), the
authors' validity rules remove failed or colliding trials, and valid trials are cut before the
first car reaches the cutoff. A run where most trials are rejected is refused. Replayed drivers
(``replay:FILE``) drive the recordings from their own start instead, one recording per trial.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.special import ndtri

from .. import validate
from ..data.trials import TrialSet
from ..scenario import DT, VALIDITY_REASONS, check_validity, lane_of, study_initial_conditions
from .drivers import DriverModel, DriverStyles, stratified_uniform
from .humans import SyntheticDrivers, human_agent, replay_start
from .world import run_episodes

MAX_TRIALS = 100_000
"""Most valid trials one run generates: a run holds about 30 KB per simulated trial (both cars'
states over :data:`~trafficweaving.sim.world.MAX_STEPS` steps and the drivers' state), about 3 GB
at this bound."""

MAX_PAIRS = MAX_TRIALS // 18
"""Most driver pairs: pair ``p`` plays round ``p`` (18 trials), so pairs beyond the rounds of the
largest run never drive."""

MIN_VALID_SHARE = 0.5
"""Least share of valid trials among those simulated that :func:`generate_trials` accepts: a run
where most are rejected has drivers that cannot do the task."""



@dataclass
class GenerationReport:
    """What happened while generating: trials simulated and why rejected ones were removed."""

    simulated: int
    kept: int
    rejected: dict[str, int]

    def as_dict(self) -> dict:
        return {"simulated": self.simulated, "kept": self.kept, "rejected": dict(self.rejected)}


def schedule(n: int, pairs: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """The study's protocol for ``n`` trials: round ``r`` (18 shuffled initial conditions) is
    played by pair ``r % pairs``. Returns ``(ic_index[n], pair[n])`` (indices into
    :func:`study_initial_conditions`)."""
    n_ic = len(study_initial_conditions())
    rounds = -(-n // n_ic)
    ic_index = np.concatenate([rng.permutation(n_ic) for _ in range(rounds)])[:n]
    pair = (np.arange(n) // n_ic) % pairs
    return ic_index, pair


def stratified_moods(ic_index: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Per-trial moods of both drivers, ``[m, 2]``, independent standard normals.

    Who goes first depends mostly on the *difference* of the two moods, so that difference is
    stratified within each initial condition: the ``c`` trials of one condition get one draw from
    each of ``c`` equal-probability strata, in random order (the sum is drawn freely). Rotating
    ``(difference, sum)`` back keeps the two moods independent N(0, 1); a condition's outcomes
    just carry less sampling noise, as a balanced experiment would.
    """
    difference = np.empty(len(ic_index))
    for ic in np.unique(ic_index):
        members = np.flatnonzero(ic_index == ic)
        difference[members] = ndtri(stratified_uniform(len(members), rng))
    total = rng.standard_normal(len(ic_index))
    return np.stack([total + difference, total - difference], axis=1) / np.sqrt(2.0)


def simulate_trials(ic_index: np.ndarray, pair: np.ndarray, styles: DriverStyles, model: DriverModel,
                    rng: np.random.Generator, progress: bool = False, drivers: str = "synthetic",
                    device: str = "cpu", first: int = 0) -> tuple[np.ndarray, np.ndarray, dict]:
    """Simulate human–human trials on the world with both cars driven by :class:`SyntheticDrivers`
    (or, with ``drivers`` another human spec of :func:`~trafficweaving.sim.humans.human_agent`,
    e.g. ``model:driver``, by two such agents, each facing a person: self-play).

    ``ic_index``, ``pair``: ``[m]`` initial condition and driver pair of each trial; ``styles``:
    the traits of all drivers (driver ``2p`` is car A of pair ``p``, ``2p + 1`` car B). Replayed
    drivers (``replay:FILE[#K]``) drive their recordings from the recordings' start instead
    (:func:`~trafficweaving.sim.humans.replay_start`; trial ``i`` of the run, counting the
    ``first`` simulated before, replays the recordings in turn). Returns ``(states[m, 2, S, 6],
    lengths[m], setup)`` with car A as agent 0, uncut and unfiltered; ``setup``: each trial's
    ``ic_dv``, ``ic_tco``, ``start_lanes``, ``drivers`` and ``roles`` (``[m]`` or ``[m, 2]``, as
    in :class:`~trafficweaving.data.trials.TrialSet`).
    """
    ics = study_initial_conditions()
    start = np.stack([ics[i].start_states() for i in ic_index])  # [m, 2, 6]
    moods = stratified_moods(ic_index, rng)
    dv = np.array([ics[i].dv_left_minus_right for i in ic_index])
    setup = {"ic_dv": dv, "ic_tco": np.where(dv == 0, np.nan, [ics[i].tco for i in ic_index]),
             "start_lanes": np.array([[ics[i].lane_a, ics[i].lane_b] for i in ic_index]),
             "drivers": np.stack([2 * pair, 2 * pair + 1], axis=1).astype(np.int32),
             "roles": np.full((len(ic_index), 2), "human")}
    if drivers == "synthetic":
        cars = [SyntheticDrivers(styles.take(2 * pair + k), model, mood=moods[:, k]) for k in (0, 1)]
    else:
        cars = [human_agent(drivers, device, other="person") for _ in (0, 1)]
        replay = replay_start(cars, episodes=first + np.arange(len(ic_index)))
        if replay is not None:
            start, cars = replay.start, replay.cars
            recorded = lambda field: getattr(replay.trials, field)[replay.rows[:, None], replay.agents]  # noqa: E731
            setup = {"ic_dv": replay.trials.ic_dv[replay.rows], "ic_tco": replay.trials.ic_tco[replay.rows],
                     "start_lanes": lane_of(start[..., 1]), "drivers": recorded("drivers"), "roles": recorded("roles")}
    return (*run_episodes(start, cars, rng, progress=progress).recorded(), setup)


def generate_trials(n_trials: int, seed: int = 0, model: DriverModel | None = None, pairs: int = 19,
                    progress: bool = False, drivers: str = "synthetic",
                    device: str = "cpu") -> tuple[TrialSet, GenerationReport]:
    """Generate ``n_trials`` (1..:data:`MAX_TRIALS`) valid human–human trials played by ``pairs``
    (1..:data:`MAX_PAIRS`) pairs of drivers (the paper's data: 1105 trials, 19 pairs).

    Trials are simulated in the protocol's order until ``n_trials`` pass the validity rules;
    the report counts the rejected ones by reason. Deterministic for a given ``seed``. Both cars
    are driven by ``drivers`` (:func:`simulate_trials`); ValueError when fewer than
    :data:`MIN_VALID_SHARE` of the trials simulated are valid (drivers that cannot do the task).
    """
    n_trials = validate.integer("n_trials", n_trials, 1, MAX_TRIALS)
    pairs = validate.integer("pairs", pairs, 1, MAX_PAIRS)
    model = model or DriverModel()
    rng = np.random.default_rng(seed)
    styles = DriverStyles.sample(model, 2 * pairs, rng)
    planned = int(np.ceil(n_trials * 1.08)) + 18
    ic_index, pair = schedule(planned, pairs, rng)
    states, lengths, setup = simulate_trials(ic_index, pair, styles, model, rng, progress, drivers, device)
    reason, cut = check_validity(states, lengths)
    while True:
        if (reason == 0).mean() < MIN_VALID_SHARE:
            rejected = ", ".join(f"{VALIDITY_REASONS[k]} {c}" for k, c in enumerate(np.bincount(reason)) if k > 0 and c)
            raise ValueError(f"{(reason != 0).sum()} of the {len(reason)} trials simulated with drivers {drivers!r} were "
                             f"rejected ({rejected}; expected drivers that swap lanes safely in at least "
                             f"{MIN_VALID_SHARE:.0%} of trials)")
        if (reason == 0).sum() >= n_trials:
            break
        more_ic, more_pair = schedule(planned, pairs, rng)  # rare: top up with further rounds
        more_pair = (more_pair + len(pair) // 18) % pairs
        more_states, more_lengths, more_setup = simulate_trials(more_ic, more_pair, styles, model, rng, progress,
                                                                drivers, device, first=len(reason))
        more_reason, more_cut = check_validity(more_states, more_lengths)
        t_max = max(states.shape[2], more_states.shape[2])
        pad = lambda a: np.pad(a, ((0, 0), (0, 0), (0, t_max - a.shape[2]), (0, 0)), mode="edge")  # noqa: E731
        states = np.concatenate([pad(states), pad(more_states)])
        setup = {name: np.concatenate([setup[name], more_setup[name]]) for name in setup}
        pair = np.concatenate([pair, more_pair])
        reason, cut = np.concatenate([reason, more_reason]), np.concatenate([cut, more_cut])

    valid = np.flatnonzero(reason == 0)[:n_trials]
    simulated = int(valid[-1]) + 1
    counts = np.bincount(reason[:simulated], minlength=len(VALIDITY_REASONS))
    report = GenerationReport(
        simulated=simulated,
        kept=n_trials,
        rejected={VALIDITY_REASONS[k]: int(c) for k, c in enumerate(counts) if k > 0},
    )
    setup = {name: values[valid] for name, values in setup.items()}
    trials = _trial_set(states[valid], cut[valid], setup, seed, pairs, model, report, drivers)
    return trials, report


def _trial_set(states, lengths, setup, seed, pairs, model, report, drivers) -> TrialSet:
    n, t_max = len(lengths), int(lengths.max())
    states = states[:, :, :t_max].copy()
    past_end = np.arange(t_max)[None, None, :] >= lengths[:, None, None]
    states[np.broadcast_to(past_end, states.shape[:3])] = np.nan
    return TrialSet(
        states=states,
        lengths=lengths.astype(np.int64),
        trial_ids=np.arange(n, dtype=np.int32),
        **setup,
        sources=np.full(n, "synthetic" if drivers == "synthetic" else f"self-play {drivers}"),
        dt=DT,
        metadata={"generator": {"seed": seed, "pairs": pairs, "drivers": drivers,
                                "model": model.as_dict(), "report": report.as_dict()}},
    )
