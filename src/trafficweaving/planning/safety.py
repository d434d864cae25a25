"""The safety layer: a check of every window before it is executed, which no driving rule overrides.

An RSS-style check (Shalev-Shwartz et al. 2017, "On a formal model of safe and scalable
self-driving cars") with the replanning period as the response time. A window's action is *safe*
when, after it, one response of the robot keeps it clear of the human over :data:`CHECK_HORIZON`
whatever the human plausibly does meanwhile:

* the robot's responses (from the end of the window, steering on to the window's lane): hold its
  speed, brake as hard as it can, or accelerate as hard as it can (:data:`RESPONSES`);
* the human's plausible motions (from now, :func:`plausible_human_paths`): longitudinally, hold its
  present acceleration for the response time and then its speed, keep its present acceleration
  (up to the study's speed alert), or brake at :data:`HUMAN_BRAKING` (or harder, if it brakes
  harder now) to a stop; laterally, continue its
  present lateral motion (its velocity, and its acceleration for the response time) up to the
  lane centre it is moving towards, or hold its lateral position;
* clear: more than :data:`CLEAR_X` apart lengthwise or :data:`CLEAR_Y` sideways at every step.

:func:`safe_action` keeps the proposed window when it is safe; otherwise it drives the best safe
action (by the last plan's costs of its window-1 actions, :attr:`~.planner.Plan.window_costs`);
where none is safe, the least-bad one: the action whose best response meets the human's worst
plausible motion latest, ties broken by hardest braking in the lane the robot is in (a
minimal-risk manoeuvre). Behind a human braking harder than the robot's kinematics can
(:func:`braking_hard_ahead`) a turn into the other lane counts as no escape (:func:`_staying_behind`):
the human, which swaps lanes too, may take that lane next, so the robot brakes in its own. So the
robot never accelerates towards a car moving into its lane ahead of it unless it stays clear
whatever that car does. The planner plans within what the layer will
let it drive: :func:`unsafe_next` marks the next windows it is expected to reject
(:data:`UNSAFE_NEXT_COST`). Assumptions and limits: docs/driving.md, Safety layer.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..scenario import COLLISION_DX, COLLISION_DY, DT, LANE_CENTRE_Y, LANES, SPEED_ALERT, lane_of
from ..dynamics import robot_longitudinal
from .candidates import N_ACTIONS, STEPS_PER_WINDOW, Kinematics, acceleration_indices, applied_accelerations, rollout

CHECK_HORIZON = 4.2
"""How far ahead (s) a window is checked: the response time and the time both cars need to brake
from 29 m/s to the speeds where a following gap stops shrinking (14 windows)."""
RESPONSE_TIME = STEPS_PER_WINDOW * DT
"""The robot's response time (s): the replanning period; a plan made next can first act after it."""
HUMAN_BRAKING = 6.0
"""The hardest braking (m/s²) expected of the human unless it brakes harder now: about the 99th
percentile of the real drivers' braking in the 30 recorded trials (6.2 m/s²)."""
CLEAR_X = COLLISION_DX + 1.0
"""Lengthwise distance (m, centre to centre) at which the cars are clear: the collision rule's
4.5 m and a metre."""
CLEAR_Y = COLLISION_DY + 0.2
"""Sideways distance (m, centre to centre) at which the cars are clear: the collision rule's
1.8 m and 0.2 m."""
UNSAFE_NEXT_COST = 100_000.0
"""The plan's cost of a candidate whose window 1 the safety layer is expected to reject
(:func:`unsafe_next`) while another would pass: more than a sampled future's collision costs can
add up to (about 66,000), so the planner plans within what the layer will let it drive."""
RESPONSES = ("hold speed", "brake", "accelerate")
"""The robot's responses after the checked window, in :func:`robot_paths`' order (accelerating up
to the study's speed alert, :data:`~trafficweaving.scenario.SPEED_ALERT`: away from a faster car
closing from behind)."""


