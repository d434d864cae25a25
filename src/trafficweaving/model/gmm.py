"""The decoder's per-step output distribution over the human's action ``[xdd, ydd]``.

* :class:`GMM`: the paper's bivariate Gaussian mixture (§III-A) as the authors' code builds it: 16
  components, clipped log-sigma, per-step log density capped at 50.
* :class:`HoldMixture`: the ``cvae-hold`` variant's output. Real drivers control intermittently:
  they set the pedal or the wheel and leave it, so the next acceleration often *equals* the
  previous one in one direction or both. The hold mixture puts weight ``w`` on four modes

  ==========  ==========================================  =================================
  mode        longitudinal ``xdd``                        lateral ``ydd``
  ==========  ==========================================  =================================
  free        the GMM (jointly, with its correlation)     the GMM
  hold x      ``N(previous_x, s_x²)``                     the GMM's lateral marginal
  hold y      the GMM's longitudinal marginal             ``N(previous_y, s_y²)``
  hold both   ``N(previous_x, s_x²)``                     ``N(previous_y, s_y²)``
  ==========  ==========================================  =================================

  with mode weights from the decoder state and learned widths ``s`` (one per direction, at least
  :data:`HOLD_MIN_SIGMA`). Every tensor is in standardised units.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

LOG_SIGMA_CLIP = 10.0
LOG_DENSITY_CAP = 50.0
HOLD_MODES = ("free", "hold x", "hold y", "hold both")
HOLD_OFF_LOGIT = -20.0
"""Mode logit of each hold mode in a head switched off (:meth:`HoldHead.switch_off`): weights of
about 2e-9, so the output is the GMM's density to well under 1e-4 nats per 15-step instance, while
the hold modes still get a gradient to switch on."""
HOLD_MIN_SIGMA = 1e-3
"""Smallest width of a hold component (standardised units, about 0.002 m/s²): real recordings
are float32, and a width below their resolution would only measure rounding."""
_LOG_2PI = math.log(2.0 * math.pi)


def _normal_log_density(y: torch.Tensor, mu: torch.Tensor, log_sigma: torch.Tensor) -> torch.Tensor:
    """Elementwise 1-D normal log density."""
    return -0.5 * _LOG_2PI - log_sigma - 0.5 * ((y - mu) / log_sigma.exp()).square()


@dataclass
class GMM:
    """Mixture parameters with leading batch dims ``[...]`` and ``M`` components:
    ``log_pi [..., M]`` (normalised), ``mu [..., M, 2]``, ``log_sigma [..., M, 2]`` (clipped),
    ``corr [..., M]`` in (-1, 1)."""

    log_pi: torch.Tensor
    mu: torch.Tensor
    log_sigma: torch.Tensor
    corr: torch.Tensor

    def log_density(self, y: torch.Tensor) -> torch.Tensor:
        """Uncapped log density of ``y [..., 2]``, ``[...]``."""
        sigma = self.log_sigma.exp()
        d = (y.unsqueeze(-2) - self.mu) / sigma  # [..., M, 2]
        dx, dy = d[..., 0], d[..., 1]
        one_minus_r2 = 1.0 - self.corr.square()
        quad = (dx.square() + dy.square() - 2.0 * self.corr * dx * dy) / one_minus_r2
        log_n = -_LOG_2PI - self.log_sigma.sum(-1) - 0.5 * torch.log(one_minus_r2) - 0.5 * quad
        return torch.logsumexp(self.log_pi + log_n, dim=-1)

    def marginal_log_density(self, y: torch.Tensor, dim: int) -> torch.Tensor:
        """Uncapped log density of direction ``dim`` (0: x, 1: y) of ``y [..., 2]``, ``[...]``."""
        log_n = _normal_log_density(y[..., dim].unsqueeze(-1), self.mu[..., dim], self.log_sigma[..., dim])
        return torch.logsumexp(self.log_pi + log_n, dim=-1)

    def log_prob(self, y: torch.Tensor) -> torch.Tensor:
        """Log density of ``y [..., 2]``, capped at ``LOG_DENSITY_CAP``; returns ``[...]``."""
        return self.log_density(y).clamp(max=LOG_DENSITY_CAP)

    def marginal_log_prob(self, y: torch.Tensor, dim: int) -> torch.Tensor:
        """Capped log density of direction ``dim`` (0: x, 1: y) of ``y [..., 2]``, ``[...]``."""
        return self.marginal_log_density(y, dim).clamp(max=LOG_DENSITY_CAP)

    def component(self, uniform: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The component chosen by inverse CDF from ``uniform [...]``: its ``mu [..., 2]``,
        ``sigma [..., 2]`` and ``corr [...]``."""
        cdf = torch.cumsum(self.log_pi.exp(), dim=-1)
        k = (cdf < uniform.unsqueeze(-1)).sum(-1, keepdim=True).clamp(max=self.log_pi.shape[-1] - 1)  # [..., 1]
        mu = torch.gather(self.mu, -2, k.unsqueeze(-1).expand(*k.shape, 2)).squeeze(-2)
        sigma = torch.gather(self.log_sigma, -2, k.unsqueeze(-1).expand(*k.shape, 2)).squeeze(-2).exp()
        return mu, sigma, torch.gather(self.corr, -1, k).squeeze(-1)

    def sample(self, generator: torch.Generator | None = None, uniform: torch.Tensor | None = None,
               normal: torch.Tensor | None = None) -> torch.Tensor:
        """One draw per batch element, ``[..., 2]``: the component by inverse-CDF sampling with
        ``uniform [...]``, then the correlated bivariate normal from ``normal [..., 2]`` (both drawn
        from ``generator`` when not given)."""
        uniform, normal = _draws(self.log_pi, generator, uniform, normal)
        mu, sigma, corr = self.component(uniform)
        second = corr * normal[..., 0] + torch.sqrt(1.0 - corr.square()) * normal[..., 1]
        return mu + sigma * torch.stack([normal[..., 0], second], dim=-1)


