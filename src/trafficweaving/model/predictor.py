"""The CVAE as a model of the human to sample from, in physical units: one history, many candidate
robot futures, many samples each.

:class:`HumanPredictor` is the one way to sample the CVAE's human futures outside training: the
planner's two-call protocol (:meth:`HumanPredictor.prepare` once per plan, then
:meth:`HumanPredictor.sample` for subsets of candidates; the planner's ``HumanModel``) and the
one-shot :meth:`HumanPredictor.predict` for figures and tests. Both run the fast batched decoder
rollout (:class:`~trafficweaving.model.sampler.BatchedRollout`): the history is encoded once, each
candidate's future once, then ``n·B`` latent values and decoder rollouts run together.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch

from .. import validate
from ..errors import InputError
from ..scenario import HORIZON
from .cvae import ACCEL, CVAE, STATE_DIM
from .mixture import Mixture
from .sampler import rollout

PRECISIONS = ("auto", "float32", "bfloat16", "int8", "float32-compiled")
"""Choices of :func:`resolve_precision`."""
MATMUL_DTYPES = {"float32": torch.float32, "bfloat16": torch.bfloat16, "int8": torch.int8,
                 "float32-compiled": torch.float32}
"""The dtype of the decoder's matrix multiplies for each precision but ``auto``."""
COMPILED_PRECISIONS = ("int8", "float32-compiled")
"""Precisions that run the decoder's steps fused and compiled (:mod:`~trafficweaving.model.fused_decoder`)."""
MAX_PLAN_FUTURES = 2**21
"""Most human futures one plan may sample (``bench plan``'s budget options): each holds about 1.7 kB
while the plan scores them (measured at the paper's budget and 8 times its second stage), so at
most about 3.6 GB; the paper's plan samples 98,304."""


def _cpuinfo() -> tuple[str, set[str]]:
    """The CPU's model name and feature flags from ``/proc/cpuinfo`` (empty where there is none)."""
    try:
        lines = Path("/proc/cpuinfo").read_text().splitlines()
    except OSError:
        return "", set()
    field = lambda key: next((line.split(":", 1)[1].strip() for line in lines if line.startswith(key)), "")  # noqa: E731
    return field("model name"), set(field("flags").split())


def native_bfloat16(device: torch.device | str = "cpu") -> bool:
    """Whether ``device`` is a CPU with native bfloat16 matrix instructions (AVX512-BF16 or AMX),
    where bfloat16 matrix multiplies run about twice as fast as float32."""
    if torch.device(device).type != "cpu" or not torch.backends.mkldnn.is_available():
        return False
    return bool(_cpuinfo()[1] & {"avx512_bf16", "amx_bf16"})


def cpu_matrix_features() -> dict:
    """What the CPU offers the decoder's matrix multiplies, on which the bfloat16 and int8 plans'
    speeds depend (docs/planner.md, Speed): its ``model`` name, ``native_bfloat16``
    (:func:`native_bfloat16`), ``int8_dot_products`` (AVX512-VNNI, AVX-VNNI or AMX: what
    ``torch._int_mm`` runs on) and ``amx`` (tile matrix multiplies)."""
    model, flags = _cpuinfo()
    return {"model": model, "native_bfloat16": native_bfloat16(),
            "int8_dot_products": bool(flags & {"avx512_vnni", "avx_vnni", "amx_int8"}),
            "amx": bool(flags & {"amx_bf16", "amx_int8", "amx_tile"})}


def compiler_available() -> bool:
    """Whether ``torch.compile``'s CPU backend (Inductor) finds the C++ compiler that the compiled
    precisions (:data:`COMPILED_PRECISIONS`) need."""
    from torch._inductor.cpp_builder import get_cpp_compiler

    try:
        get_cpp_compiler()
    except Exception:  # Inductor raises its own error types when no compiler is found
        return False
    return True


