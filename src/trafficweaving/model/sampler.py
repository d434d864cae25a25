"""Fast batched sampling of human futures for planning: one history, many candidate robot futures,
many samples each, in the model's standardised units (:class:`~trafficweaving.model.predictor.HumanPredictor`
converts physical units).

The same distribution as :meth:`CVAE.sample_actions` (given the same random numbers it returns
the same samples, to rounding), reorganised for throughput:

* the decoder's input is ``[z, x, robot_state, action]``; the ``z`` and ``x`` parts are constant
  over the 15 steps and ``z`` is one of 25 one-hot values, so their gate (and initial-state)
  contributions are one row of a 25-row table plus one row per candidate, computed once;
* each step's gates are one matrix multiply ``[h, robot_state, action] @ [W_h; W_robot; W_action]``
  added to the constant part, from one row buffer that the step writes ``h`` and the sampled
  action into;
* gate columns are reordered ``(i, f, o, j)``, the forget bias is folded into the bias and the
  ``j`` columns are doubled, so that one in-place sigmoid gives every gate: ``tanh(x) = 2σ(2x) - 1``
  (PyTorch's CPU ``tanh`` costs about seven sigmoids); the gate arithmetic runs in place;
* the mixture component is drawn by inverse CDF from one uniform (no Gumbel logarithms); with the
  hold-aware output (``cvae-hold``) the same uniform first picks the hold mode
  (:func:`~trafficweaving.model.gmm.split_uniform`), exactly as the model's own sampling does;
* rows run in cache-sized chunks (:func:`chunk_rows_for`).

With ``fused`` (always with int8 matrix multiplies) the steps run in
:mod:`~trafficweaving.model.fused_decoder` instead: fused and compiled.
"""

from __future__ import annotations

import torch

from ..scenario import HORIZON
from .cvae import CVAE, STATE_DIM
from .fused_decoder import FusedDecoder
from .lstm import FORGET_BIAS
from .gmm import HOLD_MODES, LOG_SIGMA_CLIP, compose_hold_sample, split_uniform
from .mixture import Mixture

CHUNK_ROW_UNITS = 2**17
"""Decoder rows × decoder units per chunk (:func:`chunk_rows_for`)."""
MIN_CHUNK_ROWS = 2048
"""Fewest decoder rows per chunk by default (:func:`chunk_rows_for`)."""


