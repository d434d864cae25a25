"""Hostile input to the model commands and files: mixture checkpoints whose weights were edited
(with and without a new digest), companions that cannot be mixed, unbounded counts, and messages
that must name the real culprit. Every refusal is exit status 2 and one line, before any work."""

from __future__ import annotations

import copy
import warnings
from pathlib import Path

import pytest
import torch

from trafficweaving.cli import build_parser, main
from trafficweaving.errors import InputError
from trafficweaving.model.checkpoint import (HASH_FIELD, MIXTURE_VERSION, load_checkpoint, save_checkpoint, tensor_digest,
                                             write_payload)
from trafficweaving.model.registry import load_model, shipped_model_path
from trafficweaving.model.cvae import CVAE, CVAEConfig
from trafficweaving.model.mixture import Mixture


def run(capsys, *argv) -> tuple[int, str, str]:
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def refused(capsys, *argv, expected: tuple[str, ...] = (), absent: tuple[str, ...] = ()) -> str:
    """The command exits 2 with one line on stderr holding every ``expected`` and no ``absent``
    text, and prints nothing on stdout (no work started)."""
    code, out, err = run(capsys, *argv)
    assert code == 2 and out == "" and err.count("\n") == 1 and "Traceback" not in err, (out, err)
    assert all(text in err for text in expected) and not any(text in err for text in absent), err
    return err


def loading_fails(path: Path, pattern: str) -> str:
    with pytest.raises(InputError, match=pattern) as info:
        load_checkpoint(path)
    message = str(info.value)
    assert "\n" not in message and path.name in message, message
    return message


@pytest.fixture(scope="module")
def mixture_file(tmp_path_factory) -> Path:
    """A valid mixture checkpoint of two small untrained models, facing a person weighted apart."""
    torch.manual_seed(0)
    a = CVAE(CVAEConfig.variant("cvae-hold")).eval()
    b = copy.deepcopy(a)
    path = tmp_path_factory.mktemp("mix") / "mix.pt"
    save_checkpoint(path, Mixture([a, b], [0.7, 0.3], person_weights=[0.0, 1.0]))
    return path


def crafted(source: Path, name: str, change, rehash: bool = True) -> Path:
    """A copy of ``source`` with ``change(payload)`` applied, its digest recomputed (``rehash``: as a
    crafted file can) or left as it was (an edit that the digest must catch)."""
    payload = torch.load(source, weights_only=True)
    change(payload)
    path = source.with_name(name)
    if rehash:
        write_payload(path, payload)
    else:
        torch.save(payload, path)
    return path


def set_weights(key: str, value):
    def change(payload):
        payload["mixture"][key] = value
    return change


# ---------------------------------------------------------------- mixture weights in the checkpoint
def test_mixture_weights_are_tensors_inside_the_digest(mixture_file):
    model, payload = load_checkpoint(mixture_file)
    weights = payload["mixture"]["weights"]
    assert isinstance(weights, torch.Tensor) and weights.dtype == torch.float64 and model.weights == pytest.approx([0.7, 0.3])
    assert model.person_weights == [0.0, 1.0] and isinstance(payload["mixture"]["person_weights"], torch.Tensor)
    for key in ("weights", "person_weights"):
        edited = copy.deepcopy(payload)
        edited["mixture"][key] = edited["mixture"][key].flip(0)
        assert tensor_digest(edited) != payload[HASH_FIELD], key


@pytest.mark.parametrize("key", ["weights", "person_weights"])
def test_edited_mixture_weights_without_a_new_digest_are_refused(mixture_file, key):
    path = crafted(mixture_file, "edited.pt", set_weights(key, torch.tensor([1e308, 1e308], dtype=torch.float64)),
                   rehash=False)
    loading_fails(path, r"edited\.pt: tensor data does not match the checkpoint's SHA-256")


