"""The CVAE: shapes of every variant, agreement with the authors' TensorFlow model, the mixture
density and its sampler, the sampling API, and exemplar construction."""

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from helpers_model import synthetic_trials
from trafficweaving.data.hitl import read_hitl
from trafficweaving.errors import InputError
from trafficweaving.model.cvae import CVAE, VARIANTS, CVAEConfig
from trafficweaving.model.evaluate import evaluate
from trafficweaving.model.exemplars import build_exemplars, split_by_trial, state_statistics
from trafficweaving.model.gmm import GMM, HoldMixture
from trafficweaving.model.predictor import HumanPredictor
from trafficweaving.scenario import HORIZON, MIN_HISTORY

DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])


@pytest.fixture(scope="module")
def small_trials():
    return synthetic_trials(24, seed=3)


def fitted_model(trials, config: CVAEConfig = CVAEConfig()) -> CVAE:
    """An untrained float64 model (seed 0) standardised for ``trials``."""
    torch.manual_seed(0)
    return CVAE(config).double().set_standardisation(*state_statistics(trials)).eval()


@pytest.fixture(scope="module")
def authors(authors_model_dir, hitl_trials):
    from trafficweaving.model.authors import load_authors_model

    model = load_authors_model(authors_model_dir / "weights.npz").double()
    exemplars = build_exemplars(hitl_trials)
    data = exemplars.standardised(model)
    reference = dict(np.load(authors_model_dir / "reference_outputs.npz"))
    return model, exemplars, data, reference


# ---------------------------------------------------------------- exemplars
def test_exemplars_cover_every_valid_time_of_every_human(small_trials):
    ex = build_exemplars(small_trials)
    assert len(ex.streams) == 2 * len(small_trials)  # both cars of a human–human trial are the human once
    expected = sum(2 * (n - HORIZON - (MIN_HISTORY - 1)) for n in small_trials.lengths)
    assert len(ex) == expected
    assert ex.t.min() == MIN_HISTORY - 1 and np.all(ex.t <= ex.lengths[ex.stream] - HORIZON - 1)
    # stream k of trial i, human agent a: the other car is stored first
    k = 1
    i, a = ex.stream_trial[k], ex.stream_agent[k]
    np.testing.assert_array_equal(ex.streams[k, : small_trials.lengths[i], 1], small_trials.trajectory(i, a))
    np.testing.assert_array_equal(ex.streams[k, : small_trials.lengths[i], 0], small_trials.trajectory(i, 1 - a))


def test_exemplars_refuse_data_at_another_time_step(small_trials):
    slow = replace(small_trials, dt=0.2, source_path=Path("slow.parquet"))
    with pytest.raises(InputError, match=r"slow.parquet: time step 0.2 s \(expected 0.1 s"):
        build_exemplars(slow)


def test_batches_slice_history_future_and_labels(small_trials):
    ex = build_exemplars(small_trials)
    model = fitted_model(small_trials)
    data = ex.standardised(model)
    e = 37
    batch = data.batch(torch.tensor([e]))
    s, t = ex.stream[e], ex.t[e]
    physical = lambda v: (v * model.feature_std + model.feature_mean).numpy()  # noqa: E731
    future = slice(t + 1, t + 1 + HORIZON)
    np.testing.assert_allclose(physical(batch.robot_future[0]), ex.streams[s, future, 0], atol=1e-9)
    np.testing.assert_allclose(physical(batch.human_present[0]), ex.streams[s, t, 1], atol=1e-9)
    np.testing.assert_allclose(model.actions_to_physical(batch.y[0]).numpy(), ex.streams[s, future, 1, 4:6], atol=1e-9)
    assert batch.history.shape == (1, t + 1, 12)


def test_split_is_by_trial_and_80_20():
    train, val = split_by_trial(100, 0.2, seed=1)
    assert len(val) == 20 and len(train) == 80 and not set(train) & set(val)


def test_standardisation_is_mean_and_std_of_all_states(small_trials):
    mean, std = state_statistics(small_trials)
    rows = np.concatenate([small_trials.states[i, :, : n].reshape(-1, 6) for i, n in enumerate(small_trials.lengths)])
    np.testing.assert_allclose(mean, rows.mean(0))
    np.testing.assert_allclose(std, rows.std(0))
    model = fitted_model(small_trials)
    np.testing.assert_array_equal(model.feature_mean.numpy(), mean)
    np.testing.assert_array_equal(model.label_std.numpy(), std[4:6])  # the human's actions are its accelerations
    states = torch.as_tensor(rows[:3])
    torch.testing.assert_close(model.states_to_standard(states), (states - torch.as_tensor(mean)) / torch.as_tensor(std))
    with pytest.raises(ValueError, match="positive finite std"):
        model.set_standardisation(mean, np.zeros(6))


