"""Training: the schedules (docs/model.md, "Training"), the loss, checkpoints (round trip, resume, bad files)."""

import math

import numpy as np
import pytest
import torch

from helpers_model import small_checkpoint, synthetic_trials
from trafficweaving.errors import InputError
from trafficweaving.model.checkpoint import load_checkpoint, save_checkpoint, write_payload
from trafficweaving.model.cvae import CVAE, CVAEConfig
from trafficweaving.model.exemplars import build_exemplars
from trafficweaving.model.evaluate import evaluate
from trafficweaving.model.registry import load_model
from trafficweaving.model.train import kl_weight, learning_rate, loss_terms, prepare_data, temperature, train
from trafficweaving.model.train_config import TrainConfig

QUICK = TrainConfig(steps=6, validate_every=3, checkpoint_every=3, validation_exemplars=64)


@pytest.fixture(scope="module")
def trials():
    return synthetic_trials(20, seed=5)


def test_schedules_follow_the_paper():
    tc = TrainConfig()
    assert learning_rate(tc, 0) == pytest.approx(1e-3)
    assert learning_rate(tc, 10_000) == pytest.approx(1e-5 + (1e-3 - 1e-5) * 0.9999 ** 10_000)
    assert learning_rate(tc, 10**7) == pytest.approx(1e-5)
    assert temperature(tc, 0) == pytest.approx(2.0) and temperature(tc, 10**7) == pytest.approx(0.001)
    assert kl_weight(tc, 8000) == pytest.approx(0.5 * (1 + 1e-4))
    assert kl_weight(tc, 0) == pytest.approx(1e-4 + (1 - 1e-4) / (1 + math.exp(6))) and kl_weight(tc, 50_000) == pytest.approx(1.0)
    assert kl_weight(tc, 8000 + 8000 / 6) == pytest.approx(1e-4 + (1 - 1e-4) / (1 + math.exp(-1)))


def test_kl_term_has_the_0_07_floor_per_latent_variable(trials):
    train_ex, _, statistics = prepare_data(trials, TrainConfig())
    torch.manual_seed(0)
    model = CVAE(CVAEConfig.variant("no-latent")).set_standardisation(*statistics)  # a single latent value: KL(q‖p) is 0
    batch = train_ex.standardised(model).batch(torch.arange(16))
    _, parts = loss_terms(model, batch, TrainConfig(), step=0)
    assert parts["kl"] == pytest.approx(0.0, abs=1e-6)
    tc = TrainConfig(recurrent_dropout=0, p_z_dropout=0, scheduled_sampling=0)
    model.eval()
    loss, parts = loss_terms(model, batch, tc, step=50_000)
    assert loss.item() == pytest.approx(parts["nll"] + 0.07 * kl_weight(tc, 50_000), rel=1e-5)


@pytest.mark.slow
def test_training_reduces_the_loss_and_writes_a_checkpoint(trials, tmp_path):
    out = tmp_path / "m.pt"
    result = train(trials, out, tc=TrainConfig(steps=20, validate_every=10, checkpoint_every=10, validation_exemplars=128),
                   progress=False, log=lambda _: None)
    assert [s for s, _ in result.history] == [10, 20]
    assert result.history[1][1] < result.history[0][1]  # validation NLL improves early in training
    model, payload = load_checkpoint(out)
    assert payload["step"] == 20 and payload["train_config"]["steps"] == 20
    assert len(payload["data_fingerprint"]) == 64
    assert result.validation["instances"] > 0 and np.isfinite(result.validation["nll_exact"])


@pytest.mark.slow
def test_resumed_training_equals_uninterrupted_training(trials, tmp_path):
    trials = trials.subset(np.arange(8))
    straight = train(trials, tmp_path / "a.pt", tc=QUICK, progress=False, log=lambda _: None)
    train(trials, tmp_path / "b.pt", tc=TrainConfig(**{**vars(QUICK), "steps": 3}), progress=False, log=lambda _: None)
    resumed = train(trials, tmp_path / "b.pt", tc=QUICK, resume=tmp_path / "b.pt", progress=False, log=lambda _: None)
    assert resumed.step == 6
    for (name, a), b in zip(straight.model.state_dict().items(), resumed.model.state_dict().values()):
        torch.testing.assert_close(a, b, rtol=0, atol=0, msg=name)


