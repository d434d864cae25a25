"""Human agents: who drives the human car in a simulation (:class:`~trafficweaving.sim.world.Agent`).

* :class:`SyntheticDrivers`: the simulated drivers of :mod:`~trafficweaving.sim.drivers`
  (intermittent control, sampled driving styles), batched over episodes, with given styles (the
  dataset generator); :class:`SampledDrivers` draws the styles and moods at reset (closed loop).
* :class:`ModelDriver`: a human model (the CVAE of paper §IV) as a driver: every 0.3 s it samples
  its next 3 accelerations, conditioned on its history and on the robot's future as it guesses
  it (:func:`constant_acceleration_future`) or as the simulation tells it (``robot_future``),
  every episode of a batch in one model call.
* :class:`ReplayDriver`: a recorded human (non-reactive), e.g. the authors' human-in-the-loop
  trials (``docs/real_humans.md``); :func:`replay_start` starts its episodes where its recordings
  start, so that it drives its recorded path (closed loop, the environment and the generator).
  A perturbed replay (``replay:FILE@T,V``) also shifts the other car's start in time and speed
  (:func:`replay_start`), so that the recorded human meets the robot in situations it did not
  meet the authors'.
* :class:`~trafficweaving.sim.scenarios.ScriptedHuman`: the edge-case library's scripted humans
  (``scenario:NAME``, :data:`~trafficweaving.sim.scenarios.SCENARIOS`).
* :class:`ConstantVelocityDriver`: keeps its velocity (no acceleration), the simplest baseline of
  sim-agent benchmarks; ``rules`` puts the rule-based robot
  (:class:`~trafficweaving.sim.robots.RuleBasedRobot`) in the human's seat.

:func:`human_agent` builds one from a spec string (:data:`HUMAN_SPECS`, :func:`parse_human_spec`).
"""

from __future__ import annotations

import copy
import math
import numbers
import os
import re
from dataclasses import dataclass
from typing import Sequence

import numpy as np
import torch

from .. import validate
from ..data.trials import INT32_MAX, TrialSet, _short, load_trials
from ..dynamics import constant_acceleration_future, future_states
from ..errors import InputError
from ..model.cvae import CVAE
from ..model.mixture import Mixture, facing
from ..model.registry import load_model
from ..model.spec import ModelSpec, parse_model_spec
from ..planning.steering import steer
from ..scenario import (CUTOFF_X, DT, HORIZON, MIN_HISTORY, SWAP_THRESHOLD_Y, across_divider, colliding, lane_centre_y,
                        lane_of, on_road)
from .drivers import DriverAgents, DriverModel, DriverStyles
from .robots import RuleBasedRobot
from .scenarios import SCENARIOS
from .world import Agent

MAX_SHIFT_S = 3.0
"""Largest time shift ``T`` of a perturbed replay (``replay:FILE@T,V``), s."""
MAX_SPEED_OFFSET_MPS = 5.0
"""Largest speed offset ``V`` of a perturbed replay, m/s."""

HUMAN_SPECS = ("synthetic, model:SPEC (SPEC: driver, default, a checkpoint path or authors:PATH), replay:FILE or "
               f"replay:FILE#K (perturbed: replay:FILE@T,V or replay:FILE#K@T,V, T in 0..{MAX_SHIFT_S:g} s, V in "
               f"0..{MAX_SPEED_OFFSET_MPS:g} m/s), scenario:NAME (NAME: {', '.join(SCENARIOS)}), rules, "
               "constant-velocity")
"""The forms :func:`human_agent` accepts, as messages print them."""


DRIVER_PROPOSALS = 8
"""Futures a driver model samples per decision to find a safe one (:class:`ModelDriver`)."""

DRIVER_ANTICIPATION = 8
"""Futures of the other car a driver model predicts per decision to judge its proposals by."""

DEADLINE_S = 2.0
"""A driver model's proposal is late when it leaves the car short of the divider less than this
many seconds before the cutoff (at its speed then): about how long the real drivers take from
starting a lane change to crossing the divider (1.9 s median, :func:`~trafficweaving.data.behaviour.lane_change_events`)."""

