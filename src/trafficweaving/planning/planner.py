"""The paper's two-stage exhaustive planner (paper §IV and §V-C), and its deadline.

Stage 1 scores every candidate robot future (:mod:`.candidates`) with a few sampled human
responses each; stage 2 re-scores the best ones with many samples; the best is executed. All
counts are configurable (:class:`Budget`). How the robot drives (kinematics, risk, rules) is its
:class:`~.styles.DrivingStyle`. The human is any :class:`HumanModel` (the CVAE's is
:class:`~trafficweaving.model.predictor.HumanPredictor`).

With a deadline, stage 1 samples every candidate's own human futures where at least two each fit
in :data:`OWN_FUTURES_SHARE` of it, and otherwise screens (:data:`SCREENING_SAMPLES`); after own
futures a :data:`SHORTLIST` gets more samples; stage 2 runs in rounds until the time is spent
(docs/planner.md, Deadline).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np
import torch

from .. import validate
from ..dynamics import future_states
from ..errors import InputError
from ..model.predictor import COMPILED_PRECISIONS
from ..scenario import DT, HORIZON, LANE_CENTRE_Y, STATE_NAMES
from .candidates import N_ACTIONS, N_CANDIDATES, STEPS_PER_WINDOW, WINDOWS, Candidates, Kinematics, robot_candidates
from .costs import Cost
from .safety import UNSAFE_NEXT_COST, unsafe_next
from .styles import DrivingStyle, rule_costs

SCREENING_SAMPLES = 32
"""With a deadline: human futures per window-1 action shared by stage 1's screened candidates."""
OWN_FUTURES_SHARE = 0.4
"""With a deadline: the share of it stage 1 may spend sampling every candidate's own human futures;
where at least two per candidate fit at the measured rate it does, else it screens."""
SHORTLIST = 256
"""With a deadline, where stage 1 sampled own futures: how many of the best get more samples of
their own before the finalists are chosen from them (two or three samples often miss the best)."""
SHORTLIST_SHARE = 1 / 3
"""With a deadline: the share of the time left after stage 1 that the :data:`SHORTLIST` samples
may take (the rest goes to stage 2)."""


def risk_cost(scores: torch.Tensor, risk: float) -> torch.Tensor:
    """Each candidate's cost ``[k]`` from its sampled futures' costs ``scores [n, k]``: the mean of
    the worst ``ceil(risk · n)`` (CVaR; ``risk`` 1: the mean)."""
    if risk >= 1.0:
        return scores.mean(0)
    return torch.topk(scores, max(1, int(np.ceil(risk * scores.shape[0]))), dim=0).values.mean(0)


@runtime_checkable
class HumanModel(Protocol):
    """A model of the human the planner can sample from (the distribution of the human's future
    actions given the history and the robot's future, paper §II-A), in physical units.

    ``prepare`` is called with the ``history [t+1, 2, 6]`` (robot, human states at steps 0..t) and
    the robot futures a stage samples for, ``robot_futures [C, 15, 6]``; ``sample`` then returns
    human accelerations ``[n, len(candidates), 15, 2]`` (m/s², ``[xdd, ydd]`` at steps
    t+1..t+15) for indices ``candidates [k]`` into them (a tensor on :attr:`device`), drawn with
    ``generator``.
    The planner's tensors live on :attr:`device` in :attr:`dtype`.
    """

    device: torch.device
    dtype: torch.dtype

    def prepare(self, history: np.ndarray, robot_futures: np.ndarray) -> None: ...

    def sample(self, candidates: torch.Tensor, n: int, generator: torch.Generator) -> torch.Tensor: ...


@dataclass(frozen=True)
class Budget:
    """Sample counts of the two stages (the paper's, §V-C: 16 per candidate, best 32, 1024 each):
    positive integers, at most :data:`~.candidates.N_CANDIDATES` finalists."""

    first_stage_samples: int = 16
    finalists: int = 32
    second_stage_samples: int = 1024

    def __post_init__(self):
        validate.integer("first_stage_samples", self.first_stage_samples, 1)
        validate.integer("finalists", self.finalists, 1, N_CANDIDATES)
        validate.integer("second_stage_samples", self.second_stage_samples, 1)

    @property
    def futures(self) -> int:
        """Simulated human futures per plan (all :data:`~.candidates.N_CANDIDATES` candidates scored)."""
        return N_CANDIDATES * self.first_stage_samples + self.finalists * self.second_stage_samples


