"""Training the CVAE with the paper's objective (§III) and the authors' schedules (docs/model.md, "Training").

Loss per step: ``-mean log p(y|x,z) + β·Σ_vars max(batch-mean KL(q‖p), 0.07)`` with ``k = 3``
Gumbel-softmax samples of ``q`` per exemplar, on a batch of 32 with Gaussian noise on the
standardised inputs and labels, recurrent dropout, dropout in p(z|x) and scheduled sampling in the
decoder. Adam with exponentially decaying learning rate and gradient clipping by value.

Fine-tuning (``init``) starts from a trained checkpoint, keeps its standardisation and variant, and
runs its own schedule: a learning rate of its own, the KL weight and Gumbel-softmax temperature
continued from where the initial model's training left them (``schedule_start``), a validation set
(a split of the data, or given), and optional early stopping on it with the best weights kept.
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, fields, replace
from pathlib import Path
from typing import Callable

import numpy as np
import torch
import torch.nn.functional as F
from tqdm import tqdm

from ..data.trials import TrialSet
from ..errors import InputError
from ..scenario import MIN_TRIAL_STEPS, STATE_NAMES
from .authors import load_authors_model
from .checkpoint import model_from_checkpoint, read_checkpoint, save_checkpoint
from .cvae import CVAE, Batch, CVAEConfig
from .evaluate import evaluate_tensors
from .exemplars import ExemplarSet, build_exemplars, split_by_trial, state_statistics
from .mixture import Mixture, conditioned_on
from .registry import model_path
from .spec import parse_model_spec
from .train_config import OBJECTIVES, TRAINABLE, TrainConfig


def learning_rate(tc: TrainConfig, step: int) -> float:
    return tc.lr_final + (tc.lr_initial - tc.lr_final) * tc.lr_decay ** step


def temperature(tc: TrainConfig, step: int) -> float:
    """Gumbel-softmax temperature."""
    step += tc.schedule_start
    return tc.temperature_final + (tc.temperature_initial - tc.temperature_final) * tc.temperature_decay ** step


def kl_weight(tc: TrainConfig, step: int) -> float:
    """β: a sigmoid from ``beta_min`` to 1 centred on ``beta_crossover``."""
    step += tc.schedule_start
    return tc.beta_min + (1.0 - tc.beta_min) / (1.0 + math.exp(-(step - tc.beta_crossover) / tc.beta_width))


LABELS = ("y", "human_present_action")
"""The :class:`Batch` fields holding the human's actions (the labels and the decoder's first input)."""


def _noisy(batch: Batch, sd: float, label_sd: float) -> Batch:
    """The batch with Gaussian noise of std ``sd`` on every standardised input and ``label_sd`` on
    the human's actions (:data:`LABELS`)."""
    def noisy(name, v):
        scale = label_sd if name in LABELS else sd
        return v if name == "t" or v is None or scale <= 0.0 else v + scale * torch.randn_like(v)
    return Batch(**{k: noisy(k, v) for k, v in vars(batch).items()})


def label_noise(tc: TrainConfig, config: CVAEConfig) -> float:
    """Noise std on the human's actions: the paper's ``input_noise``, except for the hold variant,
    which learns that an action *equals* the previous one — independent noise on both would teach
    it holds of the noise's width (0.07) instead."""
    return 0.0 if config.hold else tc.input_noise


def loss_terms(model: CVAE, batch: Batch, tc: TrainConfig, step: int) -> tuple[torch.Tensor, dict]:
    """The training loss on one (already noisy) batch and its parts for logging: the paper's ELBO,
    or with ``objective="exact"`` the exact NLL over every latent value (what the models are scored
    on; needs no q, so it fine-tunes the authors' published model), with the same dropouts and
    scheduled sampling."""
    x = model.encode(batch, tc.recurrent_dropout)
    if tc.objective == "exact":
        log_p_z = model.joint_log_prob(model.p_z_logits(x, tc.p_z_dropout))  # [B, Z]
        log_p_y, _ = model.decode(model.zx(model.latent_onehots.unsqueeze(1), x), batch, tc.recurrent_dropout,
                                  tc.scheduled_sampling)  # [Z, B]
        nll = -torch.logsumexp(log_p_z + log_p_y.T, dim=1).mean()
        return nll, {"nll": nll.item(), "kl": 0.0, "beta": 0.0}
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