def resolve_precision(precision: str, device: torch.device | str = "cpu") -> str:
    """The precision that ``precision`` (one of :data:`PRECISIONS`) runs in. ``auto`` picks, among the
    precisions whose plans decide as float32's do to the noise floor of two float32 plans
    (docs/planner.md, Decision quality), the fastest measured on such a CPU (docs/planner.md,
    Speed): on a CPU with a C++ compiler, int8 where it has int8 dot products
    (:func:`cpu_matrix_features`), else float32-compiled; without a compiler, bfloat16 where
    native (:func:`native_bfloat16`); else, and on other devices, float32."""
    if precision not in PRECISIONS:
        raise InputError(f"precision must be one of {', '.join(PRECISIONS)}, got {precision!r}")
    if precision == "auto":
        if torch.device(device).type == "cpu" and compiler_available():
            return "int8" if cpu_matrix_features()["int8_dot_products"] else "float32-compiled"
        return "bfloat16" if native_bfloat16(device) else "float32"
    if precision in COMPILED_PRECISIONS and torch.device(device).type != "cpu":
        raise InputError(f"precision {precision} runs on the CPU only, the model is on {device} (expected auto, "
                         f"float32 or bfloat16)")
    return precision


@dataclass
class Prediction:
    """``actions [n, B, 15, 2]`` sampled human accelerations ``[xdd, ydd]`` (m/s²) at steps
    t+1..t+15; ``latents [n, B]`` the joint latent value of each sample (0..Z-1, first latent
    variable slowest; of a mixture: its (component, value) pairs, :attr:`~.mixture.Mixture.latent_offsets`);
    ``log_p_z [B, Z]`` the prior over latent values for each candidate."""

    actions: torch.Tensor
    latents: torch.Tensor
    log_p_z: torch.Tensor


