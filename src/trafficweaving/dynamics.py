"""How cars move: the one home of integration, for NumPy arrays and torch tensors alike.

Human cars (recorded and simulated) follow the trapezoid rule, acceleration into velocity and
velocity into position (checked on the authors' recordings: residual < 5e-3 m/s per step). The
robot's candidate futures follow the authors' robot convention instead: the acceleration stored at
step ``k`` is applied from ``k`` to ``k+1``, velocity by Euler, position by the trapezoid rule
(:func:`robot_longitudinal`).
"""

from __future__ import annotations

import numpy as np
import torch

from .scenario import DT, HORIZON


def _cumsum(a, axis: int):
    return torch.cumsum(a, dim=axis) if isinstance(a, torch.Tensor) else np.cumsum(a, axis=axis)


def _cat(parts, axis: int):
    return torch.cat(parts, dim=axis) if isinstance(parts[0], torch.Tensor) else np.concatenate(parts, axis=axis)


def _add(a, b, out):
    return torch.add(a, b, out=out) if isinstance(out, torch.Tensor) else np.add(a, b, out=out)


def _trapezoid(x0, rate0, rates, dt: float):
    """``x [..., N]`` at steps 1..N from ``x0 [...]`` at step 0 and its rate of change ``rate0
    [...]`` at step 0 and ``rates [..., N]`` at steps 1..N, by the trapezoid rule (the pairwise
    sums are written into one buffer, not concatenated: the planner integrates ~10⁵ futures a plan)."""
    half_sums = (torch.empty_like if isinstance(rates, torch.Tensor) else np.empty_like)(rates)
    _add(rates[..., 1:], rates[..., :-1], half_sums[..., 1:])
    _add(rates[..., :1], rate0[..., None], half_sums[..., :1])
    half_sums *= 0.5 * dt
    return x0[..., None] + _cumsum(half_sums, -1)


def integrate_trapezoid(p0, v0, acc, dt: float = DT):
    """Positions and velocities from accelerations by the trapezoid rule along the last axis.

    ``p0``, ``v0``: ``[...]`` initial position (m) and velocity (m/s); ``acc``: ``[..., N+1]``
    accelerations (m/s²) at steps 0..N, where ``acc[..., 0]`` is the present acceleration.
    Returns ``(p, v)``, each ``[..., N+1]`` including the initial values at index 0 (NumPy float64
    for array input, tensors of ``acc``'s dtype for tensor input).
    """
    if not isinstance(acc, torch.Tensor):
        acc, p0, v0 = (np.asarray(a, dtype=float) for a in (acc, p0, v0))
    v = _trapezoid(v0, acc[..., 0], acc[..., 1:], dt)
    p = _trapezoid(p0, v0, v, dt)
    return _cat([p0[..., None], p], -1), _cat([v0[..., None], v], -1)


def trapezoid_step(p, v, a, a_next, dt: float = DT):
    """One step of :func:`integrate_trapezoid`: ``(p, v)`` at the next step, same shapes as inputs
    (m, m/s; accelerations in m/s² at this and the next step)."""
    v_next = v + 0.5 * dt * (a + a_next)
    return p + 0.5 * dt * (v + v_next), v_next


def without_reversing(v0, a0, accelerations, dt: float = DT):
    """Longitudinal ``accelerations [..., N]`` (m/s², steps t+1..t+N) of cars at speed ``v0 [...]``
    (m/s) with present acceleration ``a0 [...]`` (m/s²), each raised just enough that the speed
    integrated by the trapezoid rule never drops below 0: a car on the highway stops, it does not
    roll backwards. Accelerations that keep the speed non-negative are returned unchanged (NumPy)."""
    out = np.array(accelerations, dtype=float)
    v, a = np.asarray(v0, dtype=float), np.asarray(a0, dtype=float)
    for k in range(out.shape[-1]):
        out[..., k] = np.maximum(out[..., k], -a - 2.0 * np.maximum(v, 0.0) / dt)
        v, a = v + 0.5 * dt * (a + out[..., k]), out[..., k]
    return out


