"""Evaluation beyond the mean NLL (model/metrics.py, the per-direction NLL of model/evaluate.py,
and `trafficweaving evaluate`): coverage, minADE/minFDE, lane-change phases, per-instance output."""

import json

import numpy as np
import pyarrow.parquet as pq
import pytest
import torch

from helpers_model import synthetic_trials
from trafficweaving.cli import main
from trafficweaving.model.registry import load_model
from trafficweaving.model.cvae import CVAE, CVAEConfig
from trafficweaving.model.evaluate import evaluate
from trafficweaving.model.exemplars import ExemplarSet, build_exemplars
from trafficweaving.model.metrics import PHASES, evaluate_instances, sampled_metrics, true_positions
from trafficweaving.dynamics import future_states
from trafficweaving.model.predictor import HumanPredictor
from trafficweaving.scenario import HORIZON


@pytest.fixture(scope="module")
def trials():
    return synthetic_trials(16, seed=4)


@pytest.fixture(scope="module")
def model():
    return load_model("default")


def run(capsys, *argv):
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def test_batched_future_states_match_one_present_state_at_a_time():
    gen = torch.Generator().manual_seed(0)
    present = torch.randn(4, 6, generator=gen, dtype=torch.float64)
    actions = torch.randn(3, 4, HORIZON, 2, generator=gen, dtype=torch.float64)
    batched = future_states(present, actions)  # [3, 4, 15, 6]
    for b in range(4):
        torch.testing.assert_close(batched[:, b], future_states(present[b], actions[:, b]))
    assert torch.equal(batched[..., 4:], actions)


def test_true_positions_are_the_recorded_ones_on_synthetic_data(trials):
    exemplars = build_exemplars(trials)
    index = np.arange(0, len(exemplars), 7)
    s, t = exemplars.stream[index], exemplars.t[index]
    recorded = exemplars.streams[s[:, None], t[:, None] + np.arange(1, HORIZON + 1), 1, :2]
    np.testing.assert_allclose(true_positions(exemplars, index), recorded, atol=1e-6)


def _self_sampled(model, exemplars: ExemplarSet, picks: np.ndarray) -> ExemplarSet:
    """One stream per picked exemplar whose human future is a draw of ``model`` (through the
    planner's predictor, an independent sampling path): data the model describes exactly."""
    predictor = HumanPredictor(model)
    streams = exemplars.streams[exemplars.stream[picks]].copy()
    for k, t in enumerate(exemplars.t[picks]):
        history, robot_future = streams[k, : t + 1], streams[k, t + 1: t + 1 + HORIZON, 0]
        actions = predictor.predict(history, robot_future[None], n=1, seed=1000 + k).actions[0, 0].double()
        streams[k, t + 1: t + 1 + HORIZON, 1] = future_states(torch.as_tensor(history[-1, 1]), actions).numpy()
    n = len(picks)
    return ExemplarSet(streams, exemplars.lengths[exemplars.stream[picks]], np.arange(n), np.ones(n, np.int64),
                       exemplars.sources[exemplars.stream[picks]], np.arange(n), exemplars.t[picks].copy())


@pytest.mark.slow
def test_coverage_on_data_sampled_from_the_model_itself_is_near_nominal(trials, model):
    exemplars = build_exemplars(trials)
    picks = np.arange(0, len(exemplars), 4)
    own = _self_sampled(model, exemplars, picks)
    metrics = sampled_metrics(model, own, np.arange(len(picks)), samples=100, ade_samples=5, levels=(0.5, 0.9))
    coverage = metrics.covered.mean(axis=0)  # [2 directions, 3 horizons, 2 levels]
    assert len(picks) >= 200
    assert np.abs(coverage[..., 0] - 0.5).max() < 0.1 and np.abs(coverage[..., 1] - 0.9).max() < 0.07
    assert abs(coverage[..., 0].mean() - 0.5) < 0.05 and abs(coverage[..., 1].mean() - 0.9) < 0.04
    # the same model made overconfident (every output width halved) misses the recorded futures more often
    import copy

    narrow = copy.deepcopy(model).set_calibration(float(model.latent_temperature), tuple((0.5 * model.output_scale).tolist()))
    real = sampled_metrics(narrow, exemplars, picks, samples=40, ade_samples=5, levels=(0.9,))
    assert real.covered.mean() < coverage[..., 1].mean() - 0.05


