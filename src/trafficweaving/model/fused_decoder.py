"""The decoder's sampling step as one fused, compiled function, with int8 or float32 matrix
multiplies: the planner's ``precision="int8"`` and ``"float32-compiled"``
(:class:`~trafficweaving.model.predictor.HumanPredictor`), the fastest ways to sample the paper's
98,304 human futures per plan on a CPU, with and without int8 dot products (docs/planner.md, Speed).

Same distribution as :class:`~trafficweaving.model.sampler.BatchedRollout` (given the same random
numbers and float weights it returns the same samples, to rounding), reorganised for a compiler:

* the gates are row-major (``[rows, 4u]``): the gate matrix multiply runs fastest that way, and a
  row's constant gate input is one contiguous row of a table gathered inside the step's loop. Rows
  are decoded in chunks sorted by candidate, and a chunk first tables its candidates' constant gate
  inputs with each step's robot state (``[15, C', 4u]``), so a step adds one table row instead of
  six robot-state products per gate;
* the sampling head is feature-major (``[H, rows]``), so every per-row operation (the hold mode's
  and the mixture component's inverse CDF, the chosen component's parameters) is an elementwise
  operation over contiguous rows, written out over the 4 modes and the ``M`` components, and
  ``torch.compile`` (Inductor) fuses a step's gate, cell and sampling arithmetic into two vectorised
  loops, its multiply-adds contracted to FMAs;
* with int8 weights, the hidden state ``h`` (in (−1, 1)) is quantised to int8 at the fixed scale
  1/127 and the two hidden-state matrix multiplies (gates and output head) run on int8 weights
  quantised per output, accumulating in int32 (``torch._int_mm``: VNNI instructions on x86 CPUs);
  the action inputs and all state, gate and sampling arithmetic stay float32;
* in float32 the sigmoids are a float32-accurate rational function (:func:`rational_sigmoid`).

The inverse CDFs compare cumulative *unnormalised* weights with ``u·Σw`` (the model's own sampling
normalises first: equal up to rounding).
"""

from __future__ import annotations

import functools

import torch

from ..scenario import HORIZON
from .gmm import LOG_SIGMA_CLIP

COMPILE_OPTIONS = {"cpp.enable_floating_point_contract_flag": "fast", "assert_indirect_indexing": False}
"""Inductor options of the compiled steps: multiply-adds contract to FMAs (the gates' input sums and
:func:`rational_sigmoid`'s polynomials), which is most of a step's arithmetic; and the table rows a
step gathers (by candidate and latent value) are not bounds-checked element by element: the indices
are made in range by :meth:`FusedDecoder.decode` (``torch.unique``'s inverse and the latent values
of the model), and the check cost about 5 % of an int8 plan on an AVX-512 VNNI CPU (docs/planner.md)."""
TANH_CLAMP = 7.90531110763549805
"""Where :func:`rational_sigmoid`'s tanh is clamped: beyond it float32 tanh is ±1."""
INT8_RANGE = 127
"""The int8 code of 1: hidden states and each weight row's largest magnitude map to ±127."""


