"""Distillation: a CVAE with a smaller decoder that predicts what a larger one does, for planning
at the paper's full budget on a CPU (docs/fast_model.md).

The planner's cost is the decoder: an LSTM step and a GMM head per future step, for every one of
the ~98,000 sampled futures of a plan. A *student* keeps the *teacher*'s encoders and latent
distribution p(z|x) exactly (copied and frozen, so it has the teacher's modes and their
probabilities, candidate by candidate) and learns a decoder of ``decoder_units`` units and
``components`` GMM components (hold modes kept) from two terms per step:

* **distillation**: futures the teacher samples, latent value and actions, for situations of the
  training trials whose robot future is, with probability ``perturbed_fraction``, replaced by a
  random one (piecewise-constant accelerations over the planner's 0.3 s windows, as its candidates
  are), so the student learns the teacher's response to robot futures the data never shows;
  the loss is the student's ``-log p(y | x, z)`` at the teacher's ``z`` (fresh samples every step:
  no finite set to overfit);
* **real data**: the exact NLL ``-log Σ_z p(z|x) p(y|x,z)`` of the recorded actions, weighted by
  ``real_weight``.

The teacher is used as trained (calibration reset: the student is calibrated afterwards, like any
model, by ``calibrate``). Steps are chosen by cross-validation (``crossval --teacher-folds``, each
fold distilled from a teacher that never saw it).
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Callable

import torch
from tqdm import tqdm

from ..data.trials import TrialSet
from ..dynamics import future_states
from ..errors import InputError
from ..scenario import HORIZON, REPLAN_STEPS
from .checkpoint import save_checkpoint
from .cvae import CVAE, Batch
from .exemplars import build_exemplars
from .train import NO_EXEMPLARS, _MinibatchOrder, check_standardisation_fits, initial_model, learning_rate
from .train_config import TrainConfig

STUDENT_PARTS = ("decoder_initial_state", "decoder", "gmm", "hold")
"""The submodules a student learns; every other weight is the teacher's, frozen."""

ROBOT_ACCELERATION_RANGE = {"x": (-6.0, 4.0), "y": (-2.5, 2.5)}
"""Ranges (m/s²) of the random robot accelerations of perturbed situations: the planner's
longitudinal actions (``planning.candidates.ACCELERATIONS``) and lateral accelerations of its lane
changes."""


@dataclass(frozen=True)
class DistilConfig:
    """The student's size and the distillation's mixture of data (see the module docstring)."""

    decoder_units: int = 32
    components: int = 8
    teacher_samples: int = 4  # teacher futures per situation and step
    perturbed_fraction: float = 0.5  # situations whose robot future is replaced by a random one
    real_weight: float = 1.0  # weight of the real-data exact NLL
    hold_lr: float = 0.01  # constant learning rate of the hold modes' logits (0: frozen)

    def __post_init__(self):
        if not (1 <= self.decoder_units <= 1024 and 1 <= self.components <= 64 and 1 <= self.teacher_samples <= 256):
            raise InputError(f"distillation: expected 1..1024 decoder units, 1..64 components and 1..256 teacher samples, "
                             f"got {self.decoder_units}, {self.components}, {self.teacher_samples}")
        if not (0.0 <= self.perturbed_fraction <= 1.0 and self.real_weight >= 0.0 and 0.0 <= self.hold_lr < 1.0):
            raise InputError(f"distillation: expected a perturbed fraction in 0..1, a real weight >= 0 and a hold "
                             f"learning rate in 0..1, got {self.perturbed_fraction}, {self.real_weight} and {self.hold_lr}")