# ---------------------------------------------------------------- model shapes
@pytest.mark.parametrize("variant", list(VARIANTS))
def test_every_variant_gives_normalised_latents_and_finite_likelihoods(variant, small_trials):
    torch.manual_seed(0)
    model = CVAE(CVAEConfig.variant(variant)).set_standardisation(*state_statistics(small_trials)).eval()
    batch = build_exemplars(small_trials).standardised(model).batch(torch.arange(8))
    log_p_z, log_p_y = model.log_likelihoods(batch)
    z = model.config.latent_values
    assert log_p_z.shape == (8, z) and log_p_y.shape == (8, z)
    torch.testing.assert_close(log_p_z.exp().sum(1), torch.ones(8))
    assert torch.isfinite(log_p_y).all()
    q = model.joint_log_prob(model.q_z_logits(model.encode(batch), batch))
    torch.testing.assert_close(q.exp().sum(1), torch.ones(8))


def test_variant_names_round_trip():
    for name, (n_z, k_z, m, hold) in VARIANTS.items():
        c = CVAEConfig.variant(name)
        assert (c.latent_vars, c.latent_classes, c.components, c.hold, c.name) == (n_z, k_z, m, hold, name)
    assert CVAEConfig().latent_values == 25 and CVAEConfig().x_size == 160
    with pytest.raises(ValueError, match="unknown variant"):
        CVAEConfig.variant("transformer")


def test_latent_enumeration_has_first_variable_slowest():
    model = CVAE()
    assert model.latent_classes[:6].tolist() == [[0, 0], [0, 1], [0, 2], [0, 3], [0, 4], [1, 0]]
    assert model.latent_onehots[7].tolist() == [0, 1, 0, 0, 0, 0, 0, 1, 0, 0]


# ---------------------------------------------------------------- mixture density
def _toy_gmm():
    return GMM(log_pi=torch.log(torch.tensor([[0.3, 0.7]], dtype=torch.float64)),
               mu=torch.tensor([[[1.0, -2.0], [-0.5, 0.5]]], dtype=torch.float64),
               log_sigma=torch.log(torch.tensor([[[0.5, 1.5], [1.0, 0.3]]], dtype=torch.float64)),
               corr=torch.tensor([[0.6, -0.4]], dtype=torch.float64))


def test_gmm_density_matches_scipy():
    from scipy.stats import multivariate_normal

    gmm = _toy_gmm()
    y = torch.tensor([[0.2, -1.0]], dtype=torch.float64)
    expected = 0.0
    for k in range(2):
        s, r = gmm.log_sigma[0, k].exp().numpy(), gmm.corr[0, k].item()
        cov = [[s[0] ** 2, r * s[0] * s[1]], [r * s[0] * s[1], s[1] ** 2]]
        expected += gmm.log_pi[0, k].exp().item() * multivariate_normal(gmm.mu[0, k].numpy(), cov).pdf(y[0].numpy())
    assert gmm.log_prob(y).item() == pytest.approx(math.log(expected), rel=1e-10)


def test_gmm_log_density_is_capped_at_50():
    sharp = GMM(torch.zeros(1, 1), torch.zeros(1, 1, 2), torch.full((1, 1, 2), -40.0), torch.zeros(1, 1))
    assert sharp.log_prob(torch.zeros(1, 2)).item() == 50.0  # uncapped: 80 - log 2π
    clipped = GMM(torch.zeros(1, 1), torch.zeros(1, 1, 2), torch.full((1, 1, 2), -10.0), torch.zeros(1, 1))
    assert clipped.log_prob(torch.zeros(1, 2)).item() == pytest.approx(20 - math.log(2 * math.pi))


def test_gmm_samples_have_the_mixture_mean_and_covariance():
    gmm = _toy_gmm()
    many = GMM(*(v.expand(200_000, *v.shape[1:]) for v in (gmm.log_pi, gmm.mu, gmm.log_sigma, gmm.corr)))
    draws = many.sample(torch.Generator().manual_seed(0)).numpy()
    pi, mu = gmm.log_pi[0].exp().numpy(), gmm.mu[0].numpy()
    s, r = gmm.log_sigma[0].exp().numpy(), gmm.corr[0].numpy()
    mean = (pi[:, None] * mu).sum(0)
    second = sum(pi[k] * (np.array([[s[k, 0] ** 2, r[k] * s[k, 0] * s[k, 1]], [r[k] * s[k, 0] * s[k, 1], s[k, 1] ** 2]])
                          + np.outer(mu[k], mu[k])) for k in range(2))
    np.testing.assert_allclose(draws.mean(0), mean, atol=0.01)
    np.testing.assert_allclose(np.cov(draws.T), second - np.outer(mean, mean), atol=0.02)


