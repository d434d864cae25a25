"""The paper's receding-horizon robot policy (paper §II-B and §V-C), as an agent of the world
(:class:`~trafficweaving.sim.world.Agent`).

The robot holds its lane at constant speed for the first 8 steps, then plans every 3 steps
(0.3 s). Each plan's window 0 is fixed: it is the window already being executed, chosen by the
previous plan (the hold action for the first plan); the chosen sequence's window 1 is executed
next and becomes the next plan's fixed window. The robot acts through accelerations, which the
world integrates (trapezoid rule), so every plan starts from the robot's true state.
:class:`NonBlockingMPCPolicy` is the same policy for real time: its plans run in a background
thread and a late plan never holds up the simulation.
"""

from __future__ import annotations

import time
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import replace

import numpy as np
import torch

from .. import validate
from ..errors import InputError
from ..scenario import LANE_CENTRE_Y, LANES, STATE_NAMES, lane_of
from .candidates import STEPS_PER_WINDOW, Action, rollout
from .costs import Cost, PaperCost
from .planner import Budget, Plan, Planner, check_cost, example_history, plan_options
from .safety import SafetyDecision, braking_hard_ahead, safe_action
from .styles import DrivingStyle

HOLD_STEPS = 8
"""Steps the robot holds its lane at constant speed before its first plan."""
ACCELERATION_COLUMNS = [STATE_NAMES.index("xdd"), STATE_NAMES.index("ydd")]
"""Where a state keeps the accelerations ``[xdd, ydd]`` an agent acts with."""


