"""The LSTM cell of the authors' model (TensorFlow's ``LayerNormBasicLSTMCell`` without layer norm).

One kernel over ``concat(input, h)`` gives the gates in the order ``i, j, f, o``;
``c' = c·σ(f + 1) + σ(i)·tanh(j)``, ``h' = tanh(c')·σ(o)``. Recurrent dropout, in training only,
drops ``tanh(j)``. The kernel is kept in TensorFlow's ``[inputs, 4·units]`` layout, split into its
input rows and its recurrent rows, so that the input part of a whole sequence can be projected in
one matrix multiply and only the recurrent part runs step by step.
"""

from __future__ import annotations

import torch
from torch import nn

FORGET_BIAS = 1.0


def _tanh(x: torch.Tensor) -> torch.Tensor:
    """``tanh(x)`` as ``2σ(2x) - 1``: the same function, several times faster than PyTorch's CPU tanh."""
    return 2.0 * torch.sigmoid(2.0 * x) - 1.0


class LSTMCell(nn.Module):
    """``input_size`` inputs, ``units`` hidden units; parameters ``weight_input [input_size, 4u]``,
    ``weight_hidden [u, 4u]``, ``bias [4u]`` (TensorFlow's kernel = ``cat(weight_input, weight_hidden)``)."""

    def __init__(self, input_size: int, units: int):
        super().__init__()
        self.input_size, self.units = input_size, units
        kernel = torch.empty(input_size + units, 4 * units)
        nn.init.xavier_uniform_(kernel)  # TensorFlow's default (Glorot uniform over the whole kernel)
        self.weight_input = nn.Parameter(kernel[:input_size].clone())
        self.weight_hidden = nn.Parameter(kernel[input_size:].clone())
        self.bias = nn.Parameter(torch.zeros(4 * units))

    def project(self, inputs: torch.Tensor) -> torch.Tensor:
        """Input part of the gates, ``[..., input_size] -> [..., 4u]`` (bias included)."""
        return torch.matmul(inputs, self.weight_input) + self.bias

    def step(self, gates_in: torch.Tensor, state: tuple[torch.Tensor, torch.Tensor],
             keep: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """One step from projected inputs ``gates_in [B, 4u]`` and ``state = (c, h)`` (each ``[B, u]``);
        returns the new ``(c, h)``. ``keep [B, u]`` is the recurrent-dropout mask, already scaled
        by 1/keep-probability (None in evaluation; see :func:`dropout_masks`)."""
        c, h = state
        gates = torch.addmm(gates_in, h, self.weight_hidden)
        i, j, f, o = gates.chunk(4, dim=-1)
        g = _tanh(j)
        if keep is not None:
            g = g * keep
        c = c * torch.sigmoid(f + FORGET_BIAS) + torch.sigmoid(i) * g
        return c, _tanh(c) * torch.sigmoid(o)

    def run(self, inputs: torch.Tensor, state: tuple[torch.Tensor, torch.Tensor] | None = None,
            dropout: float = 0.0) -> tuple[torch.Tensor, tuple[torch.Tensor, torch.Tensor]]:
        """Run over ``inputs [B, L, input_size]`` from ``state`` (zeros when None); returns the
        outputs ``h`` of every step ``[B, L, u]`` and the final ``(c, h)``. Without dropout this
        is PyTorch's fused LSTM (same function, gates reordered, forget bias folded in)."""
        batch, steps = inputs.shape[:2]
        if state is None:
            zeros = inputs.new_zeros(batch, self.units)
            state = (zeros, zeros)
        if dropout <= 0.0:
            return self._run_fused(inputs, state)
        gates_in = self.project(inputs)
        keep = dropout_masks(steps, batch, self.units, dropout, inputs)
        outputs = []
        for k in range(steps):
            state = self.step(gates_in[:, k], state, None if keep is None else keep[k])
            outputs.append(state[1])
        return torch.stack(outputs, dim=1), state

    def _run_fused(self, inputs: torch.Tensor, state: tuple[torch.Tensor, torch.Tensor]):
        def reorder(w):  # gates (i, j, f, o) -> PyTorch's (i, f, g=j, o), as [4u, ·]
            i, j, f, o = w.chunk(4, dim=-1)
            return torch.cat([i, f, j, o], dim=-1)

        bias = reorder(self.bias.unsqueeze(0))[0] + torch.cat(
            [torch.zeros_like(self.bias[: self.units]), torch.full_like(self.bias[: self.units], FORGET_BIAS),
             torch.zeros_like(self.bias[: 2 * self.units])])
        c, h = state
        weights = [reorder(self.weight_input).T, reorder(self.weight_hidden).T, bias, torch.zeros_like(bias)]
        outputs, h_n, c_n = torch.lstm(inputs, (h.unsqueeze(0).contiguous(), c.unsqueeze(0).contiguous()), weights,
                                       True, 1, 0.0, self.training, False, True)
        return outputs, (c_n[0], h_n[0])


def dropout_masks(steps: int, batch: int, units: int, dropout: float, like: torch.Tensor) -> torch.Tensor | None:
    """Recurrent-dropout masks for a whole sequence in one draw, ``[steps, batch, units]``, each
    element 0 with probability ``dropout`` and ``1/(1-dropout)`` otherwise; None when ``dropout`` is 0."""
    if dropout <= 0.0:
        return None
    keep = 1.0 - dropout
    return torch.bernoulli(torch.full((steps, batch, units), keep, dtype=like.dtype, device=like.device)) / keep


class StateProjection(nn.Module):
    """Initial LSTM state from a vector: ``(tanh(W_c v + b_c), tanh(W_h v + b_h))``."""

    def __init__(self, input_size: int, units: int):
        super().__init__()
        self.initial_c = nn.Linear(input_size, units)
        self.initial_h = nn.Linear(input_size, units)

    def forward(self, v: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return torch.tanh(self.initial_c(v)), torch.tanh(self.initial_h(v))


class SequenceSummary(nn.Module):
    """Bidirectional LSTM over a fixed-length sequence, both directions sharing one cell.

    The forward direction starts from a state projected from a "present" vector, the backward
    direction from zeros; the summary is ``concat(fw_c, fw_h, bw_c, bw_h)`` of the final states
    (``4·units``). Both directions run as one batch of ``2B``.
    """

    def __init__(self, input_size: int, present_size: int, units: int):
        super().__init__()
        self.cell = LSTMCell(input_size, units)
        self.initial_state = StateProjection(present_size, units)

    def forward(self, sequence: torch.Tensor, present: torch.Tensor, dropout: float = 0.0) -> torch.Tensor:
        """``sequence [B, L, input_size]``, ``present [B, present_size]`` -> ``[B, 4·units]``."""
        batch = sequence.shape[0]
        c0, h0 = self.initial_state(present)
        zeros = torch.zeros_like(c0)
        both = torch.cat([sequence, sequence.flip(1)], dim=0)
        _, (c, h) = self.cell.run(both, (torch.cat([c0, zeros]), torch.cat([h0, zeros])), dropout)
        return torch.cat([c[:batch], h[:batch], c[batch:], h[batch:]], dim=-1)