def set_trainable(model: CVAE, trainable: str) -> None:
    """Freeze every parameter outside the parts named by ``trainable`` (:data:`TRAINABLE`)."""
    if trainable not in TRAINABLE:
        raise InputError(f"unknown trainable parts {trainable!r} (expected one of {', '.join(TRAINABLE)})")
    if trainable == "hold" and model.hold is None:
        raise InputError(f"--train-parts hold: a {model.config.name} model has no hold head (expected a cvae-hold model)")
    parts = TRAINABLE[trainable]
    for name, parameter in model.named_parameters():
        parameter.requires_grad_(parts is None or name.split(".")[0] in parts)


def make_optimizer(model: CVAE, tc: TrainConfig) -> torch.optim.Adam:
    """Adam over the trainable parameters (:func:`set_trainable`), the first group at the main
    learning rate. The hold variant's widths get their own constant learning rate (``hold_width_lr``):
    Adam moves a parameter by about its learning rate per step, and the widths must be able to travel
    from the simulator's exact holds to real drivers' (a factor of a few in ``s``) within a short
    fine-tuning; with ``hold_lr`` the hold mode logits get one too (hold modes switched off by
    :meth:`CVAE.with_hold_modes` start at logits of -20)."""
    set_trainable(model, tc.trainable)
    special = {}
    if model.hold is not None:
        special[id(model.hold.log_sigma)] = tc.hold_width_lr
        if tc.hold_lr > 0:
            special |= {id(p): tc.hold_lr for p in model.hold.logits.parameters()}
    trainable = [p for p in model.parameters() if p.requires_grad]
    groups = [{"params": [p for p in trainable if id(p) not in special], "lr": tc.lr_initial}]
    for lr in sorted(set(special.values())):
        params = [p for p in trainable if special.get(id(p)) == lr]
        if params:
            groups.append({"params": params, "lr": lr})
    return torch.optim.Adam(groups)


class _MinibatchOrder:
    """The exemplar indices ``[batch_size]`` of each training step's minibatch, drawn without
    replacement from epoch permutations that depend only on (seed, epoch), so a resumed run draws
    exactly the minibatches an uninterrupted one would."""

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
    validation: dict | None  # the final full-validation summary (evaluate.Evaluation.summary); None without validation
    steps_per_second: float
    best_step: int | None = None  # with early stopping: the step whose weights were kept


NO_EXEMPLARS = f"no prediction exemplars (need human agents in trials of at least {MIN_TRIAL_STEPS} steps)"


def prepare_data(trials: TrialSet, tc: TrainConfig, validation: TrialSet | None = None
                 ) -> tuple[ExemplarSet, ExemplarSet | None, tuple[np.ndarray, np.ndarray]]:
    """Training and validation exemplars and the training trials' state mean and std ``[6]``
    (:func:`~trafficweaving.model.exemplars.state_statistics`, for
    :meth:`CVAE.set_standardisation`). The validation set is ``validation`` when given, else a
    ``validation_fraction`` split of ``trials`` by trial (none when the fraction is 0)."""
    if validation is None and tc.validation_fraction > 0:
        if len(trials) < 2:
            raise InputError(f"need at least 2 trials to split into training and validation (got {len(trials)})")
        train_idx, val_idx = split_by_trial(len(trials), tc.validation_fraction, tc.seed)
        trials, validation = trials.subset(train_idx), trials.subset(val_idx)
    train_ex = build_exemplars(trials)
    val_ex = None if validation is None else build_exemplars(validation)
    if len(train_ex) == 0 or (val_ex is not None and len(val_ex) == 0):
        raise InputError(NO_EXEMPLARS)
    return train_ex, val_ex, state_statistics(trials)


STANDARDISED_MEAN_LIMIT = 3.0
STANDARDISED_STD_RANGE = (0.1, 10.0)