class HumanPredictor:
    """Samples human futures from a :class:`CVAE` or a :class:`~trafficweaving.model.mixture.Mixture`
    of them (evaluation mode, on the model's device).

    ``precision``: the dtype of the decoder's matrix multiplies for a float32 model (one of
    :data:`PRECISIONS`; a float64 model always runs in float64): ``float32`` samples the model
    exactly as it is; ``bfloat16`` keeps the state and gate arithmetic in float32 and is about
    twice as fast on CPUs with native bfloat16, with slightly different numbers (docs/planner.md
    measures the planner's decisions); ``auto``: :func:`resolve_precision`; ``int8`` (CPU only)
    quantises the hidden state and runs the decoder's steps fused and compiled
    (:mod:`~trafficweaving.model.fused_decoder`; the first call compiles for about 15 s, 2–4 s
    from Inductor's on-disk cache);
    ``float32-compiled`` (CPU only) runs the same fused, compiled steps with float32 weights: the
    same samples as ``float32`` to rounding, and the fastest on CPUs without int8 dot products
    (docs/planner.md, Speed).
    ``chunk_rows``: decoder rows per chunk, so that the working set stays in cache (None: by the
    decoder's width, :func:`~trafficweaving.model.sampler.chunk_rows_for`).
    ``common_random_numbers``: sample ``i`` of every candidate is drawn with the same random numbers
    (latent noise, output uniforms and normals): each candidate's futures keep their distribution,
    and the candidates' sampled costs are compared in pairs, with less noise in their differences
    (docs/planner.md).

    :attr:`device` and :attr:`dtype` are the model's; tensors returned live there.
    """

    def __init__(self, model: CVAE | Mixture, precision: str = "float32", chunk_rows: int | None = None,
                 common_random_numbers: bool = True):
        if model.config.robot_future != "recorded":
            raise InputError(f"the model is conditioned on a {model.config.robot_future} of the robot's future (a driver "
                             f"model), so it cannot tell candidate robot futures apart (expected a model conditioned on "
                             f"recorded futures, e.g. default)")
        self.model = model.eval()
        weights = next(model.parameters())
        self.device, self.dtype = weights.device, weights.dtype
        if self.dtype == torch.float32:
            self._precision = resolve_precision(precision, self.device)
            matmul_dtype, fused = MATMUL_DTYPES[self._precision], self._precision in COMPILED_PRECISIONS
        else:
            self._precision, matmul_dtype, fused = str(self.dtype).removeprefix("torch."), self.dtype, False
        chunk_rows = None if chunk_rows is None else validate.integer("chunk_rows", chunk_rows, 1)
        self.rollout = rollout(model, chunk_rows, matmul_dtype, fused)
        self.context: dict | None = None
        self.candidates = 0
        self.common_random_numbers = bool(common_random_numbers)

    @property
    def precision(self) -> str:
        """The precision it samples in (:data:`PRECISIONS`, ``auto`` resolved; a float64 model's
        ``"float64"``), e.g. ``"bfloat16"``."""
        return self._precision

    def prepare(self, history, robot_futures) -> None:
        """Encode one situation for :meth:`sample`: ``history [t+1, 2, 6]`` states ``[x, y, xd, yd,
        xdd, ydd]`` (m, m/s, m/s²) of the robot (index 0) and the human (index 1) at steps 0..t,
        ``t >= 4``; ``robot_futures [B, 15, 6]`` the robot's states at steps t+1..t+15 for each of
        ``B`` candidates. Arrays or tensors."""
        self.context = self._encode(history, robot_futures)
        self.candidates = len(self.context["log_p_joint"])

    def sample(self, candidates, n: int, generator: torch.Generator | None) -> torch.Tensor:
        """Human accelerations ``[n, len(candidates), 15, 2]`` (m/s², ``[xdd, ydd]`` at steps
        t+1..t+15) for the candidate indices ``candidates [k]`` (into the robot futures of the last
        :meth:`prepare`), drawn with ``generator`` (on :attr:`device`)."""
        if self.context is None:
            raise RuntimeError("HumanPredictor.sample needs a situation: call prepare(history, robot_futures) first")
        validate.indices("candidates", candidates, self.candidates)
        candidates = torch.as_tensor(candidates, device=self.device)
        return self._draw(self.context, candidates, validate.integer("n", n, 1), generator)[0]

    @torch.no_grad()
    def predict(self, history, robot_futures, n: int, seed: int | None = 0) -> Prediction:
        """``n`` sampled human action sequences for each candidate robot future, with their latent
        values and the prior over them. ``history`` and ``robot_futures`` as for :meth:`prepare`
        (which this leaves as it was). Deterministic for a given ``seed`` on a given device
        (``None``: nondeterministic)."""
        context = self._encode(history, robot_futures)
        n = validate.integer("n", n, 1)
        generator = torch.Generator(device=self.device)
        if seed is None:
            generator.seed()
        else:
            generator.manual_seed(validate.integer("seed", seed, 0))
        actions, latents = self._draw(context, None, n, generator)
        return Prediction(actions, latents, context["log_p_joint"])

    def _encode(self, history, robot_futures) -> dict:
        """Validated, standardised and encoded (:meth:`BatchedRollout.encode`)."""
        history = validate.history(history)
        robot_futures = validate.finite_array("robot_futures", robot_futures, (None, HORIZON, STATE_DIM),
                                              f"[B >= 1, {HORIZON}, {STATE_DIM}]")
        if len(robot_futures) == 0:
            raise InputError(f"robot_futures has shape {list(robot_futures.shape)} (expected [B >= 1, {HORIZON}, {STATE_DIM}])")
        m = self.model
        past = torch.as_tensor(history, dtype=self.dtype, device=self.device)
        futures = torch.as_tensor(robot_futures, dtype=self.dtype, device=self.device)
        return self.rollout.encode(m.states_to_standard(past).reshape(len(past), 2 * STATE_DIM),
                                   m.states_to_standard(futures), m.actions_to_standard(past[-1, 1, ACCEL]))

    @torch.no_grad()
    def _draw(self, context: dict, candidates: torch.Tensor | None, n: int,
              generator: torch.Generator | None) -> tuple[torch.Tensor, torch.Tensor]:
        """Accelerations ``[n, k, 15, 2]`` (m/s²) and latent values ``[n, k]`` for ``candidates [k]``
        (None: all)."""
        common = self.common_random_numbers
        latents = self.rollout.sample_latents(context, n, generator, candidates, common)
        actions = self.rollout.sample(context, latents, candidates, generator, common=common)
        return self.model.actions_to_physical(actions), latents