def _toy_hold(batch: int = 1, previous=(0.4, -0.3)):
    gmm = _toy_gmm()
    return HoldMixture(log_w=torch.log(torch.tensor([[0.4, 0.25, 0.15, 0.2]], dtype=torch.float64)).expand(batch, 4),
                       log_s=torch.log(torch.tensor([0.05, 0.08], dtype=torch.float64)),
                       previous=torch.tensor([previous], dtype=torch.float64).expand(batch, 2),
                       gmm=GMM(*(v.expand(batch, *v.shape[1:]) for v in (gmm.log_pi, gmm.mu, gmm.log_sigma, gmm.corr))))


@pytest.mark.slow
def test_hold_mixture_marginals_integrate_to_one_and_agree_with_the_joint():
    hold = _toy_hold()
    grid = torch.linspace(-12, 12, 240_001, dtype=torch.float64)
    for dim in (0, 1):
        y = torch.zeros(len(grid), 2, dtype=torch.float64)
        y[:, dim] = grid
        density = hold.marginal_log_prob(y, dim).exp()
        assert torch.trapezoid(density, grid).item() == pytest.approx(1.0, abs=1e-6)
    for x in (-1.0, 0.4, 0.43, 2.0):  # ∫ p(x, y) dy is the longitudinal marginal at x
        y = torch.stack([torch.full_like(grid, x), grid], dim=-1)
        joint = torch.trapezoid(hold.log_prob(y).exp(), grid).item()
        assert joint == pytest.approx(hold.marginal_log_prob(y[:1], 0).exp().item(), rel=1e-6)


def test_hold_mixture_samples_hold_with_the_mode_weights():
    from scipy.stats import norm

    n, previous, window = 200_000, np.array([0.4, -0.3]), np.array([0.2, 0.32])  # ±4 hold widths
    draws = _toy_hold(n).sample(torch.Generator().manual_seed(0)).numpy()
    near = np.abs(draws - previous) < window
    gmm = _toy_gmm()
    pi, mu, s = gmm.log_pi[0].exp().numpy(), gmm.mu[0].numpy(), gmm.log_sigma[0].exp().numpy()
    gmm_near = (pi[:, None] * (norm.cdf((previous + window - mu) / s) - norm.cdf((previous - window - mu) / s))).sum(0)
    inside = norm.cdf(4.0) - norm.cdf(-4.0)
    # P(near in x) = P(mode holds x)·inside + P(mode draws x from the GMM)·P_GMM(near in x)
    expected = np.array([0.45 * inside + 0.55 * gmm_near[0], 0.35 * inside + 0.65 * gmm_near[1]])
    np.testing.assert_allclose(near.mean(0), expected, atol=0.004)
    # the mode that holds only x draws the lateral action from the GMM's marginal, independently
    only_x = _toy_hold(n)
    only_x.log_w = torch.log(torch.tensor([0.0, 1.0, 0.0, 0.0], dtype=torch.float64)).expand(n, 4)
    draws = only_x.sample(torch.Generator().manual_seed(1)).numpy()
    assert abs(np.corrcoef(draws[:, 0], draws[:, 1])[0, 1]) < 0.01
    assert draws[:, 0].std() == pytest.approx(0.05, rel=0.01)
    np.testing.assert_allclose(draws[:, 1].mean(), (pi * mu[:, 1]).sum(), atol=0.01)


# ---------------------------------------------------------------- the authors' model
def test_reference_instances_are_ours(authors):
    _, exemplars, _, reference = authors
    assert len(exemplars) == 963
    names = np.array([Path(s).stem for s in exemplars.sources])[exemplars.stream]
    np.testing.assert_array_equal(names, reference["trial"])
    np.testing.assert_array_equal(exemplars.t, reference["t"])


@pytest.mark.slow
@pytest.mark.parametrize("device", DEVICES)
def test_authors_latent_prior_and_likelihoods_match_tensorflow(authors, device):
    """Every 4th instance (from every trial): test_authors_exact_nll_is_the_papers checks all of them
    against TensorFlow's NLL, which these two likelihoods make up."""
    model, exemplars, _, reference = authors
    model = model.to(device)
    data = exemplars.standardised(model)
    with torch.no_grad():
        log_p_z, log_p_y = model.log_likelihoods(data.batch(torch.arange(0, len(data), 4, device=device)))
    model.cpu()
    np.testing.assert_allclose(log_p_z.cpu().numpy(), reference["log_p_z"][::4], atol=1e-4, rtol=0)
    np.testing.assert_allclose(log_p_y.cpu().numpy(), reference["log_p_y_given_z_std"][::4], atol=1e-4, rtol=0)


