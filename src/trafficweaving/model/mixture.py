"""A mixture of human models: ``p(y|x) = Σ_c w_c p_c(y|x)``.

An ensemble of CVAEs trained from different starting points is one more calibration of the
predictive distribution (docs/calibration.md): the shipped ``default`` mixes the model fine-tuned on
the 30 real trials with the authors' published model, which saw 1105 real trials and keeps mass on
driving that 30 trials do not show; the weight is chosen out-of-fold (``calibrate --companion``).

Equivalently, the mixture is one CVAE whose latent variable is the pair (component, component's
latent value): :attr:`latent_values` counts them, and a sample's latent value ``k`` is component
``c``'s value ``k - offset_c``. The components share the standardisation (so one standardised
batch serves all) and the conditioning on the robot's future; each keeps its own calibration.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Sequence

import torch
from torch import nn

from ..scenario import HORIZON
from .cvae import ACTION_DIM, CVAE, Batch


FACING = ("robot", "person")
"""Who the other car is, for a driver whose mixture weights depend on it (:func:`facing`)."""


class Mixture(nn.Module):
    """Components ``[CVAE, ...]`` (at least two) with ``weights`` (positive, normalised here), and
    optionally other weights ``person_weights`` (non-negative, not all zero) for a driver whose
    other car is a person (:func:`facing`)."""

    def __init__(self, components: Sequence[CVAE], weights: Sequence[float],
                 person_weights: Sequence[float] | None = None):
        super().__init__()
        if len(components) < 2 or len(weights) != len(components):
            raise ValueError(f"a mixture needs at least two components and one weight each, got {len(components)} "
                             f"and {len(weights)}")
        for c in components:
            check_mixable(components[0], c)
        w = normalised(weights, len(components), positive=True)
        if w is None:
            raise ValueError(f"mixture weights must be one per component, positive and finite, with a finite sum, "
                             f"got {_listed(weights)}")
        self.components = nn.ModuleList(components)
        self.register_buffer("log_weights", torch.log(w))
        self.person_weights = None
        if person_weights is not None:
            p = normalised(person_weights, len(components), positive=False)
            if p is None:
                raise ValueError(f"mixture weights facing a person must be one per component, non-negative and finite, "
                                 f"not all zero, with a finite sum, got {_listed(person_weights)}")
            self.person_weights = p.tolist()

    @property
    def weights(self) -> list[float]:
        """The components' weights (sum 1)."""
        return self.log_weights.double().exp().tolist()

    @property
    def config(self):
        """The first component's :class:`~trafficweaving.model.cvae.CVAEConfig` (the conditioning and
        standardisation every component shares)."""
        return self.components[0].config

    @property
    def latent_offsets(self) -> list[int]:
        """The first joint latent value of each component (then ``latent_values``)."""
        sizes = [c.config.latent_values for c in self.components]
        return [sum(sizes[:k]) for k in range(len(sizes) + 1)]

    @property
    def latent_values(self) -> int:
        """The number of (component, latent value) pairs."""
        return self.latent_offsets[-1]

    # the shared standardisation
    feature_mean = property(lambda self: self.components[0].feature_mean)
    feature_std = property(lambda self: self.components[0].feature_std)
    label_mean = property(lambda self: self.components[0].label_mean)
    label_std = property(lambda self: self.components[0].label_std)

    def states_to_standard(self, states: torch.Tensor) -> torch.Tensor:
        return self.components[0].states_to_standard(states)

    def actions_to_standard(self, actions: torch.Tensor) -> torch.Tensor:
        return self.components[0].actions_to_standard(actions)

    def actions_to_physical(self, actions: torch.Tensor) -> torch.Tensor:
        return self.components[0].actions_to_physical(actions)

    def situations(self, histories: torch.Tensor, robot_futures: torch.Tensor) -> Batch:
        return self.components[0].situations(histories, robot_futures)

    @torch.no_grad()
    def sample_futures(self, batch: Batch, samples: int, generator: torch.Generator | None = None) -> torch.Tensor:
        """``samples`` futures per situation ``[S, B, 15, 2]`` (standardised): each draws its
        component by weight (one draw per sample, shared by the batch's situations), then a future
        from that component (:meth:`CVAE.sample_futures`)."""
        device = self.log_weights.device
        which = torch.multinomial(self.log_weights.exp(), samples, replacement=True, generator=generator)
        out = torch.empty((samples, len(batch.t), HORIZON, ACTION_DIM), dtype=batch.history.dtype, device=device)
        for k, component in enumerate(self.components):
            rows = torch.nonzero(which == k).squeeze(1)
            if len(rows):
                out[rows] = component.sample_futures(batch, len(rows), generator).to(out.dtype)
        return out


