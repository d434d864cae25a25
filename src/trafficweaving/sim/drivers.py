"""Stochastic, interactive simulated human drivers for the traffic-weaving scenario.

A :class:`DriverAgents` object drives a batch of ``m`` cars, one per trial, each facing one other
car (another simulated driver, or later a robot). Each step, every driver

1. **perceives** the other car's position and speed *relative to its own* as they were
   ``reaction_steps`` ago (a personal reaction delay), and the other's acceleration;
2. **forms and revises an intent** to pass in front or behind. Its utility for going in front is
   ``w_gap * (gap + lookahead * Δv) + lane_bias[lane] + assertiveness + noise + yield_weight * signal``,
   where ``signal`` reads the other's behaviour (accelerating = claiming the gap, braking =
   yielding). A hysteresis keeps the intent until the utility clearly flips, so when both claim
   the gap the one falling behind backs off while the other escalates to full throttle;
3. **controls longitudinal acceleration** through pedals: a personal comfort throttle level (a
   burst of full throttle when the other car fights for the same gap or while cutting into it),
   brake pulses (sharp when the situation is urgent or the car swerves into its lane change),
   coasting (aerodynamic drag only) and cruising back to a preferred speed. The gap stays
   contested, and the driver keeps pressing, until it is open and, during the first part of its
   own lane change, while it has little room beyond its margin (``PRESS_ROOM``);
4. **changes lane** in two phases, lopsided as real lane changes are (slow start, quick finish):
   past its personal earliest ``x`` it drifts towards the divider within its own lane
   (``CREEP_SPEED`` up to ``CREEP_MAX``); once the gap allows for its intent (a personal margin
   that shrinks as the cutoff nears) it completes the change from there along a minimum-jerk
   lateral profile of personal duration (3.3–5.3 s, hurried near the cutoff), tracked by a
   damped lateral controller.

Pedal and steering are **intermittent**, as real drivers' are: each control is *held* (its
acceleration stays exactly the same; ``xdd`` then changes only by the slowly varying drag, well
under 0.01 m/s² per step) between discrete adjustments. A driver adjusts a control
when its error (wanted minus held acceleration) exceeds a personal threshold or when a personal
random hold time (exponential, personal mean) runs out; an adjustment moves the control part of
the way to the wanted value (a personal pedal lag, a steering lag) with a motor error. Releasing
a pressed pedal is exact; a coasting driver's later unprompted adjustments are, some of the time
(``COAST_TOUCH_P``), light touches of a pedal around zero (``COAST_TOUCH_SD``), so coasting is
not one long hold. Lane-keeping wobble comes from the steering adjustment errors, so real
drivers' hold fractions and hold-run lengths come out (``docs/calibration.md``).

Personal style (persistent per driver) comes from :class:`DriverStyles`; the population
distribution and the decision weights are :class:`DriverModel` fields, calibrated so that the
human–human trial generator reproduces the paper's Table I and the marginal behaviour of the
authors' real human-in-the-loop drivers (see ``docs/calibration.md``).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from scipy.special import ndtri

from ..scenario import CAR_LENGTH, CUTOFF_X, DT, LANE_CENTRE_Y, SPEED_ALERT

FULL_THROTTLE = 4.5
"""Largest longitudinal acceleration the simulator's cars reach (m/s², seen in real recordings)."""
HARD_BRAKE = 8.4
"""Largest deceleration seen in real recordings, m/s²."""
MAX_LATERAL_ACCEL = 4.0
"""Largest lateral acceleration a driver steers for (m/s²); real drivers stay within ±3."""
MIN_BRAKING_SPEED = 20.0
"""Highway drivers yielding the gap start no brake pulse below this speed (real: 5 % of steps under
25 m/s), m/s; without it two drivers who both yield can brake each other to a crawl."""
DRAG_AT_28 = 0.34
"""Deceleration when coasting at 28 m/s (real recordings: -0.33 to -0.34 m/s²); grows with v²."""


def coasting_acceleration(speed: np.ndarray) -> np.ndarray:
    """Acceleration of a car with both pedals released (m/s²) at ``speed`` (m/s), any shape."""
    return -DRAG_AT_28 * (np.asarray(speed) / 28.0) ** 2


