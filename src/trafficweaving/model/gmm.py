"""Bivariate Gaussian mixtures: the decoder's per-step output distribution over ``[xdd, ydd]``."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

LOG_SIGMA_CLIP = 10.0
LOG_DENSITY_CAP = 50.0
_LOG_2PI = math.log(2.0 * math.pi)


@dataclass
class GMM:
    """Mixture parameters with leading batch dims ``[...]`` and ``M`` components:
    ``log_pi [..., M]`` (normalised), ``mu [..., M, 2]``, ``log_sigma [..., M, 2]`` (clipped),
    ``corr [..., M]`` in (-1, 1)."""

    log_pi: torch.Tensor
    mu: torch.Tensor
    log_sigma: torch.Tensor
    corr: torch.Tensor

    def log_prob(self, y: torch.Tensor) -> torch.Tensor:
        """Log density of ``y [..., 2]``, capped at ``LOG_DENSITY_CAP``; returns ``[...]``."""
        sigma = self.log_sigma.exp()
        d = (y.unsqueeze(-2) - self.mu) / sigma  # [..., M, 2]
        dx, dy = d[..., 0], d[..., 1]
        one_minus_r2 = 1.0 - self.corr.square()
        quad = (dx.square() + dy.square() - 2.0 * self.corr * dx * dy) / one_minus_r2
        log_n = -_LOG_2PI - self.log_sigma.sum(-1) - 0.5 * torch.log(one_minus_r2) - 0.5 * quad
        return torch.logsumexp(self.log_pi + log_n, dim=-1).clamp(max=LOG_DENSITY_CAP)

    def sample(self, generator: torch.Generator | None = None, uniform: torch.Tensor | None = None,
               normal: torch.Tensor | None = None) -> torch.Tensor:
        """One draw per batch element, ``[..., 2]``: the component by inverse-CDF sampling with
        ``uniform [...]``, then the correlated bivariate normal from ``normal [..., 2]`` (both drawn
        from ``generator`` when not given)."""
        batch = self.log_pi.shape[:-1]
        options = {"generator": generator, "device": self.log_pi.device, "dtype": self.log_pi.dtype}
        uniform = torch.rand(batch, **options) if uniform is None else uniform
        normal = torch.randn((*batch, 2), **options) if normal is None else normal
        cdf = torch.cumsum(self.log_pi.exp(), dim=-1)
        k = (cdf < uniform.unsqueeze(-1)).sum(-1, keepdim=True).clamp(max=self.log_pi.shape[-1] - 1)  # [..., 1]
        mu = torch.gather(self.mu, -2, k.unsqueeze(-1).expand(*k.shape, 2)).squeeze(-2)
        sigma = torch.gather(self.log_sigma, -2, k.unsqueeze(-1).expand(*k.shape, 2)).squeeze(-2).exp()
        corr = torch.gather(self.corr, -1, k).squeeze(-1)
        first = normal[..., 0]
        second = corr * normal[..., 0] + torch.sqrt(1.0 - corr.square()) * normal[..., 1]
        return mu + sigma * torch.stack([first, second], dim=-1)


class GMMHead(nn.Module):
    """Decoder output ``[..., units]`` -> :class:`GMM` with ``components`` bivariate components."""

    def __init__(self, units: int, components: int):
        super().__init__()
        self.components = components
        self.log_pi = nn.Linear(units, components)
        self.mu = nn.Linear(units, 2 * components)
        self.log_sigma = nn.Linear(units, 2 * components)
        self.corr = nn.Linear(units, components)

    def forward(self, h: torch.Tensor) -> GMM:
        shape = (*h.shape[:-1], self.components, 2)
        return GMM(
            log_pi=F.log_softmax(self.log_pi(h), dim=-1),
            mu=self.mu(h).view(shape),
            log_sigma=self.log_sigma(h).clamp(-LOG_SIGMA_CLIP, LOG_SIGMA_CLIP).view(shape),
            corr=torch.tanh(self.corr(h)),
        )
