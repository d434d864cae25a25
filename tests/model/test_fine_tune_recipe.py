"""Step 8: fine-tuning from the authors' model (hold modes added switched off, the exact objective,
trainable parts, the hold modes' learning rate) and the nested cross-validation of the recipe
(inner cross-validation of each outer fold; calibration and candidate chosen on inner folds)."""

from dataclasses import replace

import numpy as np
import pytest
import torch

from helpers_model import small_checkpoint, synthetic_trials
from trafficweaving.errors import InputError
from trafficweaving.model.checkpoint import load_checkpoint, save_checkpoint
from trafficweaving.model.crossval import CrossvalResult, crossval, out_of_fold_models
from trafficweaving.model.cvae import CVAE, CVAEConfig
from trafficweaving.model.evaluate import evaluate, physical_offset
from trafficweaving.model.exemplars import build_exemplars, state_statistics
from trafficweaving.model.gmm import HOLD_OFF_LOGIT
from trafficweaving.model.train import initial_model, loss_terms, make_optimizer, prepare_data, train
from trafficweaving.model.train_config import TrainConfig

QUICK = TrainConfig(steps=4, validate_every=2, checkpoint_every=2, validation_exemplars=64, lr_initial=1e-4,
                    lr_final=1e-5)
SILENT = {"progress": False, "log": lambda _: None}


@pytest.fixture(scope="module")
def trials():
    return synthetic_trials(12, seed=21)


@pytest.fixture(scope="module")
def cvae_checkpoint(trials, tmp_path_factory):
    """A paper-variant (cvae) model with q, untrained (weights seeded), standardised for ``trials``; of
    the paper's widths, which the upgrade to cvae-hold gives its copy."""
    path = tmp_path_factory.mktemp("cvae") / "cvae.pt"
    torch.manual_seed(0)
    save_checkpoint(path, CVAE(CVAEConfig.variant("cvae")).set_standardisation(*state_statistics(trials)))
    return path


@pytest.mark.slow
def test_hold_modes_start_switched_off_so_the_upgrade_keeps_the_density(trials, cvae_checkpoint):
    paper, _ = load_checkpoint(cvae_checkpoint)
    upgraded, provenance = initial_model(cvae_checkpoint, "cvae-hold")
    assert upgraded.config.name == "cvae-hold" and provenance["upgraded_to"] == "cvae-hold"
    for name, tensor in paper.state_dict().items():  # every paper part carries the paper model's weights
        torch.testing.assert_close(upgraded.state_dict()[name], tensor, rtol=0, atol=0, msg=name)
    assert upgraded.hold.logits.bias.tolist() == [0.0] + [HOLD_OFF_LOGIT] * 3
    exemplars = build_exemplars(trials.subset(np.arange(3)))
    before, after = evaluate(paper, exemplars), evaluate(upgraded, exemplars)
    np.testing.assert_allclose(after.nll_exact, before.nll_exact, atol=1e-4)
    np.testing.assert_allclose(after.nll_direction, before.nll_direction, atol=1e-4)


@pytest.mark.slow
def test_the_authors_model_upgraded_has_its_density_on_the_real_trials(authors_model_dir, hitl_trials,
                                                                      authors_evaluation):
    upgraded, _ = initial_model(f"authors:{authors_model_dir / 'weights.npz'}", "cvae-hold")
    before, after = authors_evaluation.nll_exact, evaluate(upgraded, build_exemplars(hitl_trials)).nll_exact
    assert np.abs(after - before).max() < 1e-4 and after.mean() == pytest.approx(-12.7168, abs=5e-4)


def test_only_a_cvae_model_is_upgraded(trials, tmp_path):
    path = tmp_path / "lstm.pt"
    save_checkpoint(path, CVAE(CVAEConfig.variant("lstm")))
    with pytest.raises(InputError, match="a lstm model, but --variant cvae-hold"):
        initial_model(path, "cvae-hold")


def test_exact_objective_is_the_exact_nll_and_needs_no_q(trials):
    train_ex, _, statistics = prepare_data(trials, TrainConfig())
    torch.manual_seed(0)
    model = CVAE(CVAEConfig.variant("cvae-hold", has_q=False)).set_standardisation(*statistics).eval()
    batch = train_ex.standardised(model).batch(torch.arange(24))
    tc = TrainConfig(objective="exact", recurrent_dropout=0, p_z_dropout=0, scheduled_sampling=0)
    loss, parts = loss_terms(model, batch, tc, step=0)
    from trafficweaving.model.exemplars import ExemplarSet

    first = ExemplarSet(**{**vars(train_ex), "stream": train_ex.stream[:24], "t": train_ex.t[:24]})
    expected = evaluate(model, first).nll_exact.mean() - physical_offset(model)
    assert loss.item() == pytest.approx(expected, abs=1e-4) and parts["kl"] == 0.0


@pytest.mark.slow
def test_a_model_without_q_fine_tunes_with_the_exact_objective_only(authors_model_dir, trials, tmp_path):
    authors = f"authors:{authors_model_dir / 'weights.npz'}"
    with pytest.raises(InputError, match="no recognition network"):
        train(trials, None, "cvae-hold", replace(QUICK, objective="elbo"), init=authors, **SILENT)
    result = train(trials, tmp_path / "a.pt", "cvae-hold", QUICK, init=authors, **SILENT)
    _, payload = load_checkpoint(tmp_path / "a.pt")
    assert payload["train_config"]["objective"] == "exact" and payload["init"]["path"] == authors
    assert result.model.config.name == "cvae-hold" and not result.model.config.has_q