@dataclass(frozen=True)
class DriverModel:
    """Population distribution of driving styles and the shared decision weights.

    Units: m, s, m/s, m/s². ``*_range`` fields are uniform ranges ``(low, high)`` of a personal
    trait; ``*_sd`` fields are standard deviations.
    """

    # decision (calibrated against Table I)
    w_gap: float = 0.207
    """Weight of the projected gap in the front/behind utility, 1/m."""
    lookahead: float = 3.674
    """Horizon over which a driver projects the relative speed into a gap, s."""
    lane_bias_right: float = 0.547
    """Extra utility of going in front for the car starting in the right lane (it moves into the
    faster, left lane); Table I shows the right-lane car in front in 62 % of equal-speed trials."""
    assertiveness_sd: float = 0.5
    """Spread of the persistent personal assertiveness across drivers (utility units)."""
    trial_noise_sd: float = 1.433
    """Spread of the per-trial mood/initial read of the situation (utility units)."""
    revision_noise_sd: float = 0.25
    """Step-to-step wander of the perceived utility (Ornstein–Uhlenbeck, utility units)."""
    yield_weight: float = 1.0
    """How strongly the other's acceleration (claim) or braking (yield) moves the utility."""
    impatience_range: tuple[float, float] = (0.4, 1.6)
    """Rate at which an unresolved stand-off (my intent not getting me clear) pushes a driver to
    switch intent, utility units per s; personal, so the less patient driver gives way first."""
    hysteresis: float = 0.6
    """Utility margin needed to change an existing intent."""

    # personal style ranges
    reaction_steps_range: tuple[int, int] = (2, 5)
    throttle_range: tuple[float, float] = (2.5, 4.5)
    brake_range: tuple[float, float] = (2.5, 7.5)
    preferred_speed_range: tuple[float, float] = (27.5, 31.5)
    front_margin_range: tuple[float, float] = (1.0, 7.0)
    """Clearance beyond a car length a driver wants before cutting in, m."""
    lane_change_duration_range: tuple[float, float] = (3.3, 5.3)
    lane_change_earliest_x_range: tuple[float, float] = (-110.0, -80.0)
    """Personal earliest ``x`` from which a driver drifts towards the divider and starts its lane change
    once the gap allows, m."""
    pedal_lag_range: tuple[float, float] = (0.03, 0.10)
    """Time constant of a pedal adjustment (first-order lag while adjusting), s."""
    pedal_threshold_range: tuple[float, float] = (0.1, 0.4)
    """Pedal error (wanted minus held acceleration) beyond which a driver adjusts at once, m/s²."""
    pedal_hold_range: tuple[float, float] = (0.05, 0.3)
    """Mean time a driver holds the pedal still while its error stays below threshold, s."""
    steer_threshold_range: tuple[float, float] = (0.05, 0.25)
    """Steering error (wanted minus held lateral acceleration) beyond which a driver adjusts at
    once, m/s²."""
    steer_hold_range: tuple[float, float] = (0.2, 0.8)
    """Mean time a driver holds the steering still while its error stays below threshold, s."""
    cruise_throttle_range: tuple[float, float] = (0.8, 2.6)
    """Gentle throttle a driver uses to regain its preferred speed, m/s²."""
    lane_offset_sd: float = 0.25
    """Spread of where in the target lane a driver ends up, m (kept off the road edges)."""
    steer_noise_sd: float = 0.12
    """Spread of the motor error of a steering adjustment (lane-keeping wobble), m/s²."""
    pedal_noise_sd: float = 0.1
    """Spread of the motor error of a pedal adjustment while a pedal is pressed, m/s²."""

    def as_dict(self) -> dict:
        return asdict(self)