def student_of(teacher: CVAE, decoder_units: int, components: int, init: CVAE | None = None) -> CVAE:
    """A student of ``teacher`` (a CVAE with hold modes or without): the teacher's configuration with
    ``decoder_units`` and ``components``, its encoders, latent distribution and standardisation
    copied, only :data:`STUDENT_PARTS` trainable (the rest frozen), calibration 1. Its decoder is
    ``init``'s (a student of another teacher of the same standardisation and sizes: the second stage
    of the fast model's recipe), or new. A new hold head, or ``init``'s while its hold modes are
    still switched off (their weights zero), starts with the teacher's hold widths and hold-mode
    biases and zero weights: off when the teacher's are off, at the teacher's rates otherwise."""
    config = replace(teacher.config, decoder_units=decoder_units, components=components)
    student = CVAE(config).to(teacher.feature_mean.device)
    copied = {k: v for k, v in teacher.state_dict().items() if k.split(".")[0] not in STUDENT_PARTS}
    if init is not None:
        if replace(init.config, has_q=config.has_q) != replace(config, has_q=config.has_q) or not torch.equal(
                init.feature_std.cpu(), teacher.feature_std.cpu()) or not torch.equal(init.feature_mean.cpu(), teacher.feature_mean.cpu()):
            raise InputError(f"distillation: the initial student ({init.config.decoder_units} units, "
                             f"{init.config.components} components) does not match the student asked for or the "
                             f"teacher's standardisation (expected a student of the same sizes, of a teacher of the "
                             f"same data units)")
        copied |= {k: v for k, v in init.state_dict().items() if k.split(".")[0] in STUDENT_PARTS}
    missing, unexpected = student.load_state_dict(copied, strict=False)
    assert not unexpected and all(k.split(".")[0] in STUDENT_PARTS for k in missing), (missing, unexpected)
    if teacher.hold is not None and (init is None or not bool(student.hold.logits.weight.any())):
        with torch.no_grad():  # a new hold head, or one still switched off: the teacher's hold modes' biases
            student.hold.log_sigma.copy_(teacher.hold.log_sigma)
            student.hold.logits.weight.zero_()
            student.hold.logits.bias.copy_(teacher.hold.logits.bias)
    for name, parameter in student.named_parameters():
        parameter.requires_grad_(name.split(".")[0] in STUDENT_PARTS)
    return student.set_calibration(1.0, 1.0)


def random_robot_futures(model: CVAE, batch: Batch, generator: torch.Generator) -> torch.Tensor:
    """Standardised robot futures ``[B, 15, 6]``: from each situation's present robot state, random
    accelerations (uniform in :data:`ROBOT_ACCELERATION_RANGE`) held over each 0.3 s window."""
    b, device = len(batch), batch.t.device
    windows = math.ceil(HORIZON / REPLAN_STEPS)
    u = torch.rand(b, windows, 2, generator=generator).to(device, model.feature_mean.dtype)
    low = torch.tensor([ROBOT_ACCELERATION_RANGE["x"][0], ROBOT_ACCELERATION_RANGE["y"][0]], dtype=u.dtype, device=device)
    high = torch.tensor([ROBOT_ACCELERATION_RANGE["x"][1], ROBOT_ACCELERATION_RANGE["y"][1]], dtype=u.dtype, device=device)
    accelerations = (low + (high - low) * u).repeat_interleave(REPLAN_STEPS, dim=1)[:, :HORIZON]
    present = batch.robot_present * model.feature_std + model.feature_mean
    return model.states_to_standard(future_states(present, accelerations))


def _repeat(batch: Batch, times: int) -> Batch:
    """``batch`` with every situation repeated ``times`` times (situation-major blocks: row
    ``s·B + b`` is situation ``b``)."""
    return Batch(**{k: None if v is None else v.repeat(times, *([1] * (v.dim() - 1))) for k, v in vars(batch).items()})