def quantize_rows(w: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``w [out, in]`` (float) as int8 codes ``[out, in]`` and per-row scales ``[out, 1]`` such that
    ``codes · scale ≈ w`` (each row's largest magnitude maps to 127)."""
    scale = w.abs().amax(1, keepdim=True).clamp_min(1e-30) / INT8_RANGE
    return torch.round(w / scale).to(torch.int8), scale


def hidden_state(h: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """The hidden state ``h [R, units]`` (in (−1, 1)) as the matrix multiplies with ``w`` take it:
    int8 codes at the fixed scale 1/127 for int8 weights, else as it is."""
    return torch.round(h * INT8_RANGE).to(torch.int8) if w.dtype == torch.int8 else h


def _hidden_product(h: torch.Tensor, w: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    """``h @ w`` for row-major ``h [R, units]`` (:func:`hidden_state`): int8 weights ``w [units,
    out]`` with column scale ``scale [1, out]`` (of the product of codes), or float weights."""
    return torch._int_mm(h, w) * scale if w.dtype == torch.int8 else h @ w


def _head_product(w: torch.Tensor, scale: torch.Tensor, h: torch.Tensor) -> torch.Tensor:
    """``w @ hᵀ`` (feature-major ``[out, R]``) for row-major ``h [R, units]`` (:func:`hidden_state`):
    int8 weights ``w [out, units]`` with row scale ``scale [out, 1]`` (of the product of codes), or
    float weights."""
    return torch._int_mm(w, h.T) * scale if w.dtype == torch.int8 else w @ h.T


def rational_sigmoid(x: torch.Tensor) -> torch.Tensor:
    """σ(x) = (1 + tanh(x/2)) / 2 with tanh as the 13/6 rational function of Eigen's float32 ``ptanh``
    (clamped at |x/2| ≤ :data:`TANH_CLAMP`, where float32 tanh is ±1): within 3e-7 of
    ``torch.sigmoid`` in float32. Polynomial arithmetic only, so it compiles to FMAs, where
    Inductor's sigmoid is an accurate ``exp`` and a division: full int8 plans take 10–20 % less time
    with it. The clamp is written as two selects: ``clamp`` compiles to NaN-propagating min and max
    (four instructions each on AVX-512), the selects to a compare and a blend each (NaN passes
    through either way)."""
    x = 0.5 * x
    x = torch.where(x > TANH_CLAMP, TANH_CLAMP, torch.where(x < -TANH_CLAMP, -TANH_CLAMP, x))  # NaN stays NaN
    x2 = x * x
    p = x2 * -2.76076847742355e-16 + 2.00018790482477e-13
    for a in (-8.60467152213735e-11, 5.12229709037114e-08, 1.48572235717979e-05, 6.37261928875436e-04,
              4.89352455891786e-03):
        p = x2 * p + a
    q = x2 * 1.19825839466702e-06 + 1.18534705686654e-04
    for b in (2.26843463243900e-03, 4.89352518554385e-03):
        q = x2 * q + b
    return 0.5 + 0.5 * (x * p / q)


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


def decode_step(c: torch.Tensor, h: torch.Tensor, action: torch.Tensor, local: torch.Tensor, z: torch.Tensor,
                candidate_gates: torch.Tensor, latent_gates: torch.Tensor, uniform: torch.Tensor, normal: torch.Tensor,
                w_hidden: torch.Tensor, hidden_scale: torch.Tensor, w_action: torch.Tensor, w_head: torch.Tensor,
                head_scale: torch.Tensor, head_bias: torch.Tensor, output_scale: torch.Tensor, hold_sigma: torch.Tensor,
                modes: int, components: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """One decoder step of ``R`` rows: the next cell and hidden states ``[R, u]`` and the sampled
    action ``[2, R]`` (standardised, feature-major).

    ``c``, ``h [R, u]``: the cell and hidden states (``h`` as :func:`hidden_state`: int8 codes with
    int8 weights); ``action [2, R]``: the previous action; ``local [R]``, ``z [R]``: each row's
    candidate (into ``candidate_gates``) and latent value, which pick its constant gate input
    ``candidate_gates[local] + latent_gates[z]`` (``[C, 4u]``: context, bias and this step's robot
    state; ``[Z, 4u]``: latent; gate columns ``(i, f, o, 2j)`` of
    :class:`~trafficweaving.model.sampler.BatchedRollout`); ``uniform [R]``, ``normal [2, R]``: the
    random numbers. Weights: ``w_hidden [u, 4u]`` (int8 with ``hidden_scale [1, 4u]``, or float),
    ``w_action [2, 4u]``, ``w_head [H, u]`` (int8 with ``head_scale [H, 1]``, or float) and
    ``head_bias [H, 1]``, head rows ``[modes, log π (M), (μx, μy, log σx, log σy, ρ) per
    component]``; ``output_scale [2]`` (calibration), ``hold_sigma [2]`` (hold widths; unused
    without ``modes``). In float32 the sigmoids are :func:`rational_sigmoid` (in float64, exact)."""
    units, hidden = c.shape[1], _hidden_product(h, w_hidden, hidden_scale)
    sigmoid = rational_sigmoid if c.dtype == torch.float32 else torch.sigmoid
    constant = candidate_gates[local] + latent_gates[z]  # gathered inside the step's loop

    def gate(block: int) -> torch.Tensor:  # sliced before the sigmoid: one loop computes a unit's gates and state
        cols = slice(block * units, (block + 1) * units)
        x = hidden[:, cols] + constant[:, cols] + w_action[0, cols] * action[0][:, None] + w_action[1, cols] * action[1][:, None]
        return sigmoid(x)

    i, f, o, j = gate(0), gate(1), gate(2), gate(3)
    c = c * f + i * (2.0 * j - 1.0)  # c·f + i·tanh(j)
    h = hidden_state(o * (2.0 * sigmoid(2.0 * c) - 1.0), w_hidden)  # o·tanh(c)
    head = _head_product(w_head, head_scale, h) + head_bias
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
    return torch.compile(decode_step, options=COMPILE_OPTIONS)


class FusedDecoder:
    """The decoder of one CVAE prepared for :func:`decode_step`: the hidden-state weights int8 when
    ``quantize``; ``compiled`` runs :func:`compiled_decode_step`.

    ``w_step [u + 8, 4u]`` (rows ``[h, robot_state, action]``), ``latent_gates [Z, 4u]`` and
    ``latent_init [Z, 2u]`` as :class:`~trafficweaving.model.sampler.BatchedRollout` holds them
    (gate columns ``(i, f, o, 2j)``), ``w_head [u, H]``, ``head_bias [H]``, ``output_scale [2]``,
    ``hold_sigma [2]`` or None, ``modes`` (0 or 4) and ``components``."""

    def __init__(self, w_step: torch.Tensor, latent_gates: torch.Tensor, latent_init: torch.Tensor,
                 w_head: torch.Tensor, head_bias: torch.Tensor, output_scale: torch.Tensor,
                 hold_sigma: torch.Tensor | None, modes: int, components: int, quantize: bool = True,
                 compiled: bool = True):
        units, dtype, device = w_head.shape[0], output_scale.dtype, output_scale.device
        hidden, head = w_step[:units].to(dtype), w_head.T.to(dtype)
        if quantize:  # per output (the gates' columns, the head's rows); the scales of products of codes
            (gate_codes, gate_scale), (self.w_head, head_scale) = quantize_rows(hidden.T), quantize_rows(head)
            self.w_hidden, self.hidden_scale = gate_codes.T.contiguous(), gate_scale.T / INT8_RANGE
            self.head_scale = head_scale / INT8_RANGE
        else:
            self.w_hidden, self.w_head = hidden.contiguous(), head.contiguous()
            self.hidden_scale = self.head_scale = torch.ones((), dtype=dtype, device=device)
        self.w_robot, self.w_action = w_step[units:units + 6].to(dtype), w_step[units + 6:].to(dtype).contiguous()  # [6, 4u], [2, 4u]
        self.latent_gates, self.latent_init = latent_gates.contiguous(), latent_init  # [Z, 4u], [Z, 2u]
        self.head_bias = head_bias.to(dtype)[:, None]
        self.output_scale = output_scale
        self.hold_sigma = hold_sigma if hold_sigma is not None else torch.ones(2, dtype=dtype, device=device)
        self.modes, self.components = modes, components
        self.compiled = compiled
        self.step = compiled_decode_step() if compiled else decode_step

    def decode_rows(self, parts: dict, cand: torch.Tensor, z: torch.Tensor, present: torch.Tensor,
                    uniform: torch.Tensor, normal: torch.Tensor, chunk_rows: int) -> torch.Tensor:
        """:meth:`decode` for any number of rows, in chunks of ``chunk_rows`` rows of as few candidates
        as possible (rows sorted by candidate), so that a chunk's gate tables stay in cache."""
        order = torch.argsort(cand, stable=True)
        chunks = [self.decode(parts, cand[rows], z[rows], present, uniform[rows], normal[rows])
                  for rows in order.split(chunk_rows)]
        return torch.empty((len(cand), HORIZON, 2), dtype=uniform.dtype, device=uniform.device).index_copy_(0, order, torch.cat(chunks))

    def decode(self, parts: dict, cand: torch.Tensor, z: torch.Tensor, present: torch.Tensor, uniform: torch.Tensor,
               normal: torch.Tensor) -> torch.Tensor:
        """Actions ``[R, 15, 2]`` of ``R`` rows: candidates ``cand [R]`` into ``parts`` (from
        :meth:`BatchedRollout.encode`: ``x_gates [C, 4u]``, ``x_init [C, 2u]``, ``robot_inputs [15,
        C, 6]``), latent values ``z [R]``, the present action ``present [2]``, ``uniform [R, 15]``
        and ``normal [R, 15, 2]``.

        The rows' candidates' constant gate inputs with each step's robot state are tabled first
        (``[15, C', 4u]`` for the ``C'`` distinct candidates), so a step adds one row of a table."""
        units = self.latent_init.shape[1] // 2
        init = parts["x_init"].index_select(0, cand).add_(self.latent_init.index_select(0, z))  # [R, 2u]
        init.mul_(2.0).sigmoid_().mul_(2.0).sub_(1.0)  # tanh, as 2σ(2x) − 1 (PyTorch's CPU tanh is slower)
        c, h = init[:, :units].contiguous(), hidden_state(init[:, units:].contiguous(), self.w_hidden)
        distinct, local = torch.unique(cand, return_inverse=True)
        tables = torch.baddbmm(parts["x_gates"].index_select(0, distinct).unsqueeze(0),  # [15, C', 4u]
                               parts["robot_inputs"].index_select(1, distinct), self.w_robot.expand(HORIZON, -1, -1))
        uniform, normal = uniform.T.contiguous(), normal.permute(1, 2, 0).contiguous()  # [15, R], [15, 2, R]
        action = present[:, None].expand(2, len(cand)).contiguous()
        if self.compiled:  # one kernel for every number of rows and of candidates (and every step's new tensors)
            torch._dynamo.mark_dynamic(local, 0)
            torch._dynamo.mark_dynamic(z, 0)
        actions = []
        for k in range(HORIZON):
            step_inputs = (tables[k], uniform[k], normal[k])
            if self.compiled:
                for x, dim in ((c, 0), (h, 0), (action, 1), (step_inputs[0], 0), (step_inputs[1], 0), (step_inputs[2], 1)):
                    torch._dynamo.mark_dynamic(x, dim)
            c, h, action = self.step(c, h, action, local, z, step_inputs[0], self.latent_gates, *step_inputs[1:],
                                     self.w_hidden, self.hidden_scale, self.w_action, self.w_head, self.head_scale,
                                     self.head_bias, self.output_scale, self.hold_sigma, self.modes, self.components)
            actions.append(action)
        return torch.stack(actions).permute(2, 0, 1)
