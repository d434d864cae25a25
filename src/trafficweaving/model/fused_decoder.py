"""The decoder's sampling step as one fused, compiled function with int8 matrix multiplies: the
planner's ``precision="int8"`` (:class:`~trafficweaving.model.predictor.HumanPredictor`), the
fastest way to sample the paper's 98,304 human futures per plan on a CPU (docs/planner.md, Speed).

Same distribution as :class:`~trafficweaving.model.sampler.BatchedRollout` (given the same random
numbers and float weights it returns the same samples, to rounding), reorganised for a compiler:

* tensors are feature-major (``[features, rows]``), so every per-row operation of the sampling head
  (the hold mode's and the mixture component's inverse CDF, the chosen component's parameters) is
  an elementwise operation over contiguous rows, written out over the 4 modes and the ``M``
  components, and ``torch.compile`` (Inductor) fuses a step's gate, cell and sampling arithmetic
  into a few vectorised loops;
* the hidden state ``h`` lies in (−1, 1), so it is quantised to int8 at the fixed scale 1/127 and
  the two hidden-state matrix multiplies (gates and output head) run on int8 weights quantised per
  output row, accumulating in int32 (``torch._int_mm``: VNNI instructions on x86 CPUs); the robot
  state and action inputs (8 columns) and all state, gate and sampling arithmetic stay float32.

The inverse CDFs compare cumulative *unnormalised* weights with ``u·Σw`` (the model's own sampling
normalises first: equal up to rounding).
"""

from __future__ import annotations

import functools

import torch

from ..scenario import HORIZON
from .gmm import LOG_SIGMA_CLIP

INT8_RANGE = 127
"""The int8 code of 1: hidden states and each weight row's largest magnitude map to ±127."""


