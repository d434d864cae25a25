"""The library workflows behind the command handlers: ``evaluate`` (model/metrics.py
``evaluate_file``), the training schedule of ``train`` / ``crossval`` (model/train_config.py
``config_from_options``) and ``stats DIR`` (web/study.py ``study_stats``)."""

import json

import numpy as np
import pyarrow.parquet as pq
import pytest

from trafficweaving.cli import main
from trafficweaving.errors import InputError
from trafficweaving.model.train_config import FINE_TUNING, TrainConfig, config_from_options
from trafficweaving.sim.generate import generate_trials


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    """Two synthetic trials (seed 3) in a Parquet file."""
    path = tmp_path_factory.mktemp("data") / "x.parquet"
    trials, _ = generate_trials(2, seed=3, progress=False)
    trials.write_parquet(path)
    return path


def test_config_from_options_from_scratch_fine_tuning_and_overrides():
    assert config_from_options(123, 9) == TrainConfig(steps=123, seed=9)
    tuned = config_from_options(10, 0, fine_tuning=True)
    assert all(getattr(tuned, key) == value for key, value in FINE_TUNING.items())
    low = config_from_options(10, 0, lr_initial=1e-6, validate_every=7, trainable="hold", patience=0)
    assert (low.lr_initial, low.lr_final, low.validate_every, low.checkpoint_every, low.trainable) == (1e-6, 1e-6, 7, 7, "hold")
    with pytest.raises(InputError, match="--patience needs a validation set"):
        config_from_options(10, 0, validation_fraction=0.0, patience=3)


@pytest.mark.slow
def test_evaluate_file_is_the_commands_payload_with_data_and_seed(data, tmp_path, capsys):
    from trafficweaving.model.metrics import evaluate_file

    table = tmp_path / "instances.parquet"
    payload, described = evaluate_file("default", str(data), samples=2, coverage_samples=2, ade_samples=1,
                                       max_sampled=3, seed=5, per_instance=table)
    assert described == payload["variant"] == "cvae-hold"
    assert list(payload)[-4:] == ["model", "variant", "data", "seed"]
    assert (payload["model"], payload["data"], payload["seed"], payload["sampled_instances"]) == ("default", str(data), 5, 3)
    meta = json.loads(pq.read_table(table).schema.metadata[b"trafficweaving"])
    assert meta == {"model": "default", "data": str(data), "seed": 5, "samples": 2, "coverage_samples": 2, "ade_samples": 1}
    assert main(["evaluate", "--data", str(data), "--samples", "2", "--coverage-samples", "2", "--ade-samples", "1",
                 "--max-sampled-instances", "3", "--seed", "5", "--json"]) == 0
    assert json.loads(capsys.readouterr().out) == payload


def test_evaluate_file_checks_the_output_before_loading(data, tmp_path):
    from trafficweaving.model.metrics import evaluate_file

    with pytest.raises(InputError, match="--per-instance .*: is a folder"):
        evaluate_file("nope.pt", tmp_path / "absent.parquet", per_instance=tmp_path)


def test_study_stats_payload_and_text(data, tmp_path, capsys):
    from trafficweaving.data.trials import load_trials
    from trafficweaving.web.study import study_stats

    trials = load_trials(data)
    for i, reason in enumerate(("finished", "stopped")):
        one = trials.subset(np.arange(len(trials)) == i)
        one.metadata = {"drive": {"mode": "human-human", "started_at": f"2025-01-01T10:0{i}:00Z", "reason": reason,
                                  "room": {"session": "s1", "participants": ["p1", None], "round": 0}}}
        one.write_parquet(tmp_path / f"drive_{i + 1:06d}.parquet")
    payload, text = study_stats(tmp_path)
    assert (payload["folder"], payload["files"], payload["completed"], payload["aborted"]) == (str(tmp_path), 2, 1, 1)
    assert list(payload)[0] == "folder" and list(payload)[-1] == "table1_vs_paper"
    assert text.splitlines()[0] == f"{tmp_path}: trials recorded 2, completed 1, aborted 1 (stopped, a page gone, a server error)"
    assert main(["stats", str(tmp_path)]) == 0
    assert capsys.readouterr().out == text + "\n"
