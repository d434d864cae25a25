"""One closed-loop episode: a robot and a human on the weaving road, from its (seed, index) alone.

Episode ``index`` of a run with ``seed`` draws everything from its own generator
``np.random.default_rng([seed, index])``: first the initial condition (one of the 18 study starts of
:func:`~trafficweaving.scenario.study_initial_conditions`, uniformly; paper §V-A), then which car
the robot drives (car A or B, uniformly), then whatever the agents draw at reset and while driving
(:func:`~trafficweaving.sim.world.run_episodes`). So an episode is the same whichever process runs
it (with the same number of torch threads) and whatever ran before — except where the robot plans
against a wall-clock deadline (the number of human futures it samples depends on the machine).

A replayed human (``replay:FILE[#K]``) drives the recording's human car from the recording's
start: such an episode starts from the recorded states instead (the robot takes the other car),
its initial condition is the recording's, and without ``#K`` episode ``index`` replays the
file's ``index % n``-th trial with a human agent. A perturbed replay (``replay:FILE@T,V``) first
draws the robot's shift in time and speed (:func:`~trafficweaving.sim.humans.perturbed_start`).
A scripted human (``scenario:NAME``) first draws its scenario's start, the robot in car 0
(:meth:`~trafficweaving.sim.scenarios.Scenario.draw`).

The result is the record in the dataset format (one trial; roles ``robot`` and ``human``; source
``episode-000042``) whose metadata key ``episode`` holds the episode's JSON record: ``index``,
``spec``, ``initial_condition``, ``robot_car``, ``metrics`` (:mod:`.metrics`; reproducible),
``latency`` and ``latencies_s`` (planner seconds per plan), ``safety_overrides`` (every window the
planner's safety layer changed: ``step``, ``proposed`` and ``chosen`` action, whether ``any_safe``;
:mod:`~trafficweaving.planning.safety`) and ``seconds`` (wall time).
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, fields

import numpy as np

from .. import validate
from ..data.trials import TrialSet, _short
from ..errors import InputError
from ..model.predictor import MAX_PLAN_FUTURES
from ..planning.planner import Budget, plan_options
from ..scenario import DT, lane_of, study_initial_conditions
from .humans import human_agent, replay_start
from .metrics import episode_metrics, latency_summary
from .robots import robot_agent
from .scenarios import ScriptedHuman
from .world import Agent, run_episodes


@dataclass(frozen=True)
class EpisodeSpec:
    """What the episodes of a run share: the robot and human specs (``sim.robots.robot_agent``,
    ``sim.humans.human_agent``), the run's ``seed`` (0..2³²−1), the planner's human ``model``, its
    wall-clock ``deadline`` (s) or sample ``budget``, the torch ``device`` and the planner's
    sampling ``precision``. Checked on construction (:meth:`__post_init__`)."""

    robot: str
    human: str
    seed: int
    model: str = "default"
    deadline: float | None = None
    budget: Budget | None = None
    device: str = "cpu"
    precision: str = "auto"

    def __post_init__(self):
        """InputError naming the field unless the specs, ``model``, ``device`` and ``precision``
        are strings, ``seed`` is an integer in 0..2³²−1, ``deadline`` None or seconds > 0 and
        ``budget`` None or a :class:`Budget` of at most :data:`~trafficweaving.model.predictor.MAX_PLAN_FUTURES`
        futures a plan (whether the strings name agents, a model, a device and a precision is
        checked by :meth:`agents`)."""
        for name in ("robot", "human", "model", "device", "precision"):
            if not isinstance(getattr(self, name), str):
                raise InputError(f"{name} must be a string, got {_short(getattr(self, name))}")
        object.__setattr__(self, "seed", validate.integer("seed", self.seed, 0, 2**32 - 1))  # NumPy's as int
        plan_options(self.budget, self.deadline)
        if self.budget is not None and self.budget.futures > MAX_PLAN_FUTURES:
            raise InputError(f"budget {self.as_dict()['budget']} samples {self.budget.futures} human futures a plan "
                             f"(expected at most {MAX_PLAN_FUTURES})")

    def agents(self) -> tuple[Agent, Agent]:
        """A new ``(robot, human)`` pair of agents; :class:`~trafficweaving.errors.InputError` for an
        unknown spec or a model that does not load."""
        return (robot_agent(self.robot, self.model, self.deadline, self.budget, self.device, self.precision),
                human_agent(self.human, self.device))

    def as_dict(self) -> dict:
        """JSON form, stored with every episode (the budget as its three sample counts)."""
        return {**asdict(self), "budget": None if self.budget is None else list(asdict(self.budget).values())}

    @staticmethod
    def from_dict(stored, name: str = "episode log") -> "EpisodeSpec":
        """The inverse of :meth:`as_dict`: the ``spec`` of an episode log, checked as the
        constructor checks its arguments (a field the log predates takes its default). InputError
        naming ``name`` (the log's file) for anything else: no spec, not an object, a field this
        release does not know, a missing robot, human or seed, a value out of range."""
        known = [f.name for f in fields(EpisodeSpec)]
        expected = f"expected simulate's episode spec: a JSON object of {', '.join(known)}"
        if stored is None:
            raise InputError(f"{name}: the episode record has no spec ({expected})")
        if not isinstance(stored, dict):
            raise InputError(f"{name}: the episode spec {_short(stored)} is not an object ({expected})")
        unknown = sorted(set(stored) - set(known))
        if unknown:
            raise InputError(f"{name}: the episode spec has an unknown field {_short(unknown[0])} ({expected})")
        missing = [key for key in ("robot", "human", "seed") if key not in stored]
        if missing:
            raise InputError(f"{name}: the episode spec has no {missing[0]} ({expected})")
        budget = stored.get("budget")
        try:
            if budget is not None and not (isinstance(budget, list) and len(budget) == 3):
                raise InputError(f"budget must be null or [first_stage_samples, finalists, second_stage_samples], "
                                 f"got {_short(budget)}")
            return EpisodeSpec(**{**stored, "budget": None if budget is None else Budget(*budget)})
        except InputError as exc:
            raise InputError(f"{name}: episode spec: {exc}") from None


@dataclass
class Episode:
    """One finished episode: ``trials`` holds the record (one trial, ``states [1, 2, T, 6]``) with
    its JSON record in ``trials.metadata["episode"]`` (:attr:`record`)."""

    index: int
    trials: TrialSet

    @property
    def record(self) -> dict:
        return self.trials.metadata["episode"]


def source_name(index: int) -> str:
    """The ``source`` of episode ``index`` in its record: ``episode-000042``."""
    return f"episode-{index:06d}"


def _start(rng: np.random.Generator, robot: Agent, human: Agent,
           index: int) -> tuple[np.ndarray, int, dict, Agent, Agent]:
    """``(start [2, 6], robot car, initial condition, robot, human)`` of episode ``index``: a study
    start with a random robot car; or, for a replayed human, the recording's start with the robot
    in the recording's other car (car 0) and the human replaying that trial
    (:func:`~trafficweaving.sim.humans.replay_start`: its fixed trial, else the recorded trials in
    turn, episode ``index`` replaying ``trial_ids[index % n]``; a perturbed replay's shift is
    recorded as ``shift_s`` and ``speed_offset_mps``); or, for a scripted human, its scenario's
    start with the robot in car 0 (no study condition: ``dv`` and ``tco`` None; the record names
    the ``scenario``, whether a collision is ``avoidable`` and the ``acceptable`` outcome)."""
    replay = replay_start([robot, human], episodes=np.array([index]), rng=rng)
    if replay is not None:
        start, row = replay.start[0], int(replay.rows[0])
        dv, tco = float(replay.trials.ic_dv[row]), float(replay.trials.ic_tco[row])
        ic = {"index": None, "trial": int(replay.trial_ids[0]), "dv": None if np.isnan(dv) else dv,
              "tco": None if np.isnan(tco) else tco, "robot_lane": str(lane_of(start[0, 1]))}
        if replay.shift_s is not None:
            ic.update(shift_s=float(replay.shift_s[0]), speed_offset_mps=float(replay.speed_offset_mps[0]))
        return start, 0, ic, *replay.cars
    if isinstance(human, ScriptedHuman):
        start, human = human.start(rng)
        scenario = human.scenario
        ic = {"index": None, "dv": None, "tco": None, "robot_lane": str(lane_of(start[0, 1])),
              "scenario": scenario.name, "avoidable": scenario.avoidable, "acceptable": scenario.acceptable}
        return start, 0, ic, robot, human
    ics = study_initial_conditions()
    k = int(rng.integers(len(ics)))
    robot_car = int(rng.integers(2))
    ic = ics[k]
    ic_record = {"index": k, "dv": ic.dv_left_minus_right + 0.0, "tco": ic.tco,  # + 0.0: no -0.0
                 "robot_lane": (ic.lane_a, ic.lane_b)[robot_car]}
    return ic.start_states(), robot_car, ic_record, robot, human


def run_episode(spec: EpisodeSpec, index: int, agents: tuple[Agent, Agent] | None = None) -> Episode:
    """Run episode ``index`` (≥ 0) of ``spec`` with ``agents = (robot, human)`` (new ones from
    ``spec.agents()`` when None; agents are reset for every episode, so one pair serves many)."""
    robot, human = agents if agents is not None else spec.agents()
    began = time.perf_counter()
    rng = np.random.default_rng([spec.seed, index])
    start, robot_car, ic, robot, human = _start(rng, robot, human, index)
    cars = [human, human]
    cars[robot_car] = robot
    states, lengths = run_episodes(start[None], cars, rng).recorded()
    latencies = [float(s) for s in getattr(robot, "latencies", [])]
    roles = np.array(["human", "human"])
    roles[robot_car] = "robot"
    record = {
        "index": index,
        "spec": spec.as_dict(),
        "initial_condition": ic,
        "robot_car": robot_car,
        "metrics": episode_metrics(states[0], int(lengths[0]), robot_car),
        "latency": latency_summary(latencies),
        "latencies_s": latencies,
        "safety_overrides": [{"step": int(step), "proposed": decision.proposed, "chosen": decision.chosen,
                              "any_safe": decision.any_safe} for step, decision in getattr(robot, "safety_log", [])],
        "seconds": time.perf_counter() - began,
    }
    trials = TrialSet(
        states=states,
        lengths=lengths.astype(np.int64),
        trial_ids=np.array([index], dtype=np.int32),
        roles=roles[None],
        start_lanes=lane_of(start[None, :, 1]),
        drivers=np.full((1, 2), -1, dtype=np.int32),
        ic_dv=np.array([np.nan if ic["dv"] is None else ic["dv"]]),
        ic_tco=np.array([np.nan if ic["tco"] is None or ic["dv"] == 0 else ic["tco"]]),
        sources=np.array([source_name(index)]),
        dt=DT,
        metadata={"episode": record},
    )
    return Episode(index, trials)


def rerun_with_plans(trials: TrialSet, max_futures: int = 32) -> list[tuple[int, np.ndarray, np.ndarray]] | None:
    """The robot's plans in the one-episode log ``trials`` (written by :func:`run_episode`), found
    by running the episode again from its record: ``(t, robot_future [15, 6], human_futures [n, 15,
    6])`` for every plan, by the step ``t`` it was made at, at most ``max_futures`` sampled human
    futures each. None when the log holds no episode record, its robot does not plan, or the run
    does not reproduce the log (a ``deadline`` run: the plans depend on the machine's speed).
    InputError naming the file when the record's spec (:meth:`EpisodeSpec.from_dict`) or index is
    malformed, or its agents cannot be built here."""
    record = trials.metadata.get("episode")
    if not isinstance(record, dict) or len(trials) != 1:
        return None
    name = str(trials.source_path or "the episode log")
    spec = EpisodeSpec.from_dict(record.get("spec"), name)
    index = record.get("index")
    if isinstance(index, bool) or not isinstance(index, int) or index < 0:
        raise InputError(f"{name}: episode index {_short(index)} in the record (expected a non-negative integer)")
    try:
        robot, human = spec.agents()
        episode = run_episode(spec, index, (robot, human))
    except InputError as exc:
        raise InputError(f"{name}: the episode spec's agents: {exc}") from None
    length = int(trials.lengths[0])
    same = int(episode.trials.lengths[0]) == length and np.array_equal(
        episode.trials.states[0, :, :length], trials.states[0, :, :length])
    if not same or not getattr(robot, "plans", None):
        return None
    return [(t, plan.robot, plan.human[:max_futures]) for t, plan in zip(robot.plan_steps, robot.plans)]