def chunk_rows_for(units: int) -> int:
    """Decoder rows per chunk for a decoder of ``units`` units: :data:`MIN_CHUNK_ROWS`, or as many
    as hold :data:`CHUNK_ROW_UNITS` row-units for a narrower decoder, whose rows are cheaper, so a
    chunk's fixed costs (15 step calls) are shared by more rows. Measured in full plans on two cores
    of an AVX-512 CPU: 32 units, 4096-row chunks 0.92× the time of 2048-row ones; 128 units, 1024
    to 4096 rows within 2 % (docs/fast_model.md, Speed)."""
    return max(MIN_CHUNK_ROWS, CHUNK_ROW_UNITS // units)


def _rows(context: dict, latents: torch.Tensor, candidates: torch.Tensor | None, generator: torch.Generator | None,
          noise: tuple[torch.Tensor, torch.Tensor] | None, common: bool) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The decoder rows of ``latents [n, C']``, row ``r`` = (sample ``r // C'``, candidate ``r % C'``):
    their candidate indices ``[nC']``, uniforms ``[nC', 15]`` and normals ``[nC', 15, 2]`` (drawn
    from ``generator`` unless ``noise`` gives them; ``common``: one draw per sample, shared by the
    candidates)."""
    n, c_count = latents.shape
    device, dtype = latents.device, context["log_p_joint"].dtype
    cand = torch.arange(c_count, device=device) if candidates is None else candidates
    if noise is None:
        draws = 1 if common else c_count
        uniform = torch.rand((n, draws, HORIZON), generator=generator, device=device, dtype=dtype)
        normal = torch.randn((n, draws, HORIZON, 2), generator=generator, device=device, dtype=dtype)
        uniform = uniform.expand(n, c_count, HORIZON).reshape(-1, HORIZON)
        normal = normal.expand(n, c_count, HORIZON, 2).reshape(-1, HORIZON, 2)
    else:
        uniform, normal = noise[0].reshape(-1, HORIZON), noise[1].reshape(-1, HORIZON, 2)
    return cand.repeat(n), uniform, normal


def _reorder_gates(w: torch.Tensor) -> torch.Tensor:
    """Gate columns from ``(i, j, f, o)`` to ``(i, f, o, 2·j)`` (see the module docstring)."""
    i, j, f, o = w.chunk(4, dim=-1)
    return torch.cat([i, f, o, 2.0 * j], dim=-1)


class BatchedRollout:
    """Batched rollouts of the CVAE's decoder: ``[n, C, 15, 2]`` human action sequences
    (standardised units) for ``C`` candidate robot futures.

    Use :meth:`encode` once per history and candidate set, then :meth:`sample_latents` and
    :meth:`sample` (possibly several times, e.g. for the two planning stages on subsets of
    candidates). ``matmul_dtype``: the dtype of the decoder's matrix multiplies (default: the
    model's; bfloat16 keeps the state and gate arithmetic in the model's dtype); ``fused``: the
    steps run in :class:`~trafficweaving.model.fused_decoder.FusedDecoder` (fused and compiled;
    always with int8).
    """

    def __init__(self, model: CVAE, chunk_rows: int | None = None, matmul_dtype: torch.dtype | None = None,
                 fused: bool = False):
        m, c = model.eval(), model.config
        self.model, self.chunk_rows = m, chunk_rows_for(c.decoder_units) if chunk_rows is None else chunk_rows
        self.matmul_dtype = matmul_dtype or next(model.parameters()).dtype
        self.components = c.components
        units = c.decoder_units
        with torch.no_grad():
            w = _reorder_gates(m.decoder.weight_input)  # [zx + 6 + 2, 4u]
            bias = _reorder_gates(m.decoder.bias.unsqueeze(0))[0].clone()
            bias[units:2 * units] += FORGET_BIAS  # the f block
            nz = c.latent_size
            self.w_gate_z, self.w_gate_x = w[:nz], w[nz:nz + c.x_size]
            # rows for the step buffer [h, robot_state, action]
            self.w_step = torch.cat([_reorder_gates(m.decoder.weight_hidden), w[nz + c.x_size:]]).contiguous()  # [u + 8, 4u]
            self.gate_bias = bias
            init = m.decoder_initial_state
            w_init = torch.cat([init.initial_c.weight, init.initial_h.weight]).T  # [zx, 2u]
            self.w_init_z, self.w_init_x = w_init[:nz], w_init[nz:]
            self.init_bias = torch.cat([init.initial_c.bias, init.initial_h.bias])
            g = m.gmm
            # head columns: log_pi (M), then per component (mu_x, mu_y, log_sigma_x, log_sigma_y, corr)
            m_count = c.components
            per_component = torch.stack([torch.arange(m_count) * 2 + m_count, torch.arange(m_count) * 2 + m_count + 1,
                                         torch.arange(m_count) * 2 + 3 * m_count, torch.arange(m_count) * 2 + 3 * m_count + 1,
                                         torch.arange(m_count) + 5 * m_count], dim=1).flatten()
            order = torch.cat([torch.arange(m_count), per_component])
            head = torch.cat([g.log_pi.weight, g.mu.weight, g.log_sigma.weight, g.corr.weight]).T[:, order]  # [u, 6M]
            self.head_bias = torch.cat([g.log_pi.bias, g.mu.bias, g.log_sigma.bias, g.corr.bias])[order]
            # the hold variant's mode logits go first: head columns [modes (4), log_pi (M), params (5M)]
            self.modes = len(HOLD_MODES) if c.hold else 0
            if c.hold:
                head = torch.cat([m.hold.logits.weight.T, head], dim=1)
                self.head_bias = torch.cat([m.hold.logits.bias, self.head_bias])
                self.hold_sigma = m.hold.widths().exp()
            self.param_offsets = (self.modes + m_count + torch.arange(5)).unsqueeze(0)
            self.output_scale = m.output_scale.detach().clone()  # [2]: x, y
            self.latent_gates = m.latent_onehots @ self.w_gate_z  # [Z, 4u]
            self.latent_init = m.latent_onehots @ self.w_init_z  # [Z, 2u]
            # the fused, compiled steps of fused_decoder.py hold their own (with int8: quantised) weights
            quantize = self.matmul_dtype == torch.int8
            self.fused = (FusedDecoder(self.w_step, self.latent_gates, self.latent_init, head, self.head_bias,
                                       self.output_scale, self.hold_sigma if c.hold else None, self.modes, m_count,
                                       quantize=quantize)
                          if fused or quantize else None)
            if self.fused is None:
                self.w_head = head.contiguous().to(self.matmul_dtype)
                self.head_bias = self.head_bias.to(self.matmul_dtype)
                self.w_step = self.w_step.to(self.matmul_dtype)

    @torch.no_grad()
    def encode(self, history: torch.Tensor, robot_futures: torch.Tensor, present_action: torch.Tensor) -> dict:
        """Per-candidate parts of the decoder for standardised ``history [t+1, 12]`` (robot, human),
        ``robot_futures [C, 15, 6]`` and the human's present action ``present_action [2]``
        (label-standardised): prior logits, constant gates and initial-state inputs, and the robot
        state fed at each decoder step."""
        m = self.model
        c_count = robot_futures.shape[0]
        robot_present = history[-1, :STATE_DIM]
        history_h = m.encode_history(history.unsqueeze(0), torch.tensor([history.shape[0] - 1], device=history.device))
        x = torch.cat([history_h.expand(c_count, -1), m.encode_robot_future(robot_futures, robot_present.expand(c_count, -1))], -1)
        robot_inputs = torch.cat([robot_present.expand(c_count, 1, -1), robot_futures[:, :-1]], dim=1)
        logits = m.p_z_logits(x)
        x_gates, x_init = x @ self.w_gate_x + self.gate_bias, x @ self.w_init_x + self.init_bias  # [C, 4u], [C, 2u]
        robot_inputs = robot_inputs.transpose(0, 1).contiguous()  # [15, C, 6]
        return {"log_p_z": torch.log_softmax(logits, dim=-1),  # [C, N_z, K_z]
                "log_p_joint": m.joint_log_prob(logits),  # [C, Z]
                "present_action": present_action, "x_gates": x_gates, "x_init": x_init, "robot_inputs": robot_inputs}

    def sample_latents(self, context: dict, n: int, generator: torch.Generator | None, candidates: torch.Tensor | None = None,
                       common: bool = False) -> torch.Tensor:
        """Joint latent values ``[n, C']`` drawn from p(z|x) of each candidate (all, or
        ``candidates``; ``common``: Gumbel-max with one draw of noise per sample, shared by the
        candidates)."""
        log_p = context["log_p_z"] if candidates is None else context["log_p_z"][candidates]
        c = self.model.config
        u = torch.rand((n, 1 if common else len(log_p), *log_p.shape[1:]), generator=generator, device=log_p.device,
                       dtype=log_p.dtype)
        classes = torch.argmax(log_p - torch.log(-torch.log(u.clamp_min(1e-20))), dim=-1)  # [n, C', N_z]
        place = c.latent_classes ** torch.arange(c.latent_vars - 1, -1, -1, device=log_p.device)
        return (classes * place).sum(-1)

    @torch.no_grad()
    def sample(self, context: dict, latents: torch.Tensor, candidates: torch.Tensor | None = None,
               generator: torch.Generator | None = None,
               noise: tuple[torch.Tensor, torch.Tensor] | None = None, common: bool = False) -> torch.Tensor:
        """Human actions ``[n, C', 15, 2]`` (standardised) for ``latents [n, C']`` of the
        candidates ``candidates [C']`` (default: all). ``noise`` optionally gives the uniforms
        ``[n, C', 15]`` and normals ``[n, C', 15, 2]`` (as :meth:`CVAE.sample_actions` takes them);
        else they are drawn, with ``common``: one draw per sample, shared by the candidates."""
        n, c_count = latents.shape
        rows_cand, uniform, normal = _rows(context, latents, candidates, generator, noise, common)
        return self.decode_rows(context, rows_cand, latents.reshape(-1), uniform, normal).view(n, c_count, HORIZON, 2)

    def decode_rows(self, context: dict, rows_cand: torch.Tensor, rows_z: torch.Tensor, uniform: torch.Tensor,
                    normal: torch.Tensor) -> torch.Tensor:
        """Actions ``[R, 15, 2]`` (standardised) of ``R`` decoder rows: candidate ``rows_cand [R]``,
        latent value ``rows_z [R]``, uniforms ``[R, 15]`` and normals ``[R, 15, 2]``, in chunks."""
        if self.fused is not None:
            return self.fused.decode_rows(context, rows_cand, rows_z, context["present_action"], uniform, normal,
                                          self.chunk_rows)
        out = torch.empty((len(rows_cand), HORIZON, 2), device=rows_cand.device, dtype=context["log_p_joint"].dtype)
        for start in range(0, len(rows_cand), self.chunk_rows):
            rows = slice(start, start + self.chunk_rows)
            out[rows] = self._decode_chunk(context, rows_cand[rows], rows_z[rows], uniform[rows], normal[rows])
        return out

    def _decode_chunk(self, ctx: dict, cand: torch.Tensor, z: torch.Tensor, uniform: torch.Tensor,
                      normal: torch.Tensor) -> torch.Tensor:
        units = self.latent_init.shape[1] // 2
        rows = len(cand)
        constant = (ctx["x_gates"].index_select(0, cand) + self.latent_gates.index_select(0, z)).to(self.matmul_dtype)  # [R, 4u]
        init = torch.tanh(ctx["x_init"].index_select(0, cand) + self.latent_init.index_select(0, z))
        robot_steps = ctx["robot_inputs"].index_select(1, cand)  # [N, R, 6]
        c = init[:, :units].contiguous()
        mixed = self.matmul_dtype != c.dtype  # matrix multiplies in lower precision, state and gates in full
        step_in = torch.empty((rows, units + STATE_DIM + 2), dtype=self.matmul_dtype, device=c.device)  # [h, robot, action]
        step_in[:, :units] = init[:, units:]
        step_in[:, units + STATE_DIM:] = ctx["present_action"]
        h, robot, action = step_in[:, :units], step_in[:, units:units + STATE_DIM], step_in[:, units + STATE_DIM:]
        uniform, normal = uniform.T.contiguous(), normal.transpose(0, 1).contiguous()  # [N, R], [N, R, 2]
        offsets = self.param_offsets.to(cand.device)
        i, f, o, j = (slice(k * units, (k + 1) * units) for k in range(4))
        squashed = torch.empty_like(c)
        actions = torch.empty((HORIZON, rows, 2), dtype=c.dtype, device=c.device)
        for k in range(HORIZON):
            robot.copy_(robot_steps[k])
            gates = torch.addmm(constant, step_in, self.w_step)
            gates = gates.to(c.dtype) if mixed else gates
            torch.sigmoid_(gates)  # i, f, o and σ(2j)
            c.mul_(gates[:, f]).addcmul_(gates[:, i], gates[:, j], value=2.0).sub_(gates[:, i])  # c·f + i·tanh(j)
            torch.mul(c, 2.0, out=squashed).sigmoid_().mul_(2.0).sub_(1.0)  # tanh(c)
            torch.mul(squashed, gates[:, o], out=h)
            head = torch.addmm(self.head_bias, h, self.w_head)
            previous = actions[k - 1] if k else ctx["present_action"].to(c.dtype).expand(rows, 2)  # full precision
            self._sample_head(head.to(c.dtype) if mixed else head, uniform[k], normal[k], offsets, previous, actions[k])
            action.copy_(actions[k])
        return actions.transpose(0, 1)

    def _sample_head(self, head: torch.Tensor, uniform: torch.Tensor, normal: torch.Tensor, offsets: torch.Tensor,
                     previous: torch.Tensor, out: torch.Tensor) -> None:
        """Draw one action per row into ``out [R, 2]`` from output parameters ``head [R, modes + 6M]``,
        uniforms ``[R]`` (hold mode and component, inverse CDF), normals ``[R, 2]`` and the
        previous actions ``[R, 2]`` (the hold modes' centres)."""
        m_count, modes = self.components, self.modes
        if modes:
            mode, uniform = split_uniform(torch.log_softmax(head[:, :modes], dim=-1), uniform)
        cdf = torch.softmax(head[:, modes:modes + m_count], dim=-1).cumsum_(-1)
        k = (cdf < uniform.unsqueeze(-1)).sum(-1, keepdim=True).clamp_(max=m_count - 1)  # [R, 1]
        params = head.gather(1, 5 * k + offsets)  # [R, 5]: mu_x, mu_y, log_sigma_x, log_sigma_y, corr
        sigma = params[:, 2:4].clamp(-LOG_SIGMA_CLIP, LOG_SIGMA_CLIP).exp_().mul_(self.output_scale)
        corr = torch.tanh(params[:, 4:5])
        if modes:
            out.copy_(compose_hold_sample(mode, params[:, :2], sigma, corr[:, 0], previous, self.hold_sigma, normal))
            return
        correlated = normal.clone()
        correlated[:, 1:].mul_(torch.sqrt(1.0 - corr * corr)).addcmul_(corr, normal[:, :1])
        torch.addcmul(params[:, :2], sigma, correlated, out=out)


class MixtureRollout:
    """:class:`BatchedRollout` for a :class:`~trafficweaving.model.mixture.Mixture`, with the same
    methods: a latent value is a (component, latent value) pair (the mixture's joint latent), each
    row decoded by its component's rollout."""

    def __init__(self, mixture: Mixture, chunk_rows: int | None = None, matmul_dtype: torch.dtype | None = None,
                 fused: bool = False):
        self.model = mixture.eval()
        self.parts = [BatchedRollout(c, chunk_rows, matmul_dtype, fused) for c in mixture.components]
        self.matmul_dtype = self.parts[0].matmul_dtype
        self.offsets = mixture.latent_offsets

    @torch.no_grad()
    def encode(self, history: torch.Tensor, robot_futures: torch.Tensor, present_action: torch.Tensor) -> dict:
        """Each component's :meth:`BatchedRollout.encode` (``parts``) and the mixture's prior over
        its joint latent values ``log_p_joint [C, Σ Z_c]``."""
        parts = [p.encode(history, robot_futures, present_action) for p in self.parts]
        log_w = self.model.log_weights.to(parts[0]["log_p_joint"].dtype)
        return {"parts": parts, "log_p_joint": torch.cat([w + p["log_p_joint"] for w, p in zip(log_w, parts)], dim=-1)}

    def sample_latents(self, context: dict, n: int, generator: torch.Generator | None, candidates: torch.Tensor | None = None,
                       common: bool = False) -> torch.Tensor:
        """Joint latent values ``[n, C']`` of the mixture drawn for each candidate (all, or
        ``candidates``; ``common`` as :meth:`BatchedRollout.sample_latents`)."""
        log_p = context["log_p_joint"] if candidates is None else context["log_p_joint"][candidates]
        u = torch.rand((n, 1 if common else len(log_p), log_p.shape[-1]), generator=generator, device=log_p.device,
                       dtype=log_p.dtype)
        return torch.argmax(log_p - torch.log(-torch.log(u.clamp_min(1e-20))), dim=-1)

    @torch.no_grad()
    def sample(self, context: dict, latents: torch.Tensor, candidates: torch.Tensor | None = None,
               generator: torch.Generator | None = None,
               noise: tuple[torch.Tensor, torch.Tensor] | None = None, common: bool = False) -> torch.Tensor:
        """As :meth:`BatchedRollout.sample`, each row by the component its latent value belongs to."""
        n, c_count = latents.shape
        rows_cand, uniform, normal = _rows(context, latents, candidates, generator, noise, common)
        rows_z = latents.reshape(-1)
        out = torch.empty((len(rows_z), HORIZON, 2), device=rows_z.device, dtype=uniform.dtype)
        for part, ctx, low, high in zip(self.parts, context["parts"], self.offsets, self.offsets[1:]):
            rows = torch.nonzero((rows_z >= low) & (rows_z < high)).squeeze(1)
            if len(rows):
                out[rows] = part.decode_rows(ctx, rows_cand[rows], rows_z[rows] - low, uniform[rows], normal[rows])
        return out.view(n, c_count, HORIZON, 2)


def rollout(model: CVAE | Mixture, chunk_rows: int | None = None, matmul_dtype: torch.dtype | None = None,
            fused: bool = False):
    """The batched rollout of ``model``: :class:`BatchedRollout` or, for a mixture, :class:`MixtureRollout`
    (``chunk_rows``: decoder rows per chunk; None: :func:`chunk_rows_for` the decoder's units;
    ``matmul_dtype`` and ``fused`` as :class:`BatchedRollout`)."""
    if isinstance(model, Mixture):
        return MixtureRollout(model, chunk_rows, matmul_dtype, fused)
    return BatchedRollout(model, chunk_rows, matmul_dtype, fused)