LATE_RISK = 0.5
"""A driver model's risk (in collisions) of a late proposal that leaves the car on its lane's centre
line; one that leaves it nearer the divider costs proportionally less, down to half at the divider
(:func:`lateness`)."""


def lateness(start_y: np.ndarray, end: np.ndarray) -> np.ndarray:
    """How late proposals are, in [0, 1] (0: on time), for cars that started at lateral positions
    ``start_y [m]`` (metres) and that the proposals leave at states ``end [..., m, 6]`` 1.5 s
    ahead. A proposal is late when it leaves the car short of the divider less than
    :data:`DEADLINE_S` before the cutoff at its speed then; it is then the later the farther it
    leaves the car from the divider: 1/2 at the divider, 1 on the centre line of the lane it
    started in, or farther. Under time pressure a driver picks the proposal that gets farthest across."""
    late = ~across_divider(start_y, end[..., 1]) & (CUTOFF_X - end[..., 0] < DEADLINE_S * end[..., 2])
    short = np.clip((SWAP_THRESHOLD_Y - end[..., 1]) / (SWAP_THRESHOLD_Y - lane_centre_y(start_y)), 0.0, 1.0)  # still to go
    return late * (0.5 + 0.5 * short)


def keep_on_road(present: np.ndarray, accelerations: np.ndarray) -> np.ndarray:
    """``accelerations [n, N, 2]`` (m/s², steps t+1..t+N) of cars at ``present [n, 6]`` with the
    lateral part replaced by the planner's optimal steering
    (:func:`~trafficweaving.planning.steering.steer`, paper §V-C) to the centre of the lane each car
    is in: how a driver about to leave the road steers back, keeping its pedal."""
    path = steer(present[:, [1, 3, 5]], lane_centre_y(present[:, 1]), DT * np.arange(1, accelerations.shape[1] + 1))
    kept = accelerations.copy()
    kept[..., 1] = path[..., 2]
    return kept


class SyntheticDrivers:
    """The simulated drivers as an agent: one driver per episode with its ``styles`` (``m`` drivers,
    :meth:`DriverStyles.take`) and optional ``mood [m]`` (standard normal; drawn at reset when
    None). A driver's target lane is the one its car does not start in."""

    def __init__(self, styles: DriverStyles, model: DriverModel | None = None, mood: np.ndarray | None = None):
        self.styles, self.model, self.mood = styles, model or DriverModel(), mood
        self.drivers: DriverAgents | None = None
        self.me = 0

    def reset(self, rng: np.random.Generator, start: np.ndarray, me: int) -> None:
        self.me = me
        self.drivers = DriverAgents(self.model, self.styles, start[:, me], lane_of(start[:, me, 1]), rng, mood=self.mood)

    def act(self, history: np.ndarray) -> np.ndarray:
        return self.drivers.act(history[:, self.me, -1], history[:, 1 - self.me, -1])


class SampledDrivers(SyntheticDrivers):
    """:class:`SyntheticDrivers` for closed loop: at each reset, one driver style per episode is
    drawn from ``rng`` (:meth:`DriverStyles.sample` of ``model``, ``m`` drivers) and then each
    episode's mood (standard normal), so a run is reproducible from the rng alone."""

    def __init__(self, model: DriverModel | None = None):
        super().__init__(styles=None, model=model)

    def reset(self, rng: np.random.Generator, start: np.ndarray, me: int) -> None:
        self.styles = DriverStyles.sample(self.model, len(start), rng)
        super().reset(rng, start, me)


