"""Lateral steering of the robot: a triple integrator in ``y`` driven by jerk.

At the start of each window the robot solves the two-point boundary value problem from
``(y, yd, ydd)`` to ``(y_target, 0, 0)`` with free final time ``T`` and cost
``∫_0^T 1 + yddd²/ρ dt`` (ρ = 1000) and follows the optimal trajectory (paper §V-C).

For a fixed ``T`` the minimum-energy jerk is ``u(t) = b(T - t)ᵀ G(T)⁻¹ d(T)`` with
``b(s) = [s²/2, s, 1]``, ``G`` the controllability Gramian of the triple integrator and ``d`` the
final state minus the free (zero-jerk) drift, so the cost is ``J(T) = T + d(T)ᵀ G(T)⁻¹ d(T) / ρ``,
minimised over ``T`` (vectorised golden-section search on ``log T``). Past ``T`` the target is held.

``min_time`` bounds ``T`` from below. The robot executes a plan as accelerations sampled every 0.1 s
(the world integrates them by the trapezoid rule), so a correction shorter than a few steps is not
executed as solved: from a lane centre the residue of the sampling is re-solved every window into
±0.7 m/s² of lateral chatter (ρ = 1000) that never settles; with ``T ≥ 0.6 s`` the same corrections
decay to rest (docs/driving.md, Driving styles).

:func:`jerk_limited_steer` is the comfort kinematics' alternative: the time-optimal steering within
bounds on the lateral acceleration and jerk (jerk switching between its bounds rather than
shrinking towards them), so a lane change within the comfort limits takes 2.7 s from rest
instead of the minimum-energy profile's 3.2 s at the same peak jerk.
"""

from __future__ import annotations

import numpy as np
from ruckig import InputParameter, Result, Ruckig, RuckigError, Trajectory

JERK_WEIGHT = 1000.0  # ρ
T_BOUNDS = (1e-3, 60.0)  # s: search range for the free final time
_GOLDEN = (np.sqrt(5.0) - 1.0) / 2.0


