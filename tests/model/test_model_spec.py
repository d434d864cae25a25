"""The model spec grammar (model/spec.py), the human specs built on it, the mix workflow as a
library function, and the package's import structure (no circle, a light spec module)."""

from __future__ import annotations

import subprocess
import sys

import pytest
import torch

from trafficweaving.errors import InputError
from trafficweaving.model.checkpoint import load_checkpoint, save_checkpoint
from trafficweaving.model.cvae import CVAE, CVAEConfig
from trafficweaving.model.mixture import Mixture
from trafficweaving.model.spec import EXPECTED, SHIPPED_MODELS, ModelSpec, check_model_spec, parse_model_spec
from trafficweaving.model.workflows import calibrate_checkpoint, mix_checkpoint
from trafficweaving.sim.humans import HumanSpec, parse_human_spec


@pytest.mark.parametrize("text, kind, path", [
    ("default", "shipped", "default"),
    ("driver", "shipped", "driver"),
    ("authors:w/weights.npz", "authors", "w/weights.npz"),
    ("runs/m.pt", "checkpoint", "runs/m.pt"),
    ("authors", "checkpoint", "authors"),
])
def test_a_model_spec_is_a_shipped_name_the_authors_weights_or_a_checkpoint(text, kind, path):
    assert parse_model_spec(text) == ModelSpec(text, kind, path)
    assert set(SHIPPED_MODELS) == {"default", "simulated-real", "driver", "fast"}


def test_an_empty_spec_is_refused_in_the_words_of_where_it_was_given():
    with pytest.raises(InputError, match=r"^model spec is empty \(expected a checkpoint path, default"):
        parse_model_spec("")
    with pytest.raises(InputError, match=r"^model spec 'authors:' has no path after authors: \(expected"):
        parse_model_spec("authors:")
    for text in ("", "authors:"):
        with pytest.raises(InputError) as info:
            parse_model_spec(text, "--companion")
        assert str(info.value) == f"--companion {text!r}: empty path ({EXPECTED})"


def test_an_option_s_spec_is_checked_for_its_file_before_any_work(tmp_path):
    assert check_model_spec("default", "--model") == "default"  # shipped: inside the package
    (tmp_path / "m.pt").write_bytes(b"not read here")
    assert check_model_spec(str(tmp_path / "m.pt"), "--model") == str(tmp_path / "m.pt")
    for text in (str(tmp_path / "none.pt"), f"authors:{tmp_path / 'none.npz'}"):
        with pytest.raises(InputError) as info:
            check_model_spec(text, "--reference")
        assert str(info.value) == f"--reference {text}: no such file ({EXPECTED})"


def test_human_specs_parse_without_loading_anything(tmp_path):
    assert parse_human_spec("synthetic") == HumanSpec("synthetic")
    assert parse_human_spec("model:authors:w.npz") == HumanSpec("model", model=ModelSpec("authors:w.npz", "authors", "w.npz"))
    assert parse_human_spec("model:default").model.kind == "shipped"
    assert parse_human_spec("replay:d.parquet#12") == HumanSpec("replay", path="d.parquet", trial=12)
    assert parse_human_spec("replay:d.parquet") == HumanSpec("replay", path="d.parquet")
    odd = tmp_path / "a#b"  # an existing file is a FILE, '#' or not
    odd.write_bytes(b"")
    assert parse_human_spec(f"replay:{odd}") == HumanSpec("replay", path=str(odd))
    with pytest.raises(InputError, match="no path after authors:"):
        parse_human_spec("model:authors:")
    for bad in ("model:", "model", "bogus", "replay:"):
        with pytest.raises(InputError, match=f"human {bad!r} is unknown"):
            parse_human_spec(bad)
    with pytest.raises(InputError, match="human None is not a spec"):
        parse_human_spec(None)


@pytest.fixture
def two_models(tmp_path):
    """Two untrained models with the same (default) standardisation, as checkpoints."""
    torch.manual_seed(0)
    paths = tmp_path / "a.pt", tmp_path / "b.pt"
    for path, variant in zip(paths, ("cvae-hold", "cvae")):
        save_checkpoint(path, CVAE(CVAEConfig.variant(variant)), step=7)
    return [str(p) for p in paths]


def test_mix_checkpoint_writes_the_mixture_and_returns_what_the_command_prints(tmp_path, two_models):
    a, b = two_models
    payload = mix_checkpoint(a, b, 0.3, tmp_path / "x.pt", person_weight=0.0)
    assert payload == {"out": str(tmp_path / "x.pt"), "companion": b, "weight": 0.3, "person_weight": 0.0, "folds": 0}
    mixed, fields = load_checkpoint(tmp_path / "x.pt")
    assert isinstance(mixed, Mixture) and mixed.weights == pytest.approx([0.3, 0.7])
    assert mixed.person_weights == pytest.approx([0.0, 1.0]) and fields["step"] == 7
    assert fields["mixture_recipe"] == {"companion": b, "weight": 0.3, "person_weight": 0.0}
    with pytest.raises(InputError, match="is a mixture already"):
        mix_checkpoint(str(tmp_path / "x.pt"), b, 0.5, tmp_path / "y.pt")
    with pytest.raises(InputError, match="--folds and --out-folds go together"):
        mix_checkpoint(a, b, 0.5, tmp_path / "y.pt", folds=tmp_path)
    with pytest.raises(InputError, match=r"^--companion 'authors:': empty path"):
        mix_checkpoint(a, "authors:", 0.5, tmp_path / "y.pt")
    assert not (tmp_path / "y.pt").exists()


def test_calibrate_checkpoint_checks_its_inputs_before_reading_the_data(tmp_path, two_models):
    a, _ = two_models
    never = tmp_path / "never_read.parquet"
    with pytest.raises(InputError, match="2 --model for 1 --folds"):
        calibrate_checkpoint(never, [a, a], [tmp_path], tmp_path / "c.pt")
    with pytest.raises(InputError, match="no fold_K.pt files"):
        calibrate_checkpoint(never, [a], [tmp_path / "folds"], tmp_path / "c.pt")
    assert not (tmp_path / "c.pt").exists()


@pytest.mark.slow
def test_the_file_format_does_not_import_the_trainer_and_the_grammar_not_torch():
    code = ("import sys, trafficweaving.model.spec; assert 'torch' not in sys.modules; "
            "import trafficweaving.model.checkpoint; "
            "assert not {'trafficweaving.model.train', 'trafficweaving.model.registry'} & set(sys.modules)")
    subprocess.run([sys.executable, "-c", code], check=True)
