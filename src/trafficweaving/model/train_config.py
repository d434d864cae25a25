"""Training settings: :class:`TrainConfig` and the named choices it refers to.

Its own module so that the checkpoint format (which checks a saved ``train_config``) does not
depend on the trainer (:mod:`~trafficweaving.model.train`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

from ..errors import InputError


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
    hold_width_lr: float = 1e-2  # constant learning rate of the hold variant's two widths (log s)
    hold_lr: float = 0.0  # constant learning rate of the hold variant's mode logits (0: the main learning rate)
    objective: str = "auto"  # "elbo": the paper's (needs q); "exact": -log Σ_z p(z|x) p(y|x,z); "auto": elbo if the model has q
    trainable: str = "all"  # which parts learn (TRAINABLE)
    robot_future: str | None = None  # the model's conditioning (CVAEConfig.robot_future); None: the init's, or recorded
    schedule_start: int = 0  # step at which the KL-weight and temperature schedules start (fine-tuning)
    patience: int = 0  # early stopping: validations without improvement before stopping (0: off)


OBJECTIVES = ("auto", "elbo", "exact")
TRAINABLE = {  # name: the CVAE submodules that learn (None: every parameter)
    "all": None,
    "decoder": ("decoder_initial_state", "decoder", "gmm", "hold"),
    "hold": ("hold",),
}

FINE_TUNING = {"lr_initial": 1e-4, "validate_every": 50, "checkpoint_every": 50}
"""Defaults of a fine-tuning run (``train --init``) that differ from training from scratch."""


def config_from_options(steps: int, seed: int, fine_tuning: bool = False, validation_fraction: float = 0.2,
                        patience: int | None = None, lr_initial: float | None = None,
                        validate_every: int | None = None, objective: str | None = None,
                        hold_lr: float | None = None, trainable: str | None = None,
                        robot_future: str | None = None) -> TrainConfig:
    """The :class:`TrainConfig` of ``train`` / ``crossval`` options: the paper's schedule from
    scratch, :data:`FINE_TUNING` when ``fine_tuning`` (``--init``); each option given (not None)
    overrides either, and the final learning rate and checkpoint period never exceed the initial
    rate and the validation period."""
    if validation_fraction == 0 and (patience or 0) > 0:
        raise InputError("--patience needs a validation set (expected --validation-fraction above 0)")
    tc = TrainConfig(steps=steps, seed=seed, validation_fraction=validation_fraction)
    if fine_tuning:
        tc = replace(tc, **FINE_TUNING)
    overrides = {"lr_initial": lr_initial, "validate_every": validate_every, "patience": patience,
                 "objective": objective, "hold_lr": hold_lr, "trainable": trainable, "robot_future": robot_future}
    tc = replace(tc, **{k: v for k, v in overrides.items() if v is not None})
    return replace(tc, lr_final=min(tc.lr_final, tc.lr_initial), checkpoint_every=min(tc.checkpoint_every, tc.validate_every))