@pytest.mark.slow
def test_resume_refuses_other_data(pretrained, tmp_path):
    other = synthetic_trials(20, seed=6)
    with pytest.raises(InputError, match="different data"):
        train(other, tmp_path / "n.pt", tc=QUICK, resume=pretrained, progress=False, log=lambda _: None)


@pytest.mark.slow
@pytest.mark.parametrize("variant", ["cvae", "lstm"])
def test_checkpoint_round_trip_keeps_predictions(trials, tmp_path, variant):
    torch.manual_seed(1)
    model = CVAE(CVAEConfig.variant(variant)).eval()
    save_checkpoint(tmp_path / "m.pt", model, step=0)
    loaded = load_model(str(tmp_path / "m.pt"))
    exemplars = build_exemplars(trials.subset(np.arange(3)))
    np.testing.assert_array_equal(evaluate(model, exemplars).nll_exact, evaluate(loaded, exemplars).nll_exact)
    assert loaded.config == model.config


def test_bad_checkpoints_give_one_line_errors(tmp_path):
    def fails(path, pattern):
        with pytest.raises(InputError, match=pattern) as info:
            load_model(str(path))
        assert "\n" not in str(info.value)

    fails(tmp_path / "none.pt", "no such file")
    (tmp_path / "junk.pt").write_bytes(b"\x00garbage")
    fails(tmp_path / "junk.pt", "junk.pt: not a readable checkpoint")
    torch.save({"hello": 1}, tmp_path / "other.pt")
    fails(tmp_path / "other.pt", "not a trafficweaving model checkpoint")
    model = CVAE()
    save_checkpoint(tmp_path / "m.pt", model)
    payload = torch.load(tmp_path / "m.pt", weights_only=True)
    payload["state_dict"]["decoder.bias"] = torch.zeros(7)
    write_payload(tmp_path / "shape.pt", payload)
    fails(tmp_path / "shape.pt", r"tensor decoder.bias has shape \[7\] \(expected \[512\]\)")
    payload["state_dict"]["decoder.bias"] = torch.full((512,), float("nan"))
    write_payload(tmp_path / "nan.pt", payload)
    fails(tmp_path / "nan.pt", "NaN or infinite")
    del payload["state_dict"]["decoder.bias"]
    write_payload(tmp_path / "missing.pt", payload)
    fails(tmp_path / "missing.pt", "lacks tensor decoder.bias")
    payload["version"] = 99
    torch.save(payload, tmp_path / "version.pt")
    fails(tmp_path / "version.pt", "checkpoint version 99")
    fails("authors:" + str(tmp_path / "none.npz"), "no such file")


def test_resume_needs_a_training_checkpoint(trials, tmp_path):
    save_checkpoint(tmp_path / "export.pt", CVAE())
    with pytest.raises(InputError, match="not a training checkpoint"):
        train(trials, tmp_path / "x.pt", tc=QUICK, resume=tmp_path / "export.pt", progress=False, log=lambda _: None)


# ---------------------------------------------------------------- fine-tuning and cross-validation
@pytest.fixture(scope="module")
def pretrained(trials, tmp_path_factory):
    """A small cvae-hold model (helpers_model.SMALL_UNITS) fine-tuned for the 6 steps of QUICK: a
    training checkpoint to fine-tune further, cross-validate or resume."""
    folder = tmp_path_factory.mktemp("init")
    train(trials, folder / "hold.pt", "cvae-hold", QUICK, init=small_checkpoint(folder / "small.pt", trials),
          progress=False, log=lambda _: None)
    return folder / "hold.pt"