@pytest.mark.slow
def test_min_ade_and_fde_never_grow_with_more_samples_and_are_deterministic(trials, model):
    exemplars = build_exemplars(trials)
    index = np.arange(0, len(exemplars), 20)
    runs = [sampled_metrics(model, exemplars, index, samples=20, ade_samples=k, seed=3) for k in (1, 5, 20)]
    for fewer, more in zip(runs, runs[1:]):
        assert (more.min_ade <= fewer.min_ade).all() and (more.min_fde <= fewer.min_fde).all()
        assert more.min_ade.mean() < fewer.min_ade.mean() and more.min_fde.mean() < fewer.min_fde.mean()
    assert (runs[0].min_fde >= 0).all() and (runs[0].min_ade > 0).all()
    again = sampled_metrics(model, exemplars, index, samples=20, ade_samples=20, seed=3)
    np.testing.assert_array_equal(again.min_ade, runs[-1].min_ade)
    np.testing.assert_array_equal(again.covered, runs[-1].covered)


def test_per_direction_nll_adds_up_to_the_exact_nll_for_one_uncorrelated_gaussian(trials):
    torch.manual_seed(0)
    model = CVAE(CVAEConfig.variant("lstm")).eval()  # one latent value, one component
    with torch.no_grad():
        model.gmm.corr.weight.zero_()
        model.gmm.corr.bias.zero_()  # correlation 0: the directions are independent
    result = evaluate(model, build_exemplars(trials.subset(np.arange(4))))
    np.testing.assert_allclose(result.nll_direction.sum(axis=1), result.nll_exact, rtol=1e-5, atol=1e-3)


@pytest.mark.slow
def test_phases_partition_the_instances_and_follow_the_lane_change(trials, model):
    trials = trials.subset(np.arange(6))
    exemplars = build_exemplars(trials)
    metrics = evaluate_instances(model, trials, exemplars, samples=10, ade_samples=5, max_sampled=50)
    summary = metrics.summary()
    by_phase = summary["nll_exact_by_phase"]
    assert list(by_phase) == list(PHASES)
    assert sum(v["instances"] for v in by_phase.values()) == summary["instances"] == len(exemplars)
    weighted = sum(v["instances"] * v["nll_exact"] for v in by_phase.values() if v["instances"])
    assert weighted / summary["instances"] == pytest.approx(summary["nll_exact"])
    assert by_phase["before"]["instances"] > 0 and by_phase["during"]["instances"] > 0
    # within one stream the phases only move forward in time
    order = {p: k for k, p in enumerate(PHASES[:3])}
    for s in np.unique(exemplars.stream):
        ranks = [order[p] for p in metrics.phase[exemplars.stream == s] if p != "none"]
        assert ranks == sorted(ranks)
    assert summary["sampled_instances"] == 50 and metrics.sampled.sum() == 50
    assert np.isnan(metrics.min_ade[~metrics.sampled]).all() and np.isfinite(metrics.min_ade[metrics.sampled]).all()


