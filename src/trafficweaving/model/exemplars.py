"""Prediction exemplars from trials: ``(history 0..t, other car's future t+1..t+15, human actions
t+1..t+15)`` for every ``4 <= t <= T-16``, and the state statistics the model's standardisation is
fitted to (:meth:`~trafficweaving.model.cvae.CVAE.set_standardisation`).

A *stream* is one trial seen from one agent taking the human role: ``[T, 2, 6]`` states with the
other car (the "robot") first. Every agent whose role is ``human`` gives a stream, so each car of a
human–human trial is the human once, and in a human-in-the-loop trial only the person is.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass

import numpy as np
import torch

from ..data.trials import TrialSet
from ..dynamics import constant_acceleration_future
from ..scenario import HORIZON, MIN_HISTORY
from .cvae import ACCEL, CVAE, STATE_DIM, Batch


def state_statistics(trials: TrialSet) -> tuple[np.ndarray, np.ndarray]:
    """Mean and std ``[6]`` (m, m/s, m/s²) over every recorded state of both cars of ``trials``;
    a component that does not vary (std below 1e-6) gets std 1."""
    rows = np.concatenate([trials.states[i, :, : trials.lengths[i]].reshape(-1, STATE_DIM) for i in range(len(trials))])
    mean, std = rows.mean(axis=0), rows.std(axis=0)
    return mean, np.where(std > 1e-6, std, 1.0)


@dataclass
class ExemplarSet:
    """Streams and exemplar indices.

    ``streams [S, T_max, 2, 6]`` physical states (other car first, then the human), NaN-padded;
    ``lengths [S]``; ``stream_trial [S]`` index of the trial in the source set; ``stream_agent [S]``
    the human's agent index; ``sources [S]`` trial source names; exemplars ``stream [E]`` and ``t [E]``.
    """

    streams: np.ndarray
    lengths: np.ndarray
    stream_trial: np.ndarray
    stream_agent: np.ndarray
    sources: np.ndarray
    stream: np.ndarray
    t: np.ndarray

    def __len__(self) -> int:
        return len(self.t)

    def standardised(self, model: CVAE) -> "ExemplarTensors":
        """The streams in ``model``'s standardised units (:meth:`CVAE.states_to_standard`,
        :meth:`CVAE.actions_to_standard`, computed in float64; padding 0), on the model's device and
        in its dtype, ready for batching."""
        device, dtype = model.feature_mean.device, model.feature_mean.dtype
        streams = torch.as_tensor(self.streams, dtype=torch.float64, device=device)  # [S, T, 2, 6]
        states = torch.nan_to_num(model.states_to_standard(streams))
        actions = torch.nan_to_num(model.actions_to_standard(streams[:, :, 1, ACCEL]))
        guess = model.config.robot_future == "guess"
        return ExemplarTensors(
            states=states.reshape(*states.shape[:2], 2 * STATE_DIM).to(dtype),
            actions=actions.to(dtype),
            stream=torch.as_tensor(self.stream, device=device),
            t=torch.as_tensor(self.t, device=device),
            guess_units=(model.feature_mean, model.feature_std) if guess else None,
        )

    def fingerprint(self) -> str:
        """SHA-256 of the streams and exemplar indices (identifies the training data)."""
        h = hashlib.sha256()
        for a in (np.nan_to_num(self.streams, nan=1e300), self.stream, self.t):
            h.update(np.ascontiguousarray(a).tobytes())
        return h.hexdigest()


@dataclass
class ExemplarTensors:
    """Standardised streams on a device: ``states [S, T, 12]`` (other car, human),
    ``actions [S, T, 2]`` (the human's, label-standardised), exemplars ``stream [E]``, ``t [E]``.
    ``guess_units``: for a model conditioned on a guess of the other car's future
    (``CVAEConfig.robot_future == "guess"``), its state mean and std ``[6]``, so that batches carry
    that guess instead of the recorded future; None otherwise."""

    states: torch.Tensor
    actions: torch.Tensor
    stream: torch.Tensor
    t: torch.Tensor
    guess_units: tuple[torch.Tensor, torch.Tensor] | None = None

    def __len__(self) -> int:
        return self.t.shape[0]

    def batch(self, index: torch.Tensor) -> Batch:
        """The :class:`Batch` of exemplars ``index [B]``; the history is cut at the batch's largest
        ``t``; the other car's future is its recorded one, or the guess (``guess_units``)."""
        s, t = self.stream[index], self.t[index]
        steps = int(t.max()) + 1
        future = t.unsqueeze(1) + torch.arange(1, HORIZON + 1, device=t.device)  # [B, N]
        states = self.states[s]  # [B, T, 12]
        rows = torch.arange(len(s), device=t.device)
        robot_present = states[rows, t, :STATE_DIM]
        if self.guess_units is None:
            robot_future = states[rows.unsqueeze(1), future, :STATE_DIM]
        else:  # the other car holding its present acceleration, computed in physical units
            mean, std = self.guess_units
            robot_future = ((constant_acceleration_future(robot_present * std + mean) - mean) / std).to(states.dtype)
        return Batch(
            history=states[:, :steps],
            t=t,
            robot_present=robot_present,
            robot_future=robot_future,
            human_present=states[rows, t, STATE_DIM:],
            human_present_action=self.actions[s, t],
            y=self.actions[s.unsqueeze(1), future],
        )


def build_exemplars(trials: TrialSet) -> ExemplarSet:
    """Every exemplar of every agent labelled ``human`` in ``trials``, conditioned on the other agent
    (refused unless the trials' time step is the model's, 0.1 s)."""
    trials.require_dt()
    pairs = [(i, a) for i in range(len(trials)) for a in (0, 1) if trials.roles[i, a] == "human"]
    n = len(pairs)
    t_max = trials.states.shape[2]
    streams = np.full((n, t_max, 2, STATE_DIM), np.nan)
    stream_list, t_list = [], []
    for k, (i, a) in enumerate(pairs):
        streams[k, :, 0] = trials.states[i, 1 - a]
        streams[k, :, 1] = trials.states[i, a]
        ts = np.arange(MIN_HISTORY - 1, trials.lengths[i] - HORIZON)
        stream_list.append(np.full(len(ts), k))
        t_list.append(ts)
    cat = lambda parts: np.concatenate(parts).astype(np.int64) if parts else np.zeros(0, np.int64)  # noqa: E731
    trial_index = np.array([i for i, _ in pairs], dtype=np.int64)
    return ExemplarSet(
        streams=streams,
        lengths=trials.lengths[trial_index] if n else np.zeros(0, np.int64),
        stream_trial=trial_index,
        stream_agent=np.array([a for _, a in pairs], dtype=np.int64),
        sources=trials.sources[trial_index] if n else np.zeros(0, str),
        stream=cat(stream_list),
        t=cat(t_list),
    )


def split_by_trial(n_trials: int, validation_fraction: float = 0.2, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Shuffled trial indices split into training and validation (``validation_fraction`` of the
    trials, at least one when there are two or more)."""
    order = np.random.default_rng(seed).permutation(n_trials)
    n_val = int(round(validation_fraction * n_trials))
    if n_trials >= 2:
        n_val = min(max(n_val, 1), n_trials - 1)
    return np.sort(order[n_val:]), np.sort(order[:n_val])