def future_states(present, accelerations, dt: float = DT):
    """A human car's states ``[..., N, 6]`` at steps t+1..t+N from its present state ``present
    [..., 6]`` (broadcastable against the leading dims of ``accelerations``) and its accelerations
    ``accelerations [..., N, 2]`` (m/s², ``[xdd, ydd]``) at those steps, by the trapezoid rule.
    NumPy arrays or torch tensors (the type of ``accelerations``)."""
    tensor = isinstance(accelerations, torch.Tensor)
    if tensor:
        present = torch.as_tensor(present, dtype=accelerations.dtype, device=accelerations.device)
        lead = torch.broadcast_shapes(present.shape[:-1], accelerations.shape[:-2])
        present, accelerations = present.expand(*lead, 6), accelerations.expand(*lead, *accelerations.shape[-2:])
    else:
        present, accelerations = np.asarray(present, dtype=float), np.asarray(accelerations, dtype=float)
        lead = np.broadcast_shapes(present.shape[:-1], accelerations.shape[:-2])
        present = np.broadcast_to(present, (*lead, 6))
        accelerations = np.broadcast_to(accelerations, (*lead, *accelerations.shape[-2:]))
    out = (torch.empty if tensor else np.empty)((*lead, accelerations.shape[-2], 6), dtype=accelerations.dtype,
                                                **({"device": accelerations.device} if tensor else {}))
    for axis in range(2):
        acceleration = accelerations[..., axis]
        velocity = _trapezoid(present[..., 2 + axis], present[..., 4 + axis], acceleration, dt)
        out[..., axis], out[..., 2 + axis] = _trapezoid(present[..., axis], present[..., 2 + axis], velocity, dt), velocity
        out[..., 4 + axis] = acceleration
    return out


def constant_acceleration_future(present, steps: int = HORIZON, dt: float = DT):
    """A car's states ``[..., steps, 6]`` at steps t+1..t+steps when it holds its present
    acceleration, from its present state ``present [..., 6]`` (m, m/s, m/s²; trapezoid rule,
    :func:`future_states`): what a driver can guess of the other car's future. NumPy or torch."""
    if isinstance(present, torch.Tensor):
        return future_states(present, present[..., None, 4:6].expand(*present.shape[:-1], steps, 2), dt)
    present = np.asarray(present, dtype=float)
    return future_states(present, np.repeat(present[..., None, 4:6], steps, axis=-2), dt)


def robot_longitudinal(x0, xd0, applied, dt: float = DT):
    """The robot's positions and velocities ``(x, xd)``, each ``[..., N]`` at steps t+1..t+N, from
    its present ``x0``, ``xd0`` ``[...]`` (m, m/s) and the accelerations ``applied [..., N]`` (m/s²)
    applied from steps t..t+N-1: Euler velocity, trapezoid position (the robot convention)."""
    applied = np.asarray(applied, dtype=float)
    x0, xd0 = np.asarray(x0, dtype=float)[..., None], np.asarray(xd0, dtype=float)[..., None]
    xd = xd0 + dt * np.cumsum(applied, axis=-1)
    xd_before = np.concatenate([np.broadcast_to(xd0, xd[..., :1].shape), xd[..., :-1]], axis=-1)
    return x0 + np.cumsum(0.5 * dt * (xd_before + xd), axis=-1), xd


def minimum_jerk_acceleration(distance, progress, duration):
    """Acceleration (m/s²) of a minimum-jerk (quintic) move from rest to rest by ``distance`` (m)
    over ``duration`` (s), at ``progress`` = elapsed / duration in [0, 1]: the smooth lane change
    of the rule-based robot and the scripted humans. Arrays broadcast; 0 at both ends."""
    s = progress
    return distance * (60 * s - 180 * s**2 + 120 * s**3) / duration**2


def minimum_jerk_from(distance, progress, duration, speed, acceleration):
    """:func:`minimum_jerk_acceleration` from a moving start: the acceleration (m/s²) of the
    quintic that moves by ``distance`` (m) over ``duration`` (s) from ``speed`` (m/s) and
    ``acceleration`` (m/s²) to rest, at ``progress`` in [0, 1] (e.g. a lane change turned back
    half-way). Arrays broadcast."""
    s = progress
    from_speed = speed * (-36 * s + 96 * s**2 - 60 * s**3) / duration
    from_acceleration = acceleration * (1 - 9 * s + 18 * s**2 - 10 * s**3)
    return minimum_jerk_acceleration(distance, progress, duration) + from_speed + from_acceleration