def _drift_gap(state: np.ndarray, target: np.ndarray, T: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The components of ``d = [target, 0, 0] - e^{AT} state`` (each ``[...]``) for ``state [..., 3]``
    (y, yd, ydd)."""
    y, v, a = state[..., 0], state[..., 1], state[..., 2]
    return target - (y + v * T + a * T * T / 2), -(v + a * T), -a


def _coefficients(state: np.ndarray, target: np.ndarray, T: np.ndarray) -> np.ndarray:
    """``G(T)⁻¹ d(T)`` ``[..., 3]``: the optimal jerk is ``b(T - t) · coefficients``. ``G`` is the
    controllability Gramian of the triple integrator over ``T [...]`` s, ``[[T⁵/20, T⁴/8, T³/6],
    [T⁴/8, T³/3, T²/2], [T³/6, T²/2, T]]``, whose inverse is written out: ``[[720/T⁵, −360/T⁴,
    60/T³], [−360/T⁴, 192/T³, −36/T²], [60/T³, −36/T², 9/T]]``."""
    d0, d1, d2 = _drift_gap(state, target, T)
    r = 1.0 / T
    return np.stack([r**3 * (r * (r * 720.0 * d0 - 360.0 * d1) + 60.0 * d2),
                     r**2 * (r * (-r * 360.0 * d0 + 192.0 * d1) - 36.0 * d2),
                     r * (r * (r * 60.0 * d0 - 36.0 * d1) + 9.0 * d2)], axis=-1)


def steering_cost(state: np.ndarray, target: np.ndarray, T: np.ndarray, weight: float = JERK_WEIGHT) -> np.ndarray:
    """``J(T) = T + (1/ρ) ∫ u² dt`` of the minimum-energy steering with final time ``T`` (s), ρ = ``weight``:
    ``∫ u² dt = dᵀ G⁻¹ d`` (:func:`_coefficients`), written out as a polynomial in ``1/T``."""
    d0, d1, d2 = _drift_gap(state, target, T)
    r = 1.0 / T
    energy = r * (9.0 * d2 * d2 + r * (-72.0 * d1 * d2 + r * (192.0 * d1 * d1 + 120.0 * d0 * d2
                                                             + r * (-720.0 * d0 * d1 + r * 720.0 * d0 * d0))))
    return T + energy / weight


def optimal_time(state: np.ndarray, target: np.ndarray, iterations: int = 50, weight: float = JERK_WEIGHT,
                 min_time: float = T_BOUNDS[0]) -> np.ndarray:
    """Free final time ``T* [...]`` (s, at least ``min_time``) minimising :func:`steering_cost` with
    ρ = ``weight``; 0 where the state is already at the target. ``state [..., 3]``, ``target [...]`` (m).
    Golden-section search on ``log T``: one new point, and one evaluation of the cost, per iteration."""
    state, target = np.asarray(state, float), np.asarray(target, float)
    lo = np.full(target.shape, np.log(max(min_time, T_BOUNDS[0])))
    hi = np.full(target.shape, np.log(T_BOUNDS[1]))
    cost = lambda u: steering_cost(state, target, np.exp(u), weight)  # noqa: E731
    a, b = hi - _GOLDEN * (hi - lo), lo + _GOLDEN * (hi - lo)
    fa, fb = cost(a), cost(b)
    for _ in range(iterations):
        left = fa < fb  # the minimum lies in [lo, b]: b becomes the upper bound and a the inner point
        hi, lo = np.where(left, b, hi), np.where(left, lo, a)
        new = np.where(left, hi - _GOLDEN * (hi - lo), lo + _GOLDEN * (hi - lo))
        f_new = cost(new)
        a, b = np.where(left, new, b), np.where(left, a, new)
        fa, fb = np.where(left, f_new, fb), np.where(left, fa, f_new)
    T = np.exp((lo + hi) / 2)
    at_target = np.all(np.abs(np.stack(_drift_gap(state, target, np.zeros_like(target)), -1)) < 1e-9, axis=-1)
    return np.where(at_target, 0.0, T)


def steer(state: np.ndarray, target: np.ndarray, times: np.ndarray, weight: float = JERK_WEIGHT,
          min_time: float = T_BOUNDS[0]) -> np.ndarray:
    """States ``[..., len(times), 4]`` = ``(y, yd, ydd, yddd)`` at ``times`` (s after the start) along
    the optimal steering from ``state [..., 3]`` to ``(target, 0, 0)`` with jerk weight ρ =
    ``weight`` (smaller: gentler and longer) and final time at least ``min_time`` (s); the target is
    held (jerk 0, at rest) once the final time is reached."""
    state, target, times = np.asarray(state, float), np.asarray(target, float), np.asarray(times, float)
    T = optimal_time(state, target, weight=weight, min_time=min_time)
    safe_T = np.where(T > 0, T, 1.0)
    c = _coefficients(state, target, safe_T)  # [..., 3]
    t = np.minimum(times, T[..., None])  # [..., K]
    s = T[..., None] - t  # time to go
    c0, c1, c2 = (c[..., k, None] for k in range(3))
    # u(t) = c0 (T-t)²/2 + c1 (T-t) + c2; integrate three times from the initial state
    # in powers of t: u = p0 + p1 t + p2 t² with
    p0 = c0 * safe_T[..., None] ** 2 / 2 + c1 * safe_T[..., None] + c2
    p1 = -(c0 * safe_T[..., None] + c1)
    p2 = c0 / 2
    y0, v0, a0 = (state[..., k, None] for k in range(3))
    acc = a0 + p0 * t + p1 * t**2 / 2 + p2 * t**3 / 3
    vel = v0 + a0 * t + p0 * t**2 / 2 + p1 * t**3 / 6 + p2 * t**4 / 12
    pos = y0 + v0 * t + a0 * t**2 / 2 + p0 * t**3 / 6 + p1 * t**4 / 24 + p2 * t**5 / 60
    jerk = np.where(times < T[..., None], c0 * s**2 / 2 + c1 * s + c2, 0.0)
    out = np.stack([pos, vel, acc, jerk], axis=-1)
    done = (T <= 0)[..., None, None]
    held = np.stack(np.broadcast_arrays(state[..., None, 0], state[..., None, 1], state[..., None, 2], np.zeros_like(t)), -1)
    return np.where(done, held, out)


def jerk_limited_steer(state: np.ndarray, target: np.ndarray, times: np.ndarray, max_acceleration: float,
                       max_jerk: float, min_time: float = 0.0) -> np.ndarray:
    """States ``[..., len(times), 3]`` = ``(y, yd, ydd)`` at ``times`` (s after the start) along the
    time-optimal steering from ``state [..., 3]`` to ``(target, 0, 0)`` with ``|ydd| <= max_acceleration``
    (m/s²) and ``|yddd| <= max_jerk`` (m/s³), taking at least ``min_time`` (s: a correction near the
    target decays instead of chattering), held once there (Ruckig: Berscheid and Kröger, RSS 2021).
    A state already accelerating harder than ``max_acceleration`` is allowed its own."""
    state, target, times = np.asarray(state, float), np.asarray(target, float), np.asarray(times, float)
    flat_state, flat_target = state.reshape(-1, 3), target.reshape(-1)
    out = np.empty((len(flat_target), len(times), 3))
    generator, problem, trajectory = Ruckig(1), InputParameter(1), Trajectory(1)
    problem.max_velocity = [100.0]  # m/s: no bound on the lateral speed that binds
    problem.target_velocity, problem.target_acceleration = [0.0], [0.0]
    problem.max_jerk = [max_jerk]
    problem.minimum_duration = min_time
    for i, ((y, v, a), goal) in enumerate(zip(flat_state, flat_target)):
        problem.current_position, problem.current_velocity, problem.current_acceleration = [y], [v], [a]
        problem.target_position = [goal]
        problem.max_acceleration = [max(max_acceleration, abs(a) + 1e-6)]
        try:
            solved = generator.calculate(problem, trajectory) in (Result.Working, Result.Finished)
        except RuckigError:
            solved = False
        if not solved:
            raise ValueError(f"no jerk-limited steering from (y, yd, ydd) = {(y, v, a)} to y = {goal}")
        out[i] = [[p[0], q[0], r[0]] for p, q, r in (trajectory.at_time(t) for t in times)]
    return out.reshape(*target.shape, len(times), 3)