class MPCPolicy:
    """Drives the robot car of one episode (``m = 1``): :meth:`reset`, then :meth:`act` every step.

    ``cost`` defaults to :class:`PaperCost` towards the lane the robot did not start in;
    ``deadline`` (s) gives each plan that many seconds (:meth:`~.planner.Planner.plan`);
    ``budget`` sets the sample counts otherwise (None: the planner's); ``hold_steps``: steps held
    before the first plan.
    :attr:`plans` keeps every plan made since :meth:`reset` and :attr:`latencies` the seconds each
    took. Bad arguments raise :class:`~trafficweaving.errors.InputError`.
    """

    def __init__(self, planner: Planner, cost: Cost | None = None, budget: Budget | None = None,
                 deadline: float | None = None, hold_steps: int = HOLD_STEPS):
        self.planner = planner
        self.fixed_cost = None if cost is None else check_cost(cost)
        self.budget, self.deadline = plan_options(budget, deadline)
        self.hold_steps = validate.integer("hold_steps", hold_steps, 0)
        self.me: int | None = None  # the robot's car index; None before reset
        self.queue: list[np.ndarray] = []  # planned robot states [6] of the steps to come
        self.plans: list[Plan] = []
        self.plan_steps: list[int] = []  # the present step t of every plan
        self.latencies: list[float] = []
        self.fallen_back: DrivingStyle | None = None  # the fallback this episode plans in (None: the planner's style)
        self.safety_log: list[tuple[int, SafetyDecision]] = []  # (step, decision) of every window the safety layer changed
        self.warmed_up = False  # whether the planner has made its warm-up plan (Planner.warm_up)

    def reset(self, rng: np.random.Generator, start: np.ndarray, me: int) -> None:
        """Start an episode from ``start [1, 2, 6]`` (both cars' states ``[x, y, xd, yd, xdd,
        ydd]``, m, m/s, m/s², finite) with the robot as car ``me`` (0 or 1). The planner's random
        generator is reseeded from ``rng`` (a NumPy Generator), so the same seed gives the same
        episode."""
        if not isinstance(rng, np.random.Generator):
            raise InputError(f"rng must be a numpy.random.Generator (np.random.default_rng(seed)), got {rng!r}")
        start = validate.finite_array("start", start, (1, 2, len(STATE_NAMES)), f"[1, 2, {len(STATE_NAMES)}]")
        self.me = validate.integer("me", me, 0, 1)
        robot = start[0, self.me]
        lane = lane_of(np.array([robot[1]]))[0]
        goal = next(other for other in LANES if other != lane)
        self.cost = self.fixed_cost or PaperCost(goal_y=LANE_CENTRE_Y[goal])
        self.hold = Action.of(0.0, lane).index
        windows = -(-self.hold_steps // STEPS_PER_WINDOW)
        self.queue = list(rollout(robot, np.full((1, windows), self.hold), self.planner.kinematics)[0, : self.hold_steps])
        self.next_fixed = self.hold
        self.plans, self.plan_steps, self.latencies, self.safety_log = [], [], [], []
        self.fallen_back = None
        if not self.warmed_up:  # compiled precisions compile now, not in the first plan
            self.planner.warm_up(example_history(), self.hold, self.cost,
                                 budget=self.budget, deadline=self.deadline)
            self.warmed_up = True
        self.planner.generator.manual_seed(int(rng.integers(2**63)))

    def act(self, history: np.ndarray) -> np.ndarray:
        """The robot's accelerations ``[1, 2]`` (``[xdd, ydd]``, m/s²) at step t+1 given both cars'
        states ``history [1, 2, t+1, 6]`` (finite; called once per step after :meth:`reset`, at
        least ``MIN_HISTORY`` steps at a plan).

        They are the planned robot state's at t+1: the hold's, then those of the window being
        executed, rolled out by the plan made at the window's start from the robot's true state
        (the plan's robot states; the last step of a window stores the next window's acceleration,
        applied from it on)."""
        if self.me is None:
            raise RuntimeError("MPCPolicy.act needs an episode: call reset(rng, start, me) first")
        history = validate.finite_array("history", history, (1, 2, None, len(STATE_NAMES)),
                                        f"[1, 2, t+1, {len(STATE_NAMES)}]")
        if not self.queue:
            robot_first = history[0, [self.me, 1 - self.me]].swapaxes(0, 1)  # [t+1, 2, 6]: robot, human
            clock = time.perf_counter()
            costs = self.plans[-1].window_costs if self.plans else None
            self.next_fixed, style = self.check_window(robot_first, self.next_fixed,
                                                       self.plan_style(robot_first, self.next_fixed), costs)
            plan = self.planner.plan(robot_first, self.next_fixed, self.cost, budget=self.budget, deadline=self.deadline,
                                     style=style)
            self.latencies.append(time.perf_counter() - clock)
            self.plans.append(plan)
            self.plan_steps.append(history.shape[2] - 1)
            self.next_fixed = int(plan.actions[1])
            self.queue = list(plan.robot[:STEPS_PER_WINDOW])
        return self.queue.pop(0)[None, ACCELERATION_COLUMNS]

    def check_window(self, history: np.ndarray, proposed: int, style: DrivingStyle, window_costs: np.ndarray | None
                     ) -> tuple[int, DrivingStyle]:
        """The window about to be executed and the style to plan it in: the ``proposed`` action in
        ``style`` where the style has no safety layer, else the safety layer's decision
        (:func:`~.safety.safe_action`) from both cars' states ``history [t+1, 2, 6]`` (robot,
        human), preferring actions by ``window_costs [N_ACTIONS]`` (None: by closeness), planned in
        the ``safety_fallback`` where it brakes as that style does, and where the human ahead in the
        robot's lane brakes harder than ``style`` can and the fallback brakes harder
        (:func:`~.safety.braking_hard_ahead`): a plan that can only brake gently behind a car braking
        hard sees every in-lane future collide and turns back into the lane the human may take next.
        Every changed window is logged in :attr:`safety_log`."""
        own = self.planner.style
        if not own.safety_layer:
            return proposed, style
        safety = own.safety_fallback.kinematics if own.safety_fallback is not None else None
        decision = safe_action(history[-1, 0], history[-1, 1], proposed, style.kinematics, window_costs, safety)
        if decision.overridden:
            self.safety_log.append((len(history) - 1, decision))
        fallback = own.safety_fallback
        if decision.kinematics is not style.kinematics or (
                fallback is not None and fallback.kinematics.hardest_braking > style.kinematics.hardest_braking
                and braking_hard_ahead(history[-1, 0], history[-1, 1], style.kinematics)):
            return decision.chosen, fallback
        return decision.chosen, style

    def plan_style(self, history: np.ndarray, first_action: int) -> DrivingStyle:
        """The driving style of the plan from both cars' states ``history [t+1, 2, 6]`` (robot,
        human) with window 0 fixed to ``first_action``: the planner's, or a fallback from the first
        plan that needs it to the end of the episode (:meth:`~.styles.DrivingStyle.fallback_for`;
        :attr:`fallen_back`)."""
        own = self.planner.style
        if self.fallen_back is None:  # once on the fallback, to the end
            self.fallen_back = own.fallback_for(history, first_action, getattr(self.cost, "goal_y", None))
        return self.fallen_back or own


class NonBlockingMPCPolicy(MPCPolicy):
    """:class:`MPCPolicy` for real-time driving: plans run in a background thread, so :meth:`act`
    never waits for the planner (the simulation keeps its pace whatever a plan costs).

    At the start ``t`` of every window the robot starts executing that window's action at once
    (rolled out from its true state, as the blocking policy does) and hands the plan with that
    window fixed as window 0 to the planner thread; the plan's window 1 is due when the next
    window starts, at ``t + 3`` (0.3 s later in real time). If the plan is done by then, its
    window 1 is executed; if it is late, the robot keeps executing its current plan (the previous
    plan's next window; once that plan's windows run out, 0 m/s² in its last window's lane), the
    late plan is discarded when it arrives and the next plan starts at the next window after it.
    :attr:`late_steps` lists the window starts whose plan was late.

    The one difference from :class:`MPCPolicy` in what the robot executes when every plan is in
    time: the acceleration stored at a window's last step is the window's own (the next window is
    not chosen yet when it is needed), where the blocking policy stores the next window's already;
    with the world's trapezoid rule the next window's acceleration takes effect half a step later.

    :attr:`plans`, :attr:`plan_steps` hold the plans executed (by the step each was made at),
    :attr:`latencies` the seconds of every finished plan (executed or late). ``threads``: the
    planner thread's torch threads (None: as many as the thread making the policy has;
    ``torch.set_num_threads`` is per thread). Call :meth:`close` to stop the planner thread (it
    waits for a running plan).
    """

    def __init__(self, planner: Planner, cost: Cost | None = None, budget: Budget | None = None,
                 deadline: float | None = None, hold_steps: int = HOLD_STEPS, threads: int | None = None):
        super().__init__(planner, cost, budget, deadline, hold_steps)
        threads = torch.get_num_threads() if threads is None else validate.thread_count("threads", threads)
        self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="planner",
                                            initializer=torch.set_num_threads, initargs=(threads,))
        self._pending: tuple[int, Future] | None = None  # (step it was made at, the plan's future)
        self.upcoming: list[int] = []  # the current plan's actions for the windows after the executing one
        self.kinematics = planner.kinematics  # how the current plan moves the robot (its style's kinematics)
        self.window = 0  # the action index of the window being executed
        self.late_steps: list[int] = []

    def reset(self, rng: np.random.Generator, start: np.ndarray, me: int) -> None:
        """As :meth:`MPCPolicy.reset`; a plan still running from a previous episode is waited for
        first (it draws from the generator being reseeded) and discarded."""
        self._drain()
        super().reset(rng, start, me)
        self.upcoming, self.window, self.late_steps, self.kinematics = [], self.hold, [], self.planner.kinematics

    def act(self, history: np.ndarray) -> np.ndarray:
        """As :meth:`MPCPolicy.act` (``history [1, 2, t+1, 6]`` -> ``[1, 2]``), without waiting for
        the planner: a plan is collected only if it is already done."""
        if self.me is None:
            raise RuntimeError("NonBlockingMPCPolicy.act needs an episode: call reset(rng, start, me) first")
        history = validate.finite_array("history", history, (1, 2, None, len(STATE_NAMES)),
                                        f"[1, 2, t+1, {len(STATE_NAMES)}]")
        if not self.queue:  # a window starts at step t
            t = history.shape[2] - 1
            plan = self._collect(t)
            if plan is not None:
                self.upcoming, self.kinematics = [int(a) for a in plan.actions[1:]], plan.style.kinematics
            self.window = self.upcoming.pop(0) if self.upcoming else Action.of(0.0, Action(self.window).lane).index
            robot_first = history[0, [self.me, 1 - self.me]].swapaxes(0, 1)  # [t+1, 2, 6]: a copy
            executing = replace(self.plan_style(robot_first, self.window), kinematics=self.kinematics)
            window, style = self.check_window(robot_first, self.window, executing,
                                              plan.window_costs if plan is not None else None)
            if (window, style.kinematics) != (self.window, self.kinematics):  # the safety layer changed it
                self.window, self.kinematics, self.upcoming = window, style.kinematics, []
            self.queue = list(rollout(robot_first[-1, 0], np.array([[self.window]]), self.kinematics)[0])
            if self._pending is None:
                style = self.plan_style(robot_first, self.window) if style is executing else style
                self._pending = (t, self._executor.submit(self._plan, robot_first, self.window, style))
        return self.queue.pop(0)[None, ACCELERATION_COLUMNS]

    def warm_up(self, history: np.ndarray, plans: int = 3) -> None:
        """Make ``plans`` plans from ``history [t+1, 2, 6]`` (robot, human) in the planner thread
        and wait for them, so that a first real plan pays no lazy initialisation and the planner
        has measured the planner thread's speed for its deadline. Nothing else is kept, and
        :meth:`reset` does not warm the planner up again (:meth:`~.planner.Planner.warm_up`)."""
        cost = self.fixed_cost or PaperCost(goal_y=LANE_CENTRE_Y[LANES[0]])
        for _ in range(validate.integer("plans", plans, 0)):
            self._executor.submit(self.planner.plan, history, 0, cost, budget=self.budget,
                                  deadline=self.deadline).result()
        self.warmed_up = self.warmed_up or plans > 0

    @property
    def planning(self) -> bool:
        """Whether a plan is running in the planner thread."""
        return self._pending is not None and not self._pending[1].done()

    def _plan(self, robot_first: np.ndarray, first_action: int, style: DrivingStyle) -> tuple[Plan, float]:
        """One plan in ``style`` (runs in the planner thread) and the seconds it took."""
        clock = time.perf_counter()
        plan = self.planner.plan(robot_first, first_action, self.cost, budget=self.budget, deadline=self.deadline,
                                 style=style)
        return plan, time.perf_counter() - clock

    def _collect(self, t: int) -> Plan | None:
        """The plan made for the window starting at ``t`` (at ``t - 3``) if it is done; a finished
        plan made earlier is late and discarded, a running one stays pending. A plan that raised
        re-raises here."""
        if self._pending is None:
            return None
        made, future = self._pending
        if not future.done():
            self.late_steps.append(t)
            return None
        self._pending = None
        plan, seconds = future.result()
        self.latencies.append(seconds)
        if made + STEPS_PER_WINDOW != t:
            return None  # its window 1 has already been replaced: late
        self.plans.append(plan)
        self.plan_steps.append(made)
        return plan

    def _drain(self) -> None:
        """Wait for a pending plan and drop it."""
        if self._pending is not None:
            _, future = self._pending
            self._pending = None
            future.exception()  # waits; a failed plan of a finished episode does not concern the next

    def close(self) -> None:
        """Stop the planner thread (after a running plan); the policy cannot plan afterwards."""
        self._drain()
        self._executor.shutdown(wait=True)
