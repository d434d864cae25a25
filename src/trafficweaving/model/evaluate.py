"""The paper's evaluation: negative log-likelihood of the human's 15 future actions, in physical
units (nats per exemplar for the 15×2 accelerations in m/s²).

* exact: ``-log Σ_z p(z|x) p(y|x,z)`` over all joint latent values;
* importance-sampled: ``-log mean_{z~q(z|x,y)} p(z|x) p(y|x,z) / q(z|x,y)`` (needs q);
* naive: ``-log mean_{z~p(z|x)} p(y|x,z)``;
* exact per direction: ``-log Σ_z p(z|x) Π_k p_k(y_k,d | x, z, y_<k)`` with the per-step
  marginal density of direction ``d`` (x longitudinal, y lateral) under teacher forcing (nats for
  the 15 accelerations of one direction; the two do not add up to the exact NLL, which also
  scores how the directions go together).

A :class:`~trafficweaving.model.mixture.Mixture` is scored component by component: each of its
NLLs is ``-log Σ_c w_c exp(-NLL_c)`` (the importance-sampled one only when every component has q).

The latent space is small (25 values), so ``p(y|x,z)`` is computed once for every value and the
sampled estimators gather from it: the same estimates as decoding each sample, much cheaper.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from ..scenario import HORIZON
from .cvae import CVAE
from .exemplars import ExemplarSet, ExemplarTensors
from .mixture import Mixture

MAX_NLL_SAMPLES = 10_000
"""Most latent samples of the sampled NLL estimators (``evaluate --samples``): a batch of 512
instances draws ``[512, samples]`` latent indices and their log weights, 16 bytes each (80 MB)."""


@dataclass
class Evaluation:
    """Per-exemplar NLLs ``[E]`` (physical units); ``nll_is`` is None for a model without q;
    ``nll_direction [E, 2]`` the exact NLL of the x and of the y accelerations alone."""

    nll_exact: np.ndarray
    nll_is: np.ndarray | None
    nll_naive: np.ndarray
    nll_direction: np.ndarray

    def summary(self) -> dict:
        mean = lambda a: None if a is None else float(np.mean(a))  # noqa: E731
        return {"instances": int(len(self.nll_exact)), "nll_exact": mean(self.nll_exact),
                "nll_is": mean(self.nll_is), "nll_naive": mean(self.nll_naive)}


def physical_offset(model: CVAE) -> float:
    """Added to a standardised NLL to express it in physical units: ``15·Σ log std_label``."""
    return float(direction_offsets(model).sum())


def direction_offsets(model: CVAE) -> np.ndarray:
    """Per direction ``[2]``, added to a standardised one-direction NLL: ``15·log std_label[d]``."""
    return HORIZON * torch.log(model.label_std.double()).cpu().numpy()


def _sampled_nll(log_weights: torch.Tensor, proposal_log: torch.Tensor, samples: int,
                 generator: torch.Generator) -> torch.Tensor:
    """``-log mean_k exp(log_weights[z_k])`` with ``z_k`` drawn from ``exp(proposal_log)`` ``[B, Z]``."""
    z = torch.multinomial(proposal_log.exp().cpu(), samples, replacement=True, generator=generator)
    picked = torch.gather(log_weights, 1, z.to(log_weights.device))
    return -(torch.logsumexp(picked, dim=1) - math.log(samples))


def _mixed(parts: list[Evaluation], log_weights: np.ndarray) -> Evaluation:
    """The NLLs of a mixture from its components' ``parts`` and log weights ``[C]``."""
    def mix(arrays):
        if any(a is None for a in arrays):
            return None
        stacked = np.stack(arrays)  # [C, E] or [C, E, 2]
        w = log_weights.reshape(-1, *([1] * (stacked.ndim - 1)))
        return -np.logaddexp.reduce(w - stacked, axis=0)
    return Evaluation(mix([p.nll_exact for p in parts]), mix([p.nll_is for p in parts]),
                      mix([p.nll_naive for p in parts]), mix([p.nll_direction for p in parts]))


@torch.no_grad()
def evaluate_tensors(model: CVAE | Mixture, data: ExemplarTensors, samples: int = 50, seed: int = 0,
                     batch_size: int = 512, index: torch.Tensor | None = None) -> Evaluation:
    """Evaluate ``model`` (evaluation mode) on standardised exemplars (all, or ``index``)."""
    if isinstance(model, Mixture):
        return _mixed([evaluate_tensors(c, data, samples, seed, batch_size, index) for c in model.components],
                      model.log_weights.double().cpu().numpy())
    model.eval()
    generator = torch.Generator().manual_seed(seed)
    index = torch.arange(len(data), device=data.t.device) if index is None else index
    exact, naive, importance, direction = [], [], [], []
    for start in range(0, len(index), batch_size):
        batch = data.batch(index[start:start + batch_size])
        x = model.encode(batch)
        log_p_z = model.joint_log_prob(model.p_z_logits(x))
        log_p_y, dist = model.decode(model.zx(model.latent_onehots.unsqueeze(1), x), batch)
        log_p_y = log_p_y.T  # [B, Z]
        exact.append(-torch.logsumexp(log_p_z + log_p_y, dim=1))
        y = batch.y.unsqueeze(0)
        direction.append(torch.stack([-torch.logsumexp(log_p_z + dist.marginal_log_prob(y, d).sum(-1).T, dim=1)
                                      for d in (0, 1)], dim=1))  # [B, 2]
        naive.append(_sampled_nll(log_p_y, log_p_z, samples, generator))
        if model.config.has_q:
            log_q_z = model.joint_log_prob(model.q_z_logits(x, batch))
            importance.append(_sampled_nll(log_p_z + log_p_y - log_q_z, log_q_z, samples, generator))
    offset = physical_offset(model)
    to_numpy = lambda parts: torch.cat(parts).double().cpu().numpy() + offset  # noqa: E731
    by_direction = torch.cat(direction).double().cpu().numpy() + direction_offsets(model)
    return Evaluation(to_numpy(exact), to_numpy(importance) if importance else None, to_numpy(naive), by_direction)


def evaluate(model: CVAE | Mixture, exemplars: ExemplarSet, samples: int = 50, seed: int = 0, batch_size: int = 512) -> Evaluation:
    """Evaluate ``model`` on every exemplar of ``exemplars`` (physical units, standardised with the
    model's own statistics, on the model's device)."""
    return evaluate_tensors(model, exemplars.standardised(model), samples, seed, batch_size)
