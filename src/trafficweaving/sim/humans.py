"""Human agents: who drives the human car in a simulation (:class:`~trafficweaving.sim.world.Agent`).

* :class:`SyntheticDrivers`: the simulated drivers of :mod:`~trafficweaving.sim.drivers`
  (intermittent control, sampled driving styles), batched over episodes.
"""

from __future__ import annotations

import numpy as np

from ..scenario import lane_of
from .drivers import DriverAgents, DriverModel, DriverStyles


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
