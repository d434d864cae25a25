"""Training: the schedules of DESIGN.md §3, the loss, checkpoints (round trip, resume, bad files)."""

import math

import numpy as np
import pytest
import torch

from trafficweaving.data.generate import generate_trials
from trafficweaving.errors import InputError
from trafficweaving.model.checkpoint import load_checkpoint, load_model, save_checkpoint
from trafficweaving.model.cvae import CVAE, CVAEConfig
from trafficweaving.model.exemplars import build_exemplars
from trafficweaving.model.evaluate import evaluate
from trafficweaving.model.train import TrainConfig, kl_weight, learning_rate, loss_terms, prepare_data, temperature, train

QUICK = TrainConfig(steps=6, validate_every=3, checkpoint_every=3, validation_exemplars=64)


@pytest.fixture(scope="module")
def trials():
    trials, _ = generate_trials(20, seed=5, progress=False)
    return trials


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
    train_ex, _, std = prepare_data(trials, TrainConfig())
    batch = train_ex.standardised(std).batch(torch.arange(16))
    torch.manual_seed(0)
    model = CVAE(CVAEConfig.variant("no-latent"))  # a single latent value: KL(q‖p) is 0
    _, parts = loss_terms(model, batch, TrainConfig(), step=0)
    assert parts["kl"] == pytest.approx(0.0, abs=1e-6)
    tc = TrainConfig(recurrent_dropout=0, p_z_dropout=0, scheduled_sampling=0)
    model.eval()
    loss, parts = loss_terms(model, batch, tc, step=50_000)
    assert loss.item() == pytest.approx(parts["nll"] + 0.07 * kl_weight(tc, 50_000), rel=1e-5)


def test_training_reduces_the_loss_and_writes_a_checkpoint(trials, tmp_path):
    out = tmp_path / "m.pt"
    result = train(trials, out, tc=TrainConfig(steps=60, validate_every=30, checkpoint_every=30, validation_exemplars=128),
                   progress=False, log=lambda _: None)
    assert [s for s, _ in result.history] == [30, 60]
    assert result.history[1][1] < result.history[0][1]  # validation NLL improves early in training
    model, payload = load_checkpoint(out)
    assert payload["step"] == 60 and payload["train_config"]["steps"] == 60
    assert len(payload["data_fingerprint"]) == 64
    assert result.validation["instances"] > 0 and np.isfinite(result.validation["nll_exact"])


def test_resumed_training_equals_uninterrupted_training(trials, tmp_path):
    straight = train(trials, tmp_path / "a.pt", tc=QUICK, progress=False, log=lambda _: None)
    train(trials, tmp_path / "b.pt", tc=TrainConfig(**{**vars(QUICK), "steps": 3}), progress=False, log=lambda _: None)
    resumed = train(trials, tmp_path / "b.pt", tc=QUICK, resume=tmp_path / "b.pt", progress=False, log=lambda _: None)
    assert resumed.step == 6
    for (name, a), b in zip(straight.model.state_dict().items(), resumed.model.state_dict().values()):
        torch.testing.assert_close(a, b, rtol=0, atol=0, msg=name)


def test_resume_refuses_other_data(trials, tmp_path):
    train(trials, tmp_path / "m.pt", tc=QUICK, progress=False, log=lambda _: None)
    other, _ = generate_trials(20, seed=6, progress=False)
    with pytest.raises(InputError, match="different data"):
        train(other, tmp_path / "n.pt", tc=QUICK, resume=tmp_path / "m.pt", progress=False, log=lambda _: None)


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
    torch.save(payload, tmp_path / "shape.pt")
    fails(tmp_path / "shape.pt", r"tensor decoder.bias has shape \[7\] \(expected \[512\]\)")
    payload["state_dict"]["decoder.bias"] = torch.full((512,), float("nan"))
    torch.save(payload, tmp_path / "nan.pt")
    fails(tmp_path / "nan.pt", "NaN or infinite")
    del payload["state_dict"]["decoder.bias"]
    torch.save(payload, tmp_path / "missing.pt")
    fails(tmp_path / "missing.pt", "lacks tensor decoder.bias")
    payload["version"] = 99
    torch.save(payload, tmp_path / "version.pt")
    fails(tmp_path / "version.pt", "checkpoint version 99")
    fails("authors:" + str(tmp_path / "none.npz"), "no such file")


def test_resume_needs_a_training_checkpoint(trials, tmp_path):
    save_checkpoint(tmp_path / "export.pt", CVAE())
    with pytest.raises(InputError, match="not a training checkpoint"):
        train(trials, tmp_path / "x.pt", tc=QUICK, resume=tmp_path / "export.pt", progress=False, log=lambda _: None)