@pytest.mark.slow
def test_evaluate_json_per_instance_parquet_round_trip(capsys, tmp_path, trials):
    data, table = tmp_path / "d.parquet", tmp_path / "out" / "instances.parquet"
    trials.subset(np.arange(3)).write_parquet(data)
    code, out, _ = run(capsys, "evaluate", "--data", data, "--coverage-samples", 20, "--ade-samples", 10,
                       "--per-instance", table, "--json")
    assert code == 0
    report = json.loads(out)
    old = evaluate(load_model("default"), build_exemplars(trials.subset(np.arange(3)))).summary()
    for key in ("instances", "nll_exact", "nll_is", "nll_naive"):  # unchanged keys and meanings
        assert report[key] == pytest.approx(old[key])
    assert set(report["coverage"]) == {"x", "y"} and set(report["coverage"]["x"]) == {"0.5", "1.0", "1.5"}
    assert set(report["coverage"]["y"]["1.5"]) == {"50", "90"}
    assert 0 < report["min_ade_m"] < report["min_fde_m"]
    rows = pq.read_table(table)
    assert json.loads(rows.schema.metadata[b"trafficweaving"])["coverage_samples"] == 20
    frame = rows.to_pydict()
    assert len(frame["t"]) == report["instances"] and not list(tmp_path.glob("out/.*.tmp"))
    assert np.mean(frame["nll_exact"]) == pytest.approx(report["nll_exact"])
    assert np.mean(frame["nll_exact_y"]) == pytest.approx(report["nll_exact_by_direction"]["y"])
    assert np.mean(frame["covered_x_1.5s_90"]) == pytest.approx(report["coverage"]["x"]["1.5"]["90"])
    assert np.mean(frame["min_fde_m"]) == pytest.approx(report["min_fde_m"])
    assert set(frame["phase"]) <= set(PHASES) and set(frame["trial"]) == set(trials.trial_ids[:3].tolist())
    code, out, _ = run(capsys, "evaluate", "--data", data, "--coverage-samples", 20, "--ade-samples", 10)
    assert code == 0 and "minADE" in out and "coverage" in out and "before" in out


@pytest.mark.parametrize("argv, message", [
    (["--per-instance", "{tmp}"], "is a folder"),
    (["--coverage-samples", "1"], "argument --coverage-samples: expected an integer in 2..25600"),
    (["--ade-samples", "0"], "argument --ade-samples: expected an integer in 1..25600"),
    (["--max-sampled-instances", "-1"], "argument --max-sampled-instances: expected an integer >= 0"),
])
def test_evaluate_rejects_bad_options_in_one_line(capsys, tmp_path, trials, argv, message):
    data = tmp_path / "d.parquet"
    trials.subset(np.arange(2)).write_parquet(data)
    code, _, err = run(capsys, "evaluate", "--data", data, *[a.format(tmp=tmp_path) for a in argv])
    assert code == 2 and message in err and err.count("\n") == 1 and "Traceback" not in err


@pytest.mark.slow
def test_real_humans_report_script_writes_tables_figures_and_its_command(tmp_path, trials):
    import subprocess
    import sys
    from pathlib import Path

    data, report = tmp_path / "d.parquet", tmp_path / "docs" / "report.md"
    trials.subset(np.arange(3)).write_parquet(data)
    script = Path(__file__).parents[2] / "scripts" / "real_humans_report.py"
    argv = ["--data", str(data), "--model", "a=default", "--model", "b=default", "--samples", "10", "--ade-samples", "5",
            "--out", str(report)]
    done = subprocess.run([sys.executable, str(script), *argv], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    text = report.read_text()
    assert "python scripts/real_humans_report.py --data" in text and "## Coverage of the human's position" in text
    assert "| a | x |" in text and "| b | y |" in text and "minFDE" in text
    assert len(list((tmp_path / "docs" / "figures").glob("real_humans_*.png"))) == 3


def test_held_fraction_counts_steps_that_keep_the_previous_acceleration():
    from trafficweaving.model.metrics import held_fraction

    present = torch.tensor([1.0, -0.5], dtype=torch.float64)
    actions = torch.tensor([[1.0, -0.5]] * 5 + [[2.0, -0.495]] * 5 + [[2.0 + 0.02 * k, 0.3] for k in range(5)],
                           dtype=torch.float64)  # x: held 5 + 4 + 1 steps; y: 5 + 1 (by 0.005) + 4 + 4 steps
    np.testing.assert_allclose(held_fraction(present, actions).numpy(), [10 / 15, 14 / 15])