@pytest.mark.slow
def test_fine_tuning_keeps_the_models_standardisation_and_records_its_origin(pretrained, tmp_path):
    from dataclasses import replace

    other = synthetic_trials(12, seed=9)
    out = tmp_path / "tuned.pt"
    result = train(other, out, None, replace(QUICK, lr_initial=1e-4), init=pretrained, progress=False, log=lambda _: None)
    initial, init_payload = load_checkpoint(pretrained)
    tuned, payload = load_checkpoint(out)
    assert tuned.config.name == "cvae-hold"
    for name in ("feature_mean", "feature_std", "label_mean", "label_std"):
        torch.testing.assert_close(getattr(tuned, name), getattr(initial, name))
    assert payload["init"]["data_fingerprint"] == init_payload["data_fingerprint"] != payload["data_fingerprint"]
    assert payload["init"]["step"] == init_payload["step"] == 6
    assert payload["train_config"]["schedule_start"] == 6  # KL weight and temperature continue from the init
    assert any(not torch.equal(a, b) for a, b in zip(tuned.parameters(), initial.parameters()))
    assert result.step == 6


@pytest.mark.slow
def test_fine_tuning_refuses_another_variant_or_data_in_other_units(pretrained, trials, tmp_path):
    with pytest.raises(InputError, match="a cvae-hold model, but --variant cvae"):
        train(trials, tmp_path / "a.pt", "cvae", QUICK, init=pretrained, progress=False, log=lambda _: None)
    feet = trials.subset(np.arange(len(trials)))
    feet.states[..., :4] *= 3.28  # positions and speeds in feet
    with pytest.raises(InputError, match="standardisation does not fit the data"):
        train(feet, tmp_path / "b.pt", None, QUICK, init=pretrained, progress=False, log=lambda _: None)
    with pytest.raises(InputError, match="no such file"):
        train(trials, tmp_path / "c.pt", None, QUICK, init=tmp_path / "missing.pt", progress=False, log=lambda _: None)


@pytest.mark.slow
def test_early_stopping_keeps_the_best_weights(pretrained, trials, tmp_path):
    from dataclasses import replace

    tc = replace(QUICK, steps=40, validate_every=2, checkpoint_every=2, lr_initial=0.1, lr_final=0.1, patience=2,
                 validation_exemplars=10**6)
    result = train(trials, tmp_path / "s.pt", None, tc, init=pretrained, progress=False, log=lambda _: None)
    steps, values = zip(*result.history)
    best = int(np.argmin(values))
    assert result.best_step == steps[best] == result.step
    assert steps[-1] == steps[best] + 2 * 2 < 40  # stopped after `patience` validations without improvement
    model, _ = load_checkpoint(tmp_path / "s.pt")
    ex = build_exemplars(trials.subset(split_val(trials)))
    assert evaluate(model, ex).nll_exact.mean() == pytest.approx(values[best], rel=1e-4)


def split_val(trials):
    from trafficweaving.model.exemplars import split_by_trial

    return split_by_trial(len(trials), QUICK.validation_fraction, QUICK.seed)[1]


def test_folds_partition_the_trials():
    from trafficweaving.model.crossval import fold_assignment

    folds = fold_assignment(23, 5, seed=1)
    assert sorted(np.concatenate(folds).tolist()) == list(range(23))
    assert [len(f) for f in folds] == [5, 5, 5, 4, 4]


def test_crossval_chooses_steps_by_the_mean_curve_and_nests_the_choice():
    from trafficweaving.model.crossval import CrossvalResult

    curves = np.array([[0.0, -2.0, -1.0], [0.0, -1.0, -3.0], [0.0, -2.5, -1.0]])
    result = CrossvalResult([np.arange(2)] * 3, np.array([0, 50, 100]), curves, np.array([10, 10, 10]),
                            np.array([-1.0, -2.0, -3.0]), "ref")
    summary = result.summary()
    assert summary["steps"] == 50 and summary["folds"] == [-2.0, -1.0, -2.5]  # mean curve 0, -1.83, -1.67
    # without fold 1 the others' mean curve is (0, -1.75, -2.0): 100 steps, where fold 1 scores -1.0;
    # without fold 2: (0, -2.25, -1.0), 50 steps; without fold 3: (0, -1.5, -2.0), 100 steps
    assert summary["nested"]["steps"] == [100, 50, 100]
    assert summary["nested"]["folds"] == [-1.0, -1.0, -1.0]
    assert summary["reference"] == {"model": "ref", "folds": [-1.0, -2.0, -3.0], "nll_exact": -2.0}


