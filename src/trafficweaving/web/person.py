"""A person at the keyboard (or gamepad) as an agent of the world
(:class:`~trafficweaving.sim.world.Agent`): one more driver behind the same contract as the
simulated ones, so a browser trial is a simulated episode with a different human."""

from __future__ import annotations

import numpy as np

from .controls import RELEASED, ControlLimits, ControlMapper, Controls


class PersonAgent:
    """Drives car ``me`` of one episode (``m = 1``) with the latest :attr:`controls` the browser
    sent (set between steps; released until the first arrives), mapped to accelerations by
    :class:`~.controls.ControlMapper`. :attr:`log` keeps the controls each step used:
    ``log[k]`` made the accelerations of step ``k + 1``."""

    def __init__(self, limits: ControlLimits = ControlLimits()):
        self.mapper = ControlMapper(limits)
        self.controls: Controls = RELEASED
        self.log: list[Controls] = []
        self.me = 0

    def reset(self, rng: np.random.Generator, start: np.ndarray, me: int) -> None:
        """Start an episode from ``start [1, 2, 6]`` as car ``me``, pedals released (draws nothing
        from ``rng``)."""
        self.me = me
        self.mapper.reset(start[0, me])
        self.controls, self.log = RELEASED, []

    def act(self, history: np.ndarray) -> np.ndarray:
        """The car's accelerations ``[1, 2]`` (``[xdd, ydd]``, m/s²) at step t+1 from the latest
        controls and its state at step t in ``history [1, 2, t+1, 6]``."""
        self.log.append(self.controls)
        return self.mapper.step(self.controls, history[0, self.me, -1])[None]