def check_standardisation_fits(model: CVAE, exemplars: ExemplarSet, where: str) -> None:
    """Refuse fine-tuning ``model`` on data its standardisation does not fit: every state feature of
    the data, standardised with the model's statistics, must have a mean within
    ``STANDARDISED_MEAN_LIMIT`` and a std within ``STANDARDISED_STD_RANGE`` (this catches other
    units, other coordinate conventions and other time steps)."""
    mean, std = model.feature_mean, model.feature_std
    if not (torch.isfinite(mean).all() and torch.isfinite(std).all() and (std > 0).all()):
        raise InputError(f"{where}: its standardisation is not finite and positive (expected a trained model)")
    rows = exemplars.streams.reshape(-1, exemplars.streams.shape[-1])
    recorded = torch.as_tensor(rows[np.isfinite(rows).all(axis=1)], dtype=torch.float64, device=mean.device)
    z = model.states_to_standard(recorded).cpu().numpy()
    for k, name in enumerate(STATE_NAMES):
        m, s = float(z[:, k].mean()), float(z[:, k].std())
        low, high = STANDARDISED_STD_RANGE
        if abs(m) > STANDARDISED_MEAN_LIMIT or not low <= s <= high:
            raise InputError(f"{where}: its standardisation does not fit the data ({name}: mean {m:+.1f}, std {s:.2f} "
                             f"in the model's units; expected |mean| <= {STANDARDISED_MEAN_LIMIT:g} and std in "
                             f"{low:g}..{high:g}, i.e. data in the same units and conventions)")


def initial_model(init: str | Path, variant: str | None, robot_future: str | None = None) -> tuple[CVAE, dict]:
    """The model that fine-tuning ``init`` (a checkpoint or ``authors:PATH``) starts from, before any
    step, and its provenance: upgraded to ``cvae-hold`` with the hold modes switched off when
    ``variant`` asks for it of a ``cvae`` model (:meth:`CVAE.with_hold_modes`), conditioned on
    ``robot_future`` when given (:attr:`CVAEConfig.robot_future`; the weights are kept, the
    training data then carries that future), calibration reset (fine-tuning changes the trained
    model itself; calibration is redone afterwards). A :class:`~trafficweaving.model.mixture.Mixture`
    (e.g. ``default``) starts from its first component, the one trained on real trials; its mixture
    weight, like the calibration, is chosen again by ``calibrate``. Another variant than ``variant`` (None: any)
    is refused."""
    spec = parse_model_spec(str(init))
    if spec.kind == "authors":
        payload, model = {}, load_authors_model(spec.path)
    else:
        payload = read_checkpoint(model_path(str(init)))
        model = model_from_checkpoint(payload, init)
    provenance = {"path": str(init), "variant": model.config.name, "step": int(payload.get("step", 0)),
                  **{k: payload[k] for k in ("data_fingerprint", "recipe", "data_command") if k in payload}}
    if isinstance(model, Mixture):
        model, provenance["mixture_component"] = model.components[0], 1
    if variant == "cvae-hold" and model.config.name == "cvae":
        model = model.with_hold_modes()
        provenance["upgraded_to"] = "cvae-hold"
    elif variant is not None and model.config.name != variant:
        raise InputError(f"--init {init}: a {model.config.name} model, but --variant {variant} was asked "
                         f"(expected a checkpoint of the same variant, or a cvae model for --variant cvae-hold)")
    if robot_future is not None and robot_future != model.config.robot_future:
        provenance["robot_future"] = model.config.robot_future
        model = conditioned_on(model, robot_future)
    return model.set_calibration(1.0, 1.0), provenance


def init_model(init: str | Path, variant: str | None, train_ex: ExemplarSet, objective: str = "auto",
               robot_future: str | None = None) -> tuple[CVAE, dict]:
    """:func:`initial_model`, refusing a standardisation that does not fit the data or the paper's
    objective for a model without q."""
    model, provenance = initial_model(init, variant, robot_future)
    if objective == "elbo" and not model.config.has_q:
        raise InputError(f"--init {init}: the model has no recognition network q(z|x,y), which the paper's objective "
                         f"needs (expected --objective exact)")
    check_standardisation_fits(model, train_ex, f"--init {init}")
    return model, provenance