@pytest.mark.parametrize("key, value, pattern", [
    ("weights", [1e308, 1e308], r"mixture\.weights is \[1e\+308, 1e\+308\] \(expected a float64 tensor of 2 finite "
                                r"positive weights, with a finite sum"),
    ("weights", [float("nan"), 1.0], r"mixture\.weights is \[nan, 1\.0\]"),
    ("weights", [float("inf"), 1.0], r"mixture\.weights is \[inf, 1\.0\]"),
    ("weights", [0.0, 1.0], r"mixture\.weights is \[0\.0, 1\.0\]"),
    ("weights", [-1.0, 2.0], r"mixture\.weights is \[-1\.0, 2\.0\]"),
    ("weights", [0.2, 0.3, 0.5], r"mixture\.weights is \[0\.2, 0\.3, 0\.5\] \(expected a float64 tensor of 2"),
    ("weights", [[0.5, 0.5]], r"mixture\.weights is \[\[0\.5, 0\.5\]\]"),
    ("person_weights", [1e308, 1e308], r"mixture\.person_weights is \[1e\+308, 1e\+308\] \(expected a float64 tensor of "
                                       r"2 finite non-negative weights, not all zero, with a finite sum"),
    ("person_weights", [0.0, 0.0], r"mixture\.person_weights is \[0\.0, 0\.0\]"),
    ("person_weights", [1.0], r"mixture\.person_weights is \[1\.0\]"),
])
def test_self_consistent_mixture_weights_with_bad_values_are_refused(mixture_file, key, value, pattern):
    path = crafted(mixture_file, "bad.pt", set_weights(key, torch.tensor(value, dtype=torch.float64)))
    loading_fails(path, r"bad\.pt: checkpoint field " + pattern)


def test_mixture_weights_of_another_type_or_an_older_layout_are_refused(mixture_file):
    loading_fails(crafted(mixture_file, "f32.pt", set_weights("weights", torch.tensor([0.7, 0.3]))),
                  r"mixture\.weights is \[0\.699.*\(expected a float64 tensor")
    loading_fails(crafted(mixture_file, "list.pt", set_weights("weights", [0.7, 0.3])),
                  r"mixture\.weights is \[0\.7, 0\.3\] \(expected a float64 tensor")

    def version_5(payload):  # the older layout: weights as numbers, outside the digest
        payload["version"] = 5
        payload["mixture"]["weights"] = [0.7, 0.3]
    loading_fails(crafted(mixture_file, "v5.pt", version_5),
                  rf"v5\.pt: a version 5 mixture, whose weights are outside the checkpoint's SHA-256 \(expected version "
                  rf"{MIXTURE_VERSION} or later")


def test_the_constructor_refuses_weights_that_cannot_be_normalised():
    a = CVAE(CVAEConfig.variant("cvae")).eval()
    for weights in ([1e308, 1e308], [float("nan"), 1.0], [0.0, 1.0], [1.0]):
        with pytest.raises(ValueError, match="mixture"):
            Mixture([a, copy.deepcopy(a)], weights)
    with pytest.raises(ValueError, match="facing a person"):
        Mixture([a, copy.deepcopy(a)], [0.5, 0.5], person_weights=[1e308, 1e308])
    with pytest.raises(ValueError, match="must be models, got a Mixture"):
        Mixture([Mixture([a, copy.deepcopy(a)], [0.5, 0.5]), a], [0.5, 0.5])


def test_a_crafted_mixture_fails_the_commands_in_one_line(mixture_file, tmp_path, capsys):
    path = crafted(mixture_file, "huge.pt", set_weights("weights", torch.tensor([1e308, 1e308], dtype=torch.float64)))
    data = tmp_path / "never_read.parquet"
    refused(capsys, "evaluate", "--model", path, "--data", data, expected=("huge.pt: checkpoint field mixture.weights",))
    refused(capsys, "realism", "--human", f"model:{path}", "--data", data, "--rollouts", 2,
            expected=(f"--human model:{path}:", "mixture.weights"), absent=("never_read",))