def test_crossval_can_require_every_fold_to_beat_the_reference():
    from trafficweaving.model.crossval import CrossvalResult

    curves = np.array([[0.0, -3.0, -4.0], [0.0, -3.0, -4.0], [0.0, -2.5, -1.5]])
    reference = np.array([-1.0, -1.0, -2.0])
    free = CrossvalResult([np.arange(2)] * 3, np.array([0, 50, 100]), curves, np.array([10] * 3), reference, "ref")
    assert free.summary()["steps"] == 100  # best mean (-3.17), but fold 3 (-1.5) is worse than the reference (-2.0)
    from dataclasses import replace

    summary = replace(free, beat_reference=True).summary()
    assert summary["steps"] == 50 and summary["folds"] == [-3.0, -3.0, -2.5]
    assert summary["selection"] == "mean, every fold better than the reference"
    # without fold 3 the constraint does not bind: folds 1 and 2 choose 100 steps; fold 3 is scored there
    assert summary["nested"]["steps"] == [50, 50, 100]


@pytest.mark.slow
def test_crossval_fine_tunes_each_fold_and_scores_the_reference(pretrained, trials, tmp_path):
    from dataclasses import replace

    from trafficweaving.model.crossval import crossval, out_of_fold_models

    tc = replace(QUICK, steps=4, validate_every=2, lr_initial=1e-4)
    nine = trials.subset(np.arange(9))
    result = crossval(nine, 3, tc, init=pretrained, reference=str(pretrained), progress=False, log=lambda _: None,
                      out=tmp_path / "folds")
    assert result.steps.tolist() == [0, 2, 4] and result.curves.shape == (3, 3)
    np.testing.assert_allclose(result.curves[:, 0], result.reference, rtol=1e-6)  # step 0 is the initial model
    models = out_of_fold_models(tmp_path / "folds")
    assert sorted(i for _, held in models for i in held) == sorted(nine.trial_ids.tolist())
    for k, (model, held) in enumerate(models):  # each saved fold model scores its fold as the curve says
        fold = nine.subset(np.flatnonzero(np.isin(nine.trial_ids, held)))
        nll = evaluate(model, build_exemplars(fold)).nll_exact.mean()
        assert nll == pytest.approx(result.curves[k, result.chosen], rel=1e-5)


def test_crossval_rejects_too_few_trials_or_no_humans(trials):
    from trafficweaving.model.crossval import crossval

    with pytest.raises(InputError, match="fewer than --folds 5"):
        crossval(trials.subset(np.arange(4)), 5, QUICK, progress=False, log=lambda _: None)
    robots = trials.subset(np.arange(6))
    robots.roles[:] = "robot"
    with pytest.raises(InputError, match="no prediction instances"):
        crossval(robots, 3, QUICK, progress=False, log=lambda _: None)


@pytest.mark.slow
def test_hold_widths_learn_at_their_own_rate(pretrained, trials, tmp_path):
    from dataclasses import replace

    from trafficweaving.model.train import make_optimizer

    initial, _ = load_checkpoint(pretrained)
    groups = make_optimizer(initial, TrainConfig()).param_groups
    assert [g["lr"] for g in groups] == [1e-3, 1e-2] and groups[1]["params"][0] is initial.hold.log_sigma
    tc = replace(QUICK, steps=20, lr_initial=1e-5, lr_final=1e-5)
    result = train(trials, tmp_path / "w.pt", None, tc, init=pretrained, progress=False, log=lambda _: None)
    moved = (result.model.hold.log_sigma - initial.hold.log_sigma).abs().max().item()
    assert moved > 20 * 1e-4  # far more than the rest of the model's learning rate allows (Adam: ~lr per step)
