"""The console command: the JSON contracts of every command (README "Commands") and one-line errors
on bad input (more cases in test_bad_input.py)."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

from helpers_model import small_checkpoint
from trafficweaving.cli import main
from trafficweaving.data.trials import load_trials


def run(capsys, *argv):
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def test_generate_then_stats_json(capsys, tmp_path):
    data = tmp_path / "d.parquet"
    code, out, _ = run(capsys, "generate", "--trials", 60, "--seed", 0, "--out", data, "--json")
    assert code == 0
    report = json.loads(out)
    assert report["trials"] == 60 and data.is_file()
    code, out, _ = run(capsys, "stats", data, "--json")
    stats = json.loads(out)
    assert stats["trials"] == 60
    assert set(stats["table1"]) == {"-2", "0", "2"}
    assert set(stats["table1"]["-2"]) == {"1", "2", "3"} and set(stats["table1"]["0"]) == {"all"}
    assert 0 <= stats["table1"]["0"]["all"] <= 1
    assert {"speed", "long_accel", "lat_accel", "lane_change_x"} <= set(stats["behaviour"])
    test = stats["table1_vs_paper"]
    assert test["dof"] == sum(1 for row in stats["table1"].values() for v in row.values() if v is not None)
    assert 0.0 <= test["p_value"] <= 1.0 and test["chi2"] >= 0.0


def test_human_readable_stats_show_table1(capsys, tmp_path):
    data = tmp_path / "d.parquet"
    run(capsys, "generate", "--trials", 40, "--out", data, "--json")
    code, out, _ = run(capsys, "stats", data)
    assert code == 0 and "Table I" in out and "paper 38.2%" in out and "χ²(" in out


def test_import_hitl_gives_30_trials_and_compares_behaviour(capsys, tmp_path, hitl_files):
    hitl = tmp_path / "hitl.parquet"
    code, out, _ = run(capsys, "import", "hitl", *hitl_files, "--out", hitl, "--json")
    assert code == 0 and json.loads(out)["trials"] == 30
    data = tmp_path / "d.parquet"
    run(capsys, "generate", "--trials", 40, "--out", data, "--json")
    code, out, _ = run(capsys, "stats", data, "--reference", hitl, "--json")
    comparison = json.loads(out)["behaviour_vs_reference"]
    assert comparison["speed"]["real"]["count"] > 1000 and comparison["speed"]["wasserstein"] >= 0


@pytest.mark.slow
def test_plot_writes_pngs(capsys, tmp_path):
    data = tmp_path / "d.parquet"
    run(capsys, "generate", "--trials", 40, "--out", data, "--json")
    code, out, _ = run(capsys, "plot", data, "--out", tmp_path / "fig", "--reference", data, "--json")
    figures = [Path(p) for p in json.loads(out)["figures"]]
    assert code == 0 and len(figures) == 4
    assert all(p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" for p in figures)


@pytest.mark.parametrize("argv, expected", [
    (["stats", "{tmp}/absent.parquet"], "no such file"),
    (["stats", "{tmp}/junk.parquet"], "not a readable Parquet file"),
    (["generate", "--trials", "0", "--out", "{tmp}/x.parquet"], "argument --trials: expected an integer in 1..100000"),
    (["import", "hitl", "{tmp}/junk.parquet", "--out", "{tmp}/x.parquet"], "junk.parquet"),
    (["import", "rosbag", "{tmp}/nowhere", "--out", "{tmp}/x.parquet"], "nowhere"),
])
def test_bad_input_is_one_line_on_stderr_with_exit_2(capsys, tmp_path, argv, expected):
    (tmp_path / "junk.parquet").write_text("not parquet")
    code, out, err = run(capsys, *[a.format(tmp=tmp_path) for a in argv])
    assert code == 2 and out == ""
    assert expected in err and err.count("\n") == 1 and "Traceback" not in err


@pytest.mark.slow
def test_python_dash_m_entry_point(tmp_path):
    result = subprocess.run([sys.executable, "-m", "trafficweaving", "generate", "--trials", "20",
                             "--out", str(tmp_path / "d.parquet"), "--json"], capture_output=True, text=True)
    assert result.returncode == 0 and json.loads(result.stdout)["trials"] == 20


# ---------------------------------------------------------------- human model commands
@pytest.mark.slow
def test_evaluate_authors_model_on_the_real_trials_gives_the_papers_nll(capsys, tmp_path, hitl_files, authors_model_dir):
    weights = authors_model_dir / "weights.npz"
    data = tmp_path / "hitl.parquet"
    run(capsys, "import", "hitl", *hitl_files, "--out", data, "--json")
    code, out, _ = run(capsys, "evaluate", "--model", f"authors:{weights}", "--data", data, "--max-sampled-instances", 0,
                       "--json")
    assert code == 0
    report = json.loads(out)
    assert report["instances"] == 963
    assert report["nll_exact"] == pytest.approx(-12.717, abs=0.01)
    assert report["nll_is"] is None and report["nll_naive"] > report["nll_exact"] - 0.05
    code, out, _ = run(capsys, "predict", "--model", f"authors:{weights}", "--data", data,
                       "--at", "2:10", "--at", "7:20:1", "--samples", 10, "--out", tmp_path / "fig3.png", "--json")
    assert code == 0 and json.loads(out)["panels"] == 2 and (tmp_path / "fig3.png").stat().st_size > 10_000


@pytest.mark.slow
def test_train_then_evaluate_a_checkpoint(capsys, tmp_path):
    data, model = tmp_path / "d.parquet", tmp_path / "m.pt"
    run(capsys, "generate", "--trials", 12, "--seed", 2, "--out", data, "--json")
    code, out, _ = run(capsys, "train", "--data", data, "--out", model, "--steps", 4, "--variant", "lstm", "--json")
    assert code == 0
    trained = json.loads(out)
    assert trained["variant"] == "lstm" and trained["steps"] == 4 and model.is_file()
    code, out, _ = run(capsys, "evaluate", "--model", model, "--data", data, "--max-sampled-instances", 0, "--json")
    report = json.loads(out)
    assert code == 0 and report["instances"] > trained["instances"]  # all trials, not just the validation split
    # a single latent value: all three estimators are the same number
    assert report["nll_exact"] == pytest.approx(report["nll_is"]) == pytest.approx(report["nll_naive"])
    code, out, _ = run(capsys, "train", "--data", data, "--out", model, "--steps", 6, "--resume", model, "--json")
    assert code == 0 and json.loads(out)["steps"] == 6
    # fine-tune on every trial (no validation split), as the shipped model is made
    tuned = tmp_path / "tuned.pt"
    code, out, _ = run(capsys, "train", "--data", data, "--out", tuned, "--init", model, "--steps", 3,
                       "--validation-fraction", 0, "--json")
    report = json.loads(out)
    assert code == 0 and report["variant"] == "lstm" and report["nll_exact"] is None and report["init"] == str(model)


@pytest.mark.parametrize("argv, message", [
    (["evaluate", "--model", "nope.pt", "--data", "DATA"], "nope.pt: no such file"),
    (["evaluate", "--model", "authors:nope.npz", "--data", "DATA"], "nope.npz: no such file"),
    (["evaluate", "--model", "MODEL", "--data", "nope.parquet"], "nope.parquet"),
    (["evaluate", "--model", "MODEL", "--data", "DATA", "--device", "tpu9"], "unknown device"),
    (["train", "--data", "DATA", "--out", "x.pt", "--resume", "DATA"], "not a readable checkpoint"),
    (["predict", "--model", "MODEL", "--data", "DATA", "--at", "0", "--out", "f.png"], "expected TRIAL:T"),
    (["predict", "--model", "MODEL", "--data", "DATA", "--at", "0:2", "--out", "f.png"], "t must be within 4.."),
    (["predict", "--model", "MODEL", "--data", "DATA", "--at", "99:5", "--out", "f.png"], "trial index 99 is outside"),
    (["train", "--data", "DATA", "--out", "x.pt", "--init", "MODEL", "--variant", "lstm"], "a cvae model, but --variant lstm"),
    (["train", "--data", "DATA", "--out", "x.pt", "--init", "MODEL"], "its standardisation does not fit the data"),
    (["train", "--data", "DATA", "--out", "x.pt", "--init", "MODEL", "--resume", "MODEL"], "exclude each other"),
    (["train", "--data", "DATA", "--out", "x.pt", "--validation-fraction", "0", "--patience", "3"], "--patience needs a validation set"),
    (["crossval", "--data", "DATA", "--folds", "5"], "fewer than --folds 5"),
    (["crossval", "--data", "DATA", "--folds", "2", "--beat-reference"], "--beat-reference needs a --reference"),
    (["crossval", "--data", "DATA", "--folds", "2", "--init", "nope.pt"], "nope.pt: no such file"),
])
def test_model_commands_reject_bad_input_in_one_line(capsys, tmp_path, argv, message):
    from trafficweaving.model.checkpoint import save_checkpoint
    from trafficweaving.model.cvae import CVAE

    data, model = tmp_path / "d.parquet", tmp_path / "m.pt"
    run(capsys, "generate", "--trials", 4, "--seed", 1, "--out", data, "--json")
    save_checkpoint(model, CVAE())
    argv = [str(data) if a == "DATA" else str(model) if a == "MODEL" else a for a in argv]
    argv = [a.replace("nope", str(tmp_path / "nope")) for a in argv]
    code, out, err = run(capsys, *argv)
    assert code == 2 and message in err and err.count("\n") == 1 and "Traceback" not in err


def test_crossval_rejects_data_without_human_agents(capsys, tmp_path):
    from trafficweaving.data.trials import load_trials

    data = tmp_path / "d.parquet"
    run(capsys, "generate", "--trials", 6, "--seed", 1, "--out", data, "--json")
    robots = load_trials(data)
    robots.roles[:] = "robot"
    robots.write_parquet(tmp_path / "robots.parquet")
    code, _, err = run(capsys, "crossval", "--data", tmp_path / "robots.parquet", "--folds", 3)
    assert code == 2 and "no prediction instances" in err and "expected agents with role 'human'" in err
    assert err.count("\n") == 1


@pytest.mark.slow
def test_crossval_json_reports_folds_mean_and_reference(capsys, tmp_path):
    data, model = tmp_path / "d.parquet", tmp_path / "m.pt"
    run(capsys, "generate", "--trials", 9, "--seed", 3, "--out", data, "--json")
    small_checkpoint(model, load_trials(data))
    code, out, _ = run(capsys, "crossval", "--data", data, "--folds", 3, "--init", model, "--steps", 4,
                       "--validate-every", 2, "--reference", model, "--out", tmp_path / "folds", "--json")
    report = json.loads(out)
    assert code == 0 and len(report["folds"]) == 3 and report["steps"] in (0, 2, 4)
    assert report["nll_exact"] == pytest.approx(sum(report["folds"]) / 3)
    assert len(report["reference"]["folds"]) == 3 and [s for s, _ in report["curve"]] == [0, 2, 4]
    assert sorted(p.name for p in (tmp_path / "folds").iterdir()) == ["fold_1.pt", "fold_2.pt", "fold_3.pt"]


@pytest.mark.slow
def test_fine_tuning_a_model_into_a_driver_conditioned_on_the_guess(capsys, tmp_path):
    from trafficweaving.model.checkpoint import load_checkpoint

    data, model, driver = tmp_path / "d.parquet", tmp_path / "m.pt", tmp_path / "driver.pt"
    run(capsys, "generate", "--trials", 6, "--seed", 3, "--out", data, "--json")
    small_checkpoint(model, load_trials(data))
    code, _, _ = run(capsys, "train", "--data", data, "--init", model, "--robot-future", "guess", "--steps", 2,
                     "--out", driver, "--json")
    trained, payload = load_checkpoint(driver)
    assert code == 0 and trained.config.robot_future == "guess" and payload["init"]["robot_future"] == "recorded"
    code, out, _ = run(capsys, "realism", "--human", f"model:{driver}", "--data", data, "--rollouts", 2, "--json")
    assert code == 0 and json.loads(out)["streams"] == 12
    code, _, err = run(capsys, "bench", "plan", "--model", driver, "--json")
    assert code == 2 and "cannot tell candidate robot futures apart" in err


@pytest.mark.slow
def test_calibrate_chooses_on_out_of_fold_models_and_writes_calibrated_checkpoints(capsys, tmp_path):
    from trafficweaving.model.calibrate import MIX_WEIGHTS
    from trafficweaving.model.checkpoint import load_checkpoint, save_checkpoint
    from trafficweaving.model.mixture import Mixture

    data, model, folds = tmp_path / "d.parquet", tmp_path / "m.pt", tmp_path / "folds"
    run(capsys, "generate", "--trials", 3, "--seed", 3, "--out", data, "--json")
    small_checkpoint(model, load_trials(data))
    run(capsys, "crossval", "--data", data, "--folds", 3, "--init", model, "--steps", 2, "--validate-every", 2,
        "--out", folds, "--json")
    code, out, _ = run(capsys, "calibrate", "--data", data, "--folds", folds, "--model", model, "--out", tmp_path / "c.pt",
                       "--out-folds", tmp_path / "cfolds", "--samples", 10, "--temperatures", "1,2", "--scales", "1,2",
                       "--json")
    report = json.loads(out)
    grid = report["grid"]  # 2 x 2 settings, the scale in both directions, then per temperature each direction's own
    assert code == 0 and 4 <= len(grid) <= 6 and {tuple(r["output_scale"].values()) for r in grid[:4]} == {(1, 1), (2, 2)}
    assert all(r["latent_temperature"] in (1, 2) and set(r["output_scale"].values()) <= {1, 2} for r in grid[4:])
    scale = [report["output_scale"]["x"], report["output_scale"]["y"]]
    calibrated, payload = load_checkpoint(tmp_path / "c.pt")
    assert calibrated.latent_temperature.item() == report["latent_temperature"] and calibrated.output_scale.tolist() == scale
    assert payload["calibration"]["nll_exact"] == report["nll_exact"]
    fold, fold_payload = load_checkpoint(tmp_path / "cfolds" / "fold_2.pt")
    assert fold.output_scale.tolist() == scale and len(fold_payload["held_out_trials"]) == 1
    # scored in worker processes, the same rows (their models are private copies, not shared and overwritten)
    code, out, _ = run(capsys, "calibrate", "--data", data, "--folds", folds, "--model", model, "--out", tmp_path / "w.pt",
                       "--samples", 10, "--temperatures", "1", "--scales", "1,2", "--workers", 2, "--json")
    pooled = json.loads(out)["grid"]
    assert code == 0 and len(pooled) >= 2 and all(row in grid for row in pooled)
    # with a companion, the calibrated setting is then mixed with it at the weight chosen out-of-fold
    code, out, _ = run(capsys, "calibrate", "--data", data, "--folds", folds, "--model", model, "--companion", model,
                       "--out", tmp_path / "mixed.pt", "--out-folds", tmp_path / "mfolds", "--samples", 10,
                       "--temperatures", "1,2", "--scales", "1,2", "--json")
    mixed = json.loads(out)
    extra = mixed["grid"][len(grid):]
    assert code == 0 and mixed["grid"][:len(grid)] == grid and mixed["companion"] == str(model)
    assert [r["mixture_weight"] for r in extra] == list(MIX_WEIGHTS) and all(r["mixture_weight"] == 1 for r in grid)
    assert {(r["latent_temperature"], tuple(r["output_scale"].values())) for r in extra} == {(report["latent_temperature"], tuple(scale))}
    weight = mixed["mixture_weight"]
    loaded, _ = load_checkpoint(tmp_path / "mixed.pt")
    fold, _ = load_checkpoint(tmp_path / "mfolds" / "fold_1.pt")
    assert isinstance(loaded, Mixture) == isinstance(fold, Mixture) == (weight < 1)
    assert weight == 1 or loaded.weights == pytest.approx([weight, 1 - weight])
    trained, _ = load_checkpoint(model)
    save_checkpoint(tmp_path / "mixture.pt", Mixture([trained, trained], [0.5, 0.5]))
    code, _, err = run(capsys, "calibrate", "--data", data, "--folds", folds, "--model", tmp_path / "mixture.pt",
                       "--out", tmp_path / "x.pt")
    assert code == 2 and "is a mixture" in err and err.count("\n") == 1
    code, _, err = run(capsys, "calibrate", "--data", data, "--folds", tmp_path, "--model", model, "--out", tmp_path / "x.pt")
    assert code == 2 and "no fold_K.pt files" in err and err.count("\n") == 1


@pytest.mark.slow
def test_mix_writes_a_mixture_with_a_companion_conditioned_like_the_model(capsys, tmp_path):
    import torch

    from trafficweaving.model.checkpoint import load_checkpoint
    from trafficweaving.model.mixture import Mixture, facing

    data, companion, model, folds = tmp_path / "d.parquet", tmp_path / "c.pt", tmp_path / "m.pt", tmp_path / "folds"
    run(capsys, "generate", "--trials", 9, "--seed", 3, "--out", data, "--json")
    small_checkpoint(companion, load_trials(data), "cvae")  # recorded futures
    run(capsys, "train", "--data", data, "--init", companion, "--robot-future", "guess", "--out", model, "--steps", 2, "--json")
    run(capsys, "crossval", "--data", data, "--folds", 3, "--init", companion, "--robot-future", "guess", "--steps", 2,
        "--validate-every", 2, "--out", folds, "--json")
    code, out, _ = run(capsys, "mix", "--model", model, "--companion", companion, "--weight", 0.3, "--out", tmp_path / "x.pt",
                       "--folds", folds, "--out-folds", tmp_path / "xfolds", "--json")
    assert code == 0 and json.loads(out) == {"out": str(tmp_path / "x.pt"), "companion": str(companion), "weight": 0.3,
                                              "person_weight": None, "folds": 3}
    mixed, payload = load_checkpoint(tmp_path / "x.pt")
    trained, _ = load_checkpoint(model)
    original, _ = load_checkpoint(companion)
    assert isinstance(mixed, Mixture) and mixed.weights == pytest.approx([0.3, 0.7])
    assert [c.config.robot_future for c in mixed.components] == ["guess", "guess"] and original.config.robot_future == "recorded"
    for component, source in zip(mixed.components, (trained, original)):  # the weights kept
        assert all(torch.equal(v, source.state_dict()[k]) for k, v in component.state_dict().items())
    assert payload["mixture_recipe"] == {"companion": str(companion), "weight": 0.3, "person_weight": None}
    assert mixed.person_weights is None and facing(mixed, "person") is mixed
    fold, fold_payload = load_checkpoint(tmp_path / "xfolds" / "fold_2.pt")
    assert isinstance(fold, Mixture) and len(fold_payload["held_out_trials"]) == 3
    # facing a person, the companion alone: self-play drives with it, realism where both cars are human
    code, out, _ = run(capsys, "mix", "--model", model, "--companion", companion, "--weight", 0.3, "--person-weight", 0,
                       "--out", tmp_path / "p.pt")
    assert code == 0 and "facing a person 0 and 1" in out
    person, _ = load_checkpoint(tmp_path / "p.pt")
    assert person.weights == pytest.approx([0.3, 0.7]) and person.person_weights == pytest.approx([0.0, 1.0])
    alone = facing(person, "person")
    assert all(torch.equal(v, original.state_dict()[k]) for k, v in alone.state_dict().items())
    assert facing(person, "robot") is person
    # a mixture is not mixed again; the fold models need a folder to go to; the weight is a share
    code, _, err = run(capsys, "mix", "--model", tmp_path / "x.pt", "--companion", companion, "--weight", 0.5,
                       "--out", tmp_path / "y.pt")
    assert code == 2 and "is a mixture already" in err and err.count("\n") == 1
    code, _, err = run(capsys, "mix", "--model", model, "--companion", companion, "--weight", 0.5, "--out", tmp_path / "y.pt",
                       "--folds", folds)
    assert code == 2 and "--folds and --out-folds go together" in err and not (tmp_path / "y.pt").exists()
    code, _, err = run(capsys, "mix", "--model", model, "--companion", tmp_path / "x.pt", "--weight", 0.5, "--out",
                       tmp_path / "y.pt")
    assert code == 2 and "is a mixture (expected one model)" in err and err.count("\n") == 1
    code, _, err = run(capsys, "mix", "--model", model, "--companion", companion, "--weight", 1, "--out", tmp_path / "y.pt")
    assert code == 2 and "(0, 1)" in err
    code, _, err = run(capsys, "mix", "--model", model, "--companion", companion, "--weight", 0.5, "--person-weight", 1.5,
                       "--out", tmp_path / "y.pt")
    assert code == 2 and "[0, 1]" in err and not (tmp_path / "y.pt").exists()


@pytest.mark.slow
def test_nested_recipe_search_chooses_candidate_and_calibration_on_inner_folds(capsys, tmp_path):
    from trafficweaving.model.checkpoint import load_checkpoint

    data, model = tmp_path / "d.parquet", tmp_path / "m.pt"
    run(capsys, "generate", "--trials", 3, "--seed", 3, "--out", data, "--json")
    small_checkpoint(model, load_trials(data))
    folders = []
    for parts in ("all", "hold"):  # two candidate recipes: fine-tune everything, or the hold head alone
        folders.append(tmp_path / parts)
        code, out, _ = run(capsys, "crossval", "--data", data, "--folds", 3, "--init", model, "--variant", "cvae-hold",
                           "--train-parts", parts, "--hold-lr", 0.05, "--steps", 2, "--validate-every", 2, "--nested",
                           "--out", folders[-1], "--json")
        report = json.loads(out)
        assert code == 0 and report["nested"]["method"] == "inner cross-validation"
        assert set(report["folds_by_direction"]) == {"x", "y"}
    code, out, _ = run(capsys, "calibrate", "--data", data, "--folds", folders[0], "--model", model, "--folds", folders[1],
                       "--model", model, "--nested", "--samples", 4, "--temperatures", "1", "--scales", "1,2",
                       "--out", tmp_path / "c.pt", "--json")
    report = json.loads(out)
    assert code == 0 and len(report["candidates_nll_exact"]) == 2  # the recipe by likelihood, then its calibration
    best = min(range(2), key=lambda c: report["candidates_nll_exact"][c])
    assert {(r["candidate"], r["output_scale"]["x"]) for r in report["grid"]} == {(best, 1), (best, 2)}
    nested = report["nested"]
    assert len(nested["folds"]) == 3 and all(f["candidate"] in (0, 1) for f in nested["folds"])
    assert nested["fold_mean_nll_exact"] == pytest.approx(sum(f["nll_exact"] for f in nested["folds"]) / 3)
    calibrated, payload = load_checkpoint(tmp_path / "c.pt")
    assert calibrated.output_scale.tolist() == list(report["output_scale"].values()) and payload["calibration"]["nested"] == nested
    code, _, err = run(capsys, "calibrate", "--data", data, "--folds", folders[0], "--model", model, "--model", model,
                       "--out", tmp_path / "x.pt")
    assert code == 2 and "2 --model for 1 --folds" in err


@pytest.mark.slow
def test_default_model_is_shipped_trained_and_evaluates(capsys, tmp_path):
    from trafficweaving.model.checkpoint import read_checkpoint
    from trafficweaving.model.registry import default_model_path

    payload = read_checkpoint(default_model_path())
    assert "optimizer" not in payload and payload["data_command"].startswith("trafficweaving import hitl")
    assert payload["config"]["hold"] and payload["config"]["components"] == 16
    # the authors' real-data model given hold modes, then fine-tuned on the real trials by the recipe
    assert payload["init"]["path"].startswith("authors:") and payload["init"]["upgraded_to"] == "cvae-hold"
    assert "trafficweaving crossval" in payload["recipe"] and "--nested" in payload["recipe"]
    cv = payload["crossval"]  # the cross-validation that chose the steps: better than the authors' on every fold
    assert len(cv["folds"]) == 5 and all(a < b for a, b in zip(cv["nested"]["folds"], cv["reference"]["folds"]))
    calibration = payload["calibration"]  # chosen out-of-fold: 90 % position intervals at 1.5 s cover 85-95 %
    assert all(0.85 <= c <= 0.95 for c in calibration["coverage_90"].values())
    assert payload["state_dict"]["output_scale"].tolist() == pytest.approx(list(calibration["output_scale"].values()))
    nested = calibration["nested"]  # every choice made on inner folds: the estimate for new trials
    assert all(f["nll_exact"] < ref for f, ref in zip(nested["folds"], cv["reference"]["folds"]))
    assert all(0.85 <= c <= 0.95 for c in nested["coverage_90"].values())
    data = tmp_path / "fresh.parquet"  # trials the shipped model never saw (another seed)
    run(capsys, "generate", "--trials", 8, "--seed", 12345, "--out", data, "--json")
    code, out, _ = run(capsys, "evaluate", "--model", "default", "--data", data, "--json", "--max-sampled-instances", 0)
    report = json.loads(out)
    assert code == 0 and report["variant"] == "cvae-hold" and report["instances"] > 300
    # an untrained model scores about +30 nats here; the trained one predicts simulated humans
    assert report["nll_exact"] < 0 and report["nll_exact"] <= report["nll_naive"] + 0.5


def test_simulated_real_model_is_shipped_without_the_authors_weights(capsys):
    from trafficweaving.model.checkpoint import read_checkpoint
    from trafficweaving.model.registry import shipped_model_path

    payload = read_checkpoint(shipped_model_path("simulated-real"))
    assert not payload["init"]["path"].startswith("authors:") and "--init authors:" not in payload["recipe"]
    # pre-trained on simulated drivers, then fine-tuned: both data fingerprints and the recipe
    assert len(payload["init"]["data_fingerprint"]) == len(payload["data_fingerprint"]) == 64
    assert payload["init"]["data_fingerprint"] != payload["data_fingerprint"]
    assert "trafficweaving generate" in payload["recipe"]
    assert all(0.85 <= c <= 0.95 for c in payload["calibration"]["coverage_90"].values())


@pytest.mark.slow
def test_bench_plan_reports_futures_and_seconds(capsys):
    from trafficweaving.model.predictor import native_bfloat16

    code, out, _ = run(capsys, "bench", "plan", "--first-stage-samples", 1, "--finalists", 4,
                       "--second-stage-samples", 8, "--repeats", 1, "--json")
    report = json.loads(out)
    assert code == 0 and report["futures"] == 4096 + 4 * 8 and report["candidates"] == 4096
    assert report["seconds"] > 0 and report["device"] in ("cpu", "cuda")
    cpu = report["cpu"]  # the CPU's matrix instructions, on which the figure depends
    assert set(cpu) == {"model", "native_bfloat16", "int8_dot_products", "amx"} and isinstance(cpu["model"], str)
    assert all(isinstance(cpu[k], bool) for k in ("native_bfloat16", "int8_dot_products", "amx"))
    assert cpu["native_bfloat16"] == native_bfloat16()