@dataclass
class DriverStyles:
    """Persistent personal traits of ``k`` drivers, each an array ``[k]`` (units as in
    :class:`DriverModel`)."""

    assertiveness: np.ndarray
    reaction_steps: np.ndarray
    throttle: np.ndarray
    brake: np.ndarray
    preferred_speed: np.ndarray
    front_margin: np.ndarray
    lane_change_duration: np.ndarray
    lane_change_earliest_x: np.ndarray
    pedal_lag: np.ndarray
    pedal_threshold: np.ndarray
    pedal_hold: np.ndarray
    steer_threshold: np.ndarray
    steer_hold: np.ndarray
    cruise_throttle: np.ndarray
    impatience: np.ndarray

    @staticmethod
    def sample(model: DriverModel, k: int, rng: np.random.Generator) -> "DriverStyles":
        """Draw ``k`` drivers from the population ``model`` by Latin hypercube sampling: each trait's
        ``k`` values fall one in each of ``k`` equal-probability strata, in random order, so a small
        group (the study's 38 drivers) spans the population without sample-mean noise."""
        uniform = lambda r: r[0] + (r[1] - r[0]) * stratified_uniform(k, rng)  # noqa: E731
        low, high = model.reaction_steps_range
        return DriverStyles(
            assertiveness=model.assertiveness_sd * ndtri(stratified_uniform(k, rng)),
            reaction_steps=low + np.floor((high - low + 1) * stratified_uniform(k, rng)).astype(int),
            throttle=uniform(model.throttle_range),
            brake=uniform(model.brake_range),
            preferred_speed=uniform(model.preferred_speed_range),
            front_margin=uniform(model.front_margin_range),
            lane_change_duration=uniform(model.lane_change_duration_range),
            lane_change_earliest_x=uniform(model.lane_change_earliest_x_range),
            pedal_lag=uniform(model.pedal_lag_range),
            pedal_threshold=uniform(model.pedal_threshold_range),
            pedal_hold=uniform(model.pedal_hold_range),
            steer_threshold=uniform(model.steer_threshold_range),
            steer_hold=uniform(model.steer_hold_range),
            cruise_throttle=uniform(model.cruise_throttle_range),
            impatience=uniform(model.impatience_range),
        )

    def take(self, index: np.ndarray) -> "DriverStyles":
        """The styles of drivers ``index`` (``[m]`` integer array), e.g. one per trial."""
        return DriverStyles(**{name: value[index] for name, value in vars(self).items()})


def stratified_uniform(k: int, rng: np.random.Generator) -> np.ndarray:
    """``k`` draws on (0, 1), one in each stratum ``[i/k, (i+1)/k)``, in random order (``[k]``)."""
    return (rng.permutation(k) + rng.random(k)) / k