def plan_options(budget: Budget | None, deadline: float | None) -> tuple[Budget | None, float | None]:
    """``budget`` and ``deadline`` (s) of :meth:`Planner.plan`, checked: a :class:`Budget` or
    None, and None or a finite number of seconds > 0."""
    if budget is not None and not isinstance(budget, Budget):
        raise InputError(f"budget must be a Budget(first_stage_samples, finalists, second_stage_samples) or None, got {budget!r}")
    return budget, None if deadline is None else validate.positive_seconds("deadline", deadline)


def check_cost(cost) -> Cost:
    """``cost``, checked to be callable (see :mod:`.costs`)."""
    if not callable(cost):
        raise InputError(f"cost must be a callable (robot [..., 15, 6], human [..., 15, 6]) -> [...], got {cost!r}")
    return cost



@dataclass
class Plan:
    """A planning result. ``actions [5]`` the chosen action sequence (window 0 = the fixed one),
    ``index`` its candidate index, ``robot [15, 6]`` its robot states; diagnostics:
    ``candidates`` (all robot futures), ``first_stage_cost [C]`` (the style's cost: risk over the
    futures plus its rules), ``finalists [k]`` and ``second_stage_cost [k]``, ``human [n, 15, 6]``
    sampled human futures for the chosen candidate, ``futures`` (human futures simulated),
    ``seconds``, the samples per candidate actually used (``first_stage_samples``,
    ``shortlist_samples``: 0 without a shortlist, ``second_stage_samples``), the ``style`` it
    planned in and ``timings`` (s per part)."""

    actions: np.ndarray
    index: int
    robot: np.ndarray
    candidates: Candidates
    first_stage_cost: np.ndarray
    finalists: np.ndarray
    second_stage_cost: np.ndarray
    human: np.ndarray
    futures: int
    seconds: float
    first_stage_samples: int
    shortlist_samples: int
    second_stage_samples: int
    style: DrivingStyle
    timings: dict = field(default_factory=dict)

    @property
    def window_costs(self) -> np.ndarray:
        """Per window-1 action, the lowest first-stage cost of the candidates taking it
        ``[N_ACTIONS]``, the chosen one's -inf: the order in which this plan prefers its next
        window (the safety layer's, :func:`~.safety.safe_action`)."""
        costs = np.full(N_ACTIONS, np.inf)
        np.minimum.at(costs, self.candidates.actions[:, 1], self.first_stage_cost)
        costs[int(self.actions[1])] = -np.inf
        return costs