def quantize_rows(w: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``w [out, in]`` (float) as int8 codes ``[out, in]`` and per-row scales ``[out, 1]`` such that
    ``codes · scale ≈ w`` (each row's largest magnitude maps to 127)."""
    scale = w.abs().amax(1, keepdim=True).clamp_min(1e-30) / INT8_RANGE
    return torch.round(w / scale).to(torch.int8), scale


def _hidden_product(w: torch.Tensor, scale: torch.Tensor, h: torch.Tensor) -> torch.Tensor:
    """``w @ h`` for feature-major ``h [units, R]``: int8 weights ``w [out, units]`` with row
    ``scale [out, 1]`` against ``h`` quantised at 1/127, or float weights (``scale`` unused)."""
    if w.dtype == torch.int8:
        codes = torch.round(h * INT8_RANGE).to(torch.int8)
        return torch._int_mm(w, codes) * (scale / INT8_RANGE)
    return w @ h


def _inverse_cdf(weights: list[torch.Tensor], target: torch.Tensor) -> tuple[list[torch.Tensor], torch.Tensor]:
    """For unnormalised ``weights`` (K tensors ``[R]``) and ``target = u·Σw [R]``: per index ``q`` the
    mask ``chosen_q`` of rows whose draw is ``q`` (the first index whose cumulative weight reaches
    the target; the last if none) and where within that interval the target lies, in [0, 1]."""
    running, lower, width = torch.zeros_like(target), torch.zeros_like(target), weights[0]
    below = []
    for q in range(len(weights) - 1):
        running = running + weights[q]
        beyond = running < target
        below.append(beyond)
        lower = torch.where(beyond, running, lower)
        width = torch.where(beyond, weights[q + 1], width)
    if not below:
        return [torch.ones_like(target, dtype=torch.bool)], (target / width.clamp_min(1e-30)).clamp(0.0, 1.0)
    chosen = [~below[0]] + [before & ~now for before, now in zip(below[:-1], below[1:])] + [below[-1]]
    return chosen, ((target - lower) / width.clamp_min(1e-30)).clamp(0.0, 1.0)


def _softmax_weights(logits: list[torch.Tensor]) -> tuple[list[torch.Tensor], torch.Tensor]:
    """``exp(logit − max)`` of K logits ``[R]`` each, and their sum ``[R]``."""
    top = logits[0]
    for x in logits[1:]:
        top = torch.maximum(top, x)
    weights = [torch.exp(x - top) for x in logits]
    total = weights[0]
    for w in weights[1:]:
        total = total + w
    return weights, total


def decode_step(c: torch.Tensor, h: torch.Tensor, action: torch.Tensor, constant: torch.Tensor, robot: torch.Tensor,
                uniform: torch.Tensor, normal: torch.Tensor, w_hidden: torch.Tensor, hidden_scale: torch.Tensor,
                w_inputs: torch.Tensor, w_head: torch.Tensor, head_scale: torch.Tensor, head_bias: torch.Tensor,
                output_scale: torch.Tensor, hold_sigma: torch.Tensor, modes: int,
                components: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """One decoder step of ``R`` rows, feature-major: the next cell and hidden states ``[u, R]``
    and the sampled action ``[2, R]`` (standardised).

    ``c``, ``h [u, R]``: the cell and hidden states; ``action [2, R]``: the previous action;
    ``constant [4u, R]``: each row's constant gate input (latent, context, bias; gate rows
    ``(i, f, o, 2j)`` of :class:`~trafficweaving.model.sampler.BatchedRollout`); ``robot [6, R]``:
    the robot state fed at this step; ``uniform [R]``, ``normal [2, R]``: the random numbers.
    Weights: ``w_hidden [4u, u]`` (int8 with ``hidden_scale [4u, 1]``, or float), ``w_inputs
    [4u, 8]`` (robot state, action), ``w_head [H, u]`` (int8 with ``head_scale [H, 1]``, or float)
    and ``head_bias [H, 1]``, head rows ``[modes, log π (M), (μx, μy, log σx, log σy, ρ) per
    component]``; ``output_scale [2]`` (calibration), ``hold_sigma [2]`` (hold widths; unused
    without ``modes``)."""
    units, hidden = c.shape[0], _hidden_product(w_hidden, hidden_scale, h)

    def gate(block: int) -> torch.Tensor:  # sliced before the sigmoid: one loop computes a unit's gates and state
        rows = slice(block * units, (block + 1) * units)
        x = hidden[rows] + constant[rows] + w_inputs[rows, 6:7] * action[0] + w_inputs[rows, 7:8] * action[1]
        for q in range(6):
            x = x + w_inputs[rows, q:q + 1] * robot[q]
        return torch.sigmoid(x)

    i, f, o, j = gate(0), gate(1), gate(2), gate(3)
    c = c * f + i * (2.0 * j - 1.0)  # c·f + i·tanh(j)
    h = o * (2.0 * torch.sigmoid(2.0 * c) - 1.0)  # o·tanh(c)
    head = _hidden_product(w_head, head_scale, h) + head_bias
    if modes:
        mode_weights, total = _softmax_weights([head[q] for q in range(modes)])
        mode, uniform = _inverse_cdf(mode_weights, uniform * total)
    weights, total = _softmax_weights([head[modes + q] for q in range(components)])
    chosen, _ = _inverse_cdf(weights, uniform * total)
    at = modes + components  # component 0's parameters
    params = [head[at + p] for p in range(5)]
    for q in range(1, components):
        params = [torch.where(chosen[q], head[at + 5 * q + p], params[p]) for p in range(5)]
    sx = params[2].clamp(-LOG_SIGMA_CLIP, LOG_SIGMA_CLIP).exp() * output_scale[0]
    sy = params[3].clamp(-LOG_SIGMA_CLIP, LOG_SIGMA_CLIP).exp() * output_scale[1]
    corr = torch.tanh(params[4])
    nx, ny = normal[0], normal[1]
    lateral = corr * nx + torch.sqrt(1.0 - corr * corr) * ny
    if not modes:
        return c, h, torch.stack([params[0] + sx * nx, params[1] + sy * lateral])
    lateral = torch.where(mode[0], lateral, ny)  # HOLD_MODES: free, hold x, hold y, hold both
    ax = torch.where(mode[1] | mode[3], action[0] + hold_sigma[0] * nx, params[0] + sx * nx)
    ay = torch.where(mode[2] | mode[3], action[1] + hold_sigma[1] * ny, params[1] + sy * lateral)
    return c, h, torch.stack([ax, ay])


@functools.cache
def compiled_decode_step():
    """:func:`decode_step` compiled by Inductor (``torch.compile``; on its first call per model kind
    about 15 s on two cores, then cached on disk for later processes)."""
    return torch.compile(decode_step, dynamic=False)


class FusedDecoder:
    """The decoder of one CVAE prepared for :func:`decode_step`: feature-major weights, the
    hidden-state ones int8 when ``quantize``; ``compiled`` runs :func:`compiled_decode_step`.

    ``w_step [u + 8, 4u]`` (rows ``[h, robot_state, action]``), ``latent_gates [Z, 4u]`` and
    ``latent_init [Z, 2u]`` as :class:`~trafficweaving.model.sampler.BatchedRollout` holds them
    (gate columns ``(i, f, o, 2j)``), ``w_head [u, H]``, ``head_bias [H]``, ``output_scale [2]``,
    ``hold_sigma [2]`` or None, ``modes`` (0 or 4) and ``components``."""

    def __init__(self, w_step: torch.Tensor, latent_gates: torch.Tensor, latent_init: torch.Tensor,
                 w_head: torch.Tensor, head_bias: torch.Tensor, output_scale: torch.Tensor,
                 hold_sigma: torch.Tensor | None, modes: int, components: int, quantize: bool = True,
                 compiled: bool = True):
        units, dtype, device = w_head.shape[0], output_scale.dtype, output_scale.device
        hidden, head = w_step[:units].T.to(dtype), w_head.T.to(dtype)
        if quantize:
            (self.w_hidden, self.hidden_scale), (self.w_head, self.head_scale) = quantize_rows(hidden), quantize_rows(head)
        else:
            self.w_hidden, self.w_head = hidden.contiguous(), head.contiguous()
            self.hidden_scale = self.head_scale = torch.ones((), dtype=dtype, device=device)
        self.w_inputs = w_step[units:].T.to(dtype).contiguous()  # [4u, 8]
        self.latent_gates = latent_gates.T.contiguous()  # [4u, Z]
        self.latent_init = latent_init.T.contiguous()  # [2u, Z]
        self.head_bias = head_bias.to(dtype)[:, None]
        self.output_scale = output_scale
        self.hold_sigma = hold_sigma if hold_sigma is not None else torch.ones(2, dtype=dtype, device=device)
        self.modes, self.components = modes, components
        self.compiled = compiled
        self.step = compiled_decode_step() if compiled else decode_step

    def prepare(self, x_gates: torch.Tensor, x_init: torch.Tensor, robot_inputs: torch.Tensor) -> dict:
        """Feature-major per-candidate parts from :meth:`BatchedRollout.encode`'s ``x_gates [C, 4u]``,
        ``x_init [C, 2u]`` and ``robot_inputs [15, C, 6]``."""
        return {"x_gates": x_gates.T.contiguous(), "x_init": x_init.T.contiguous(),
                "robot_inputs": robot_inputs.permute(0, 2, 1).contiguous()}

    def decode(self, parts: dict, cand: torch.Tensor, z: torch.Tensor, present: torch.Tensor, uniform: torch.Tensor,
               normal: torch.Tensor) -> torch.Tensor:
        """Actions ``[R, 15, 2]`` of ``R`` rows: candidates ``cand [R]`` (into :meth:`prepare`'s
        ``parts``), latent values ``z [R]``, the present action ``present [2]``, ``uniform [R, 15]``
        and ``normal [R, 15, 2]``."""
        units = self.latent_init.shape[0] // 2
        constant = parts["x_gates"].index_select(1, cand) + self.latent_gates.index_select(1, z)  # [4u, R]
        init = torch.tanh(parts["x_init"].index_select(1, cand) + self.latent_init.index_select(1, z))  # [2u, R]
        c, h = init[:units], init[units:]
        robot_steps = parts["robot_inputs"].index_select(2, cand)  # [15, 6, R]
        uniform, normal = uniform.T.contiguous(), normal.permute(1, 2, 0).contiguous()  # [15, R], [15, 2, R]
        action = present[:, None].expand(2, len(cand)).contiguous()
        if self.compiled:
            for x in (constant, c, h, robot_steps, uniform, normal, action):  # one kernel for every number of rows
                torch._dynamo.maybe_mark_dynamic(x, x.dim() - 1)
        actions = []
        for k in range(HORIZON):
            c, h, action = self.step(c, h, action, constant, robot_steps[k], uniform[k], normal[k], self.w_hidden,
                                     self.hidden_scale, self.w_inputs, self.w_head, self.head_scale, self.head_bias,
                                     self.output_scale, self.hold_sigma, self.modes, self.components)
            actions.append(action)
        return torch.stack(actions).permute(2, 0, 1)
