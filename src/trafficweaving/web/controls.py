"""From a person's controls to a car's accelerations: the one home of the driving limits.

The browser sends the raw control state of each car it drives (:class:`Controls`: ``throttle``
and ``brake`` in ``[0, 1]``, ``steer`` in ``[-1, 1]``, negative to the left); the server turns it
into the car's next accelerations ``[xdd, ydd]`` (m/s²) once per simulation step
(:class:`ControlMapper`), within :class:`ControlLimits`:

* **longitudinal**: ``throttle·max_accel − brake·max_brake − coast_decel`` (with neither pedal the
  car slows gently, as a real one does with the accelerator released), never braking the car
  below standstill (no reverse);
* **lateral**: the steering sets a target lateral speed, ``−steer·max_lateral_speed`` (left is
  ``+y``), reached by a lateral acceleration proportional to the speed error
  (``1/lateral_response_s``) and bounded by ``max_lateral_accel``; with the steering centred the
  car straightens (its lateral speed returns to 0), as a car does when the driver recentres the
  wheel at the end of a lane change;
* **smoothing**: the commanded accelerations pass through a first-order lag of time constant
  ``smoothing_s`` (pedal travel, tyre and suspension lag), so a key press ramps the
  acceleration over a few tenths of a second instead of stepping it.

The defaults are a mid-size car at highway speed: ``max_accel`` 3.5 m/s² is a brisk full-throttle
pull at 30 m/s, ``max_brake`` 8 m/s² (0.8 g) a full stop on dry asphalt, and the lateral limits
(2.5 m/s, 3 m/s²) let a lane change of 4.26 m take about 2.5 s — the study's drivers' swaps take
2–4 s; their recorded lateral speeds stay within ±4.1 m/s and accelerations within ±8.4 m/s²
(:data:`~trafficweaving.data.trials.PLAUSIBLE_RANGES` documents the recordings).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

from ..scenario import DT


@dataclass(frozen=True)
class ControlLimits:
    """How controls become accelerations (module docstring); m/s², m/s and s."""

    max_accel: float = 3.5
    """Full throttle, m/s²."""
    max_brake: float = 8.0
    """Full brake, m/s² (a deceleration)."""
    coast_decel: float = 0.3
    """Deceleration with neither pedal (rolling resistance, drag, engine braking at 30 m/s), m/s²."""
    max_lateral_speed: float = 2.5
    """Lateral speed at full steering, m/s."""
    max_lateral_accel: float = 3.0
    """Largest lateral acceleration, m/s²."""
    lateral_response_s: float = 0.4
    """Time constant with which the lateral speed follows the steering, s."""
    smoothing_s: float = 0.2
    """Time constant of the first-order lag on both accelerations, s."""

    def as_dict(self) -> dict:
        """JSON form (sent to the page and stored with every recorded trial)."""
        return asdict(self)


@dataclass(frozen=True)
class Controls:
    """A car's raw control state: ``throttle`` and ``brake`` in ``[0, 1]``, ``steer`` in ``[-1, 1]``
    (negative: left)."""

    throttle: float = 0.0
    brake: float = 0.0
    steer: float = 0.0

    def as_list(self) -> list[float]:
        return [self.throttle, self.brake, self.steer]


RELEASED = Controls()
"""No pedal, steering centred."""


class ControlMapper:
    """One car's control mapping with its smoothing state (module docstring)."""

    def __init__(self, limits: ControlLimits = ControlLimits(), dt: float = DT):
        self.limits = limits
        self.blend = 1.0 - math.exp(-dt / limits.smoothing_s)  # lag filter gain per step
        self.dt = dt
        self.acceleration = np.zeros(2)  # the smoothed [xdd, ydd] last returned, m/s²

    def reset(self, state: np.ndarray) -> None:
        """Start from the car's state ``[x, y, xd, yd, xdd, ydd]`` (its present accelerations)."""
        self.acceleration = np.array(state[4:6], dtype=float)

    def commanded(self, controls: Controls, state: np.ndarray) -> np.ndarray:
        """The unsmoothed accelerations ``[xdd, ydd]`` (m/s²) of ``controls`` for a car in
        ``state [6]``."""
        lim = self.limits
        xdd = controls.throttle * lim.max_accel - controls.brake * lim.max_brake - lim.coast_decel
        target_yd = -controls.steer * lim.max_lateral_speed
        ydd = float(np.clip((target_yd - state[3]) / lim.lateral_response_s, -lim.max_lateral_accel,
                            lim.max_lateral_accel))
        return np.array([xdd, ydd])

    def step(self, controls: Controls, state: np.ndarray) -> np.ndarray:
        """The car's next accelerations ``[xdd, ydd]`` (m/s²) from ``state [6]``: the commanded
        ones through the lag, the longitudinal one bounded so that the next speed (trapezoid rule,
        as the world integrates) is not negative: brakes stop a car, they do not reverse it."""
        smoothed = self.acceleration + self.blend * (self.commanded(controls, state) - self.acceleration)
        smoothed[0] = max(smoothed[0], -2.0 * state[2] / self.dt - state[4])
        self.acceleration = smoothed
        return smoothed.copy()