def normalised(weights, count: int, positive: bool) -> torch.Tensor | None:
    """``weights`` (``count`` numbers) divided by their sum as float64 ``[count]``, or None unless
    they are finite and positive (``positive``) or non-negative and not all zero, with a finite
    sum: weights that overflow when summed cannot be normalised."""
    try:
        w = torch.as_tensor(weights, dtype=torch.float64).detach().cpu()
    except (TypeError, ValueError, RuntimeError):
        return None
    if w.shape != (count,) or not torch.isfinite(w).all() or not ((w > 0).all() if positive else (w >= 0).all()):
        return None
    total = w.sum()
    return w / total if torch.isfinite(total) and total > 0 else None


def _listed(weights) -> list:
    return weights.tolist() if isinstance(weights, torch.Tensor) else list(weights)


STANDARDISATION = ("feature_mean", "feature_std", "label_mean", "label_std")
"""The buffers every component shares: the first component's standardise the inputs and turn
every component's sampled actions back into m/s²."""


def check_mixable(first: CVAE, other: CVAE) -> None:
    """ValueError unless ``other`` can be a component of a :class:`Mixture` whose first component is
    ``first``: a model (not a mixture) conditioned on the same robot future, with the same
    standardisation (:data:`STANDARDISATION`)."""
    if not isinstance(other, CVAE):
        raise ValueError(f"mixture components must be models, got a {type(other).__name__}")
    if other.config.robot_future != first.config.robot_future:
        raise ValueError(f"mixture components must condition on the same robot future, got "
                         f"{first.config.robot_future} and {other.config.robot_future}")
    a, b = ([getattr(m, n).detach().double().cpu() for n in STANDARDISATION] for m in (first, other))
    if not all(x.shape == y.shape and torch.allclose(x, y) for x, y in zip(a, b)):
        raise ValueError("mixture components must share the standardisation (fine-tune one from the other)")


def companion_for(model: CVAE, companion: CVAE | Mixture) -> CVAE:
    """``companion`` ready to be mixed with ``model`` (``mix``, ``calibrate --companion``): one
    model, conditioned like ``model`` (:func:`conditioned_on`), that :func:`check_mixable` accepts;
    ValueError otherwise."""
    if isinstance(companion, Mixture):
        raise ValueError("is a mixture (expected one model)")
    companion = conditioned_on(companion, model.config.robot_future)
    check_mixable(model, companion)
    return companion


def facing(model: CVAE | Mixture, other: str) -> CVAE | Mixture:
    """The model of a driver whose other car is ``other`` (one of :data:`FACING`): ``model`` itself,
    except a mixture with ``person_weights`` facing a person: its components so weighted (one
    alone when only one has weight). People drive against a robot differently from against a
    person: the shipped ``driver`` is fine-tuned on people facing the authors' planner and mixed
    with the authors' model of people facing people (docs/realism.md)."""
    if other not in FACING:
        raise ValueError(f"other car {other!r} is unknown (expected one of {', '.join(FACING)})")
    if other == "robot" or not isinstance(model, Mixture) or model.person_weights is None:
        return model
    kept = [(c, w) for c, w in zip(model.components, model.person_weights) if w > 0]
    if len(kept) == 1:
        return kept[0][0]
    return Mixture([c for c, _ in kept], [w for _, w in kept]).eval()


def conditioned_on(model: CVAE, robot_future: str) -> CVAE:
    """``model`` conditioned on ``robot_future`` (:attr:`CVAEConfig.robot_future`), weights kept:
    e.g. the authors' model, trained on recorded futures, given the guess a driver model drives with
    (``train --init authors:PATH --robot-future guess`` starts from it; ``mix`` mixes it so)."""
    if model.config.robot_future != robot_future:
        model.config = replace(model.config, robot_future=robot_future)
    return model


def describe(model: CVAE | Mixture) -> str:
    """A model's variant for people: ``cvae-hold``, or ``mixture of cvae-hold (0.95), cvae (0.05)``."""
    if isinstance(model, Mixture):
        weights = lambda ws: ", ".join(f"{c.config.name} ({w:.3g})" for c, w in zip(model.components, ws))  # noqa: E731
        person = f"; facing a person {weights(model.person_weights)}" if model.person_weights is not None else ""
        return f"mixture of {weights(model.weights)}{person}"
    return model.config.name