def distillation_loss(student: CVAE, teacher: CVAE, batch: Batch, dc: DistilConfig,
                      generator: torch.Generator) -> tuple[torch.Tensor, dict]:
    """The student's loss on one minibatch ``batch`` of real situations (with their recorded
    actions ``y``): the mean ``-log p_student(y|x,z)`` of the teacher's samples ``(z, y)`` in the
    (partly perturbed) situations, plus ``real_weight`` times the student's exact NLL of the
    recorded actions; and both parts for logging."""
    perturbed = batch
    if dc.perturbed_fraction > 0:
        swap = torch.rand(len(batch), generator=generator).to(batch.t.device) < dc.perturbed_fraction
        futures = random_robot_futures(teacher, batch, generator)
        perturbed = replace(batch, robot_future=torch.where(swap[:, None, None], futures, batch.robot_future))
    s = dc.teacher_samples
    with torch.no_grad():
        x = teacher.encode(perturbed)
        p_z = teacher.joint_log_prob(teacher.p_z_logits(x)).exp()  # [B, Z]
        z = torch.multinomial(p_z.cpu(), s, replacement=True, generator=generator).T.to(x.device)  # [S, B]
        zx = teacher.zx(teacher.latent_onehots[z], x)
        y = teacher.sample_actions(zx, teacher.decoder_robot_inputs(perturbed), perturbed.human_present_action, generator)
    repeated = replace(_repeat(perturbed, s), y=y.reshape(s * len(batch), HORIZON, -1))
    log_p_y, _ = student.decode(zx.reshape(1, s * len(batch), -1), repeated)
    distil = -log_p_y.mean()
    loss, parts = distil, {"distil": distil.item(), "real": 0.0}
    if dc.real_weight > 0:
        with torch.no_grad():
            x_real = student.encode(batch)
            log_p_z = student.joint_log_prob(student.p_z_logits(x_real))
        log_p_y, _ = student.decode(student.zx(student.latent_onehots.unsqueeze(1), x_real), batch)
        real = -torch.logsumexp(log_p_z + log_p_y.T, dim=1).mean()
        loss = loss + dc.real_weight * real
        parts["real"] = real.item()
    return loss, parts


def distil_schedule(steps: int = 3000, seed: int = 0, lr_initial: float | None = None,
                    validate_every: int | None = None) -> TrainConfig:
    """The optimisation settings of a distillation (the fields :func:`distil` reads): ``steps`` Adam
    steps of 64 situations, learning rate ``lr_initial`` (default 1e-3) decaying by 0.999 per step
    towards 1e-4, scored every ``validate_every`` steps (default 100)."""
    lr = 1e-3 if lr_initial is None else lr_initial
    return TrainConfig(steps=steps, seed=seed, batch_size=64, lr_initial=lr, lr_final=min(1e-4, lr), lr_decay=0.999,
                       validate_every=validate_every or 100, validation_fraction=0.0)


