"""The two-stage exhaustive planner (DESIGN.md §4) and its real-time (deadline) mode.

Stage 1 scores every candidate robot future with a few sampled human responses each; stage 2
re-scores the best ones with many samples; the best is executed. All counts are configurable.
With a deadline, the same two stages run anytime: stage 1 with as many samples as the measured
speed allows, then stage 2 in rounds until the time is spent, so a plan is always returned in
time.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol

import numpy as np
import torch

from ..model.cvae import CVAE, HORIZON, MIN_HISTORY, STATE_DIM
from ..dynamics import future_states
from ..model.sampler import BatchedSampler
from ..scenario import DT, LANE_CENTRE_Y
from .candidates import Candidates, robot_candidates
from .costs import Cost


def native_bfloat16(device: torch.device | str = "cpu") -> bool:
    """Whether ``device`` is a CPU with native bfloat16 matrix instructions (AVX512-BF16 or AMX),
    where bfloat16 matrix multiplies run about twice as fast as float32."""
    if torch.device(device).type != "cpu" or not torch.backends.mkldnn.is_available():
        return False
    try:
        flags = Path("/proc/cpuinfo").read_text()
    except OSError:
        return False
    return "avx512_bf16" in flags or "amx_bf16" in flags


def resolve_precision(precision: str, device: torch.device | str = "cpu") -> torch.dtype:
    """``auto``: bfloat16 decoder matrix multiplies on CPUs with native bfloat16, else float32."""
    if precision == "auto":
        return torch.bfloat16 if native_bfloat16(device) else torch.float32
    return {"float32": torch.float32, "bfloat16": torch.bfloat16}[precision]


class HumanSampler(Protocol):
    """What the planner needs of a human model: ``prepare`` once per plan with the physical
    ``history [t+1, 2, 6]`` (robot, human) and ``robot_futures [C, 15, 6]``, then ``sample``
    accelerations ``[n, len(candidates), 15, 2]`` (m/s²) for candidate indices ``candidates``."""

    def prepare(self, history: np.ndarray, robot_futures: np.ndarray) -> None: ...

    def sample(self, candidates: torch.Tensor, n: int, generator: torch.Generator) -> torch.Tensor: ...


class CVAESampler:
    """:class:`HumanSampler` for a :class:`CVAE`, through the fast :class:`BatchedSampler`."""

    def __init__(self, model: CVAE, chunk_rows: int = 2048, matmul_dtype: torch.dtype | None = None):
        self.model = model.eval()
        self.batched = BatchedSampler(model, chunk_rows, matmul_dtype)
        self.device = next(model.parameters()).device
        self.dtype = next(model.parameters()).dtype
        self.context: dict | None = None

    def prepare(self, history: np.ndarray, robot_futures: np.ndarray) -> None:
        self.context = self.batched.encode_states(history, robot_futures)

    def sample(self, candidates: torch.Tensor, n: int, generator: torch.Generator) -> torch.Tensor:
        latents = self.batched.sample_latents(self.context, n, generator, candidates)
        actions = self.batched.sample(self.context, latents, candidates, generator)
        return actions * self.model.label_std + self.model.label_mean


@dataclass(frozen=True)
class Budget:
    """Sample counts of the two stages (the paper's: 16 per candidate, best 32, 1024 each)."""

    first_stage_samples: int = 16
    finalists: int = 32
    second_stage_samples: int = 1024

    @property
    def futures(self) -> int:
        """Simulated human futures per plan for 4096 candidates."""
        return 4096 * self.first_stage_samples + self.finalists * self.second_stage_samples


@dataclass
class Plan:
    """A planning result. ``actions [5]`` the chosen action sequence (window 0 = the fixed one),
    ``index`` its candidate index, ``robot [15, 6]`` its robot states; diagnostics:
    ``candidates`` (all robot futures), ``first_stage_cost [C]`` (mean cost, +inf if not scored),
    ``finalists [k]`` and ``second_stage_cost [k]``, ``human [n, 15, 6]`` sampled human futures
    for the chosen candidate, ``futures`` (human futures simulated), ``seconds``, and
    ``first_stage_samples`` / ``second_stage_samples`` actually used."""

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
    second_stage_samples: int
    timings: dict = field(default_factory=dict)


class Planner:
    """Plans robot action sequences against a human model (a :class:`CVAE`, on its device, or
    any :class:`HumanSampler`)."""

    def __init__(self, model: CVAE | HumanSampler, budget: Budget = Budget(), seed: int = 0,
                 device: torch.device | str | None = None, precision: str = "auto"):
        """``precision`` (for a CVAE): the dtype of the decoder's matrix multiplies, ``float32``,
        ``bfloat16`` (state and gate arithmetic stay float32; about twice as fast on CPUs with
        native bfloat16, slightly different numbers: docs/planner.md measures the decisions) or
        ``auto`` (bfloat16 where native, see :func:`resolve_precision`)."""
        if isinstance(model, CVAE):
            weights = next(model.parameters())
            dtype = resolve_precision(precision, weights.device) if weights.dtype == torch.float32 else weights.dtype
            model = CVAESampler(model, matmul_dtype=dtype)
        self.sampler = model
        self.device = torch.device(device) if device is not None else getattr(self.sampler, "device", torch.device("cpu"))
        self.dtype = getattr(self.sampler, "dtype", torch.float32)
        self.budget = budget
        self.generator = torch.Generator(device=self.device).manual_seed(seed)
        self.rows_per_second: float | None = None  # measured futures sampled and scored per second

    def _scores(self, cand: torch.Tensor, n: int, robot: torch.Tensor, human_present: torch.Tensor,
                cost: Cost) -> tuple[torch.Tensor, torch.Tensor]:
        """Costs ``[n, len(cand)]`` of ``n`` sampled human futures for candidates ``cand``, and those futures."""
        start = time.perf_counter()
        actions = self.sampler.sample(cand, n, self.generator)
        human = future_states(human_present, actions.to(self.dtype))  # [n, C', 15, 6]
        scores = cost(robot[cand].unsqueeze(0), human)
        rate = n * len(cand) / max(time.perf_counter() - start, 1e-6)
        self.rows_per_second = rate if self.rows_per_second is None else 0.7 * self.rows_per_second + 0.3 * rate
        return scores, human

    @torch.no_grad()
    def plan(self, history: np.ndarray, first_action: int, cost: Cost, budget: Budget | None = None,
             deadline: float | None = None, keep_samples: int = 64) -> Plan:
        """Plan from ``history [t+1, 2, 6]`` (robot, human states at steps 0..t, physical units)
        with window 0 fixed to ``first_action``.

        Without ``deadline``, ``budget`` (default: the planner's) is spent in full. With
        ``deadline`` (s), the plan returns within it: stage 1 takes as many samples per candidate
        as the measured speed allows (at most the budget's, scoring candidates in chunks and
        leaving the rest unscored if time runs out), stage 2 runs in rounds of samples until the
        time is spent.
        """
        clock = time.perf_counter()
        history = np.asarray(history, dtype=np.float64)
        if history.ndim != 3 or history.shape[1:] != (2, STATE_DIM) or history.shape[0] < MIN_HISTORY:
            raise ValueError(f"history has shape {list(history.shape)} (expected [t+1 >= {MIN_HISTORY}, 2, {STATE_DIM}])")
        budget = budget or self.budget
        left = (lambda: deadline - (time.perf_counter() - clock)) if deadline is not None else (lambda: np.inf)  # noqa: E731
        timings = {}
        candidates = robot_candidates(history[-1, 0], first_action)
        robot = torch.as_tensor(candidates.states, dtype=self.dtype, device=self.device)
        human_present = torch.as_tensor(history[-1, 1], dtype=self.dtype, device=self.device)
        self.sampler.prepare(history, candidates.states)
        timings["candidates_and_encoding"] = time.perf_counter() - clock
        count = len(candidates)

        # stage 1: every candidate, n1 samples each, in chunks while time allows
        n1 = budget.first_stage_samples
        if deadline is not None:
            n1 = int(np.clip(0.4 * left() * self._rate() // count, 1, n1))
        first_cost = torch.full((count,), float("inf"), dtype=self.dtype, device=self.device)
        chunk = count if deadline is None else max(256, int(0.05 * self._rate() / n1))
        for start in range(0, count, chunk):
            cand = torch.arange(start, min(start + chunk, count), device=self.device)
            if deadline is not None and start > 0 and 1.5 * n1 * len(cand) / self._rate() > left() - 0.01:
                break
            scores, _ = self._scores(cand, n1, robot, human_present, cost)
            first_cost[cand] = scores.mean(0)
        scored = int(torch.isfinite(first_cost).sum())
        timings["first_stage"] = time.perf_counter() - clock - sum(timings.values())

        # stage 2: the finalists, n2 samples each, in rounds while time allows
        k = min(budget.finalists, scored)
        finalists = torch.topk(first_cost, k, largest=False).indices
        n2 = budget.second_stage_samples
        total, used, kept = torch.zeros(k, dtype=self.dtype, device=self.device), 0, []
        round_size = n2 if deadline is None else max(8, min(n2, 64))
        while used < n2:
            n = min(round_size, n2 - used)
            if deadline is not None and 1.5 * n * k / self._rate() > left() - 0.01:
                break
            scores, human = self._scores(finalists, n, robot, human_present, cost)
            total += scores.sum(0)
            used += n
            kept.append(human)
        second_cost = total / used if used else first_cost[finalists]
        best = int(torch.argmin(second_cost))
        index = int(finalists[best])
        human = torch.cat(kept, 0)[:keep_samples, best] if kept else torch.zeros((0, HORIZON, 6))
        timings["second_stage"] = time.perf_counter() - clock - sum(timings.values())
        return Plan(
            actions=candidates.actions[index], index=index, robot=candidates.states[index], candidates=candidates,
            first_stage_cost=first_cost.cpu().numpy(), finalists=finalists.cpu().numpy(),
            second_stage_cost=second_cost.cpu().numpy(), human=human.cpu().double().numpy(),
            futures=n1 * scored + used * k, seconds=time.perf_counter() - clock,
            first_stage_samples=n1, second_stage_samples=used, timings=timings)

    @torch.no_grad()
    def score(self, history: np.ndarray, first_action: int, cost: Cost, indices, samples: int) -> tuple[np.ndarray, np.ndarray]:
        """Expected costs ``[k]`` of candidates ``indices`` (of :func:`robot_candidates` with window 0
        fixed to ``first_action``) from ``samples`` fresh human futures each, and those futures
        ``[samples, k, 15, 6]`` (for re-scoring a choice and for figures)."""
        candidates = robot_candidates(np.asarray(history, float)[-1, 0], first_action)
        self.sampler.prepare(np.asarray(history, float), candidates.states)
        robot = torch.as_tensor(candidates.states, dtype=self.dtype, device=self.device)
        human_present = torch.as_tensor(np.asarray(history, float)[-1, 1], dtype=self.dtype, device=self.device)
        scores, human = self._scores(torch.as_tensor(np.asarray(indices), device=self.device), samples, robot, human_present, cost)
        return scores.mean(0).cpu().double().numpy(), human.cpu().double().numpy()

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
