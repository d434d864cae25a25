"""One browser trial, without the browser: the simulated world, both cars' agents and the end rule.

A trial starts from one of the study's 18 initial conditions
(:func:`~trafficweaving.scenario.study_initial_conditions`) and steps the
:class:`~trafficweaving.sim.world.World` at 0.1 s with two agents: in ``robot`` mode the
planner (:class:`~trafficweaving.planning.mpc.NonBlockingMPCPolicy`) and a person
(:class:`~.person.PersonAgent`), in ``human-human`` mode two people. It ends (:data:`END_REASONS`)
when both cars are past ``RECORD_END_X`` (``finished``, as a simulated episode ends), at the
world's last step (``time_limit``), at the first step where the cars collide (``collision``) or
one leaves the road (``off_road``), or when the session stops it (``aborted``: the person asked;
``disconnected``: the page went away; ``server_error``).

:meth:`Trial.trial_set` is its record in the dataset format, like a simulated episode's
(:func:`~trafficweaving.sim.episodes.run_episode`): one trial, roles ``robot``/``human``
(``human``/``human`` in human–human mode), source ``drive-000042``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..data.trials import TrialSet
from ..scenario import DT, MIN_TRIAL_STEPS, colliding, lane_of, on_road, study_initial_conditions
from ..sim.metrics import episode_metrics
from ..sim.world import Agent, World

END_REASONS = ("finished", "time_limit", "collision", "off_road", "aborted", "disconnected", "server_error")
"""Why a trial ended (module docstring)."""
COMPLETED = END_REASONS[:4]
"""The reasons of a completed trial, ended by the scenario's rules; the others are aborted trials
(stopped by a person, a page gone away, a server error)."""


@dataclass(frozen=True)
class TrialSetup:
    """What a trial starts from: ``mode``, the kind of room (:data:`~.options.ROOM_KINDS`), the
    initial condition's index ``ic`` (0..17 in :func:`study_initial_conditions`), the robot's car
    ``robot_car`` (0 = car A or 1 = car B; None in human–human mode), the drivers' ids ``drivers``
    per car (-1: the robot or unknown) and the ``seed`` of the trial's random draws."""

    mode: str
    ic: int
    robot_car: int | None
    drivers: tuple[int, int]
    seed: int

    @property
    def roles(self) -> tuple[str, str]:
        """Each car's role label in the record."""
        return tuple("robot" if car == self.robot_car else "human" for car in (0, 1))

    def initial_condition_record(self) -> dict:
        """The initial condition as stored and shown: ``index``, ``dv`` (``Δv = v_left − v_right``,
        m/s), ``tco`` (s), ``lanes`` (car A's and car B's start lanes)."""
        ic = study_initial_conditions()[self.ic]
        return {"index": self.ic, "dv": ic.dv_left_minus_right + 0.0, "tco": ic.tco,  # + 0.0: no -0.0
                "lanes": [ic.lane_a, ic.lane_b]}


class Trial:
    """A trial in progress: :attr:`world` (one episode) driven by ``agents`` (car A's, car B's),
    advanced by :meth:`step` until :attr:`end_reason` is set."""

    def __init__(self, number: int, setup: TrialSetup, agents: tuple[Agent, Agent]):
        self.number, self.setup, self.agents = number, setup, agents
        self.start = study_initial_conditions()[setup.ic].start_states()  # [2, 6]
        self.world = World(self.start[None])
        rng = np.random.default_rng(setup.seed)
        for me, agent in enumerate(agents):
            agent.reset(rng, self.world.states[:, :, 0], me)
        self.end_reason: str | None = None

    @property
    def step_index(self) -> int:
        """The present step t."""
        return self.world.t

    @property
    def states(self) -> np.ndarray:
        """Both cars' states at steps 0..t, ``[2, t+1, 6]`` (a view)."""
        return self.world.history[0]

    def step(self) -> None:
        """Advance one step (0.1 s) and apply the end rule."""
        if self.end_reason is not None:
            raise RuntimeError(f"trial {self.number} has ended ({self.end_reason})")
        history = self.world.history
        self.world.step(np.stack([agent.act(history) for agent in self.agents], axis=1))
        now = self.world.states[0, :, self.world.t]  # [2, 6]
        if colliding(now[0], now[1]):
            self.end_reason = "collision"
        elif not on_road(now[:, 1]).all():
            self.end_reason = "off_road"
        elif not self.world.running[0]:
            self.end_reason = "finished"
        elif self.world.done:
            self.end_reason = "time_limit"

    def stop(self, reason: str) -> None:
        """End the trial now for ``reason`` (one of :data:`END_REASONS`), unless it has ended."""
        if reason not in END_REASONS:
            raise ValueError(f"unknown end reason {reason!r} (expected one of {', '.join(END_REASONS)})")
        self.end_reason = self.end_reason or reason

    @property
    def recordable(self) -> bool:
        """Whether the record is long enough for the dataset format (``MIN_TRIAL_STEPS``)."""
        return self.world.t + 1 >= MIN_TRIAL_STEPS

    def metrics(self) -> dict:
        """What happened (:func:`~trafficweaving.sim.metrics.episode_metrics`, JSON-ready). In
        robot mode, the episode metrics of the robot's car. In human–human mode, from car A's view:
        ``outcome``, ``collision``, ``near_collision``, ``min_gap_m``, ``min_distance_m``, plus
        ``swapped`` (per car) and ``first`` (the car ahead when the first reached the cutoff)."""
        states, length = self.states, self.world.t + 1
        if self.setup.robot_car is not None:
            return episode_metrics(states, length, self.setup.robot_car)
        seen_from_a = episode_metrics(states, length, 0)
        shared = ("outcome", "collision", "near_collision", "min_gap_m", "min_distance_m")
        return {**{key: seen_from_a[key] for key in shared},
                "swapped": [seen_from_a["robot_swapped"], seen_from_a["human_swapped"]],
                "first": "A" if seen_from_a["robot_first"] else "B"}

    def trial_set(self, metadata: dict) -> TrialSet:
        """The record in the dataset format with ``metadata`` (the file's provenance, under its
        own keys); the trial id is :attr:`number`."""
        length = self.world.t + 1
        setup = self.setup
        ic = setup.initial_condition_record()
        return TrialSet(
            states=self.states[None].copy(),
            lengths=np.array([length], dtype=np.int64),
            trial_ids=np.array([self.number], dtype=np.int32),
            roles=np.array([setup.roles]),
            start_lanes=lane_of(self.start[None, :, 1]),
            drivers=np.array([setup.drivers], dtype=np.int32),
            ic_dv=np.array([ic["dv"]]),
            ic_tco=np.array([np.nan if ic["dv"] == 0 else ic["tco"]]),
            sources=np.array([source_name(self.number)]),
            dt=DT,
            metadata=metadata,
        )


def source_name(number: int) -> str:
    """The ``source`` of browser trial ``number`` in its record: ``drive-000042``."""
    return f"drive-{number:06d}"
