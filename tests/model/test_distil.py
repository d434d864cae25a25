"""Distillation (model/distil.py): the student keeps the teacher's latent distribution and learns a
smaller decoder from the teacher's samples; cross-validation distils each fold from the teacher
that never saw it; the ``distil`` command."""

from dataclasses import replace

import numpy as np
import pytest
import torch

from helpers_model import small_checkpoint, small_model, synthetic_trials
from trafficweaving.cli import main
from trafficweaving.errors import InputError
from trafficweaving.model.checkpoint import load_checkpoint
from trafficweaving.model.crossval import crossval, teacher_file
from trafficweaving.model.cvae import ACCEL
from trafficweaving.model.distil import (ROBOT_ACCELERATION_RANGE, STUDENT_PARTS, DistilConfig, distil,
                                         distil_schedule, distillation_loss, random_robot_futures, student_of)
from trafficweaving.model.evaluate import evaluate
from trafficweaving.model.exemplars import build_exemplars
from trafficweaving.model.mixture import Mixture
from trafficweaving.model.registry import load_model
from trafficweaving.model.train_config import TrainConfig
from trafficweaving.scenario import DT, REPLAN_STEPS

SILENT = {"progress": False, "log": lambda _: None}
SMALL = DistilConfig(decoder_units=8, components=2, teacher_samples=4)


@pytest.fixture(scope="module")
def trials():
    return synthetic_trials(6, seed=5)


@pytest.fixture(scope="module")
def teacher(trials):
    return small_model(trials).eval()