def test_authors_gmm_parameters_match_tensorflow(authors):
    model, _, data, reference = authors
    batch = data.batch(torch.arange(8))
    with torch.no_grad():
        x = model.encode(batch)
        _, gmm = model.decode(model.zx(model.latent_onehots.unsqueeze(1), x), batch)  # dims [25, 8, 15]
    ours = {"gmm_log_pis": gmm.log_pi, "gmm_mus": gmm.mu, "gmm_log_sigmas": gmm.log_sigma, "gmm_corrs": gmm.corr}
    for name, value in ours.items():
        np.testing.assert_allclose(value.transpose(0, 1).numpy(), reference[name], atol=1e-4, rtol=0, err_msg=name)


@pytest.mark.slow
def test_authors_exact_nll_is_the_papers(authors):
    model, exemplars, _, reference = authors
    result = evaluate(model, exemplars)
    np.testing.assert_allclose(result.nll_exact, reference["nll"], atol=1e-4)
    assert result.summary()["nll_exact"] == pytest.approx(-12.717, abs=0.01)
    assert result.nll_is is None  # the published weights have no recognition network
    # the naive estimator with 50 prior samples is a noisy, upward-biased estimate of the exact NLL
    assert result.summary()["nll_naive"] >= result.summary()["nll_exact"] - 0.05


@pytest.mark.slow
def test_authors_model_in_float32_agrees_too(authors_model_dir, authors_evaluation):
    reference = np.load(authors_model_dir / "reference_outputs.npz")
    np.testing.assert_allclose(authors_evaluation.nll_exact, reference["nll"], atol=2e-3)


def test_authors_import_rejects_bad_files(tmp_path):
    from trafficweaving.errors import InputError
    from trafficweaving.model.authors import load_authors_model

    with pytest.raises(InputError, match="no such file"):
        load_authors_model(tmp_path / "missing.npz")
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(InputError, match="junk.npz: not a readable .npz"):
        load_authors_model(tmp_path / "junk.npz")


def test_authors_import_rejects_edited_weights(tmp_path, authors_model_dir):
    from trafficweaving.errors import InputError
    from trafficweaving.model.authors import load_authors_model

    weights = dict(np.load(authors_model_dir / "weights.npz"))
    missing = {k: v for k, v in weights.items() if "corr_projection/bias" not in k}
    np.savez(tmp_path / "missing_tensor.npz", **missing)
    with pytest.raises(InputError, match="missing tensor decoder/p_y_xz/rnn/corr_projection/bias"):
        load_authors_model(tmp_path / "missing_tensor.npz")
    wrong = dict(weights, **{"encoder/p_z_x/dense0/kernel": np.zeros((150, 16), np.float32)})
    np.savez(tmp_path / "wrong_shape.npz", **wrong)
    with pytest.raises(InputError, match=r"dense0/kernel has shape \[150, 16\] \(expected \[160, 16\]\)"):
        load_authors_model(tmp_path / "wrong_shape.npz")
    lstm = dict(weights, **{"car_history_rnn/rnn/multi_rnn_cell/cell_0/layer_norm_basic_lstm_cell/kernel": np.zeros((40, 128), np.float32)})
    np.savez(tmp_path / "wrong_lstm.npz", **lstm)
    with pytest.raises(InputError, match=r"has shape \[40, 128\] \(expected \[44, 128\]\)"):
        load_authors_model(tmp_path / "wrong_lstm.npz")


# ---------------------------------------------------------------- sampling API
def _situation(trials, t=12, candidates=5):
    s = trials.states[0]
    history = s[:, : t + 1].transpose(1, 0, 2)
    futures = np.repeat(s[0, t + 1:t + 16][None], candidates, 0)
    futures[:, :, 0] += np.linspace(-3, 3, candidates)[:, None]
    return history, futures


@pytest.mark.parametrize("device", DEVICES)
def test_sampling_shapes_and_determinism(small_trials, device):
    torch.manual_seed(0)
    predictor = HumanPredictor(CVAE().to(device))
    history, futures = _situation(small_trials)
    a = predictor.predict(history, futures, n=7, seed=11)
    b = predictor.predict(history, futures, n=7, seed=11)
    c = predictor.predict(history, futures, n=7, seed=12)
    assert a.actions.shape == (7, 5, 15, 2) and a.latents.shape == (7, 5) and a.log_p_z.shape == (5, 25)
    assert torch.equal(a.actions, b.actions) and torch.equal(a.latents, b.latents)
    assert not torch.equal(a.actions, c.actions)
    assert a.latents.min() >= 0 and a.latents.max() < 25 and torch.isfinite(a.actions).all()


