"""Robot agents: who drives the robot car in a simulation (:class:`~trafficweaving.sim.world.Agent`).

* :class:`~trafficweaving.planning.mpc.MPCPolicy`: the paper's planner (paper §IV, §V-C) against
  a human model, the CVAE's (:class:`~trafficweaving.model.predictor.HumanPredictor`) or the
  non-interactive :class:`~trafficweaving.model.constant_velocity.ConstantVelocityHuman`;
* :class:`RuleBasedRobot`: a rule-based baseline, IDM car following with a MOBIL-style
  gap-acceptance lane change, batched over episodes.

:func:`robot_agent` builds one from a spec string (:data:`ROBOT_SPECS`). Every robot agent has
``latencies``: the seconds each of its plans took (none for the rule-based robot).
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass, fields

import numpy as np
import torch

from .. import validate
from ..dynamics import minimum_jerk_acceleration
from ..errors import InputError
from ..model.device import choose_device
from ..model.registry import load_model
from ..model.constant_velocity import ConstantVelocityHuman
from ..model.predictor import HumanPredictor
from ..planning.mpc import MPCPolicy
from ..planning.planner import Budget, Planner
from ..planning.styles import STYLES
from ..scenario import CAR_LENGTH, COLLISION_DY, DT, LANE_CENTRE_Y, LANES, ROAD_END_X, STATE_NAMES, lane_of
from .world import Agent

ROBOT_SPECS = (*STYLES, "planner-cv", "rules")
"""The robots :func:`robot_agent` builds: a planner in each driving style
(:data:`~trafficweaving.planning.styles.STYLES`), ``planner-cv`` (the decisive style against a
constant-velocity human) and the rule-based robot."""


@dataclass(frozen=True)
class RuleParameters:
    """Parameters of :class:`RuleBasedRobot` (m, s, m/s²).

    Car following is Treiber's Intelligent Driver Model with its standard parameters (the desired
    speed is the robot's start speed); the lane change is MOBIL's (Kesting, Treiber & Helbing
    2007) incentive and safety criteria with a bias for the mandatory change, made urgent near
    the cutoff; the lateral motion is a minimum-jerk profile.
    """

    time_headway: float = 1.5
    """IDM ``T``: desired time gap to the leader, s."""
    min_gap: float = 2.0
    """IDM ``s0``: bumper-to-bumper gap kept at standstill, m; also the least gap a lane change accepts."""
    max_accel: float = 1.5
    """IDM ``a``: maximum acceleration, m/s²."""
    comfortable_decel: float = 2.0
    """IDM ``b``: comfortable deceleration, m/s²."""
    delta: float = 4.0
    """IDM acceleration exponent."""
    max_brake: float = 6.0
    """Hardest braking, m/s² (the planner's hardest action, :data:`~trafficweaving.planning.candidates.ACCELERATIONS`)."""
    safe_decel: float = 4.0
    """MOBIL ``b_safe``: a lane change is safe when the new follower's IDM acceleration stays above
    ``-safe_decel``; yielding brakes no harder, m/s²."""
    politeness: float = 0.5
    """MOBIL ``p``: weight of the new follower's acceleration loss in the incentive."""
    threshold: float = 0.1
    """MOBIL ``Δa_th``: acceleration gain a lane change must bring, m/s²."""
    bias: float = 1.0
    """MOBIL bias towards the goal lane (the change is mandatory), m/s²."""
    urgent_time: float = 4.0
    """Time to the cutoff (at the present speed) from which any safe gap is accepted and, if there
    is none, the robot brakes to let the human pass and merges behind, s."""
    lane_change_time: float = 3.0
    """Duration of an unhurried lane change, s."""
    hurried_lane_change_time: float = 2.0
    """Shortest lane change, s: a late one takes the time to the cutoff, but no less than this."""

    def __post_init__(self):
        for field in fields(self):
            value, low = getattr(self, field.name), ">= 0" if field.name == "politeness" else "> 0"
            if (isinstance(value, bool) or not isinstance(value, numbers.Real) or not math.isfinite(value)
                    or not (value >= 0 if low == ">= 0" else value > 0)):
                raise InputError(f"{field.name} must be a finite number {low}, got {value!r}")
        if self.hurried_lane_change_time > self.lane_change_time:
            raise InputError(f"hurried_lane_change_time must be at most lane_change_time ({self.lane_change_time} s), "
                             f"got {self.hurried_lane_change_time!r}")


class RuleBasedRobot:
    """IDM car following and a MOBIL-style lane change to the lane the robot did not start in,
    for ``m`` episodes at once (:class:`RuleParameters`).

    Each step, from both cars' present states:

    * **leader**: the human when it is ahead and in the robot's lane, in the lane it is changing
      to, or overlapping it laterally (``|Δy| < COLLISION_DY``); the robot accelerates by IDM
      behind it (free road otherwise), clipped to ``[-max_brake, max_accel]``;
    * **lane change** (once, committed): the target lane's gap is safe when the human is not in
      it or is ``>= min_gap`` away bumper to bumper with the new follower (the robot behind the
      human, or the human behind the robot, assumed to keep its speed) braking less than
      ``safe_decel``. The robot changes when the gap is safe and its own acceleration gain plus
      ``politeness`` times the human's plus ``bias`` reaches ``threshold``; within
      ``urgent_time`` of the cutoff it accepts any safe gap, and if there is none it yields:
      IDM behind the human as if it were already in its lane (braking at most ``safe_decel``),
      so that the human passes and the robot merges behind;
    * **lateral**: a minimum-jerk profile from its lane to the goal lane's centre over
      ``lane_change_time`` (hurried to the time to the cutoff near it, at least
      ``hurried_lane_change_time``), at rest in its lane before.

    Deterministic: :meth:`reset` draws nothing from its rng. :attr:`latencies` stays empty.
    """

    def __init__(self, parameters: RuleParameters | None = None):
        if parameters is not None and not isinstance(parameters, RuleParameters):
            raise InputError(f"parameters must be a RuleParameters or None, got {parameters!r}")
        self.parameters = parameters or RuleParameters()
        self.latencies: list[float] = []
        self.me: int | None = None

    def reset(self, rng: np.random.Generator, start: np.ndarray, me: int) -> None:
        """Start ``m`` episodes from ``start [m, 2, 6]`` (finite states ``[x, y, xd, yd, xdd, ydd]``)
        with the robot as car ``me`` (0 or 1); each robot's desired speed is its start speed."""
        start = validate.finite_array("start", start, (None, 2, len(STATE_NAMES)), f"[m, 2, {len(STATE_NAMES)}]")
        self.me = validate.integer("me", me, 0, 1)
        robot = start[:, self.me]
        self.desired_speed = np.maximum(robot[:, 2], 1.0)
        start_lane = lane_of(robot[:, 1])
        self.goal_lane = np.where(start_lane == LANES[0], LANES[1], LANES[0])
        self.goal_y = np.array([LANE_CENTRE_Y[lane] for lane in self.goal_lane])
        m = len(start)
        self.changing = np.zeros(m, dtype=bool)
        self.change_y0 = robot[:, 1].copy()  # lateral start of the lane change, m
        self.change_step = np.zeros(m, dtype=np.int64)  # step at which it began
        self.change_time = np.full(m, self.parameters.lane_change_time)  # its duration, s

    def idm(self, speed, desired, gap, closing) -> np.ndarray:
        """IDM acceleration (m/s²) at ``speed`` towards ``desired`` (m/s) behind a leader ``gap`` m
        ahead bumper to bumper (``inf``: free road; ``<= 0`` brakes hardest) approached at
        ``closing`` m/s; arrays of one shape, clipped to ``[-max_brake, max_accel]``."""
        p = self.parameters
        wanted = p.min_gap + np.maximum(0.0, speed * p.time_headway + speed * closing / (2 * math.sqrt(p.max_accel * p.comfortable_decel)))
        crowding = (wanted / np.maximum(gap, 1e-3)) ** 2
        free = (np.maximum(speed, 0.0) / desired) ** p.delta
        return np.clip(p.max_accel * (1.0 - free - crowding), -p.max_brake, p.max_accel)

    def act(self, history: np.ndarray) -> np.ndarray:
        """The robots' accelerations ``[m, 2]`` (``[xdd, ydd]``, m/s²) at step t+1 given both cars'
        states ``history [m, 2, t+1, 6]``."""
        if self.me is None:
            raise RuntimeError("RuleBasedRobot.act needs episodes: call reset(rng, start, me) first")
        p = self.parameters
        history = validate.finite_array("history", history, (len(self.goal_y), 2, None, len(STATE_NAMES)),
                                        f"[{len(self.goal_y)}, 2, t+1, {len(STATE_NAMES)}]")
        t = history.shape[2] - 1
        robot, human = history[:, self.me, -1], history[:, 1 - self.me, -1]
        x, y, v = robot[:, 0], robot[:, 1], robot[:, 2]
        dx, v_h = human[:, 0] - x, human[:, 2]
        ahead = dx > 0
        gap = np.abs(dx) - CAR_LENGTH  # bumper to bumper, m
        human_lane = lane_of(human[:, 1])
        in_target = human_lane == self.goal_lane
        leads = ahead & ((human_lane == lane_of(y)) | (self.changing & in_target) | (np.abs(human[:, 1] - y) < COLLISION_DY))
        now = self.idm(v, self.desired_speed, np.where(leads, gap, np.inf), v - v_h)

        # MOBIL: the robot's acceleration in the target lane and that of its new follower there
        after = self.idm(v, self.desired_speed, np.where(in_target & ahead, gap, np.inf), v - v_h)
        follower = np.where(in_target & ~ahead, self.idm(v_h, np.maximum(v_h, 1.0), gap, v_h - v), 0.0)
        safe = ~in_target | ((gap >= p.min_gap) & (np.where(ahead, after, follower) >= -p.safe_decel))
        incentive = after - now + p.politeness * follower + p.bias >= p.threshold
        time_left = (ROAD_END_X - x) / np.maximum(v, 1.0)
        urgent = time_left <= p.urgent_time
        start = ~self.changing & safe & (incentive | urgent)
        waiting = ~self.changing & ~start & urgent & in_target
        behind_human = np.maximum(self.idm(v, self.desired_speed, dx - CAR_LENGTH, v - v_h), -p.safe_decel)
        xdd = np.where(waiting, np.minimum(now, behind_human), now)

        self.change_y0 = np.where(start, y, self.change_y0)
        self.change_step = np.where(start, t, self.change_step)
        self.change_time = np.where(start, np.clip(time_left, p.hurried_lane_change_time, p.lane_change_time),
                                    self.change_time)
        self.changing |= start
        s = np.clip((t + 1 - self.change_step) * DT / self.change_time, 0.0, 1.0)  # progress at step t+1
        ydd = np.where(self.changing, minimum_jerk_acceleration(self.goal_y - self.change_y0, s, self.change_time), 0.0)
        return np.stack([xdd, ydd], axis=1)


def robot_agent(spec: str, model: str = "default", deadline: float | None = None, budget: Budget | None = None,
                device: torch.device | str = "cpu", precision: str = "auto") -> Agent:
    """The robot agent named by ``spec`` (one of :data:`ROBOT_SPECS`):

    * ``planner``, ``planner-decisive``, ``planner-paper``, ``planner-comfort``,
      ``planner-cautious``: :class:`~trafficweaving.planning.mpc.MPCPolicy` in that driving style
      (:data:`~trafficweaving.planning.styles.STYLES`; ``planner``: comfort first, the default;
      ``planner-paper``: the paper's planner exactly) planning against the human model ``model``
      (``default``, a checkpoint path or ``authors:PATH``, as
      :func:`~trafficweaving.model.registry.load_model`) through :class:`HumanPredictor` (with
      ``precision``);
    * ``planner-cv``: the decisive style against :class:`ConstantVelocityHuman` (``model`` unused);
    * ``rules``: :class:`RuleBasedRobot` (``model``, ``deadline``, ``budget`` unused).

    The planners run on ``device`` (``auto``, ``cpu``, ``cuda`` or ``cuda:N``) with the sample
    counts ``budget`` (None: the paper's) or, with ``deadline`` (s), within that many seconds a
    plan, sampling at ``precision`` (:data:`~trafficweaving.model.predictor.PRECISIONS`). An
    unknown spec or precision raises :class:`~trafficweaving.errors.InputError`.
    """
    if spec not in ROBOT_SPECS:
        raise InputError(f"robot {spec!r} is unknown (expected one of: {', '.join(ROBOT_SPECS)})")
    if spec == "rules":
        return RuleBasedRobot()
    return MPCPolicy(robot_planner(spec, model, budget, device, precision), deadline=deadline)


def robot_planner(spec: str, model: str = "default", budget: Budget | None = None,
                  device: torch.device | str = "cpu", precision: str = "auto") -> Planner:
    """The :class:`Planner` of the planning robot ``spec`` (a planning robot of :data:`ROBOT_SPECS`,
    as :func:`robot_agent`), for policies that drive it their own way (the browser's non-blocking
    one)."""
    device = choose_device(str(device))
    human_model = (ConstantVelocityHuman(device) if spec == "planner-cv"
                   else HumanPredictor(load_model(model, device), precision=precision))
    return Planner(human_model, budget, style=STYLES["planner-decisive" if spec == "planner-cv" else spec])