@pytest.mark.slow
def test_trainable_parts_freeze_the_rest(trials, cvae_checkpoint, tmp_path):
    initial, _ = initial_model(cvae_checkpoint, "cvae-hold")
    tc = replace(QUICK, trainable="hold", hold_lr=0.05)
    result = train(trials, tmp_path / "h.pt", "cvae-hold", tc, init=cvae_checkpoint, **SILENT)
    for name, tensor in result.model.state_dict().items():
        moved = not torch.equal(tensor, initial.state_dict()[name])
        assert moved == (name in ("hold.logits.weight", "hold.logits.bias", "hold.log_sigma")), name
    _, payload = load_checkpoint(tmp_path / "h.pt")  # its optimizer covers the trainable parameters only
    assert sum(len(g["params"]) for g in payload["optimizer"]["param_groups"]) == 3


@pytest.mark.slow
def test_hold_logits_learn_at_their_own_rate(cvae_checkpoint):
    model, _ = initial_model(cvae_checkpoint, "cvae-hold")
    groups = make_optimizer(model, replace(QUICK, hold_lr=0.05)).param_groups
    assert [g["lr"] for g in groups] == [1e-4, 1e-2, 0.05]
    assert {id(p) for p in groups[2]["params"]} == {id(model.hold.logits.weight), id(model.hold.logits.bias)}
    assert len(make_optimizer(model, QUICK).param_groups) == 2  # without hold_lr: the logits learn at the main rate


def test_nested_steps_come_from_the_inner_cross_validation():
    # outer curves would choose 100 steps for every fold; each fold's inner folds say otherwise
    curves = np.array([[0.0, -1.0, -2.0], [0.0, -1.0, -2.0], [0.0, -1.0, -2.0]])
    inner = np.full((3, 3, 3), np.nan)
    inner[0, 1], inner[0, 2] = [0.0, -3.0, -1.0], [0.0, -3.0, -1.0]  # fold 1's inner folds prefer 50 steps
    inner[1, 0], inner[1, 2] = [0.0, -1.0, -2.0], [0.0, -1.0, -2.0]
    inner[2, 0], inner[2, 1] = [-5.0, -1.0, -2.0], [-5.0, -1.0, -2.0]  # fold 3's prefer 0 steps
    result = CrossvalResult([np.arange(2)] * 3, np.array([0, 50, 100]), curves, np.array([10] * 3), inner=inner)
    summary = result.summary()
    assert summary["steps"] == 100 and summary["nested"]["method"] == "inner cross-validation"
    assert summary["nested"]["steps"] == [50, 100, 0] and summary["nested"]["folds"] == [-1.0, -2.0, 0.0]


@pytest.mark.slow
def test_nested_crossval_trains_without_each_pair_of_folds_saves_the_inner_models_and_workers_agree(trials, tmp_path):
    three = trials.subset(np.arange(3))  # three folds of one trial
    init = small_checkpoint(tmp_path / "init.pt", three)
    out = tmp_path / "folds"
    result = crossval(three, 3, QUICK, variant="cvae-hold", init=init, nested=True, out=out, **SILENT)
    assert result.inner.shape == (3, 3, 3) and np.isnan(np.diagonal(result.inner, axis1=0, axis2=1)).all()
    # step 0 is the initial model: the same on a fold whichever model holds it out
    np.testing.assert_allclose(result.inner[0, 1, 0], result.curves[1, 0], rtol=1e-6)
    np.testing.assert_allclose(result.inner[1, 0, 2], result.inner[1, 0, 2])  # finite
    assert np.isfinite(result.inner[~np.eye(3, dtype=bool)]).all() and result.directions.shape == (3, 3, 2)
    nested_steps, nested = result.nested()
    for k, (model, held) in enumerate(out_of_fold_models(out / "nested")):  # fold k's model at its inner-chosen steps
        fold = three.subset(np.flatnonzero(np.isin(three.trial_ids, held)))
        assert evaluate(model, build_exemplars(fold)).nll_exact.mean() == pytest.approx(nested[k], rel=1e-5)
        inner = out_of_fold_models(out / "nested" / f"fold_{k + 1}")
        assert len(inner) == 2 and not set(held) & {i for _, h in inner for i in h}  # the inner folds exclude fold k
        for inner_model, inner_held in inner:  # trained without folds k and j, it scores fold j as the inner curve says
            j = next(f for f, part in enumerate(result.fold_trials) if set(three.trial_ids[part]) == set(inner_held))
            fold_j = three.subset(np.flatnonzero(np.isin(three.trial_ids, inner_held)))
            pick = int(np.flatnonzero(result.steps == nested_steps[k])[0])
            assert evaluate(inner_model, build_exemplars(fold_j)).nll_exact.mean() == pytest.approx(result.inner[k, j, pick], rel=1e-5)
    # the fits in two worker processes (the same function as the inner fits) give the same curves as in one
    two = crossval(three, 3, QUICK, variant="cvae-hold", init=init, workers=2, **SILENT)
    np.testing.assert_allclose(two.curves, result.curves, rtol=1e-5)