@pytest.mark.slow
def test_sampled_latents_follow_the_prior(authors_model_dir, hitl_files):
    from trafficweaving.model.authors import load_authors_model

    trials = read_hitl(hitl_files[:1])
    predictor = HumanPredictor(load_authors_model(authors_model_dir / "weights.npz"))
    history, futures = _situation(trials, t=10, candidates=2)
    draw = predictor.predict(history, futures, n=20_000, seed=0)
    frequencies = torch.stack([torch.bincount(draw.latents[:, j], minlength=25) for j in range(2)]).double() / 20_000
    torch.testing.assert_close(frequencies, draw.log_p_z.exp().double(), atol=0.012, rtol=0)


def test_sampling_rejects_bad_inputs(small_trials):
    predictor = HumanPredictor(CVAE())
    history, futures = _situation(small_trials)
    with pytest.raises(ValueError, match=r"history has 3 steps \(expected at least 5\)"):
        predictor.predict(history[:3], futures, 2)
    with pytest.raises(ValueError, match=r"robot_futures has shape \[5, 14, 6\]"):
        predictor.predict(history, futures[:, :14], 2)
    bad = futures.copy()
    bad[0, 0, 0] = np.nan
    with pytest.raises(ValueError, match="robot_futures has NaN"):
        predictor.predict(history, bad, 2)
    with pytest.raises(ValueError, match="n must be a positive integer"):
        predictor.predict(history, futures, 0)


# ---------------------------------------------------------------- calibration
def test_calibration_scales_the_gmm_widths_and_tempers_the_latent_prior(small_trials):
    model = fitted_model(small_trials, CVAEConfig.variant("cvae-hold"))
    batch = build_exemplars(small_trials).standardised(model).batch(torch.arange(6))
    x = model.encode(batch)
    zx = model.zx(model.latent_onehots.unsqueeze(1), x)
    _, plain = model.decode(zx, batch)
    logits = model.p_z_logits(x)
    model.set_calibration(2.0, 1.5)
    _, wide = model.decode(zx, batch)
    torch.testing.assert_close(wide.gmm.log_sigma, plain.gmm.log_sigma + math.log(1.5))
    torch.testing.assert_close(wide.log_s, plain.log_s)  # a held control's width is not widened
    torch.testing.assert_close(model.p_z_logits(x), logits / 2.0)
    with pytest.raises(ValueError, match="calibration must be positive"):
        model.set_calibration(0.0, 1.0)


def test_calibration_choice_is_the_best_nll_within_the_coverage_band():
    from trafficweaving.model.calibrate import _choose

    row = lambda nll, x, y: {"nll_exact": nll, "coverage_90": {"x": x, "y": y}}  # noqa: E731
    assert _choose([row(-21, 0.78, 0.74), row(-20, 0.86, 0.85), row(-19, 0.9, 0.9), row(-25, 0.97, 0.96)]) == 1
    # none inside: the one whose worse direction is closest to 90 % (|0.99 - 0.9| < |0.78 - 0.9|)
    assert _choose([row(-21, 0.70, 0.74), row(-20, 0.80, 0.78), row(-22, 0.99, 0.98)]) == 2


# ---------------------------------------------------------------- conditioning on a guess (driver models)
def test_a_guess_model_sees_the_other_car_holding_its_acceleration_not_its_recorded_future(small_trials):
    from trafficweaving.dynamics import constant_acceleration_future

    exemplars = build_exemplars(small_trials)
    model = fitted_model(small_trials, CVAEConfig.variant("cvae-hold", robot_future="guess"))
    batch = exemplars.standardised(model).batch(torch.arange(40))
    s, t = exemplars.stream[:40], exemplars.t[:40]
    present = torch.as_tensor(exemplars.streams[s, t, 0])
    expected = model.states_to_standard(constant_acceleration_future(present))
    torch.testing.assert_close(batch.robot_future, expected)
    recorded = exemplars.standardised(fitted_model(small_trials)).batch(torch.arange(40))
    assert not torch.allclose(batch.robot_future, recorded.robot_future)  # the trials' cars do not hold
    torch.testing.assert_close(batch.history, recorded.history)
    with pytest.raises(InputError, match="cannot tell candidate robot futures apart"):
        HumanPredictor(model)
    with pytest.raises(ValueError, match="robot_future must be one of recorded, guess"):
        CVAEConfig(robot_future="oracle")