class ModelDriver:
    """A human model as a driver, batched over ``m`` episodes.

    Every :attr:`BLOCK` steps (0.3 s) it samples one 15-step future of its accelerations per
    episode from ``model`` (:meth:`~trafficweaving.model.cvae.CVAE.sample_futures`, one batch for
    all episodes), conditioned on both cars' history and on the robot's future states, and then
    executes that sample's first 3 accelerations. The first sample is drawn once ``MIN_HISTORY``
    steps exist; before that it holds its present acceleration. It draws from one
    ``torch.Generator`` seeded at reset from the rng, so a run is reproducible from its seed.

    ``proposals`` > 1 samples that many futures per episode and executes the one with the least
    risk: the share of the robot's futures its 1.5 s of own positions (from its present state)
    collide with, leaving the road counting as more than any collision; among equally risky ones
    the first, or when all are unsafe the one whose first danger comes latest; when every one
    leaves the road, that one's pedal with the steering back to its lane's centre
    (:func:`keep_on_road`). The robot's futures: the one it is conditioned on and, with
    ``anticipation`` > 0, that many the model predicts for the robot (:meth:`others`: each car
    sampling the other's future from its own model); such a driver also knows the task: a proposal
    that leaves it short of the divider too near the cutoff (:data:`DEADLINE_S`) counts as up to
    half a collision, the less the nearer the divider it gets (:func:`lateness`). That is the
    model's distribution conditioned on a safe near future, as a driver who sees a collision coming
    picks another action. Defaults: :data:`DRIVER_PROPOSALS` and :data:`DRIVER_ANTICIPATION` for
    a driver model (one conditioned on the guess, ``CVAEConfig.robot_future == "guess"``), 1 and 0
    (plain samples) for the paper's models.

    ``other``: who the other car ("the robot" below) is, ``robot`` or ``person``; a mixture with
    weights for facing a person (the shipped ``driver``) drives with those against a person
    (:func:`~trafficweaving.model.mixture.facing`).

    The robot's future: by default the guess :func:`constant_acceleration_future` (the robot holds
    its present acceleration). With ``robot_plan=True`` the simulation tells it the robot's plan:
    before *every* :meth:`act` it sets :attr:`robot_future` to the robot's planned states
    ``[m, 15, 6]`` at steps t+1..t+15 (e.g. the planner's ``Plan.robot``); :meth:`act` consumes
    and clears it, and raises RuntimeError when it is needed and not set.
    """

    BLOCK = 3
    """Steps executed from each sample (0.3 s)."""

    def __init__(self, model: CVAE | Mixture, robot_plan: bool = False, proposals: int | None = None,
                 anticipation: int | None = None, other: str = "robot"):
        if robot_plan and model.config.robot_future == "guess":
            raise InputError("this model is conditioned on a guess of the robot's future, not on its plan "
                             "(expected a model conditioned on recorded futures for robot_plan)")
        try:
            model = facing(model, other)
        except ValueError as exc:
            raise InputError(str(exc)) from None
        self.model = model.eval()
        if proposals is None:
            proposals = DRIVER_PROPOSALS if model.config.robot_future == "guess" else 1
        if anticipation is None:
            anticipation = DRIVER_ANTICIPATION if model.config.robot_future == "guess" else 0
        self.proposals = validate.integer("proposals", proposals, 1)
        self.anticipation = validate.integer("anticipation", anticipation, 0)
        self.start_y = np.zeros(0)  # [m] each episode's lateral position at reset: the lane it leaves
        weights = next(model.parameters())
        self.device, self.dtype = weights.device, weights.dtype
        self.robot_plan = robot_plan
        self.robot_future: np.ndarray | None = None
        self.me = 1
        self.generator = torch.Generator(device=self.device)
        self.block = np.zeros((0, self.BLOCK, 2))  # accelerations [m, 3, 2] of the current block
        self.left = 0  # accelerations of the block still to execute

    def reset(self, rng: np.random.Generator, start: np.ndarray, me: int) -> None:
        self.me = me
        self.start_y = np.asarray(start)[:, me, 1].copy()
        self.generator.manual_seed(int(rng.integers(0, 2**63)))
        self.robot_future, self.left = None, 0

    def conditioning(self, history: np.ndarray,
                     robot_future: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """What the model is conditioned on for the world's ``history [m, 2, t+1, 6]``: the
        robot-first histories ``[m, t+1, 2, 6]`` and the robot's future states ``[m, 15, 6]``
        (``robot_future`` when given, else :func:`constant_acceleration_future`)."""
        ordered = history[:, [1 - self.me, self.me]].transpose(0, 2, 1, 3)
        if robot_future is None:
            return ordered, constant_acceleration_future(ordered[:, -1, 0])
        m = len(history)
        return ordered, validate.finite_array("robot_future", robot_future, (m, HORIZON, 6), f"[{m}, {HORIZON}, 6]")

    def act(self, history: np.ndarray) -> np.ndarray:
        robot_future, self.robot_future = self.robot_future, None
        if history.shape[2] < MIN_HISTORY:
            return history[:, self.me, -1, 4:6].copy()
        if self.left == 0:
            if self.robot_plan and robot_future is None:
                raise RuntimeError("ModelDriver(robot_plan=True) needs robot_future [m, 15, 6] set before every act")
            self.block = self.sample(*self.conditioning(history, robot_future if self.robot_plan else None))
            self.left = self.BLOCK
        self.left -= 1
        return self.block[:, self.BLOCK - 1 - self.left].copy()

    def sample(self, histories: np.ndarray, robot_futures: np.ndarray) -> np.ndarray:
        """The next block's accelerations ``[m, 3, 2]`` (m/s²), one model sample per episode, for
        robot-first ``histories [m, t+1, 2, 6]`` and ``robot_futures [m, 15, 6]`` (the world stops
        a car that they would brake to reversing, :class:`~trafficweaving.sim.world.World`)."""
        samples = self._futures(histories, robot_futures, self.proposals)  # [K, m, 15, 2]
        chosen = samples[0]
        if self.proposals > 1:
            own = future_states(histories[:, -1, 1], samples)  # [K, m, 15, 6]
            others = robot_futures[None]
            if self.anticipation:
                others = np.concatenate([others, self.others(histories)])  # [A+1, m, 15, 6]
            hits = colliding(own[:, None], others[None])  # [K, A+1, m, 15]
            off = ~on_road(own[..., 1])  # [K, m, 15]
            unsafe = hits.any(1) | off
            first = np.where(unsafe.any(-1), unsafe.argmax(-1), HORIZON)  # first unsafe step; 15: none
            risk = hits.any(-1).mean(1) + 2.0 * off.any(-1) + 1e-3 * (HORIZON - first) / HORIZON  # [K, m]
            if self.anticipation:
                risk = risk + LATE_RISK * lateness(self.start_y, own[:, :, -1])  # where each leaves the car in 1.5 s
            pick, rows = risk.argmin(0), np.arange(len(histories))
            chosen = samples[pick, rows]  # [m, 15, 2]
            leaves = off[pick, rows].any(-1)  # every proposal leaves the road
            if leaves.any():
                chosen[leaves] = keep_on_road(histories[leaves, -1, 1], chosen[leaves])
        return chosen[:, : self.BLOCK].copy()

    def _futures(self, histories: np.ndarray, robot_futures: np.ndarray, k: int) -> np.ndarray:
        """``k`` sampled futures ``[k, m, 15, 2]`` (m/s²) of the human's accelerations for robot-first
        ``histories [m, t+1, 2, 6]`` and ``robot_futures [m, 15, 6]``."""
        tensor = lambda a: torch.as_tensor(np.ascontiguousarray(a), dtype=self.dtype, device=self.device)  # noqa: E731
        batch = self.model.situations(tensor(histories), tensor(robot_futures))
        return self.model.actions_to_physical(self.model.sample_futures(batch, k, self.generator)).double().cpu().numpy()

    def others(self, histories: np.ndarray) -> np.ndarray:
        """The robot's futures as this driver's model predicts them, ``[A, m, 15, 6]``: the model
        with the seats swapped, conditioned on this driver holding its present acceleration."""
        swapped = histories[:, :, ::-1]
        samples = self._futures(swapped, constant_acceleration_future(swapped[:, -1, 0]), self.anticipation)
        return future_states(histories[:, -1, 0], samples)


class ReplayedCar:
    """Replays given accelerations ``accelerations [m, T, 2]`` (m/s², one row per episode): at
    step t+1 those of step t+1, past the end the last ones. Non-reactive."""

    def __init__(self, accelerations: np.ndarray):
        self.accelerations = accelerations

    def reset(self, rng: np.random.Generator, start: np.ndarray, me: int) -> None:
        pass

    def act(self, history: np.ndarray) -> np.ndarray:
        return self.accelerations[:, min(history.shape[2], self.accelerations.shape[1] - 1)].copy()


class ReplayDriver(ReplayedCar):
    """A recorded human, non-reactive: replays the accelerations ``[xdd, ydd]`` of the agent
    labelled ``human`` (the first one where both are) of a recorded trial, from its step 1 on;
    past the end of the recording it keeps its last recorded acceleration.

    ``trials``: the recordings (time step ``DT``); only trials with a human agent are kept, their
    ids in :attr:`trial_ids`. ``trial``: the trial id (the file's ``trial`` column) every episode
    replays; None: each episode's trial is drawn uniformly from :attr:`trial_ids` with the rng at
    reset (:attr:`played` tells which). The car follows its recorded path only from the
    recording's start: :func:`replay_start` starts episodes there and binds a copy of the driver
    to their trials (:meth:`bind`). ``perturbation``: ``(T, V)`` (s, m/s; :func:`check_perturbation`)
    makes it a perturbed replay: :func:`replay_start` shifts the other car's start by a time
    uniform in ``[-T, T]`` and a speed uniform in ``[-V, V]``; None: the recorded start.
    """

    def __init__(self, trials: TrialSet, trial: int | None = None, perturbation: tuple[float, float] | None = None):
        self.name = str(trials.source_path) if trials.source_path is not None else "the trial set"
        self.perturbation = None if perturbation is None else check_perturbation(*perturbation, name=self.name)
        trials.require_dt(DT, "the simulation")
        with_human = (trials.roles == "human").any(axis=1)
        if not with_human.any():
            raise InputError(f"{self.name}: no agent is labelled human (expected a dataset with an agent labelled human)")
        self.trials = trials.subset(np.flatnonzero(with_human))
        self.trial_ids = self.trials.trial_ids
        self.human = np.argmax(self.trials.roles == "human", axis=1)  # [n] the replayed agent of each trial
        self.trial = None if trial is None else int(self.trial_ids[self._rows(trial)])
        self.played = np.zeros(0, dtype=self.trial_ids.dtype)
        self.bound: tuple[np.ndarray, np.ndarray] | None = None  # (rows [m], agents [m]) set by bind
        super().__init__(np.zeros((0, 1, 2)))

    def _rows(self, trial) -> np.ndarray:
        """Positions in :attr:`trials` of trial ids ``trial`` (an id or an array of ids)."""
        trial = np.asarray(trial)
        match = self.trial_ids == trial[..., None]  # [..., n]
        found = match.any(axis=-1)
        if trial.dtype.kind not in "iu" or not found.all():
            bad = trial[~found].flat[0] if trial.dtype.kind in "iu" else trial
            raise InputError(f"{self.name}: no trial {bad} with an agent labelled human (expected one of the "
                             f"{len(self.trial_ids)} trial ids {self.trial_ids.min()}..{self.trial_ids.max()} with one)")
        return match.argmax(axis=-1)

    def seats(self, rows: np.ndarray, me: int) -> np.ndarray:
        """The recorded agent in each car of trials ``rows`` (positions in :attr:`trials`, any
        shape), ``[..., 2]``: the recorded human in car ``me``, the recording's other car in car
        ``1 - me``."""
        human = self.human[rows][..., None]
        return np.concatenate([1 - human, human] if me == 1 else [human, 1 - human], axis=-1)

    def start_states(self, trial, me: int = 1) -> np.ndarray:
        """The recorded start of both cars of trial id ``trial`` (an id, or ``[m]`` ids), ``[2, 6]``
        (``[m, 2, 6]``), with the recorded human as car ``me`` and the other car as car ``1 - me``
        (the default ``me = 1``: robot first)."""
        me = validate.integer("me", me, 0, 1)
        rows = self._rows(trial)
        return self.trials.states[rows[..., None], self.seats(rows, me), 0].copy()

    def bind(self, rows: np.ndarray, agents: np.ndarray) -> "ReplayDriver":
        """A copy of this driver whose next reset (of ``m`` episodes) replays, in episode ``i``,
        recorded agent ``agents[i]`` of trial ``rows[i]`` (positions in :attr:`trials`), ``[m]``
        each; this driver keeps its own choice."""
        bound = copy.copy(self)
        bound.bound = (np.asarray(rows), np.asarray(agents))
        return bound

    def reset(self, rng: np.random.Generator, start: np.ndarray, me: int) -> None:
        m = len(start)
        if self.bound is not None:
            rows, agents = self.bound
            if len(rows) != m:
                raise RuntimeError(f"this replay driver is bound to {len(rows)} episodes, reset with {m}")
        else:
            rows = (np.full(m, self._rows(self.trial)) if self.trial is not None
                    else rng.integers(len(self.trial_ids), size=m))
            agents = self.human[rows]
        self.played = self.trial_ids[rows]
        steps = np.minimum(np.arange(self.trials.states.shape[2]), self.trials.lengths[rows, None] - 1)  # [m, T]
        self.accelerations = self.trials.states[rows[:, None], agents[:, None], steps, 4:6]  # [m, T, 2]


@dataclass
class ReplayStart:
    """Episodes that start where their recordings start (:func:`replay_start`): both cars'
    recorded start states ``start [m, 2, 6]``, the agents by car ``cars`` (the replaying ones bound
    to these episodes), and which recordings: trial ``rows [m]`` of ``trials`` and the recorded
    agent in each car, ``agents [m, 2]``; for a perturbed replay the drawn time shifts ``shift_s
    [m]`` (s) and speed offsets ``speed_offset_mps [m]`` (m/s) of the car that does not replay
    (None otherwise)."""

    start: np.ndarray
    cars: list
    trials: TrialSet
    rows: np.ndarray
    agents: np.ndarray
    shift_s: np.ndarray | None = None
    speed_offset_mps: np.ndarray | None = None

    @property
    def trial_ids(self) -> np.ndarray:
        """The replayed trials' ids, ``[m]``."""
        return self.trials.trial_ids[self.rows]


def replay_start(cars: Sequence[Agent | None], episodes: np.ndarray | None = None,
                 rng: np.random.Generator | None = None) -> ReplayStart | None:
    """Where episodes driven by ``cars`` (an agent per car; None: one that no agent drives, such as
    a learner) start when a car is a :class:`ReplayDriver`; None when none is.

    Such episodes start from the recorded start of both cars of a recorded trial, so that each
    replayed car drives its own recorded path: the first replay driver's recorded human in its car,
    the recording's other car in the other car; a replay driver there too (self-play) replays that
    other car of the same recording. The trial: the driver's own ``trial`` when it has one; else
    episode ``episodes[i]`` (``[m]`` non-negative episode numbers) replays the recordings in turn,
    ``trial_ids[episodes[i] % n]``; with ``episodes`` None, one episode replays a trial drawn
    uniformly with ``rng``. A perturbed replay driver then draws its perturbation from ``rng``
    (:func:`perturbed_start`)."""
    seats = [k for k, car in enumerate(cars) if isinstance(car, ReplayDriver)]
    if not seats:
        return None
    me, driver = seats[0], cars[seats[0]]
    m = 1 if episodes is None else len(episodes)
    if driver.trial is not None:
        rows = np.full(m, driver._rows(driver.trial))
    elif episodes is not None:
        rows = np.asarray(episodes, dtype=np.int64) % len(driver.trial_ids)
    else:
        rows = rng.integers(len(driver.trial_ids), size=1)
    agents = driver.seats(rows, me)  # [m, 2]
    bound = [driver.bind(rows, agents[:, k]) if k in seats else car for k, car in enumerate(cars)]
    replay = ReplayStart(driver.start_states(driver.trial_ids[rows], me), bound, driver.trials, rows, agents)
    if driver.perturbation is not None:
        free = [k for k in range(len(cars)) if k not in seats]
        replay.start, replay.shift_s, replay.speed_offset_mps = perturbed_start(driver, replay, free, rng)
    return replay


def check_perturbation(shift_s, speed_offset_mps, name: str) -> tuple[float, float]:
    """A perturbed replay's bounds ``(T, V)`` as floats: a time shift ``T`` in
    0..:data:`MAX_SHIFT_S` s and a speed offset ``V`` in 0..:data:`MAX_SPEED_OFFSET_MPS` m/s;
    InputError naming ``name`` otherwise."""
    real = all(isinstance(v, numbers.Real) and not isinstance(v, (bool, np.bool_)) and math.isfinite(v)
               for v in (shift_s, speed_offset_mps))
    if not (real and 0 <= shift_s <= MAX_SHIFT_S and 0 <= speed_offset_mps <= MAX_SPEED_OFFSET_MPS):
        raise InputError(f"{name}: perturbation {_short(shift_s)},{_short(speed_offset_mps)} is out of range (expected "
                         f"T,V: a time shift T in 0..{MAX_SHIFT_S:g} s and a speed offset V in "
                         f"0..{MAX_SPEED_OFFSET_MPS:g} m/s)")
    return float(shift_s), float(speed_offset_mps)


def perturbed_start(driver: ReplayDriver, replay: ReplayStart, free: list[int],
                    rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(start [m, 2, 6], shift_s [m], speed_offset_mps [m])``: ``replay``'s start with the cars
    ``free`` (those that do not replay, e.g. the robot) shifted by a time uniform in ``[-T, T]``
    (its ``x`` moves by its recorded speed times that time) and a speed uniform in ``[-V, V]``,
    for ``driver``'s perturbation ``(T, V)``, drawn from ``rng`` in that order (a bound of 0 draws
    nothing: ``@0,0`` is the plain replay). InputError when every car replays (nothing to
    perturb) or the cars overlap at a perturbed start (recordings whose cars start in one lane)."""
    if not free:
        raise InputError(f"{driver.name}: a perturbed replay shifts the start of the car that does not replay, and "
                         f"every car here replays (expected replay:FILE or replay:FILE#K)")
    (shift, speed), m = driver.perturbation, len(replay.start)
    shift_s = rng.uniform(-shift, shift, m) if shift else np.zeros(m)
    speed_offset = rng.uniform(-speed, speed, m) if speed else np.zeros(m)
    start = replay.start.copy()
    start[:, free, 0] += start[:, free, 2] * shift_s[:, None]
    start[:, free, 2] += speed_offset[:, None]
    overlap = colliding(start[:, 0], start[:, 1])
    if overlap.any():
        raise InputError(f"{driver.name}: trial {replay.trial_ids[overlap][0]}: the cars overlap at the perturbed "
                         f"start (expected recordings whose cars start in different lanes)")
    return start, shift_s, speed_offset


class ConstantVelocityDriver:
    """Keeps its present velocity: zero acceleration in both directions, every step."""

    def reset(self, rng: np.random.Generator, start: np.ndarray, me: int) -> None:
        pass

    def act(self, history: np.ndarray) -> np.ndarray:
        return np.zeros((len(history), 2))


REPLAY_FORMS = "replay:FILE, replay:FILE#K, replay:FILE@T,V or replay:FILE#K@T,V"
"""The forms of a replay spec, as messages print them."""

_DECIMAL = "([0-9]+(?:[.][0-9]*)?|[.][0-9]+)"


def _replay_target(target: str) -> tuple[str, int | None, tuple[float, float] | None]:
    """``FILE``, ``FILE#K``, ``FILE@T,V`` or ``FILE#K@T,V`` as ``(FILE, K or None, (T, V) or
    None)``: ``K`` a trial id in ASCII digits (0..2³¹−1), ``T`` and ``V`` decimal numbers
    (:func:`check_perturbation`); a ``target`` (or the part before ``@``) that names an existing
    path is a ``FILE``, ``#`` and ``@`` or not. InputError for a missing file whose ``K`` or
    ``T,V`` is not such."""
    spec = f"replay:{target}"
    perturbation = None
    head, sep, tail = target.rpartition("@")
    if sep and head and not os.path.exists(target):
        match = re.fullmatch(f"{_DECIMAL},{_DECIMAL}", tail)
        if match is None:
            raise InputError(f"human '{spec}': no such file, and {tail!r} after its last '@' is not T,V (expected "
                             f"{REPLAY_FORMS}, T and V decimal numbers)")
        perturbation = check_perturbation(float(match[1]), float(match[2]), f"human '{spec}'")
        target = head
    path, sep, trial = target.rpartition("#")
    if not sep or not path or os.path.exists(target):
        return target, None, perturbation
    if re.fullmatch("[0-9]{1,10}", trial) is None or int(trial) > INT32_MAX:
        raise InputError(f"human '{spec}': no such file, and {trial!r} after its last '#' is not a trial id "
                         f"(expected {REPLAY_FORMS}, K a trial id in 0..{INT32_MAX} in ASCII digits)")
    return path, int(trial), perturbation


@dataclass(frozen=True)
class HumanSpec:
    """A parsed human spec (:data:`HUMAN_SPECS`): its ``kind`` (``synthetic``, ``rules``,
    ``constant-velocity``, ``model``, ``replay`` or ``scenario``); for ``model:SPEC`` the
    ``model`` it names; for ``replay:FILE[#K][@T,V]`` the dataset ``path``, ``trial`` id ``K``
    (None: drawn per episode) and ``perturbation`` ``(T, V)`` (s, m/s; None: the recorded start);
    for ``scenario:NAME`` the ``scenario``'s name."""

    kind: str
    model: ModelSpec | None = None
    path: str | None = None
    trial: int | None = None
    perturbation: tuple[float, float] | None = None
    scenario: str | None = None


def parse_human_spec(spec: str) -> HumanSpec:
    """``spec`` as a :class:`HumanSpec`, nothing loaded (the ``SPEC`` of ``model:SPEC`` by
    :func:`~trafficweaving.model.spec.parse_model_spec`); InputError for what is not a human spec."""
    if not isinstance(spec, str):
        raise InputError(f"human {_short(spec)} is not a spec (expected one of: {HUMAN_SPECS})")
    kind, _, target = spec.partition(":")
    if spec in ("synthetic", "rules", "constant-velocity"):
        return HumanSpec(spec)
    if kind == "model" and target:
        return HumanSpec(kind, model=parse_model_spec(target))
    if kind == "replay" and target:
        path, trial, perturbation = _replay_target(target)
        return HumanSpec(kind, path=path, trial=trial, perturbation=perturbation)
    if kind == "scenario":
        if target not in SCENARIOS:
            raise InputError(f"human {spec!r}: no such scenario (expected scenario:NAME, NAME one of: "
                             f"{', '.join(SCENARIOS)})")
        return HumanSpec(kind, scenario=target)
    raise InputError(f"human {spec!r} is unknown (expected one of: {HUMAN_SPECS})")


def human_agent(spec: str, device: torch.device | str = "cpu", robot_plan: bool = False, other: str = "robot") -> Agent:
    """The human agent of ``spec`` (:func:`parse_human_spec`): ``synthetic`` (:class:`SampledDrivers`),
    ``model:SPEC`` (:class:`ModelDriver` of :func:`~trafficweaving.model.registry.load_model`'s
    ``SPEC``, on ``device``; ``robot_plan`` and ``other``, who the other car is, as there),
    ``replay:FILE[#K][@T,V]`` (:class:`ReplayDriver` of the Parquet dataset ``FILE``, trial id
    ``K`` or drawn per episode, perturbed by ``T,V``) or ``scenario:NAME`` (the scenario's
    :class:`~trafficweaving.sim.scenarios.ScriptedHuman`). InputError for an unknown spec, a
    missing or invalid file, or ``robot_plan`` with a human that is not a model."""
    human = parse_human_spec(spec)
    if robot_plan and human.kind != "model":
        raise InputError(f"robot_plan applies only to model:SPEC humans, got human {spec!r}")
    if human.kind == "synthetic":
        return SampledDrivers()
    if human.kind == "rules":
        return RuleBasedRobot()
    if human.kind == "constant-velocity":
        return ConstantVelocityDriver()
    if human.kind == "model":
        return ModelDriver(load_model(human.model, device), robot_plan=robot_plan, other=other)
    if human.kind == "scenario":
        return SCENARIOS[human.scenario].agent()
    return ReplayDriver(load_trials(human.path), human.trial, human.perturbation)
