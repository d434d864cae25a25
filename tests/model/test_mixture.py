"""Mixtures of human models (model/mixture.py): the density, the sampled component frequencies, the
fast planning rollout row by row, checkpoints, and fine-tuning's start from a mixture."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch

from trafficweaving.errors import InputError
from trafficweaving.model.checkpoint import load_checkpoint, read_checkpoint, save_checkpoint, write_payload
from trafficweaving.model.cvae import CVAE, CVAEConfig
from trafficweaving.model.evaluate import evaluate
from trafficweaving.model.exemplars import build_exemplars
from trafficweaving.model.mixture import Mixture, facing
from trafficweaving.model.predictor import HumanPredictor
from trafficweaving.model.sampler import BatchedRollout, MixtureRollout
from trafficweaving.model.train import initial_model

from helpers_model import SMALL_UNITS, synthetic_trials


@pytest.fixture(scope="module")
def components() -> tuple[CVAE, CVAE]:
    """Two different untrained small models, a hold-aware one and a paper one, in float64."""
    torch.manual_seed(0)
    return (CVAE(CVAEConfig.variant("cvae-hold", **SMALL_UNITS)).double().eval(),
            CVAE(CVAEConfig.variant("cvae", **SMALL_UNITS)).double().eval())


@pytest.fixture(scope="module")
def exemplars():
    return build_exemplars(synthetic_trials(2, seed=4))


@pytest.mark.slow
def test_mixture_density_is_the_weighted_sum_of_the_components(components, exemplars):
    a, b = components
    ea, eb = evaluate(a, exemplars), evaluate(b, exemplars)
    em = evaluate(Mixture([a, b], [0.7, 0.3]), exemplars)
    expected = -np.log(0.7 * np.exp(-ea.nll_exact) + 0.3 * np.exp(-eb.nll_exact))
    np.testing.assert_allclose(em.nll_exact, expected, rtol=1e-9)
    np.testing.assert_allclose(em.nll_direction, -np.log(0.7 * np.exp(-ea.nll_direction) + 0.3 * np.exp(-eb.nll_direction)),
                               rtol=1e-9)
    # between the components and no worse than their weighted mean (log is concave)
    assert np.all(em.nll_exact >= np.minimum(ea.nll_exact, eb.nll_exact) - 1e-9)
    assert np.all(em.nll_exact <= 0.7 * ea.nll_exact + 0.3 * eb.nll_exact + 1e-9)
    # a mixture of a model with itself is that model
    same = evaluate(Mixture([a, copy.deepcopy(a)], [0.4, 0.6]), exemplars)
    np.testing.assert_allclose(same.nll_exact, ea.nll_exact, rtol=1e-9)


@pytest.mark.slow
def test_samples_come_from_the_components_at_their_weights(components):
    a, b = components
    marked = copy.deepcopy(b)
    with torch.no_grad():  # every sample of this component has a huge longitudinal acceleration
        marked.gmm.mu.bias[0::2] += 100.0
    mixture = Mixture([a, marked], [0.75, 0.25])
    trials = synthetic_trials(1, seed=4)
    exemplars = build_exemplars(trials)
    batch = exemplars.standardised(mixture).batch(torch.arange(3))
    samples = mixture.sample_futures(batch, 4000, torch.Generator().manual_seed(0))
    assert samples.shape == (4000, 3, 15, 2)
    share = (samples[:, 0, 0, 0] > 50).double().mean().item()
    assert abs(share - 0.25) < 4 * np.sqrt(0.25 * 0.75 / 4000)
    history = exemplars.streams[0, :10]
    futures = np.repeat(exemplars.streams[0, 10:25, 0][None], 3, 0)
    prediction = HumanPredictor(mixture).predict(history, futures, 4000, seed=1)
    assert prediction.log_p_z.shape == (3, 50)
    torch.testing.assert_close(prediction.log_p_z.exp().sum(-1), torch.ones(3, dtype=torch.float64))
    from_marked = prediction.latents >= 25
    assert abs(from_marked.double().mean().item() - 0.25) < 4 * np.sqrt(0.25 * 0.75 / 12000)
    assert torch.equal(prediction.actions[..., 0, 0] > 50, from_marked)  # each sample decoded by its own component


def test_the_mixture_rollout_decodes_each_row_as_its_component_does(components):
    a, b = components
    fast = MixtureRollout(Mixture([a, b], [0.5, 0.5]), chunk_rows=7)
    torch.manual_seed(2)
    history, futures = torch.randn(9, 12, dtype=torch.float64), torch.randn(5, 15, 6, dtype=torch.float64)
    present = torch.randn(2, dtype=torch.float64)
    context = fast.encode(history, futures, present)
    g = torch.Generator().manual_seed(3)
    latents = fast.sample_latents(context, 6, g)
    assert latents.shape == (6, 5) and {0, 1} == set((latents // 25).unique().tolist())
    noise = (torch.rand(6, 5, 15, generator=g, dtype=torch.float64), torch.randn(6, 5, 15, 2, generator=g, dtype=torch.float64))
    ours = fast.sample(context, latents, noise=noise)
    for k, model in enumerate((a, b)):
        alone = BatchedRollout(model)
        reference = alone.sample(alone.encode(history, futures, present), (latents - 25 * k).clamp(0, 24), noise=noise)
        rows = latents // 25 == k
        torch.testing.assert_close(ours[rows], reference[rows], rtol=0, atol=1e-12)


@pytest.mark.slow
def test_a_mixture_checkpoint_round_trips_and_a_malformed_one_is_refused(components, exemplars, tmp_path):
    a, b = components
    mixture = Mixture([copy.deepcopy(a).float(), copy.deepcopy(b).float()], [0.9, 0.1])
    path = tmp_path / "mix.pt"
    save_checkpoint(path, mixture, summary="a test mixture")
    loaded, payload = load_checkpoint(path)
    assert isinstance(loaded, Mixture) and loaded.weights == pytest.approx([0.9, 0.1])
    assert [c.config for c in loaded.components] == [a.config, b.config] and payload["summary"] == "a test mixture"
    np.testing.assert_array_equal(evaluate(loaded, exemplars).nll_exact, evaluate(mixture, exemplars).nll_exact)
    f64 = lambda *w: torch.tensor(w, dtype=torch.float64)  # noqa: E731
    for change, pattern in ((lambda m: m | {"weights": f64(0.9)}, r"mixture\.weights is \[0\.9\] \(expected a float64 tensor of 2"),
                            (lambda m: m | {"weights": f64(0.9, -0.1)}, r"mixture\.weights is \[0\.9, -0\.1\]"),
                            (lambda m: m | {"weights": [0.9, 0.1]}, r"mixture\.weights is \[0\.9, 0\.1\] \(expected a float64 tensor"),
                            (lambda m: m | {"weights": f64(0.9, 0.1).float()}, r"mixture\.weights is"),
                            (lambda m: m | {"person_weights": f64(0.0, 0.0)}, r"mixture\.person_weights is \[0\.0, 0\.0\]"),
                            (lambda m: m | {"person_weights": f64(1.0)}, r"mixture\.person_weights is \[1\.0\]"),
                            (lambda m: {k: v for k, v in m.items() if k != "weights"}, r"mixture\.weights is None"),
                            (lambda m: m | {"components": []}, "checkpoint field mixture is not a mixture"),
                            (lambda m: m | {"components": [{**m["components"][0], "state_dict": {}}]},
                             r"mixture component 2\): checkpoint lacks tensor")):
        edited = read_checkpoint(path)
        edited["mixture"] = change(edited["mixture"])
        write_payload(tmp_path / "bad.pt", edited)
        with pytest.raises(InputError, match=pattern) as info:
            load_checkpoint(tmp_path / "bad.pt")
        assert "bad.pt" in str(info.value) and "\n" not in str(info.value)


def test_fine_tuning_a_mixture_starts_from_its_first_component(components, tmp_path):
    a, b = components
    first = copy.deepcopy(a).float().set_calibration(3.0, (2.0, 1.5))
    save_checkpoint(tmp_path / "mix.pt", Mixture([first, copy.deepcopy(b).float()], [0.8, 0.2]))
    model, provenance = initial_model(tmp_path / "mix.pt", "cvae-hold")
    assert isinstance(model, CVAE) and provenance["mixture_component"] == 1
    assert model.latent_temperature.item() == 1.0 and model.output_scale.tolist() == [1.0, 1.0]  # calibration reset
    assert all(torch.equal(v, first.state_dict()[k]) for k, v in model.state_dict().items()
               if k not in ("latent_temperature", "output_scale"))


def test_a_driver_facing_a_person_uses_the_person_weights(components, tmp_path):
    a, b = components
    driver = Mixture([a, b], [0.5, 0.5], person_weights=[1.0, 3.0])
    assert facing(driver, "robot") is driver
    person = facing(driver, "person")
    assert isinstance(person, Mixture) and person.weights == pytest.approx([0.25, 0.75]) and person.person_weights is None
    assert facing(Mixture([a, b], [0.5, 0.5], person_weights=[0.0, 2.0]), "person") is b  # one component alone
    assert facing(a, "person") is a and facing(Mixture([a, b], [0.5, 0.5]), "person").weights == pytest.approx([0.5, 0.5])
    with pytest.raises(ValueError, match="other car 'cyclist' is unknown"):
        facing(driver, "cyclist")
    with pytest.raises(ValueError, match="facing a person must be one per component"):
        Mixture([a, b], [0.5, 0.5], person_weights=[0.0, 0.0])
    path = tmp_path / "driver.pt"
    save_checkpoint(path, Mixture([copy.deepcopy(a).float(), copy.deepcopy(b).float()], [0.5, 0.5], [1.0, 3.0]))
    loaded, _ = load_checkpoint(path)
    assert loaded.person_weights == pytest.approx([0.25, 0.75])


def test_a_model_driver_drives_with_the_model_facing_its_other_car(components):
    from trafficweaving.sim.humans import ModelDriver

    a, b = components
    driver = Mixture([a, b], [0.5, 0.5], person_weights=[0.0, 1.0])
    assert ModelDriver(driver).model is driver and ModelDriver(driver, other="person").model is b
    with pytest.raises(InputError, match="other car 'nobody' is unknown"):
        ModelDriver(driver, other="nobody")
