"""Training the CVAE with the paper's objective and every schedule of DESIGN.md §3.

Loss per step: ``-mean log p(y|x,z) + β·Σ_vars max(batch-mean KL(q‖p), 0.07)`` with ``k = 3``
Gumbel-softmax samples of ``q`` per exemplar, on a batch of 32 with Gaussian noise on the
standardised inputs and labels, recurrent dropout, dropout in p(z|x) and scheduled sampling in the
decoder. Adam with exponentially decaying learning rate and gradient clipping by value.
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Callable

import numpy as np
import torch
import torch.nn.functional as F
from tqdm import tqdm

from ..data.trials import TrialSet
from ..errors import InputError
from .checkpoint import model_from_checkpoint, read_checkpoint, save_checkpoint
from .cvae import CVAE, Batch, CVAEConfig
from .evaluate import evaluate_tensors
from .exemplars import ExemplarSet, Standardisation, build_exemplars, split_by_trial


@dataclass(frozen=True)
class TrainConfig:
    """Optimisation settings; defaults are the paper's and the authors'."""

    steps: int = 50_000
    batch_size: int = 32
    latent_samples: int = 3
    lr_initial: float = 1e-3
    lr_final: float = 1e-5
    lr_decay: float = 0.9999
    clip_value: float = 1.0
    temperature_initial: float = 2.0
    temperature_final: float = 0.001
    temperature_decay: float = 0.9999
    kl_floor: float = 0.07
    beta_min: float = 1e-4
    beta_crossover: float = 8000.0
    beta_width: float = 8000.0 / 6.0
    input_noise: float = 0.05
    recurrent_dropout: float = 0.25  # keep probability 0.75
    p_z_dropout: float = 0.1  # keep probability 0.9
    scheduled_sampling: float = 0.1
    validation_fraction: float = 0.2
    validate_every: int = 1000
    validation_exemplars: int = 2048  # periodic validation uses a fixed subset; the final one uses all
    checkpoint_every: int = 1000
    seed: int = 0


def learning_rate(tc: TrainConfig, step: int) -> float:
    return tc.lr_final + (tc.lr_initial - tc.lr_final) * tc.lr_decay ** step


def temperature(tc: TrainConfig, step: int) -> float:
    """Gumbel-softmax temperature."""
    return tc.temperature_final + (tc.temperature_initial - tc.temperature_final) * tc.temperature_decay ** step


def kl_weight(tc: TrainConfig, step: int) -> float:
    """β: a sigmoid from ``beta_min`` to 1 centred on ``beta_crossover``."""
    return tc.beta_min + (1.0 - tc.beta_min) / (1.0 + math.exp(-(step - tc.beta_crossover) / tc.beta_width))


def _noisy(batch: Batch, sd: float) -> Batch:
    """The batch with Gaussian noise of std ``sd`` on every standardised input and label."""
    if sd <= 0.0:
        return batch
    return Batch(**{k: (v if k == "t" or v is None else v + sd * torch.randn_like(v)) for k, v in vars(batch).items()})


def loss_terms(model: CVAE, batch: Batch, tc: TrainConfig, step: int) -> tuple[torch.Tensor, dict]:
    """The training loss on one (already noisy) batch and its parts for logging."""
    x = model.encode(batch, tc.recurrent_dropout)
    p_log = F.log_softmax(model.p_z_logits(x, tc.p_z_dropout), dim=-1)  # [B, N_z, K_z]
    q_log = F.log_softmax(model.q_z_logits(x, batch, tc.recurrent_dropout), dim=-1)
    kl_per_var = (q_log.exp() * (q_log - p_log)).sum(-1).mean(0)  # [N_z]
    kl = kl_per_var.clamp_min(tc.kl_floor).sum()
    gumbel = -torch.log(-torch.log(torch.rand((tc.latent_samples, *q_log.shape), device=x.device).clamp_min(1e-20)))
    z = F.softmax((q_log.unsqueeze(0) + gumbel) / temperature(tc, step), dim=-1).flatten(2)  # [k, B, N_z·K_z]
    log_p_y, _ = model.decode(model.zx(z, x), batch, tc.recurrent_dropout, tc.scheduled_sampling)
    nll = -log_p_y.mean()
    beta = kl_weight(tc, step)
    return nll + beta * kl, {"nll": nll.item(), "kl": kl_per_var.sum().item(), "beta": beta}


class _Sampler:
    """Batches drawn without replacement from epoch permutations that depend only on (seed, epoch),
    so a resumed run draws exactly the batches an uninterrupted one would."""

    def __init__(self, n: int, batch_size: int, seed: int):
        self.n, self.batch_size, self.seed = n, batch_size, seed
        self.per_epoch = max(n // batch_size, 1)
        self.epoch, self.perm = -1, None

    def __call__(self, step: int) -> torch.Tensor:
        epoch, k = divmod(step, self.per_epoch)
        if epoch != self.epoch:
            self.epoch = epoch
            self.perm = torch.randperm(self.n, generator=torch.Generator().manual_seed(self.seed * 1_000_003 + epoch))
        return self.perm[k * self.batch_size:(k + 1) * self.batch_size]


@dataclass
class TrainResult:
    model: CVAE
    step: int
    history: list  # [(step, validation nll_exact)]
    validation: dict  # the final full-validation summary (evaluate.Evaluation.summary)
    steps_per_second: float


def prepare_data(trials: TrialSet, tc: TrainConfig) -> tuple[ExemplarSet, ExemplarSet, Standardisation]:
    """Training and validation exemplars (split by trial) and the training-set standardisation."""
    if len(trials) < 2:
        raise InputError(f"need at least 2 trials to split into training and validation (got {len(trials)})")
    train_idx, val_idx = split_by_trial(len(trials), tc.validation_fraction, tc.seed)
    train_ex, val_ex = build_exemplars(trials.subset(train_idx)), build_exemplars(trials.subset(val_idx))
    if len(train_ex) == 0 or len(val_ex) == 0:
        raise InputError("no prediction exemplars (need human agents in trials of at least 21 steps)")
    return train_ex, val_ex, Standardisation.fit(trials.subset(train_idx))


def train(trials: TrialSet, out: str | Path, variant: str = "cvae", tc: TrainConfig = TrainConfig(),
          resume: str | Path | None = None, device: torch.device | str = "cpu",
          progress: bool = True, log: Callable[[str], None] = print) -> TrainResult:
    """Train a ``variant`` model on ``trials`` and write checkpoints to ``out`` (every
    ``checkpoint_every`` steps and at the end). With ``resume``, continue the run saved in that
    checkpoint (its configurations are used; the data must be the same)."""
    device = torch.device(device)
    payload = read_checkpoint(resume) if resume else None
    if payload is not None:
        if "train_config" not in payload or "optimizer" not in payload:
            raise InputError(f"{resume}: not a training checkpoint (expected one written during `trafficweaving train`)")
        known = {f.name for f in fields(TrainConfig)}
        tc = TrainConfig(**{**{k: v for k, v in payload["train_config"].items() if k in known}, "steps": tc.steps})

    train_ex, val_ex, standardisation = prepare_data(trials, tc)
    fingerprint = train_ex.fingerprint()
    if payload is not None:
        if payload.get("data_fingerprint") != fingerprint:
            raise InputError(f"{resume}: checkpoint was trained on different data (fingerprint mismatch)")
        model = model_from_checkpoint(payload, resume).to(device)  # same data, so the same standardisation
    else:
        torch.manual_seed(tc.seed)
        model = CVAE(CVAEConfig.variant(variant)).to(device)
        with torch.no_grad():
            for name in ("feature_mean", "feature_std", "label_mean", "label_std"):
                getattr(model, name).copy_(torch.as_tensor(getattr(standardisation, name)))
    train_data = train_ex.standardised(standardisation, device)
    val_data = val_ex.standardised(standardisation, device)
    val_subset = torch.randperm(len(val_data), generator=torch.Generator().manual_seed(tc.seed))[: tc.validation_exemplars].to(device)

    optimizer = torch.optim.Adam(model.parameters(), lr=tc.lr_initial)
    step, history = 0, []
    if payload is not None:
        optimizer.load_state_dict(payload["optimizer"])
        step, history = int(payload["step"]), [tuple(h) for h in payload.get("history", [])]
        torch.set_rng_state(payload["rng"])
    sampler = _Sampler(len(train_data), tc.batch_size, tc.seed)
    log(f"training {model.config.name}: {len(train_ex)} training / {len(val_ex)} validation exemplars "
        f"from {len(np.unique(train_ex.stream_trial))} / {len(np.unique(val_ex.stream_trial))} trials, "
        f"steps {step}..{tc.steps} on {device}")

    def checkpoint(path):
        save_checkpoint(path, model, step=step, history=history, data_fingerprint=fingerprint,
                        train_config=asdict(tc), optimizer=optimizer.state_dict(), rng=torch.get_rng_state())

    start_step, start_time = step, time.perf_counter()
    bar = tqdm(total=tc.steps, initial=step, disable=not progress, desc=f"train {model.config.name}", unit="step")
    while step < tc.steps:
        model.train()
        for group in optimizer.param_groups:
            group["lr"] = learning_rate(tc, step)
        batch = _noisy(train_data.batch(sampler(step).to(device)), tc.input_noise)
        loss, parts = loss_terms(model, batch, tc, step)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_value_(model.parameters(), tc.clip_value)
        optimizer.step()
        step += 1
        bar.update(1)
        if step % tc.validate_every == 0 or step == tc.steps:
            val = evaluate_tensors(model, val_data, index=val_subset).summary()["nll_exact"]
            history.append((step, val))
            bar.set_postfix(loss=f"{loss.item():.2f}", kl=f"{parts['kl']:.2f}", val_nll=f"{val:.3f}")
        if step % tc.checkpoint_every == 0 or step == tc.steps:
            checkpoint(out)
    bar.close()
    elapsed = time.perf_counter() - start_time
    final = evaluate_tensors(model, val_data).summary()
    checkpoint(out)
    return TrainResult(model.eval(), step, history, final, (step - start_step) / max(elapsed, 1e-9))