class DriverAgents:
    """A batch of ``m`` simulated drivers, each in its own trial against one other car.

    ``styles``: one driver per car (:meth:`DriverStyles.take`); ``start_states``: ``[m, 6]``
    initial states (``STATE_NAMES``); ``start_lanes``: ``[m]`` ``"left"``/``"right"``. Call
    :meth:`act` once per step with both cars' current states; it returns this driver's
    accelerations for the next step, ``[m, 2]`` (``xdd, ydd``). ``mood``: optional ``[m]`` standard
    normal draws for each trial's mood (drawn here when not given).
    """

    HISTORY = 8  # steps of relative observations kept for the reaction delay
    LATERAL_LAG = 0.15  # time constant of a steering adjustment (first-order lag while adjusting), s
    LATERAL_GAINS = (1.5, 2.4)  # lane tracking stiffness (1/s²) and damping (1/s)
    PRESS_ROOM = 15.0  # a driver keeps pressing into its lane change until it has this much room beyond its margin, m
    COAST_TOUCH_SD = 0.08  # spread of the light pedal touches of a coasting driver, m/s²
    COAST_TOUCH_P = 0.4  # chance that an unprompted adjustment of a coasting driver touches the pedal
    CREEP_SPEED = 0.35  # lateral speed of the drift towards the divider before the lane change, m/s
    CREEP_MAX = 0.9  # how far a driver drifts towards the divider within its own lane, m

    def __init__(self, model: DriverModel, styles: DriverStyles, start_states: np.ndarray,
                 start_lanes: np.ndarray, rng: np.random.Generator, mood: np.ndarray | None = None):
        m = len(start_states)
        self.model, self.styles, self.rng = model, styles, rng
        to_left = start_lanes == "right"
        offset = np.clip(rng.normal(0.0, model.lane_offset_sd, m), -0.5, 0.5)
        # drivers heading for the left lane stay clear of the left road edge (y = -1)
        offset = np.where(to_left, np.minimum(offset, 0.25), offset)
        self.target_y = np.where(to_left, LANE_CENTRE_Y["left"], LANE_CENTRE_Y["right"]) + offset
        self.start_y = np.asarray(start_states[:, 1], dtype=float)
        self.lane_bias = np.where(to_left, model.lane_bias_right, 0.0)
        self.trial_noise = model.trial_noise_sd * (rng.standard_normal(m) if mood is None else mood)
        self.wander = np.zeros(m)
        self.pressure = np.zeros(m)  # accumulated impatience of an unresolved stand-off
        self.front = np.zeros(m, dtype=bool)  # intent: True = pass in front
        self.committed = np.zeros(m, dtype=bool)  # lane change started; intent locked
        self.lc_t = np.zeros(m)  # time since the lane change started, s
        self.lc_duration = styles.lane_change_duration.copy()  # of the lane change under way, s
        self.lc_y0 = self.start_y.copy()
        self.creep = np.zeros(m)  # drift towards the divider before the lane change, m (>= 0)
        self.toward = np.sign(self.target_y - self.start_y)  # +1: the target lane lies at larger y
        self.pedal = np.zeros(m)  # held pedal acceleration; real drivers mostly coast at the start
        self.pedal_hold_left = np.zeros(m)  # time until the next unprompted pedal adjustment, s
        self.brake_left = np.zeros(m)  # remaining time of the current brake pulse, s
        self.brake_level = np.zeros(m)
        self.ydd = np.zeros(m)  # held lateral acceleration
        self.steer_hold_left = np.zeros(m)  # time until the next unprompted steering adjustment, s
        self.obs = np.zeros((self.HISTORY, m, 3))  # ring buffer of (gap, Δv, other's xdd)
        self.steps = 0

    def _perceive(self, own: np.ndarray, other: np.ndarray) -> tuple[np.ndarray, ...]:
        """Store this step's relative observation and return the delayed one: gap (m, positive when
        ahead), Δv (m/s, positive when faster) and the other's acceleration (m/s²), each ``[m]``."""
        now = np.stack([own[:, 0] - other[:, 0], own[:, 2] - other[:, 2], other[:, 4]], axis=1)
        if self.steps == 0:
            self.obs[:] = now
        self.obs = np.roll(self.obs, 1, axis=0)
        self.obs[0] = now
        delay = np.minimum(self.styles.reaction_steps, self.HISTORY - 1)
        seen = self.obs[delay, np.arange(len(own))]
        return seen[:, 0], seen[:, 1], seen[:, 2]

    def _update_intent(self, gap, dv, other_acc, stand_off, urgency) -> None:
        """Form (first step) or revise the front/behind intent; committed drivers keep theirs."""
        m, model = len(gap), self.model
        decay = np.exp(-DT)  # Ornstein–Uhlenbeck wander with a 1 s time constant
        self.wander = self.wander * decay + model.revision_noise_sd * np.sqrt(1 - decay**2) * self.rng.standard_normal(m)
        rate = self.styles.impatience * (1.0 + 2.0 * urgency)
        self.pressure = np.where(stand_off, self.pressure + rate * DT, self.pressure * 0.8)
        signal = -np.tanh(other_acc / 2.0)  # other accelerating: it claims the gap; braking: it yields
        utility = (model.w_gap * (gap + model.lookahead * dv) + self.lane_bias + self.styles.assertiveness
                   + self.trial_noise + self.wander + model.yield_weight * signal)
        if self.steps == 0:
            self.front = utility > 0
            return
        utility = utility + np.where(self.front, -self.pressure, self.pressure)
        flip = np.where(self.front, utility < -model.hysteresis, utility > model.hysteresis) & ~self.committed
        self.front = self.front ^ flip
        self.pressure = np.where(flip, 0.0, self.pressure)

    def act(self, own: np.ndarray, other: np.ndarray) -> np.ndarray:
        """Accelerations ``[m, 2]`` (``xdd, ydd``, m/s²) for the next step, given both cars' current
        states ``own``, ``other`` ``[m, 6]``."""
        gap, dv, other_acc = self._perceive(own, other)
        x = own[:, 0]
        urgency = np.clip((x + 90.0) / 70.0, 0.0, 1.0)  # 0 before x = -90 m, 1 from x = -20 m
        margin, ahead, clear = self._decide(own, gap, dv, other_acc, urgency)
        xdd = self._pedal(own[:, 2], gap, dv, other_acc, urgency, margin, ahead, clear)
        self._steer(own)
        return np.stack([xdd, self.ydd], axis=1)

    def _decide(self, own: np.ndarray, gap: np.ndarray, dv: np.ndarray, other_acc: np.ndarray,
                urgency: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Revise the intent and start the lane change where the gap is open for it; returns the
        personal ``margin`` (m), the gap projected 1.5 s ``ahead`` (m) and whether it is ``clear``
        for the intent, each ``[m]``."""
        st = self.styles
        x, v = own[:, 0], own[:, 2]
        # ---- is the gap open for my intent? (relative position projected 1.5 s ahead)
        margin = CAR_LENGTH + st.front_margin * (1.0 - 0.8 * urgency)
        ahead = gap + 1.5 * dv
        stand_off = ~self.committed & np.where(self.front, (ahead < margin) & (dv < 0.5),
                                               (ahead > -margin) & (dv > -0.5))
        self._update_intent(gap, dv, other_acc, stand_off, urgency)
        self.steps += 1
        clear = np.where(self.front, ahead > margin, ahead < -margin)
        start_change = ~self.committed & clear & ((x > st.lane_change_earliest_x) | (urgency > 0))
        self.lc_y0 = np.where(start_change, own[:, 1], self.lc_y0)
        # a late lane change is hurried so that the car is across the divider before the cutoff
        hurried = np.minimum(st.lane_change_duration, np.maximum(2.5, 1.8 * (CUTOFF_X - x) / np.maximum(v, 1.0)))
        self.lc_duration = np.where(start_change, hurried, self.lc_duration)
        self.lc_t = np.where(start_change, 0.0, self.lc_t)
        self.committed |= start_change
        return margin, ahead, clear

    def _pedal(self, v: np.ndarray, gap: np.ndarray, dv: np.ndarray, other_acc: np.ndarray, urgency: np.ndarray,
               margin: np.ndarray, ahead: np.ndarray, clear: np.ndarray) -> np.ndarray:
        """The longitudinal pedal command, held or adjusted; returns ``xdd`` ``[m]`` (m/s²) at speed
        ``v`` ``[m]`` (m/s), with the rest as :meth:`_decide` returns them."""
        st, model, m = self.styles, self.model, len(v)
        below_alert = v < SPEED_ALERT - 1.0
        # cruising: coast, with gentle throttle while well below the preferred speed
        cruise = np.where(below_alert & (v < st.preferred_speed - 1.0), st.cruise_throttle, 0.0)
        claims = (other_acc > 0.8) & (np.abs(gap) < 12.0)  # the other is fighting for the same gap
        # the gap is contested until it is open, and while the car swerves into it with little room
        room = np.abs(ahead) - margin  # m
        swerving = self.committed & (self.lc_t < 0.8 * self.lc_duration) & (room < self.PRESS_ROOM)
        contesting = ~clear | swerving
        # contesting the gap, or cutting in with little room: a burst of full throttle
        push = np.where(claims | swerving, FULL_THROTTLE, st.throttle)
        push = np.where(below_alert, push, 0.0)
        # behind: a brake pulse while the other car's lead, projected over 1.5 s, is still short
        missing = gap + 1.5 * dv + margin
        self.brake_left = np.maximum(self.brake_left - DT, 0.0)
        short = (missing > 0) | ((missing > -self.PRESS_ROOM) & (dv > -1.0))  # into the lane change: until slower
        new_pulse = (~self.front & contesting & short & (dv > -2.5) & (v > MIN_BRAKING_SPEED) & (self.brake_left <= 0)
                     & (self.rng.random(m) < 0.3))
        hard = np.where((urgency > 0.5) | swerving, np.maximum(st.brake, 0.7 * HARD_BRAKE), st.brake)
        self.brake_level = np.where(new_pulse, -hard * self.rng.uniform(0.6, 1.0, m), self.brake_level)
        self.brake_left = np.where(new_pulse, self.rng.uniform(0.3, 0.8, m), self.brake_left)
        braking = self.brake_left > 0

        settled_rear = ~self.front & (clear | self.committed) & (gap > -(CAR_LENGTH + 3.0))
        command = np.select(
            [braking, self.front & contesting, ~self.front & contesting, settled_rear],
            [self.brake_level, push, 0.0, np.minimum(cruise, 0.0)],
            default=cruise,
        )
        adjust = self._adjusting(command - self.pedal, st.pedal_threshold, self.pedal_hold_left, st.pedal_hold)
        lagged = self.pedal + DT / (st.pedal_lag + DT) * (command - self.pedal)
        pressed = lagged + model.pedal_noise_sd * self.rng.standard_normal(m)
        # releasing a pressed pedal is exact (feet off); a coasting driver's later adjustments are
        # light touches of the pedal around zero
        touch = np.where(self.rng.random(m) < self.COAST_TOUCH_P, self.COAST_TOUCH_SD * self.rng.standard_normal(m), self.pedal)
        released = np.where(np.abs(self.pedal) > 2 * self.COAST_TOUCH_SD, 0.0, touch)
        self.pedal = np.where(adjust, np.where(command == 0.0, released, pressed), self.pedal)
        return np.clip(self.pedal + coasting_acceleration(v), -HARD_BRAKE, FULL_THROTTLE)

    def _steer(self, own: np.ndarray) -> None:
        """The lateral control, held or adjusted into :attr:`ydd`: a slow drift towards the divider
        once past the personal earliest x (a lane change's slow start), then a minimum-jerk lane
        change tracked by held steering."""
        st, model, m = self.styles, self.model, len(own)
        x = own[:, 0]
        creeping = ~self.committed & (x > st.lane_change_earliest_x) & (self.creep < self.CREEP_MAX)
        self.creep = np.where(creeping, np.minimum(self.creep + self.CREEP_SPEED * DT, self.CREEP_MAX), self.creep)
        self.lc_t = np.where(self.committed, self.lc_t + DT, 0.0)
        duration = self.lc_duration
        s = np.clip(self.lc_t / duration, 0.0, 1.0)
        dy = np.where(self.committed, self.target_y - self.lc_y0, 0.0)
        y_ref = (np.where(self.committed, self.lc_y0, self.start_y + self.toward * self.creep)
                 + dy * (10 * s**3 - 15 * s**4 + 6 * s**5))
        yd_ref = dy * (30 * s**2 - 60 * s**3 + 30 * s**4) / duration + np.where(creeping, self.toward * self.CREEP_SPEED, 0.0)
        ydd_ref = dy * (60 * s - 180 * s**2 + 120 * s**3) / duration**2
        k_p, k_d = self.LATERAL_GAINS
        wanted = ydd_ref + k_p * (y_ref - own[:, 1]) + k_d * (yd_ref - own[:, 3])
        adjust = self._adjusting(wanted - self.ydd, st.steer_threshold, self.steer_hold_left, st.steer_hold)
        steered = (self.ydd + DT / (self.LATERAL_LAG + DT) * (wanted - self.ydd)
                   + model.steer_noise_sd * self.rng.standard_normal(m))
        self.ydd = np.where(adjust, np.clip(steered, -MAX_LATERAL_ACCEL, MAX_LATERAL_ACCEL), self.ydd)

    def _adjusting(self, error: np.ndarray, threshold: np.ndarray, hold_left: np.ndarray,
                   mean_hold: np.ndarray) -> np.ndarray:
        """Event-triggered correction of one control: which drivers adjust it this step (``[m]`` bool).

        A driver adjusts when its ``error`` (wanted minus held acceleration, m/s²) exceeds its
        personal ``threshold`` (m/s²) or when its hold time runs out; otherwise it keeps exactly the
        previous acceleration. ``hold_left`` (s, ``[m]``) is counted down in place and, for those
        adjusting, redrawn from an exponential distribution of personal mean ``mean_hold`` (s).
        """
        hold_left -= DT
        adjust = (np.abs(error) > threshold) | (hold_left <= 0.0)
        hold_left[adjust] = (mean_hold * self.rng.standard_exponential(len(error)))[adjust]
        return adjust