@dataclass(frozen=True)
class SafetyDecision:
    """What the safety layer decided for one window: the ``proposed`` and the ``chosen`` action
    indices, the chosen one's ``kinematics``, whether the proposed one was safe (``proposed_safe``)
    and whether any was (``any_safe``), and the seconds until the chosen action's best response
    meets the human's worst plausible motion (``conflict_s``; inf: it stays clear)."""

    proposed: int
    chosen: int
    kinematics: Kinematics
    proposed_safe: bool
    any_safe: bool
    conflict_s: float

    @property
    def overridden(self) -> bool:
        """Whether the safety layer drives something other than the proposed window."""
        return self.chosen != self.proposed or not self.proposed_safe


def plausible_human_paths(human: np.ndarray, steps: int) -> np.ndarray:
    """The human's plausible positions ``[6, steps, 2]`` (x, y, m) at steps t+1..t+steps from its
    present state ``human [6]``: (hold its acceleration for the response time then its speed; keep
    its acceleration, between standstill and the study's speed alert; brake at
    :data:`HUMAN_BRAKING` or harder to a stop) × (continue its lateral motion to the lane centre
    it moves towards, hold its lateral position)."""
    t = DT * np.arange(1, steps + 1)
    x, y, v, vy, a, ay = human
    held = np.minimum(t, RESPONSE_TIME)
    speed_after = max(v + a * RESPONSE_TIME, 0.0)
    holding = x + v * held + 0.5 * a * held ** 2 + speed_after * (t - held)
    speeds = np.clip(v + a * np.concatenate([[0.0], t]), 0.0, max(v, SPEED_ALERT))
    keeping = x + np.cumsum(0.5 * DT * (speeds[:-1] + speeds[1:]))
    braking = max(HUMAN_BRAKING, -a)
    moving = np.minimum(t, max(v, 0.0) / braking)
    stopping = x + max(v, 0.0) * moving - 0.5 * braking * moving ** 2
    lateral = y + vy * t + 0.5 * ay * held ** 2 + ay * RESPONSE_TIME * (t - held)
    centres = np.array([LANE_CENTRE_Y[lane] for lane in LANES])
    lateral = np.clip(lateral, min(y, centres.min()), max(y, centres.max()))  # not beyond the lane centres
    holding_y = np.full(steps, y)
    return np.stack([np.stack([px, py], -1) for px in (holding, keeping, stopping) for py in (lateral, holding_y)])


def robot_paths(robot: np.ndarray, kinematics: Kinematics, braking: Kinematics) -> np.ndarray:
    """The robot's states ``[N_ACTIONS, len(RESPONSES), steps, 6]`` at steps t+1..t+steps
    (:data:`CHECK_HORIZON`) from its present state ``robot [6]``: each action of ``kinematics``
    for one window (as the window is executed), then each response of :data:`RESPONSES`, steering
    on to the window's lane as ``kinematics`` steers from the window's end (one manoeuvre) and
    moving lengthwise as ``braking`` does (holding the speed, its hardest braking or its hardest
    acceleration)."""
    first = rollout(robot, np.arange(N_ACTIONS)[:, None], kinematics)  # [A, 3, 6]
    end = first[:, -1]
    after = round(CHECK_HORIZON / DT) - STEPS_PER_WINDOW
    targets = np.array([LANE_CENTRE_Y[LANES[a % len(LANES)]] for a in range(N_ACTIONS)])
    lateral = kinematics.steer(end[:, [1, 3, 5]], targets, DT * np.arange(1, after + 1))  # [A, after, 3]
    paths = np.empty((N_ACTIONS, len(RESPONSES), STEPS_PER_WINDOW + after, 6))
    paths[:, :, :STEPS_PER_WINDOW] = first[:, None]
    for r, target in enumerate((0.0, -braking.hardest_braking, max(braking.accelerations))):
        acc = _within_speeds(end[:, 2], applied_accelerations(end[:, 4], np.full((N_ACTIONS, after), target), braking.jerk))
        x, xd = robot_longitudinal(end[:, 0], end[:, 2], acc)
        paths[:, r, STEPS_PER_WINDOW:] = np.stack([x, lateral[..., 0], xd, lateral[..., 1], acc, lateral[..., 2]], -1)
    return paths