def distil(trials: TrialSet, teacher: CVAE, out: str | Path | None = None, dc: DistilConfig = DistilConfig(),
           tc: TrainConfig = distil_schedule(),
           device: torch.device | str = "cpu", progress: bool = True, log: Callable[[str], None] = print,
           on_validate: Callable[[int, CVAE], None] | None = None, fields: dict | None = None,
           init: CVAE | None = None) -> CVAE:
    """Distil ``teacher`` (a trained :class:`CVAE`, calibration 1) into a student of ``dc``'s size
    on the situations and recorded actions of ``trials``, for ``tc.steps`` Adam steps of
    ``tc.batch_size`` situations (learning rate ``tc.lr_initial`` decaying to ``tc.lr_final`` by
    ``tc.lr_decay`` per step, gradients clipped at ``tc.clip_value``, seed ``tc.seed``).
    ``on_validate(step, student)`` is called every ``tc.validate_every`` steps and at the end, and at
    step 0; with ``out``, the student is saved there at the end (with ``fields``). The student's
    decoder starts as ``init``'s (:func:`student_of`). The hold modes' logits learn at their own
    constant rate ``dc.hold_lr`` (frozen at 0), as in fine-tuning (docs/model.md). Returns the
    student in evaluation mode."""
    device = torch.device(device)
    if not isinstance(teacher, CVAE):
        raise InputError(f"distillation: the teacher must be one CVAE (got a {type(teacher).__name__}; expected a "
                         f"trained model, a mixture's first component)")
    if float(teacher.latent_temperature) != 1.0 or not bool((teacher.output_scale == 1.0).all()):
        raise InputError("distillation: the teacher is calibrated (expected its trained density, calibration 1 and 1; "
                         "the student is calibrated afterwards)")
    exemplars = build_exemplars(trials)
    if len(exemplars) == 0:
        raise InputError(NO_EXEMPLARS)
    teacher = teacher.to(device).eval()
    check_standardisation_fits(teacher, exemplars, "the teacher")
    torch.manual_seed(tc.seed)
    student = student_of(teacher, dc.decoder_units, dc.components, init)
    data = exemplars.standardised(teacher)
    hold = [] if student.hold is None else list(student.hold.logits.parameters())
    for parameter in hold:
        parameter.requires_grad_(dc.hold_lr > 0)
    parameters = [p for p in student.parameters() if p.requires_grad]
    groups = [{"params": [p for p in parameters if all(p is not h for h in hold)], "lr": tc.lr_initial}]
    if dc.hold_lr > 0 and hold:
        groups.append({"params": hold, "lr": dc.hold_lr})
    optimizer = torch.optim.Adam(groups)
    minibatch = _MinibatchOrder(len(data), tc.batch_size, tc.seed)
    generator = torch.Generator().manual_seed(tc.seed)
    log(f"distilling a {teacher.config.decoder_units}-unit, {teacher.config.components}-component decoder into "
        f"{dc.decoder_units} units, {dc.components} components{'' if init is None else ' (from a student)'}: "
        f"{len(exemplars)} situations from {len(trials)} trials, {tc.steps} steps on {device}")
    if on_validate is not None:
        on_validate(0, student.eval())
    start = time.perf_counter()
    bar = tqdm(total=tc.steps, disable=not progress, desc="distil", unit="step")
    for step in range(tc.steps):
        student.train()
        optimizer.param_groups[0]["lr"] = learning_rate(tc, step)
        loss, parts = distillation_loss(student, teacher, data.batch(minibatch(step).to(device)), dc, generator)
        if not torch.isfinite(loss):
            raise InputError(f"distillation diverged at step {step} (loss {loss.item()}; expected a smaller learning rate "
                             f"than {learning_rate(tc, step):.3g})")
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_value_(parameters, tc.clip_value)
        optimizer.step()
        bar.update(1)
        bar.set_postfix(distil=f"{parts['distil']:.2f}", real=f"{parts['real']:.2f}")
        done = step + 1
        if on_validate is not None and (done % tc.validate_every == 0 or done == tc.steps):
            on_validate(done, student.eval())
    bar.close()
    log(f"distilled in {time.perf_counter() - start:.0f} s")
    student.eval()
    for parameter in student.parameters():
        parameter.requires_grad_(True)
    if out is not None:
        save_checkpoint(out, student, step=tc.steps, data_fingerprint=exemplars.fingerprint(),
                        distillation={**asdict(dc), "steps": tc.steps, "batch_size": tc.batch_size,
                                      "lr_initial": tc.lr_initial, "lr_final": tc.lr_final, "lr_decay": tc.lr_decay,
                                      "seed": tc.seed},
                        **(fields or {}))
    return student


def teacher_model(spec: str, device: torch.device | str = "cpu", variant: str | None = None) -> CVAE:
    """The teacher a model spec names, as trained: a mixture's first component (the one trained on
    real trials), calibration reset to 1 and 1; with ``variant`` ``cvae-hold``, a ``cvae`` model is
    given hold modes, switched off (:func:`~trafficweaving.model.train.initial_model`), so that its
    student has a hold head to learn later."""
    return initial_model(spec, variant)[0].to(device).eval()

