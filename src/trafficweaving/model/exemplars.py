"""Prediction exemplars from trials: ``(history 0..t, other car's future t+1..t+15, human actions
t+1..t+15)`` for every ``4 <= t <= T-16``, and the standardisation the model learns them in.

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
from .cvae import HORIZON, MIN_HISTORY, Batch

ACCEL = slice(4, 6)  # xdd, ydd within a state


@dataclass(frozen=True)
class Standardisation:
    """Feature mean/std ``[6]`` shared by both cars' states and label mean/std ``[2]`` for the
    human's actions (physical units)."""

    feature_mean: np.ndarray
    feature_std: np.ndarray
    label_mean: np.ndarray
    label_std: np.ndarray

    @staticmethod
    def fit(trials: TrialSet) -> "Standardisation":
        """Mean and std over every recorded state of both cars; the labels use the acceleration
        columns of the same statistics (the human's actions are its accelerations)."""
        rows = np.concatenate([trials.states[i, :, : trials.lengths[i]].reshape(-1, 6) for i in range(len(trials))])
        mean, std = rows.mean(axis=0), rows.std(axis=0)
        std = np.where(std > 1e-6, std, 1.0)
        return Standardisation(mean, std, mean[ACCEL].copy(), std[ACCEL].copy())


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

    def standardised(self, std: Standardisation, device: torch.device | str = "cpu",
                     dtype: torch.dtype = torch.float32) -> "ExemplarTensors":
        """The streams standardised and moved to ``device``, ready for batching."""
        states = np.nan_to_num((self.streams - std.feature_mean) / std.feature_std)  # [S, T, 2, 6]
        actions = np.nan_to_num((self.streams[:, :, 1, ACCEL] - std.label_mean) / std.label_std)
        as_tensor = lambda a: torch.as_tensor(a, dtype=dtype, device=device)  # noqa: E731
        return ExemplarTensors(
            states=as_tensor(states.reshape(*states.shape[:2], 12)),
            actions=as_tensor(actions),
            stream=torch.as_tensor(self.stream, device=device),
            t=torch.as_tensor(self.t, device=device),
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
    ``actions [S, T, 2]`` (the human's, label-standardised), exemplars ``stream [E]``, ``t [E]``."""

    states: torch.Tensor
    actions: torch.Tensor
    stream: torch.Tensor
    t: torch.Tensor

    def __len__(self) -> int:
        return self.t.shape[0]

    def batch(self, index: torch.Tensor) -> Batch:
        """The :class:`Batch` of exemplars ``index [B]``; the history is cut at the batch's largest ``t``."""
        s, t = self.stream[index], self.t[index]
        steps = int(t.max()) + 1
        future = t.unsqueeze(1) + torch.arange(1, HORIZON + 1, device=t.device)  # [B, N]
        states = self.states[s]  # [B, T, 12]
        rows = torch.arange(len(s), device=t.device)
        return Batch(
            history=states[:, :steps],
            t=t,
            robot_present=states[rows, t, :6],
            robot_future=states[rows.unsqueeze(1), future, :6],
            human_present=states[rows, t, 6:],
            human_present_action=self.actions[s, t],
            y=self.actions[s.unsqueeze(1), future],
        )


def build_exemplars(trials: TrialSet) -> ExemplarSet:
    """Every exemplar of every agent labelled ``human`` in ``trials``, conditioned on the other agent."""
    pairs = [(i, a) for i in range(len(trials)) for a in (0, 1) if trials.roles[i, a] == "human"]
    n = len(pairs)
    t_max = trials.states.shape[2]
    streams = np.full((n, t_max, 2, 6), np.nan)
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