def _within_speeds(speed: np.ndarray, accelerations: np.ndarray) -> np.ndarray:
    """``accelerations [C, steps]`` (m/s²) applied from ``speed [C]`` (m/s), cut where the robot's
    Euler-integrated speed would leave 0..``SPEED_ALERT``: it stops rather than reverses, and does
    not speed up past the study's speed alert."""
    out, v = np.array(accelerations, dtype=float), np.clip(speed, 0.0, SPEED_ALERT)
    for k in range(out.shape[1]):
        out[:, k] = np.clip(out[:, k], -v / DT, np.maximum(SPEED_ALERT - v, 0.0) / DT)
        v = v + DT * out[:, k]
    return out


def conflict_times(robot: np.ndarray, human: np.ndarray, apart_x: float, apart_y: float) -> np.ndarray:
    """Seconds from now until each robot path ``robot [..., steps, 6]`` first comes within
    ``apart_x`` lengthwise and ``apart_y`` sideways (m) of each human path ``human [B, steps, 2]``,
    ``[..., B]`` (inf: never)."""
    close = ((np.abs(robot[..., None, :, 0] - human[..., 0]) < apart_x)
             & (np.abs(robot[..., None, :, 1] - human[..., 1]) < apart_y))  # [..., B, steps]
    first = np.argmax(close, axis=-1)
    return np.where(close.any(-1), DT * (first + 1), np.inf)


def action_times(robot: np.ndarray, human: np.ndarray, kinematics: Kinematics, braking: Kinematics) -> np.ndarray:
    """Per action of ``kinematics``, the seconds until its best response (:func:`robot_paths`)
    meets the human's worst plausible motion (:func:`plausible_human_paths`), from both cars'
    present states ``robot [6]``, ``human [6]``, ``[2, N_ACTIONS]``: row 0 within :data:`CLEAR_X`
    and :data:`CLEAR_Y` (inf: the action is safe), row 1 within the collision rule (inf: no
    collision)."""
    paths = robot_paths(robot, kinematics, braking)
    humans = plausible_human_paths(human, paths.shape[2])
    return np.stack([conflict_times(paths, humans, *apart).min(-1).max(-1)
                     for apart in ((CLEAR_X, CLEAR_Y), (COLLISION_DX, COLLISION_DY))])


def predicted_human(human: np.ndarray, seconds: float) -> np.ndarray:
    """The human's state ``[6]`` ``seconds`` from its present state ``human [6]``, holding its
    accelerations (the first of :func:`plausible_human_paths`' motions, without a stop)."""
    x, y, v, vy, a, ay = human
    return np.array([x + v * seconds + 0.5 * a * seconds ** 2, y + vy * seconds + 0.5 * ay * seconds ** 2,
                     v + a * seconds, vy + ay * seconds, a, ay])


def unsafe_next(robot_next: np.ndarray, human: np.ndarray, kinematics: Kinematics, braking: Kinematics) -> np.ndarray:
    """Per action of ``kinematics``, whether the safety layer is expected to reject it as the next
    window ``[N_ACTIONS]`` (bool): not safe (:func:`action_times`) from the robot's state at the
    next window's start ``robot_next [6]`` and the human's, predicted from its present state
    ``human [6]`` by :func:`predicted_human`; all False where none would be safe (the layer's
    least-bad choice is made when the window starts). Responses brake as ``braking``."""
    human_next = predicted_human(human, RESPONSE_TIME)
    unsafe = np.isfinite(_staying_behind(action_times(robot_next, human_next, kinematics, braking), robot_next,
                                         human_next, kinematics)[0])
    return unsafe if not unsafe.all() else np.zeros(N_ACTIONS, dtype=bool)