def test_the_shipped_driver_is_a_mixture_whose_weights_the_digest_covers():
    model, payload = load_checkpoint(shipped_model_path("driver"))
    assert isinstance(model, Mixture) and model.weights == [0.5, 0.5] and model.person_weights == [0.0, 1.0]
    assert payload["mixture"]["weights"].dtype == torch.float64 and payload[HASH_FIELD] == tensor_digest(payload)


# ---------------------------------------------------------------- companions
@pytest.fixture(scope="module")
def folds(tmp_path_factory) -> Path:
    """Two fold models (the shipped default, as a fine-tuned recipe's folds share its standardisation)."""
    folder = tmp_path_factory.mktemp("folds")
    model = load_model("default")
    for k in (1, 2):
        save_checkpoint(folder / f"fold_{k}.pt", model, held_out_trials=[k])
    return folder


@pytest.mark.parametrize("companion, expected", [
    ("simulated-real", "--companion simulated-real: mixture components must share the standardisation"),
    ("driver", "--companion driver: is a mixture (expected one model)"),
    ("", "--companion '': empty path"),
    ("authors:", "--companion 'authors:': empty path"),
])
def test_calibrate_refuses_a_companion_it_cannot_mix_before_any_work(capsys, tmp_path, folds, companion, expected):
    refused(capsys, "calibrate", "--data", tmp_path / "never_read.parquet", "--folds", folds, "--model", "default",
            "--temperatures", 1, "--scales", 1, "--samples", 2, "--companion", companion, "--out", tmp_path / "c.pt",
            expected=(expected,), absent=("never_read",))
    assert not (tmp_path / "c.pt").exists()


def test_mix_refuses_the_same_companions_by_the_same_rule(capsys, tmp_path):
    for companion, expected in (("simulated-real", "mixture components must share the standardisation"),
                                ("driver", "is a mixture")):
        refused(capsys, "mix", "--model", "default", "--companion", companion, "--weight", 0.5, "--out", tmp_path / "m.pt",
                expected=(f"--companion {companion}: {expected}",))
    assert not (tmp_path / "m.pt").exists()


def test_calibrate_refuses_fold_models_that_are_mixtures(capsys, tmp_path, folds):
    mixed = tmp_path / "mixed_folds"
    mixed.mkdir()
    save_checkpoint(mixed / "fold_1.pt", load_model("driver"), held_out_trials=[1])
    refused(capsys, "calibrate", "--data", tmp_path / "never_read.parquet", "--folds", mixed, "--model", "default",
            "--out", tmp_path / "c.pt", expected=("fold_1.pt: is a mixture (expected a fold model",))


# ---------------------------------------------------------------- bounded counts
@pytest.mark.parametrize("argv, option, largest", [
    (["realism", "--human", "synthetic", "--data", "d"], "--rollouts", 512),
    (["evaluate", "--data", "d"], "--samples", 10_000),
    (["evaluate", "--data", "d"], "--coverage-samples", 25_600),
    (["evaluate", "--data", "d"], "--ade-samples", 25_600),
    (["predict", "--data", "d", "--at", "0:9", "--out", "p.png"], "--samples", 25_600),
    (["calibrate", "--data", "d", "--folds", "f", "--model", "m", "--out", "c.pt"], "--samples", 25_600),
    (["bench", "plan"], "--first-stage-samples", 512),
    (["bench", "plan"], "--second-stage-samples", 2**21),
    (["crossval", "--data", "d"], "--folds", 100),
])
def test_counts_that_allocate_have_an_upper_bound_stated_in_the_help(capsys, argv, option, largest):
    parser = build_parser()
    assert getattr(parser.parse_args([*argv, option, str(largest)]), option[2:].replace("-", "_")) == largest
    refused(capsys, *argv, option, largest + 1, expected=(f"argument {option}: expected an integer in ", f"..{largest}, "))
    code, out, _ = run(capsys, argv[0], "--help")
    assert code == 0 and str(largest) in out