def _draws(like: torch.Tensor, generator, uniform, normal) -> tuple[torch.Tensor, torch.Tensor]:
    """``uniform [...]`` and ``normal [..., 2]`` for batch dims ``like.shape[:-1]``, drawn when None."""
    batch = like.shape[:-1]
    options = {"generator": generator, "device": like.device, "dtype": like.dtype}
    uniform = torch.rand(batch, **options) if uniform is None else uniform
    normal = torch.randn((*batch, 2), **options) if normal is None else normal
    return uniform, normal


def split_uniform(log_w: torch.Tensor, uniform: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Inverse-CDF choice among ``log_w [..., K]`` (normalised) with ``uniform [...]``: the chosen
    index ``[...]`` and a fresh uniform ``[...]`` (``uniform`` rescaled within the chosen interval,
    so one random number picks both the mode and the GMM component)."""
    w = log_w.exp()
    cdf = torch.cumsum(w, dim=-1)
    mode = (cdf < uniform.unsqueeze(-1)).sum(-1, keepdim=True).clamp(max=w.shape[-1] - 1)
    upper, width = torch.gather(cdf, -1, mode).squeeze(-1), torch.gather(w, -1, mode).squeeze(-1)
    rest = ((uniform - (upper - width)) / width.clamp_min(1e-30)).clamp(0.0, 1.0)
    return mode.squeeze(-1), rest


@dataclass
class HoldMixture:
    """The hold-aware output (module docstring): ``log_w [..., 4]`` mode weights (normalised, in
    :data:`HOLD_MODES` order), ``log_s [2]`` hold widths, ``previous [..., 2]`` the action fed to
    the decoder at this step (the previous action), and the free-mode :class:`GMM`."""

    log_w: torch.Tensor
    log_s: torch.Tensor
    previous: torch.Tensor
    gmm: GMM

    def _mode_log_densities(self, y: torch.Tensor) -> torch.Tensor:
        """``[..., 4]`` log densities of ``y [..., 2]`` under each mode (uncapped)."""
        hold = _normal_log_density(y, self.previous, self.log_s)  # [..., 2]
        gx, gy = self.gmm.marginal_log_density(y, 0), self.gmm.marginal_log_density(y, 1)
        modes = (self.gmm.log_density(y), hold[..., 0] + gy, gx + hold[..., 1], hold.sum(-1))
        return torch.stack(torch.broadcast_tensors(*modes), dim=-1)

    def log_prob(self, y: torch.Tensor) -> torch.Tensor:
        """Log density of ``y [..., 2]``, capped at ``LOG_DENSITY_CAP``; returns ``[...]``."""
        return torch.logsumexp(self.log_w + self._mode_log_densities(y), dim=-1).clamp(max=LOG_DENSITY_CAP)

    def marginal_log_prob(self, y: torch.Tensor, dim: int) -> torch.Tensor:
        """Capped log density of direction ``dim`` (0: x, 1: y) of ``y [..., 2]``, ``[...]``."""
        held = _normal_log_density(y[..., dim], self.previous[..., dim], self.log_s[dim])
        free = self.gmm.marginal_log_density(y, dim)
        holds_dim = torch.tensor([False, dim == 0, dim == 1, True], device=y.device)  # modes holding `dim`
        per_mode = torch.where(holds_dim, held.unsqueeze(-1), free.unsqueeze(-1))
        return torch.logsumexp(self.log_w + per_mode, dim=-1).clamp(max=LOG_DENSITY_CAP)

    def sample(self, generator: torch.Generator | None = None, uniform: torch.Tensor | None = None,
               normal: torch.Tensor | None = None) -> torch.Tensor:
        """One draw per batch element, ``[..., 2]``, from one ``uniform [...]`` (mode, then GMM
        component: :func:`split_uniform`) and ``normal [..., 2]`` (drawn from ``generator`` when not
        given). The free mode draws the GMM jointly; a mode holding one direction draws the other
        from its marginal with the normal of that direction, so the two directions are independent."""
        uniform, normal = _draws(self.log_w, generator, uniform, normal)
        mode, rest = split_uniform(self.log_w, uniform)
        mu, sigma, corr = self.gmm.component(rest)
        return compose_hold_sample(mode, mu, sigma, corr, self.previous.expand_as(mu), self.log_s.exp(), normal)


def compose_hold_sample(mode: torch.Tensor, mu: torch.Tensor, sigma: torch.Tensor, corr: torch.Tensor,
                        previous: torch.Tensor, hold_sigma: torch.Tensor, normal: torch.Tensor) -> torch.Tensor:
    """A hold-mixture draw ``[R, 2]`` (or ``[..., 2]``) from its mode ``[...]``, the chosen GMM
    component (``mu``, ``sigma [..., 2]``, ``corr [...]``), the previous action ``[..., 2]``, the
    hold widths ``[2]`` and standard normals ``[..., 2]``."""
    free_y = corr * normal[..., 0] + torch.sqrt(1.0 - corr.square()) * normal[..., 1]
    holds_x, holds_y = (mode == 1) | (mode == 3), (mode == 2) | (mode == 3)
    lateral = torch.where(mode == 0, free_y, normal[..., 1])
    gmm_draw = mu + sigma * torch.stack([normal[..., 0], lateral], dim=-1)
    held = previous + hold_sigma * normal
    return torch.where(torch.stack([holds_x, holds_y], dim=-1), held, gmm_draw)


class GMMHead(nn.Module):
    """Decoder output ``[..., units]`` -> :class:`GMM` with ``components`` bivariate components."""

    def __init__(self, units: int, components: int):
        super().__init__()
        self.components = components
        self.log_pi = nn.Linear(units, components)
        self.mu = nn.Linear(units, 2 * components)
        self.log_sigma = nn.Linear(units, 2 * components)
        self.corr = nn.Linear(units, components)

    def forward(self, h: torch.Tensor, log_scale: torch.Tensor | float = 0.0) -> GMM:
        """``h [..., units]``; ``log_scale`` is added to every (clipped) log-sigma (calibration)."""
        shape = (*h.shape[:-1], self.components, 2)
        return GMM(
            log_pi=F.log_softmax(self.log_pi(h), dim=-1),
            mu=self.mu(h).view(shape),
            log_sigma=self.log_sigma(h).clamp(-LOG_SIGMA_CLIP, LOG_SIGMA_CLIP).view(shape) + log_scale,
            corr=torch.tanh(self.corr(h)),
        )


class HoldHead(nn.Module):
    """Mode weights of :class:`HoldMixture` from the decoder output (``logits``: Linear(units → 4))
    and the learned hold widths (``log_sigma [2]``, kept at least ``log HOLD_MIN_SIGMA``)."""

    def __init__(self, units: int):
        super().__init__()
        self.logits = nn.Linear(units, len(HOLD_MODES))
        self.log_sigma = nn.Parameter(torch.full((2,), math.log(0.05)))

    @torch.no_grad()
    def switch_off(self) -> "HoldHead":
        """Hold modes off: constant mode logits (free 0, each hold mode :data:`HOLD_OFF_LOGIT`), so
        the output is the free GMM's (a paper model upgraded to ``cvae-hold`` starts as it was)."""
        self.logits.weight.zero_()
        self.logits.bias.copy_(torch.tensor([0.0] + [HOLD_OFF_LOGIT] * (len(HOLD_MODES) - 1)))
        return self

    def widths(self) -> torch.Tensor:
        """``log s [2]``, clamped below at ``log HOLD_MIN_SIGMA``."""
        return self.log_sigma.clamp(min=math.log(HOLD_MIN_SIGMA), max=LOG_SIGMA_CLIP)

    def forward(self, h: torch.Tensor, gmm: GMM, previous: torch.Tensor) -> HoldMixture:
        """``h [..., units]``, the free-mode ``gmm`` and ``previous [..., 2]`` (broadcastable)."""
        return HoldMixture(F.log_softmax(self.logits(h), dim=-1), self.widths(), previous, gmm)