class Planner:
    """Plans robot action sequences against a :class:`HumanModel`, on its device, drawing its
    random numbers from one generator seeded with ``seed`` (the same seed, model and calls give
    the same plans). ``budget``: the default sample counts of :meth:`plan` (None: the paper's);
    ``style``: how it drives (:class:`~.styles.DrivingStyle`; default: the paper's)."""

    def __init__(self, human_model: HumanModel, budget: Budget | None = Budget(), seed: int = 0,
                 style: DrivingStyle = DrivingStyle()):
        if not isinstance(human_model, HumanModel):
            raise InputError(f"human_model must be a HumanModel (prepare, sample, device, dtype; for a CVAE: "
                             f"HumanPredictor(cvae)), got {type(human_model).__name__}")
        self.human_model = human_model
        if not isinstance(style, DrivingStyle):
            raise InputError(f"style must be a DrivingStyle, got {style!r}")
        self.style = style
        self.budget = plan_options(budget, None)[0] or Budget()
        self.device, self.dtype = torch.device(human_model.device), human_model.dtype
        self.generator = torch.Generator(device=self.device).manual_seed(validate.integer("seed", seed, 0))
        self.rows_per_second: float | None = None  # measured futures sampled and scored per second

    def warm_up(self, history, first_action: int, cost: Cost, budget: Budget | None = None,
                deadline: float | None = None) -> None:
        """Compile before the first plan that counts: where the human model samples with fused,
        compiled decoder steps (precision ``int8`` or ``float32-compiled``, which compile on their
        first call: seconds), one :meth:`plan` with these arguments is made and thrown away; the
        random generator is left as it was and the measured sampling rate forgotten."""
        if getattr(self.human_model, "precision", None) not in COMPILED_PRECISIONS:
            return
        state = self.generator.get_state()
        self.plan(history, first_action, cost, budget=budget, deadline=deadline)
        self.generator.set_state(state)
        self.rows_per_second = None

    @property
    def kinematics(self) -> Kinematics:
        """How the candidates move the robot (the style's; a plan in another style moves as its
        :attr:`Plan.style`)."""
        return self.style.kinematics

    def _situation(self, history, first_action, style: DrivingStyle | None) -> tuple[
            np.ndarray, DrivingStyle, Candidates, torch.Tensor, torch.Tensor]:
        """The checked ``history [t+1, 2, 6]``, the checked ``style`` (None: the planner's), the
        candidates from the history moving as that style with window 0 fixed to the checked
        ``first_action``, their states ``[C, 15, 6]`` and the human's present state ``[6]`` as
        tensors."""
        history = validate.history(history)
        style = self.style if style is None else style
        if not isinstance(style, DrivingStyle):
            raise InputError(f"style must be a DrivingStyle or None, got {style!r}")
        candidates = robot_candidates(history[-1, 0], validate.integer("first_action", first_action, 0, N_ACTIONS - 1),
                                      style.kinematics)
        robot = torch.as_tensor(candidates.states, dtype=self.dtype, device=self.device)
        human_present = torch.as_tensor(history[-1, 1], dtype=self.dtype, device=self.device)
        return history, style, candidates, robot, human_present

    def _rules(self, style: DrivingStyle, candidates: Candidates, history: np.ndarray, cost: Cost) -> torch.Tensor:
        """``style``'s rule costs of each candidate ``[C]`` (:func:`~.styles.rule_costs`) towards the
        goal lane of ``cost`` (its ``goal_y``; none for a cost without one), and where the planner's
        style has a safety layer, :data:`~.safety.UNSAFE_NEXT_COST` for a window 1 the layer is
        expected to reject (:func:`~.safety.unsafe_next`; responses braking as the planner's
        ``safety_fallback``)."""
        rules = rule_costs(style, candidates, history, getattr(cost, "goal_y", None))
        if self.style.safety_layer:
            braking = (self.style.safety_fallback or style).kinematics
            unsafe = unsafe_next(candidates.states[0, STEPS_PER_WINDOW - 1], history[-1, 1], style.kinematics, braking)
            rules = rules + UNSAFE_NEXT_COST * unsafe[candidates.actions[:, 1]]
        return torch.as_tensor(rules, dtype=self.dtype, device=self.device)

    def _sample(self, prepared: torch.Tensor, n: int, human_present: torch.Tensor) -> torch.Tensor:
        """``n`` sampled human futures ``[n, k, 15, 6]`` for the prepared robot futures ``prepared [k]``
        (indices into the last ``prepare``)."""
        actions = self.human_model.sample(prepared, n, self.generator)
        return future_states(human_present, actions.to(self.dtype))

    def _scores(self, prepared: torch.Tensor, robot: torch.Tensor, n: int, human_present: torch.Tensor,
                cost: Cost) -> tuple[torch.Tensor, torch.Tensor]:
        """Costs ``[n, k]`` of ``n`` sampled human futures for each of the robot futures ``robot [k,
        15, 6]`` (prepared as ``prepared [k]``), and those futures; updates the measured rate."""
        start = time.perf_counter()
        human = self._sample(prepared, n, human_present)
        scores = cost(robot.unsqueeze(0), human)
        rate = n * len(prepared) / max(time.perf_counter() - start, 1e-6)
        self.rows_per_second = rate if self.rows_per_second is None else 0.7 * self.rows_per_second + 0.3 * rate
        return scores, human

    def _screen(self, history: np.ndarray, candidates: Candidates, robot: torch.Tensor, human_present: torch.Tensor,
                cost: Cost, risk: float) -> torch.Tensor:
        """Stage 1 with a deadline, screened: costs ``[C]`` (judged with ``risk``, :func:`risk_cost`)
        of every candidate against :data:`SCREENING_SAMPLES` human futures shared by the candidates
        with the same window-1 action, sampled conditioned on the candidate that holds that action
        to the horizon."""
        holding = np.arange(N_ACTIONS) * sum(N_ACTIONS ** w for w in range(WINDOWS - 1))  # [a, a, a, a] (action_sequences)
        self.human_model.prepare(history, candidates.states[holding])
        human = self._sample(torch.arange(N_ACTIONS, device=self.device), SCREENING_SAMPLES, human_present)
        # action_sequences orders the candidates by their window-1 action: [N_ACTIONS, C / N_ACTIONS] groups
        grouped = cost(robot.reshape(N_ACTIONS, -1, *robot.shape[1:]).unsqueeze(0), human.unsqueeze(2))
        return risk_cost(grouped.reshape(len(grouped), -1), risk)

    def _own_futures(self, history: np.ndarray, candidates: Candidates, robot: torch.Tensor, n1: int,
                     human_present: torch.Tensor, cost: Cost) -> torch.Tensor:
        """Stage 1 as in the paper: the costs ``[n1, C]`` of ``n1`` human futures of every candidate's own."""
        self.human_model.prepare(history, candidates.states)
        return self._scores(torch.arange(len(candidates), device=self.device), robot, n1, human_present, cost)[0]

    def _second_stage(self, prepared: torch.Tensor, robot: torch.Tensor, human_present: torch.Tensor, cost: Cost,
                      n2: int, round_size: int, left) -> tuple[list[torch.Tensor], int, list[torch.Tensor]]:
        """Stage 2: the finalists' costs of their own human futures, ``[n, k]`` per round of at most
        ``round_size``, for the finalists' robot futures ``robot [k, 15, 6]`` (prepared as
        ``prepared [k]``), until ``n2`` samples each or, after the first round, until the next round
        would not fit in the seconds ``left()``; the rounds' costs, the samples used and the rounds'
        human futures ``[n, k, 15, 6]``."""
        rounds, used, kept = [], 0, []
        while used < n2:
            n = min(round_size, n2 - used)
            if used and 1.5 * n * len(prepared) / self._rate() > left() - 0.01:
                break
            scores, human = self._scores(prepared, robot, n, human_present, cost)
            rounds.append(scores)
            used += n
            kept.append(human)
        return rounds, used, kept

    @torch.no_grad()
    def plan(self, history: np.ndarray, first_action: int, cost: Cost, budget: Budget | None = None,
             deadline: float | None = None, keep_samples: int = 64, style: DrivingStyle | None = None) -> Plan:
        """Plan from ``history [t+1, 2, 6]`` (robot, human states at steps 0..t, physical units)
        with window 0 fixed to ``first_action``: without ``deadline``, ``budget`` (default: the
        planner's) is spent in full, as in the paper; with ``deadline`` (s) the plan returns within
        it once stage 1 is done (module docstring), sampling at most the budget's counts.
        ``keep_samples``: how many of the chosen candidate's human futures the plan keeps;
        ``style``: plan in this :class:`~.styles.DrivingStyle` instead of the planner's (its
        fallback, say). Bad arguments raise :class:`~trafficweaving.errors.InputError`: ``history``
        finite with at least ``MIN_HISTORY`` steps, ``first_action`` an integer in
        ``0..N_ACTIONS-1``, ``deadline`` None or finite > 0."""
        clock = time.perf_counter()
        check_cost(cost)
        budget, deadline = plan_options(budget, deadline)
        budget = budget or self.budget
        keep_samples = validate.integer("keep_samples", keep_samples, 0)
        left = (lambda: deadline - (time.perf_counter() - clock)) if deadline is not None else (lambda: np.inf)  # noqa: E731
        timings = {}
        history, style, candidates, robot, human_present = self._situation(history, first_action, style)
        rules = self._rules(style, candidates, history, cost)
        timings["candidates"] = time.perf_counter() - clock
        count = len(candidates)

        # stage 1: every candidate with n1 samples of its own each (paper; real time: as many as fit) or screened
        n1 = budget.first_stage_samples
        if deadline is not None:
            n1 = min(n1, int(self._rate() * OWN_FUTURES_SHARE * deadline) // count)
        screening = deadline is not None and n1 < 2
        if screening:
            first_cost, n1 = self._screen(history, candidates, robot, human_present, cost, style.risk), SCREENING_SAMPLES
        else:
            scores = self._own_futures(history, candidates, robot, n1, human_present, cost)
            first_cost = risk_cost(scores, style.risk)
        first_cost = first_cost + rules
        timings["first_stage"] = time.perf_counter() - clock - sum(timings.values())

        # the finalists; in real time after own futures, the best of a shortlist given more samples
        k, n_short = budget.finalists, 0
        finalists = torch.topk(first_cost, k, largest=False).indices
        if deadline is not None and not screening and k < SHORTLIST < count:
            n_short = max(int(self._rate() * SHORTLIST_SHARE * left()) // SHORTLIST, 0)
            if n_short:
                shortlist = torch.topk(first_cost, SHORTLIST, largest=False).indices
                more = self._scores(shortlist, robot[shortlist], n_short, human_present, cost)[0]
                shortlist_cost = risk_cost(torch.cat([scores[:, shortlist], more]), style.risk) + rules[shortlist]
                finalists = shortlist[torch.topk(shortlist_cost, k, largest=False).indices]
            timings["shortlist"] = time.perf_counter() - clock - sum(timings.values())

        # stage 2: the finalists, n2 samples of their own each, in rounds while time allows (one at least)
        if screening:
            self.human_model.prepare(history, candidates.states[finalists.cpu().numpy()])
        prepared = torch.arange(k, device=self.device) if screening else finalists
        round_size = budget.second_stage_samples if deadline is None else min(budget.second_stage_samples, 16)
        rounds, used, kept = self._second_stage(prepared, robot[finalists], human_present, cost,
                                                budget.second_stage_samples, round_size, left)
        second_cost = (risk_cost(torch.cat(rounds), style.risk) + rules[finalists] if used
                       else first_cost[finalists])
        best = int(torch.argmin(second_cost))
        index = int(finalists[best])
        human = torch.cat(kept, 0)[:keep_samples, best] if kept else torch.zeros((0, HORIZON, len(STATE_NAMES)))
        timings["second_stage"] = time.perf_counter() - clock - sum(timings.values())
        return Plan(
            actions=candidates.actions[index], index=index, robot=candidates.states[index], candidates=candidates,
            first_stage_cost=first_cost.cpu().numpy(), finalists=finalists.cpu().numpy(),
            second_stage_cost=second_cost.cpu().numpy(), human=human.cpu().double().numpy(),
            futures=(N_ACTIONS if screening else count) * n1 + n_short * SHORTLIST + used * k,
            seconds=time.perf_counter() - clock, first_stage_samples=n1, shortlist_samples=n_short,
            second_stage_samples=used, style=style, timings=timings)

    @torch.no_grad()
    def score(self, history: np.ndarray, first_action: int, cost: Cost, indices, samples: int) -> tuple[np.ndarray, np.ndarray]:
        """The style's costs ``[k]`` (risk over the futures, plus its rules) of candidates
        ``indices [k]`` (of :func:`~.candidates.robot_candidates` with window 0 fixed to
        ``first_action``) from ``samples`` fresh human futures each, and those futures
        ``[samples, k, 15, 6]`` (for re-scoring a choice and for figures). Arguments are checked
        as by :meth:`plan`."""
        check_cost(cost)
        indices = validate.indices("indices", indices, N_CANDIDATES)
        samples = validate.integer("samples", samples, 1)
        history, style, candidates, robot, human_present = self._situation(history, first_action, None)
        self.human_model.prepare(history, candidates.states[indices])
        chosen = torch.as_tensor(indices, device=self.device)
        scores, human = self._scores(torch.arange(len(chosen), device=self.device), robot[chosen], samples,
                                     human_present, cost)
        total = risk_cost(scores, style.risk) + self._rules(style, candidates, history, cost)[chosen]
        return total.cpu().double().numpy(), human.cpu().double().numpy()

    def _rate(self) -> float:
        """Measured human futures sampled and scored per second (a conservative guess before any)."""
        return self.rows_per_second or 20_000.0


def example_history(steps: int = 10, gap: float = 2.0) -> np.ndarray:
    """A contested situation ``[steps, 2, 6]`` for benchmarks and figures: the robot in the right
    lane and the human in the left lane ``gap`` m ahead, both at 29 m/s, at constant speed for
    ``steps`` steps ending about 90 m before the cutoff (both must swap lanes)."""
    t = DT * np.arange(steps)[:, None]
    robot = np.array([-90.0 - 29.0 * DT * (steps - 1), LANE_CENTRE_Y["right"], 29.0, 0.0, 0.0, 0.0])
    human = robot + [gap, LANE_CENTRE_Y["left"] - LANE_CENTRE_Y["right"], 0.0, 0.0, 0.0, 0.0]
    motion = t * np.array([29.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    return np.stack([robot + motion, human + motion], axis=1)
