"""The world: two cars on the weaving road, stepped at 0.1 s, for a batch of ``m`` episodes at once.

Both cars move by the trapezoid rule (:func:`~trafficweaving.dynamics.trapezoid_step`): each step
every agent names its acceleration ``[xdd, ydd]`` for the next step, and velocity and position
follow from the present and the next acceleration, as the authors' recordings of human cars do.
Braking stops a car; it never rolls backwards (:func:`~trafficweaving.dynamics.without_reversing`
raises a braking that would reverse it just enough to stop it).
An episode is recorded until both cars are past ``RECORD_END_X`` (as the authors' recordings
end) or ``max_steps`` is reached; the scenario's rules (collision, off-road, lane swap before the
cutoff) are judged on the record by :func:`~trafficweaving.scenario.check_validity`.

The agent contract (:class:`Agent`), after Gymnasium's reset/step split:

* ``reset(rng, start, me)`` once per batch, with the episodes' start states ``start [m, 2, 6]``
  and the agent's car index ``me`` (0 or 1);
* ``act(history) -> [m, 2]`` once per step, with both cars' states so far ``history [m, 2, t+1,
  6]`` (finished episodes included; their actions are ignored): the car's accelerations
  ``[xdd, ydd]`` (m/s²) at step ``t+1``.

Agents are batched over episodes where that pays (the simulated drivers); an agent that is not
(the planner) acts for ``m = 1``.
"""

from __future__ import annotations

from typing import Protocol, Sequence

import numpy as np
from tqdm import tqdm

from ..dynamics import trapezoid_step, without_reversing
from ..scenario import RECORD_END_X, STATE_NAMES

MAX_STEPS = 110
"""Longest episode (11 s): long enough for every car of the study to pass ``RECORD_END_X``."""


class Agent(Protocol):
    """Drives one car of a batch of episodes (see the module docstring)."""

    def reset(self, rng: np.random.Generator, start: np.ndarray, me: int) -> None: ...

    def act(self, history: np.ndarray) -> np.ndarray: ...


class World:
    """Both cars' states of ``m`` episodes, ``states [m, 2, max_steps, 6]`` (``STATE_NAMES``),
    advanced by :meth:`step`. Every episode advances until all have ended (the agents of a batch see
    every car move, so an episode's random draws do not depend on when others end); steps past an
    episode's ``lengths`` are not part of its record."""

    def __init__(self, start: np.ndarray, max_steps: int = MAX_STEPS):
        start = np.asarray(start, dtype=float)
        if start.ndim != 3 or start.shape[1:] != (2, len(STATE_NAMES)) or not np.isfinite(start).all():
            raise ValueError(f"start has shape {list(start.shape)} (expected finite [m, 2, {len(STATE_NAMES)}])")
        m = len(start)
        self.states = np.full((m, 2, max_steps, len(STATE_NAMES)), np.nan)
        self.states[:, :, 0] = start
        self.t = 0  # the present step
        self.lengths = np.full(m, max_steps)  # recorded steps of each episode (max_steps while running)
        self.running = np.ones(m, dtype=bool)
        self.max_steps = max_steps

    @classmethod
    def from_history(cls, history: np.ndarray, max_steps: int = MAX_STEPS) -> "World":
        """A world whose first ``k`` steps are given, ``history [m, 2, k, 6]`` (e.g. recorded), with
        step ``k - 1`` as the present: agents take over from there."""
        history = np.asarray(history, dtype=float)
        if history.ndim != 4 or history.shape[2] < 1 or history.shape[2] > max_steps:
            raise ValueError(f"history has shape {list(history.shape)} (expected [m, 2, k, 6] with 1 <= k <= {max_steps})")
        world = cls(history[:, :, 0], max_steps)
        if not np.isfinite(history).all():
            raise ValueError("history has NaN or infinite states (expected finite recorded steps)")
        world.states[:, :, : history.shape[2]] = history
        world.t = history.shape[2] - 1
        return world

    @property
    def history(self) -> np.ndarray:
        """Both cars' states at steps 0..t, ``[m, 2, t+1, 6]`` (a view)."""
        return self.states[:, :, : self.t + 1]

    @property
    def done(self) -> bool:
        """Whether every episode has ended (or the last step is reached)."""
        return not self.running.any() or self.t + 1 >= self.max_steps

    def step(self, accelerations: np.ndarray) -> None:
        """Advance every running episode by one step with both cars' accelerations at the next
        step, ``accelerations [m, 2, 2]`` (episode, car, ``[xdd, ydd]``, m/s²), a braking that would
        reverse a car raised to stop it; an episode ends once both cars are past ``RECORD_END_X``."""
        now = self.states[:, :, self.t]
        acc = np.array(accelerations, dtype=float)
        acc[..., 0] = without_reversing(now[..., 2], now[..., 4], acc[..., :1])[..., 0]
        x, xd = trapezoid_step(now[..., 0], now[..., 2], now[..., 4], acc[..., 0])
        y, yd = trapezoid_step(now[..., 1], now[..., 3], now[..., 5], acc[..., 1])
        self.t += 1
        self.states[:, :, self.t] = np.stack([x, y, xd, yd, acc[..., 0], acc[..., 1]], axis=-1)
        ended = self.running & (self.states[:, :, self.t, 0] > RECORD_END_X).all(axis=1)
        self.lengths[ended] = self.t + 1
        self.running &= ~ended

    def recorded(self) -> tuple[np.ndarray, np.ndarray]:
        """``(states [m, 2, T, 6], lengths [m])`` up to the longest episode (steps past an episode's
        length are the world's continuation, not its record)."""
        return self.states[:, :, : int(self.lengths.max())], self.lengths.copy()


def run_episodes(start: np.ndarray, agents: Sequence[Agent], rng: np.random.Generator,
                 max_steps: int = MAX_STEPS, progress: bool = False, until_max_steps: bool = False) -> World:
    """Run ``m`` episodes from ``start [m, 2, 6]`` with ``agents[k]`` driving car ``k``, until every
    episode has ended; returns the world. ``rng`` is handed to each agent's ``reset`` in car order
    (agents draw from it in car order at every step, so a run is reproducible from its seed).
    ``start`` may also be the first ``k`` steps ``[m, 2, k, 6]`` (e.g. recorded; the agents take
    over at step ``k - 1``, :meth:`World.from_history`); ``until_max_steps`` runs every episode to
    ``max_steps`` steps, ended or not (to compare with recordings step by step)."""
    start = np.asarray(start, dtype=float)
    world = World.from_history(start, max_steps) if start.ndim == 4 else World(start, max_steps)
    for me, agent in enumerate(agents):
        agent.reset(rng, world.states[:, :, 0], me)
    steps = tqdm(total=max_steps - 1 - world.t, desc="simulating", unit="step", disable=not progress, leave=False)
    while world.t + 1 < max_steps if until_max_steps else not world.done:
        history = world.history
        world.step(np.stack([agent.act(history) for agent in agents], axis=1))
        steps.update()
    steps.close()
    return world
