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
file's ``index % n``-th trial with a human agent.

The result is the record in the dataset format (one trial; roles ``robot`` and ``human``; source
``episode-000042``) whose metadata key ``episode`` holds the episode's JSON record: ``index``,
``spec``, ``initial_condition``, ``robot_car``, ``metrics`` (:mod:`.metrics`; reproducible),
``latency`` and ``latencies_s`` (planner seconds per plan) and ``seconds`` (wall time).
"""

from __future__ import annotations

import copy
import time
from dataclasses import asdict, dataclass

import numpy as np

from ..data.trials import TrialSet
from ..planning.planner import Budget
from ..scenario import DT, lane_of, study_initial_conditions
from .humans import ReplayDriver, human_agent
from .metrics import episode_metrics, latency_summary
from .robots import robot_agent
from .world import Agent, run_episodes


@dataclass(frozen=True)
class EpisodeSpec:
    """What the episodes of a run share: the robot and human specs (``sim.robots.robot_agent``,
    ``sim.humans.human_agent``), the run's ``seed`` (0..2³²−1), the planner's human ``model``, its
    wall-clock ``deadline`` (s) or sample ``budget``, the torch ``device`` and the planner's
    sampling ``precision``."""

    robot: str
    human: str
    seed: int
    model: str = "default"
    deadline: float | None = None
    budget: Budget | None = None
    device: str = "cpu"
    precision: str = "auto"

    def agents(self) -> tuple[Agent, Agent]:
        """A new ``(robot, human)`` pair of agents; :class:`~trafficweaving.errors.InputError` for an
        unknown spec or a model that does not load."""
        return (robot_agent(self.robot, self.model, self.deadline, self.budget, self.device, self.precision),
                human_agent(self.human, self.device))

    def as_dict(self) -> dict:
        """JSON form, stored with every episode (the budget as its three sample counts)."""
        return {**asdict(self), "budget": None if self.budget is None else list(asdict(self.budget).values())}

    @staticmethod
    def from_dict(fields: dict) -> "EpisodeSpec":
        """The inverse of :meth:`as_dict` (an episode log's ``spec``)."""
        budget = fields.get("budget")
        return EpisodeSpec(**{**fields, "budget": None if budget is None else Budget(*budget)})


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


def _start(rng: np.random.Generator, human: Agent, index: int) -> tuple[np.ndarray, int, dict, Agent]:
    """``(start [2, 6], robot car, initial condition, human)`` of episode ``index``: a study start
    with a random robot car; or, for a replayed human, the recording's start with the robot in the
    recording's other car (car 0) and the human replaying that trial (its fixed trial, else the
    recorded trials in turn: episode ``index`` replays ``trial_ids[index % n]``)."""
    if isinstance(human, ReplayDriver):
        trial = human.trial if human.trial is not None else int(human.trial_ids[index % len(human.trial_ids)])
        human = copy.copy(human)  # the shared agent keeps its own trial choice
        human.trial = trial
        start = human.start_states(trial, me=1)
        row = int(np.flatnonzero(human.trial_ids == trial)[0])
        dv, tco = float(human.trials.ic_dv[row]), float(human.trials.ic_tco[row])
        ic = {"index": None, "trial": trial, "dv": None if np.isnan(dv) else dv, "tco": None if np.isnan(tco) else tco,
              "robot_lane": str(lane_of(start[0, 1]))}
        return start, 0, ic, human
    ics = study_initial_conditions()
    k = int(rng.integers(len(ics)))
    robot_car = int(rng.integers(2))
    ic = ics[k]
    ic_record = {"index": k, "dv": ic.dv_left_minus_right + 0.0, "tco": ic.tco,  # + 0.0: no -0.0
                 "robot_lane": (ic.lane_a, ic.lane_b)[robot_car]}
    return ic.start_states(), robot_car, ic_record, human


def run_episode(spec: EpisodeSpec, index: int, agents: tuple[Agent, Agent] | None = None) -> Episode:
    """Run episode ``index`` (≥ 0) of ``spec`` with ``agents = (robot, human)`` (new ones from
    ``spec.agents()`` when None; agents are reset for every episode, so one pair serves many)."""
    robot, human = agents if agents is not None else spec.agents()
    began = time.perf_counter()
    rng = np.random.default_rng([spec.seed, index])
    start, robot_car, ic, human = _start(rng, human, index)
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
    does not reproduce the log (a ``deadline`` run: the plans depend on the machine's speed)."""
    record = trials.metadata.get("episode")
    if not isinstance(record, dict) or len(trials) != 1:
        return None
    spec = EpisodeSpec.from_dict(record["spec"])
    robot, human = spec.agents()
    episode = run_episode(spec, int(record["index"]), (robot, human))
    length = int(trials.lengths[0])
    same = int(episode.trials.lengths[0]) == length and np.array_equal(
        episode.trials.states[0, :, :length], trials.states[0, :, :length])
    if not same or not getattr(robot, "plans", None):
        return None
    return [(t, plan.robot, plan.human[:max_futures]) for t, plan in zip(robot.plan_steps, robot.plans)]