def test_realism_refuses_a_million_rollouts_in_one_line(capsys, tmp_path):
    refused(capsys, "realism", "--human", "synthetic", "--data", tmp_path / "d.parquet", "--rollouts", 1_000_000,
            expected=("argument --rollouts: expected an integer in 2..512, got 1000000",))


@pytest.mark.parametrize("command", ["crossval", "calibrate"])
def test_workers_are_bounded_by_the_cores(capsys, tmp_path, command):
    import os

    from trafficweaving.sim.batch import WORKERS_PER_CPU

    most = WORKERS_PER_CPU * (os.cpu_count() or 1)
    argv = (["crossval", "--data", "d"] if command == "crossval"
            else ["calibrate", "--data", "d", "--folds", "f", "--model", "m", "--out", tmp_path / "c.pt"])
    refused(capsys, *argv, "--workers", most + 1, expected=(f"argument --workers: expected an integer in 1..{most}",))


def test_a_plan_budget_beyond_the_bound_is_refused_before_the_model_loads(capsys, tmp_path):
    refused(capsys, "bench", "plan", "--model", tmp_path / "missing.pt", "--finalists", 4096,
            "--second-stage-samples", 1024, expected=("sample 4259840 human futures a plan", "at most 2097152"),
            absent=("missing.pt",))


def test_crossval_refuses_keeping_more_model_copies_than_the_bound_before_fitting(tmp_path):
    from helpers_model import synthetic_trials
    from trafficweaving.model.crossval import MAX_KEPT_MODELS, crossval
    from trafficweaving.model.train_config import TrainConfig

    with pytest.raises(InputError, match=rf"--out keeps the weights of 5 fits .*: 500010 model copies \(expected at "
                                         rf"most {MAX_KEPT_MODELS}") as info:
        crossval(synthetic_trials(5, seed=1), 5, TrainConfig(steps=100_000, validate_every=1), out=tmp_path / "cv")
    assert "\n" not in str(info.value) and not (tmp_path / "cv").exists()


def test_the_realism_function_refuses_rollouts_beyond_the_bound():
    from helpers_model import synthetic_trials
    from trafficweaving.sim.realism import MAX_ROLLOUTS, realism

    with pytest.raises(ValueError, match=rf"rollouts must be an integer in 2\.\.{MAX_ROLLOUTS}, got {MAX_ROLLOUTS + 1}"):
        realism(synthetic_trials(1, seed=1), lambda ids, other: [], rollouts=MAX_ROLLOUTS + 1)


# ---------------------------------------------------------------- messages that name the culprit
def test_realism_blames_the_human_spec_not_the_data(capsys, tmp_path):
    data = tmp_path / "trials.parquet"
    data.write_bytes(b"")  # never read: the agent is checked first
    refused(capsys, "realism", "--human", "bogus", "--data", data,
            expected=("--human bogus: human 'bogus' is unknown",), absent=("trials.parquet",))
    err = refused(capsys, "realism", "--human", "model:authors:", "--data", data,
                  expected=("--human model:authors:", "no path after authors:"), absent=("trials.parquet", "is a folder"))
    assert "authors:PATH" in err


def test_an_empty_model_spec_or_authors_path_says_so():
    with pytest.raises(InputError, match=r"^model spec is empty \(expected a checkpoint path"):
        load_model("")
    with pytest.raises(InputError, match=r"^model spec 'authors:' has no path after authors: \(expected"):
        load_model("authors:")


def test_a_pickle_protocol_4_checkpoint_is_refused_without_a_warning(mixture_file, tmp_path, capsys):
    payload = torch.load(mixture_file, weights_only=True)
    path = tmp_path / "p4.pt"
    torch.save(payload, path, pickle_protocol=4)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        loading_fails(path, r"p4\.pt: not a readable checkpoint")
    assert caught == []
    refused(capsys, "evaluate", "--model", path, "--data", tmp_path / "d.parquet", expected=("p4.pt: not a readable",))