@pytest.fixture(scope="module")
def batch(trials, teacher):
    data = build_exemplars(trials).standardised(teacher)
    return data.batch(torch.arange(0, len(data), max(len(data) // 24, 1))[:24])


def test_the_student_has_the_teachers_latent_distribution_and_learns_only_its_decoder(teacher, batch):
    student = student_of(teacher, 8, 2)
    assert (student.config.decoder_units, student.config.components) == (8, 2)
    assert replace(student.config, decoder_units=teacher.config.decoder_units, components=teacher.config.components) \
        == teacher.config
    with torch.no_grad():
        student_p_z, teacher_p_z = (m.joint_log_prob(m.p_z_logits(m.encode(batch))) for m in (student, teacher))
    torch.testing.assert_close(student_p_z, teacher_p_z, rtol=0, atol=0)
    for name in ("feature_mean", "feature_std", "label_mean", "label_std"):
        torch.testing.assert_close(getattr(student, name), getattr(teacher, name), rtol=0, atol=0)
    trainable = {name.split(".")[0] for name, p in student.named_parameters() if p.requires_grad}
    assert trainable == set(STUDENT_PARTS)
    torch.testing.assert_close(student.hold.log_sigma, teacher.hold.log_sigma, rtol=0, atol=0)


def test_random_robot_futures_start_at_the_present_and_hold_each_windows_accelerations(teacher, batch):
    futures = random_robot_futures(teacher, batch, torch.Generator().manual_seed(0))
    physical = (futures * teacher.feature_std + teacher.feature_mean).double()
    present = (batch.robot_present * teacher.feature_std + teacher.feature_mean).double()
    accelerations = physical[..., ACCEL]  # [B, 15, 2]
    for k, (low, high) in enumerate(ROBOT_ACCELERATION_RANGE.values()):
        assert bool(((accelerations[..., k] >= low - 1e-4) & (accelerations[..., k] <= high + 1e-4)).all())
    windows = accelerations.reshape(len(batch), -1, REPLAN_STEPS, 2)
    torch.testing.assert_close(windows, windows[:, :, :1].expand_as(windows), rtol=0, atol=1e-4)
    assert accelerations[:, ::REPLAN_STEPS].std() > 1.0  # they vary between windows and situations
    # the trapezoid rule from the present state: velocity after one step
    expected = present[:, 2:4] + 0.5 * DT * (present[:, 4:6] + accelerations[:, 0])
    torch.testing.assert_close(physical[:, 0, 2:4], expected, rtol=0, atol=1e-3)


def _teacher_sample_nll(student, teacher, batch, seed=1) -> float:
    """The student's mean ``-log p(y|x,z)`` of fresh teacher samples in ``batch``'s situations."""
    with torch.no_grad():
        _, parts = distillation_loss(student, teacher, batch, replace(SMALL, real_weight=0.0),
                                     torch.Generator().manual_seed(seed))
    return parts["distil"]


@pytest.mark.slow
def test_distillation_brings_the_student_to_the_teachers_samples_and_saves_it(trials, teacher, batch, tmp_path):
    seen = []
    before = _teacher_sample_nll(student_of(teacher, 8, 2), teacher, batch)
    out = tmp_path / "student.pt"
    alone = replace(SMALL, real_weight=0.0)  # the teacher's samples alone (an untrained teacher is not the data)
    student = distil(trials, teacher, out, alone, distil_schedule(120, validate_every=50, lr_initial=1e-2),
                     on_validate=lambda step, model: seen.append(step), **SILENT)
    assert seen == [0, 50, 100, 120]
    after, floor = _teacher_sample_nll(student, teacher, batch), _teacher_sample_nll(teacher, teacher, batch)
    assert floor < after < floor + 0.7 * (before - floor), (before, after, floor)  # the KL to the teacher shrinks
    loaded, payload = load_checkpoint(out)
    assert (loaded.config.decoder_units, loaded.config.components) == (8, 2)
    assert payload["distillation"]["steps"] == 120 and payload["distillation"]["teacher_samples"] == 4
    for name, tensor in student.state_dict().items():
        torch.testing.assert_close(loaded.state_dict()[name], tensor, rtol=0, atol=0, msg=name)


def test_distil_refuses_a_calibrated_teacher_and_a_mixture(trials, teacher):
    calibrated = small_model(trials).set_calibration(2.0, 1.5)
    with pytest.raises(InputError, match="the teacher is calibrated"):
        distil(trials, calibrated, None, SMALL, distil_schedule(1), **SILENT)
    with pytest.raises(InputError, match="the teacher must be one CVAE"):
        distil(trials, Mixture([teacher, small_model(trials, seed=1)], [0.5, 0.5]), None, SMALL, distil_schedule(1), **SILENT)
    with pytest.raises(InputError, match="decoder units"):
        DistilConfig(decoder_units=0)


@pytest.mark.slow
def test_crossval_distils_each_fold_from_the_teacher_that_never_saw_it(trials, tmp_path):
    three = trials.subset(np.arange(3))  # three folds of one trial
    init = small_checkpoint(tmp_path / "init.pt", three)
    quick = TrainConfig(steps=2, validate_every=2, checkpoint_every=2, lr_initial=1e-4, lr_final=1e-5)
    teachers = tmp_path / "teachers"
    crossval(three, 3, quick, variant="cvae-hold", init=init, nested=True, out=teachers, **SILENT)
    schedule = distil_schedule(4, validate_every=2)
    result = crossval(three, 3, schedule, nested=True, out=tmp_path / "students", teacher_folds=teachers,
                      distillation=SMALL, **SILENT)
    assert list(result.steps) == [0, 2, 4] and np.isfinite(result.curves).all()
    assert np.isfinite(result.inner[~np.eye(3, dtype=bool)]).all()
    student, payload = load_checkpoint(tmp_path / "students" / "fold_1.pt")
    assert student.config.decoder_units == 8 and payload["held_out_trials"] == [int(three.trial_ids[result.fold_trials[0][0]])]
    assert teacher_file(teachers, (0, 2)) == teachers / "nested" / "fold_1" / "fold_3.pt"
    # a teacher folder cross-validated on other folds (another seed) would have seen the held-out trials
    with pytest.raises(InputError, match="holds out other trials"):
        crossval(three, 3, schedule, seed=1, teacher_folds=teachers, distillation=SMALL, **SILENT)
    with pytest.raises(InputError, match="no nested"):
        crossval(three, 3, schedule, teacher_folds=tmp_path, distillation=SMALL, **SILENT)


@pytest.mark.slow
def test_the_distil_command_writes_a_student_and_refuses_a_missing_teacher(trials, tmp_path, capsys):
    data = tmp_path / "trials.parquet"
    trials.write_parquet(data)
    teacher = small_checkpoint(tmp_path / "teacher.pt", trials)
    out = tmp_path / "student.pt"
    assert main(["distil", "--data", str(data), "--teacher", str(teacher), "--out", str(out), "--steps", "3",
                 "--decoder-units", "8", "--components", "2", "--json"]) == 0
    capsys.readouterr()
    student, payload = load_checkpoint(out)
    assert (student.config.decoder_units, student.config.components, payload["teacher"]) == (8, 2, str(teacher))
    assert main(["distil", "--data", str(data), "--teacher", str(tmp_path / "none.pt"), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--teacher" in err[0] and "no such file" in err[0]


@pytest.mark.slow
def test_the_shipped_fast_model_is_the_default_distilled_and_predicts_the_real_trials_as_well(hitl_trials):
    fast, default = load_model("fast"), load_model("default")
    assert (fast.config.decoder_units, fast.config.components) == (16, 8)
    for name, tensor in default.state_dict().items():  # the default's encoders, latent distribution, standardisation
        if name.split(".")[0] not in STUDENT_PARTS and name not in ("latent_temperature", "output_scale"):
            torch.testing.assert_close(fast.state_dict()[name], tensor, rtol=0, atol=0, msg=name)
    exemplars = build_exemplars(hitl_trials)  # in-sample for both: -39.9 against -41.0 nats (docs/fast_model.md)
    assert evaluate(fast, exemplars).nll_exact.mean() < evaluate(default, exemplars).nll_exact.mean() + 2.0
