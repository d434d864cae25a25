"""The human predictor (model/predictor.py): the int8 and float32-compiled precisions, its planning protocol,
common random numbers."""

import numpy as np
import pytest
import torch

from helpers_model import SMALL_UNITS
from trafficweaving.errors import InputError
from trafficweaving.model.cvae import CVAE, CVAEConfig
from trafficweaving.model.fused_decoder import decode_step
from trafficweaving.model.predictor import HumanPredictor, resolve_precision
from trafficweaving.model.registry import load_model
from trafficweaving.planning.candidates import robot_candidates
from trafficweaving.planning.planner import example_history


@pytest.mark.slow
def test_int8_precision_compiles_and_samples_what_float32_samples_to_quantisation_error():
    """precision int8 (compiled) against the same steps run eagerly (the same numbers to float
    rounding, but for rare draws on a component boundary) and against float32 with the same random
    numbers, on a trained model: the first step's draws agree to within the quantisation, and over
    the 15 steps (where a draw that picks another mixture component makes the rest of its future
    differ) about as closely as bfloat16's."""
    model = load_model("default")
    history = example_history()
    futures = robot_candidates(history[-1, 0], 0).states[:64]
    coarse = HumanPredictor(model, precision="int8")
    assert coarse.precision == "int8"
    a, b = HumanPredictor(model, precision="float32").predict(history, futures, n=8, seed=3), coarse.predict(history, futures, n=8, seed=3)
    bf16 = HumanPredictor(model, precision="bfloat16").predict(history, futures, n=8, seed=3)
    assert torch.equal(a.latents, b.latents)
    difference = (a.actions - b.actions).abs()  # m/s²
    assert difference[:, :, 0].median() < 0.01
    assert difference.mean() < 2 * (a.actions - bf16.actions).abs().mean()
    coarse.rollout.fused.step = decode_step  # eagerly
    eager = coarse.predict(history, futures, n=8, seed=3)
    torch.testing.assert_close(eager.actions[:, :, 0], b.actions[:, :, 0], rtol=0, atol=1e-4)
    # compiled multiply-adds round differently, so a draw on the boundary of two mixture components
    # (or hold modes) may take the other one at a later step, and the rest of its future differs
    agree = ((eager.actions - b.actions).abs() <= 1e-3).all(-1).float()  # [n, B, 15]
    assert agree.mean() > 0.99 and agree[:, :, :5].mean() > 0.998
    with pytest.raises(InputError, match="CPU only"):
        resolve_precision("int8", "cuda")


@pytest.mark.slow
def test_float32_compiled_precision_samples_what_float32_samples_to_rounding():
    """precision float32-compiled (the fused, compiled steps with float32 weights and the rational
    sigmoid) draws the futures float32 draws from the same random numbers: the same latent values,
    the first step's actions to rounding, and, but for rare draws on a mixture component's boundary,
    every step."""
    model = load_model("fast")
    history = example_history()
    futures = robot_candidates(history[-1, 0], 0).states[:64]
    compiled = HumanPredictor(model, precision="float32-compiled")
    assert compiled.precision == "float32-compiled" and compiled.rollout.fused is not None
    a, b = HumanPredictor(model, precision="float32").predict(history, futures, n=8, seed=3), compiled.predict(history, futures, n=8, seed=3)
    assert torch.equal(a.latents, b.latents)
    torch.testing.assert_close(b.actions[:, :, 0], a.actions[:, :, 0], rtol=0, atol=1e-4)  # m/s²
    agree = ((a.actions - b.actions).abs() <= 1e-3).all(-1).float()  # [n, B, 15]
    assert agree.mean() > 0.99
    with pytest.raises(InputError, match="CPU only"):
        resolve_precision("float32-compiled", "cuda")


def test_the_predictors_one_shot_prediction_is_its_planning_protocol():
    torch.manual_seed(0)
    predictor = HumanPredictor(CVAE(CVAEConfig.variant("cvae-hold")))
    history = example_history()
    futures = robot_candidates(history[-1, 0], 0).states[:6]
    prediction = predictor.predict(history, futures, n=3, seed=5)
    predictor.prepare(history, futures)
    actions = predictor.sample(torch.arange(6), 3, torch.Generator().manual_seed(5))
    assert prediction.actions.shape == (3, 6, 15, 2) and prediction.log_p_z.shape == (6, 25)
    torch.testing.assert_close(actions, prediction.actions, rtol=0, atol=0)
    subset = predictor.sample(torch.tensor([4, 1]), 2, torch.Generator().manual_seed(1))
    assert subset.shape == (2, 2, 15, 2) and torch.isfinite(subset).all()
    assert predictor.precision == "float32"


@pytest.mark.slow
@pytest.mark.parametrize("variant", ["cvae", "cvae-hold"])
def test_common_random_numbers_give_every_candidate_each_samples_draws(variant):
    """Sample i of every candidate is drawn with the same random numbers: identical robot futures get
    identical futures, a candidate's futures do not depend on which others are sampled with it, and
    they have the distribution of independent draws (mean and spread of 4000 samples)."""
    torch.manual_seed(0)
    model = CVAE(CVAEConfig.variant(variant, **SMALL_UNITS))
    history = example_history()
    candidates = robot_candidates(history[-1, 0], 0).states
    futures = np.concatenate([candidates[:1], candidates[:1], candidates[-1:]])  # 0 and 1 the same
    common, independent = HumanPredictor(model), HumanPredictor(model, common_random_numbers=False)
    for predictor in (common, independent):
        predictor.prepare(history, futures)
    shared = common.sample(torch.arange(3), 4000, torch.Generator().manual_seed(3))
    torch.testing.assert_close(shared[:, 0], shared[:, 1], rtol=0, atol=0)
    alone = common.sample(torch.tensor([2]), 4000, torch.Generator().manual_seed(3))
    torch.testing.assert_close(alone[:, 0], shared[:, 2], rtol=0, atol=0)
    apart = independent.sample(torch.arange(3), 4000, torch.Generator().manual_seed(3))
    assert not torch.equal(apart[:, 0], apart[:, 1])
    torch.testing.assert_close(shared.mean(0), apart.mean(0), rtol=0, atol=0.15)
    torch.testing.assert_close(shared.std(0), apart.std(0), rtol=0.1, atol=0.05)


@pytest.mark.parametrize("compiler, int8_dot_products, bfloat16, expected", [
    (True, True, True, "int8"), (True, False, True, "float32-compiled"), (True, False, False, "float32-compiled"),
    (False, True, True, "bfloat16"), (False, True, False, "float32")])
def test_auto_precision_is_the_compiled_one_the_cpu_runs_fastest_where_a_compiler_is_found(
        monkeypatch, compiler, int8_dot_products, bfloat16, expected):
    import trafficweaving.model.predictor as predictor

    monkeypatch.setattr(predictor, "compiler_available", lambda: compiler)
    monkeypatch.setattr(predictor, "cpu_matrix_features", lambda: {"int8_dot_products": int8_dot_products})
    monkeypatch.setattr(predictor, "native_bfloat16", lambda device="cpu": bfloat16 and torch.device(device).type == "cpu")
    assert resolve_precision("auto") == expected
    assert resolve_precision("auto", "cuda") == "float32"
    assert resolve_precision("float32") == "float32"