def _resumed(resume: str | Path | None, tc: TrainConfig) -> tuple[dict | None, TrainConfig]:
    """The training checkpoint ``resume`` (None: none) and the configuration the run continues
    with: the checkpoint's, with ``tc``'s ``steps``."""
    if not resume:
        return None, tc
    payload = read_checkpoint(resume)
    if "train_config" not in payload or "optimizer" not in payload:
        raise InputError(f"{resume}: not a training checkpoint (expected one written during `trafficweaving train`)")
    known = {f.name for f in fields(TrainConfig)}
    return payload, TrainConfig(**{**{k: v for k, v in payload["train_config"].items() if k in known}, "steps": tc.steps})


def _start(payload: dict | None, resume, init, variant: str | None, tc: TrainConfig, train_ex: ExemplarSet,
           fingerprint: str, statistics: tuple[np.ndarray, np.ndarray], device: torch.device
           ) -> tuple[CVAE, TrainConfig, dict]:
    """The model a run starts from (resumed, fine-tuned from ``init``, or new), the configuration
    it runs (``schedule_start`` and ``objective`` resolved) and the checkpoint fields it carries on."""
    extra = {}
    if payload is not None:
        if payload.get("data_fingerprint") != fingerprint:
            raise InputError(f"{resume}: checkpoint was trained on different data (fingerprint mismatch)")
        model = model_from_checkpoint(payload, resume).to(device)  # same data, so the same standardisation
        extra.update({k: payload[k] for k in ("init", "recipe") if k in payload})
    elif init is not None:
        torch.manual_seed(tc.seed)
        model, extra["init"] = init_model(init, variant, train_ex, tc.objective, tc.robot_future)
        model = model.to(device)
        tc = replace(tc, schedule_start=extra["init"]["step"])
    else:
        torch.manual_seed(tc.seed)
        config = CVAEConfig.variant(variant or "cvae", robot_future=tc.robot_future or "recorded")
        model = CVAE(config).to(device).set_standardisation(*statistics)
    if tc.objective == "auto":
        tc = replace(tc, objective="elbo" if model.config.has_q else "exact")
    return model, tc, extra


def _start_line(model: CVAE, train_ex: ExemplarSet, val_ex: ExemplarSet | None, fine_tuning: bool, step: int,
                tc: TrainConfig, device: torch.device) -> str:
    """The log line that opens a run: exemplars, trials, steps and device."""
    count = lambda ex: "no" if ex is None else f"{len(ex)}"  # noqa: E731
    trials_of = lambda ex: 0 if ex is None else len(np.unique(ex.stream_trial))  # noqa: E731
    return (f"{'fine-tuning' if fine_tuning else 'training'} {model.config.name}: {count(train_ex)} training / "
            f"{count(val_ex)} validation exemplars from {trials_of(train_ex)} / {trials_of(val_ex)} trials, "
            f"steps {step}..{tc.steps} on {device}")


def _step(model: CVAE, optimizer: torch.optim.Optimizer, batch: Batch, tc: TrainConfig, step: int
          ) -> tuple[torch.Tensor, dict]:
    """One optimisation step at ``step`` on the standardised minibatch ``batch`` (noise added
    here): the loss and its parts (:func:`loss_terms`); InputError when the loss is not finite."""
    model.train()
    optimizer.param_groups[0]["lr"] = learning_rate(tc, step)
    batch = _noisy(batch, tc.input_noise, label_noise(tc, model.config))
    loss, parts = loss_terms(model, batch, tc, step)
    if not torch.isfinite(loss):
        raise InputError(f"training diverged at step {step} (loss {loss.item()}; expected a smaller learning rate "
                         f"than {learning_rate(tc, step):.3g})")
    optimizer.zero_grad(set_to_none=True)
    loss.backward()
    torch.nn.utils.clip_grad_value_(model.parameters(), tc.clip_value)
    optimizer.step()
    return loss, parts


class _EarlyStopping:
    """Early stopping on the validation NLL (``patience`` > 0): the best NLL so far, its ``step``
    and the model's weights then."""

    def __init__(self, tc: TrainConfig):
        self.patience, self.every = tc.patience, tc.validate_every
        self.nll, self.step, self.weights = math.inf, None, None

    def stop(self, step: int, nll: float, model: CVAE, log: Callable[[str], None]) -> bool:
        """Record the validation NLL ``nll`` at ``step``; whether to stop."""
        if self.patience <= 0:
            return False
        if nll < self.nll:
            self.nll, self.step, self.weights = nll, step, {k: v.clone() for k, v in model.state_dict().items()}
        elif (step - self.step) >= self.patience * self.every:
            log(f"early stopping at step {step}: no improvement since step {self.step} ({self.nll:.3f})")
            return True
        return False


