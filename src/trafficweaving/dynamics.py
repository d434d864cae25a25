"""Integrators shared by data generation, prediction and planning.

Recorded human cars follow trapezoid integration of acceleration into velocity and of velocity
into position (checked on the authors' recordings: residual < 5e-3 m/s per step).
"""

from __future__ import annotations

import numpy as np

from .scenario import DT


def integrate_trapezoid(p0: np.ndarray, v0: np.ndarray, acc: np.ndarray, dt: float = DT):
    """Positions and velocities from accelerations by the trapezoid rule along the last axis.

    ``p0``, ``v0``: ``[...]`` initial position (m) and velocity (m/s); ``acc``: ``[..., N+1]``
    accelerations (m/s²) at steps 0..N, where ``acc[..., 0]`` is the present acceleration.
    Returns ``(p, v)``, each ``[..., N+1]`` including the initial values at index 0.
    """
    acc = np.asarray(acc, dtype=float)
    dv = 0.5 * dt * (acc[..., 1:] + acc[..., :-1])
    v = np.concatenate([np.asarray(v0, float)[..., None], v0[..., None] + np.cumsum(dv, axis=-1)], axis=-1)
    dp = 0.5 * dt * (v[..., 1:] + v[..., :-1])
    p = np.concatenate([np.asarray(p0, float)[..., None], p0[..., None] + np.cumsum(dp, axis=-1)], axis=-1)
    return p, v


def trapezoid_step(p: np.ndarray, v: np.ndarray, a: np.ndarray, a_next: np.ndarray, dt: float = DT):
    """One step of :func:`integrate_trapezoid`: ``(p, v)`` at the next step, same shapes as inputs
    (m, m/s; accelerations in m/s² at this and the next step)."""
    v_next = v + 0.5 * dt * (a + a_next)
    return p + 0.5 * dt * (v + v_next), v_next