def safe_action(robot: np.ndarray, human: np.ndarray, proposed: int, kinematics: Kinematics,
                window_costs: np.ndarray | None = None, safety: Kinematics | None = None) -> SafetyDecision:
    """The window the robot executes from both cars' present states ``robot [6]``, ``human [6]``
    instead of the ``proposed`` action index of ``kinematics``: the proposed one if safe; else the
    safe action with the lowest ``window_costs [N_ACTIONS]`` (the last plan's, lower is better;
    None: the proposed lane first, then the nearest acceleration); else, with ``safety`` (a
    kinematics that brakes harder), its safe actions the same way; else the least-bad action of
    either (:func:`_least_bad`). Responses brake as ``safety`` (None: ``kinematics``)."""
    braking = safety or kinematics
    options = [kinematics] + ([safety] if safety is not None and safety != kinematics else [])
    times = np.stack([_staying_behind(action_times(robot, human, k, braking), robot, human, kinematics)
                      for k in options])  # [K, 2, A]
    proposed_safe = bool(np.isinf(times[0, 0, proposed]))
    if proposed_safe:
        return SafetyDecision(proposed, proposed, kinematics, True, True, np.inf)
    order = _preference(proposed, kinematics, window_costs)
    for k, option in enumerate(options):
        safe = [a for a in order if np.isinf(times[k, 0, a])]
        if safe:
            return SafetyDecision(proposed, int(safe[0]), option, False, True, np.inf)
    k, a = _least_bad(times, robot, options)
    return SafetyDecision(proposed, a, options[k], False, False, float(times[k, 0, a]))


def _preference(proposed: int, kinematics: Kinematics, window_costs: np.ndarray | None) -> list[int]:
    """The action indices from most to least preferred: by ``window_costs [N_ACTIONS]`` (lower
    first), or without them the ``proposed`` action's lane first, then the acceleration of
    ``kinematics`` nearest the proposed one."""
    if window_costs is not None:
        return [int(a) for a in np.argsort(window_costs, kind="stable")]
    accelerations = np.asarray(kinematics.accelerations)
    actions = np.arange(N_ACTIONS)
    other_lane = actions % len(LANES) != proposed % len(LANES)
    distance = np.abs(accelerations[acceleration_indices(actions)] - accelerations[acceleration_indices(proposed)])
    return [int(a) for a in np.lexsort((distance, other_lane))]


def _least_bad(times: np.ndarray, robot: np.ndarray, options: list[Kinematics]) -> tuple[int, int]:
    """Where no action is safe: ``(kinematics index, action index)`` of the action that meets the
    human's worst plausible motion latest, by :func:`action_times` ``times [K, 2, N_ACTIONS]``:
    the latest collision first (none at all best), then the latest conflict; ties go to the
    hardest braking in the lane the robot ``robot [6]`` is in."""
    lane = LANES.index(str(lane_of(np.array([robot[1]]))[0]))
    ranked = [(-times[k, 1, a], -times[k, 0, a], a % len(LANES) != lane, option.accelerations[acceleration_indices(a)], k, a)
              for k, option in enumerate(options) for a in range(N_ACTIONS)]
    *_, k, a = min(ranked)
    return k, a


def _staying_behind(times: np.ndarray, robot: np.ndarray, human: np.ndarray, kinematics: Kinematics) -> np.ndarray:
    """``times [2, N_ACTIONS]`` (:func:`action_times`) with every action that leaves the robot's lane
    counted as meeting the human now where the human brakes hard ahead of it
    (:func:`braking_hard_ahead`): behind a car braking hard the response is braking in lane, not
    a swerve into the other lane, which the human (both cars swap lanes) may take next."""
    if not braking_hard_ahead(robot, human, kinematics):
        return times
    lane = LANES.index(str(lane_of(np.array([robot[1]]))[0]))
    times = times.copy()
    times[:, np.arange(N_ACTIONS) % len(LANES) != lane] = 0.0
    return times


def braking_hard_ahead(robot: np.ndarray, human: np.ndarray, kinematics: Kinematics) -> bool:
    """Whether the human, ahead of the robot in the robot's lane (present states ``robot [6]``,
    ``human [6]``), brakes harder than ``kinematics`` can."""
    same_lane = lane_of(np.array([robot[1]]))[0] == lane_of(np.array([human[1]]))[0]
    return bool(same_lane and human[0] > robot[0] and -human[4] > kinematics.hardest_braking)