def train(trials: TrialSet, out: str | Path | None, variant: str | None = "cvae", tc: TrainConfig = TrainConfig(),
          resume: str | Path | None = None, device: torch.device | str = "cpu",
          progress: bool = True, log: Callable[[str], None] = print, init: str | Path | None = None,
          validation: TrialSet | None = None,
          on_validate: Callable[[int, CVAE], None] | None = None) -> TrainResult:
    """Train a ``variant`` model on ``trials`` and write checkpoints to ``out`` (every
    ``checkpoint_every`` steps and at the end; None: no files). With ``resume``, continue the run
    saved in that checkpoint (its configurations are used; the data must be the same). With
    ``init``, fine-tune that checkpoint's model (``variant`` None: whatever it is). ``validation``
    replaces the split of ``trials``; ``on_validate(step, model)`` is called after each validation
    (without a validation set, at the steps a validation would run)."""
    device = torch.device(device)
    if tc.objective not in OBJECTIVES:
        raise InputError(f"unknown objective {tc.objective!r} (expected one of {', '.join(OBJECTIVES)})")
    payload, tc = _resumed(resume, tc)
    train_ex, val_ex, statistics = prepare_data(trials, tc, validation)
    fingerprint = train_ex.fingerprint()
    model, tc, extra = _start(payload, resume, init, variant, tc, train_ex, fingerprint, statistics, device)
    train_data = train_ex.standardised(model)  # fine-tuning keeps the initial model's standardisation
    val_data = None if val_ex is None else val_ex.standardised(model)
    if val_data is not None:
        val_subset = torch.randperm(len(val_data), generator=torch.Generator().manual_seed(tc.seed))[: tc.validation_exemplars].to(device)

    optimizer = make_optimizer(model, tc)
    step, history = 0, []
    if payload is not None:
        optimizer.load_state_dict(payload["optimizer"])
        step, history = int(payload["step"]), [tuple(h) for h in payload.get("history", [])]
        torch.set_rng_state(payload["rng"])
    minibatch = _MinibatchOrder(len(train_data), tc.batch_size, tc.seed)
    log(_start_line(model, train_ex, val_ex, "init" in extra, step, tc, device))

    def checkpoint(path):
        if path is not None:
            save_checkpoint(path, model, step=step, history=history, data_fingerprint=fingerprint, **extra,
                            train_config=asdict(tc), optimizer=optimizer.state_dict(), rng=torch.get_rng_state())

    stopping = _EarlyStopping(tc)
    start_step, start_time = step, time.perf_counter()
    bar = tqdm(total=tc.steps, initial=step, disable=not progress, desc=f"train {model.config.name}", unit="step")
    while step < tc.steps:
        loss, parts = _step(model, optimizer, train_data.batch(minibatch(step).to(device)), tc, step)
        step += 1
        bar.update(1)
        due = step % tc.validate_every == 0 or step == tc.steps
        if val_data is not None and due:
            val = evaluate_tensors(model, val_data, index=val_subset).summary()["nll_exact"]
            history.append((step, val))
            bar.set_postfix(loss=f"{loss.item():.2f}", kl=f"{parts['kl']:.2f}", val_nll=f"{val:.3f}")
            if on_validate is not None:
                on_validate(step, model)
            if stopping.stop(step, val, model, log):
                break
        elif on_validate is not None and due:
            on_validate(step, model)  # no validation set: the caller scores the model itself
        if step % tc.checkpoint_every == 0 or step == tc.steps:
            checkpoint(out)
    bar.close()
    elapsed = time.perf_counter() - start_time
    steps_per_second = (step - start_step) / max(elapsed, 1e-9)
    if stopping.weights is not None:
        model.load_state_dict(stopping.weights)
        step = stopping.step
    final = None if val_data is None else evaluate_tensors(model, val_data).summary()
    checkpoint(out)
    return TrainResult(model.eval(), step, history, final, steps_per_second, stopping.step)
