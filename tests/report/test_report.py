"""``trafficweaving report``: tables and figures rendered from tiny real runs of ``simulate``,
``evaluate --json`` and ``realism --json`` carry the runs' numbers, are byte-identical on a rerun,
and bad inputs are refused in one line naming the path."""

from __future__ import annotations

import contextlib
import io
import json
import os
import re
import shutil
from pathlib import Path

import pytest
from PIL import Image

from trafficweaving.errors import InputError
from trafficweaving.report import render_report


def _command_json(args: list[str], path: Path) -> Path:
    """Run a ``trafficweaving`` command with ``--json`` and save what it prints to ``path``."""
    from trafficweaving.cli import main

    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        assert main([*args, "--json"]) == 0
    path.write_text(printed.getvalue())
    return path


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> dict[str, Path]:
    """Two simulate run folders (the rule robot against two humans), two evaluate files (the shipped
    model at two seeds) and two realism files, all made by the real commands at tiny sizes."""
    from trafficweaving.sim.batch import simulate
    from trafficweaving.sim.generate import generate_trials

    base = tmp_path_factory.mktemp("runs")
    made = {}
    for human in ("synthetic", "constant-velocity"):
        made[f"sim_{human}"] = base / f"rules_{human}"
        simulate(2, "rules", human, seed=0, out=made[f"sim_{human}"])
    data = base / "one_trial.parquet"
    generate_trials(1, seed=4)[0].write_parquet(data)
    for seed in (0, 1):
        made[f"eval_{seed}"] = _command_json(["evaluate", "--model", "default", "--data", str(data), "--samples", "2",
                                              "--coverage-samples", "4", "--ade-samples", "2",
                                              "--max-sampled-instances", "10", "--seed", str(seed)],
                                             base / f"evaluate_seed{seed}.json")
    for human in ("rules", "constant-velocity"):
        made[f"realism_{human}"] = _command_json(["realism", "--human", human, "--data", str(data), "--rollouts", "2"],
                                                 base / f"realism_{human}.json")
    return made


@pytest.fixture(scope="module")
def report(runs, tmp_path_factory) -> tuple[dict, Path]:
    """The report of every run, in a fresh folder."""
    out = tmp_path_factory.mktemp("report") / "results"
    return render_report([str(p) for p in runs.values()], out), out


def _rows(text: str, first: str, nth: int = 0) -> list[dict[str, str]]:
    """The rows of the ``nth`` Markdown table whose header starts with ``first``, as header -> cell."""
    lines = text.splitlines()
    start = [i for i, line in enumerate(lines) if line.startswith(f"| {first} |")][nth]
    header = [cell.strip() for cell in lines[start].strip("|").split("|")]
    rows = []
    for line in lines[start + 2:]:
        if not line.startswith("|"):
            break
        cells = line[2:-2].split(" | ")
        assert len(cells) == len(header), line
        rows.append(dict(zip(header, cells)))
    return rows


def _numbers(cell: str) -> list[float]:
    return [float(v) for v in re.findall(r"-?\d+(?:\.\d+)?", cell)]


def _close(cell: str, values: list, digits: int, scale: float = 1.0) -> bool:
    """Whether the numbers in ``cell`` are ``values`` (times ``scale``) printed to ``digits`` places."""
    expected = [scale * v for v in values]
    return len(_numbers(cell)) == len(expected) and all(
        abs(a - b) <= 0.5 * 10 ** -digits + 1e-9 for a, b in zip(_numbers(cell), expected))


@pytest.mark.slow
def test_the_report_lists_every_run_and_writes_a_table_and_a_figure_per_kind(runs, report):
    result, out = report
    assert [(r["path"], r["kind"]) for r in result["runs"]] == [
        (str(p), "simulate" if name.startswith("sim") else "evaluate" if name.startswith("eval") else "realism")
        for name, p in runs.items()]
    assert [r["label"] for r in result["runs"]] == ["rules vs synthetic, seed 0, 2 episodes",
                                                    "rules vs constant-velocity, seed 0, 2 episodes",
                                                    "default", "default", "rules", "constant-velocity"]
    names = ["closed_loop", "models", "realism"]
    assert result["tables"] == [str(out / f"{n}.md") for n in names]
    assert result["figures"] == [str(out / n) for n in ("closed_loop_score.png", "models_nll_by_direction.png",
                                                         "realism.png")]
    for path in result["figures"]:
        with Image.open(path) as image:
            assert image.format == "PNG" and min(image.size) > 100
            image.verify()
    for path, figure in zip(result["tables"], result["figures"]):
        text = Path(path).read_text()
        caption = text.splitlines()[0]
        assert caption.startswith(("Closed loop", "Human models", "Realism")) and text.splitlines()[1] == ""
        assert f"({Path(figure).name})" in text.splitlines()[-1]


def test_closed_loop_rows_carry_the_summaries_numbers(runs, report):
    text = (report[1] / "closed_loop.md").read_text()
    caption = text.splitlines()[0]
    for human in ("synthetic", "constant-velocity"):
        assert f"`{runs[f'sim_{human}']}` (seed 0, 2 episodes, model `default`, full budget)" in caption
    rows = _rows(text, "robot")
    assert [(r["robot"], r["human"]) for r in rows] == [("`rules`", "`constant-velocity`"), ("`rules`", "`synthetic`")]
    for row in rows:
        summary = json.loads((Path(row["run"].strip("`")) / "summary.json").read_text())
        assert row["human"] == f"`{summary['human']}`" and int(row["episodes"]) == summary["episodes"] == 2
        assert _close(row["score (95 % CI)"], [summary["score"]["mean"], *summary["score"]["ci95"]], 3)
        success = summary["success_rate"]
        assert _close(row["success (95 % CI)"], [success["rate"], *success["ci95"]], 1, 100)
        collisions = [summary["collisions"], summary["robot_at_fault_collisions"]]
        assert _numbers(row["collisions (robot at fault)"]) == collisions
        assert int(row["near collisions"]) == summary["near_collisions"]
        assert _close(row["smallest gap (m)"], [summary["min_gap_m"]["min"]], 2)
        assert _close(row["lane reversals per episode"], [summary["lane_reversals"]["mean"]], 2)
        assert _close(row["comfort"], [summary["score_parts"]["comfort"]["mean"]], 1, 100)


def test_model_and_realism_rows_carry_the_files_numbers(runs, report):
    text = (report[1] / "models.md").read_text()
    rows = _rows(text, "model")
    assert [r["file"] for r in rows] == [f"`{runs['eval_0']}`", f"`{runs['eval_1']}`"]  # label, then path
    for row, position in zip(rows, _rows(text, "model", 1)):
        result = json.loads(Path(row["file"].strip("`")).read_text())
        assert int(row["instances"]) == result["instances"] and row["variant"] == f"`{result['variant']}`"
        for column, key in (("exact", "nll_exact"), ("naive", "nll_naive")):
            assert _close(row[column], [result[key]], 3)
        assert row["importance-sampled"] == ("n/a" if result["nll_is"] is None else f"{result['nll_is']:.3f}")
        for d in ("x", "y"):
            assert _close(row[d], [result["nll_exact_by_direction"][d]], 3)
        for phase, value in result["nll_exact_by_phase"].items():
            cell, count = row[f"{phase} (instances)"], value["instances"]
            if value["nll_exact"] is None:
                assert cell == f"n/a ({count})"
            else:
                assert _close(cell, [value["nll_exact"], count], 3)
        assert _close(position["coverage y 1.5 s (50 / 90 %)"], list(result["coverage"]["y"]["1.5"].values()), 1, 100)
        assert _close(position["minADE (m)"], [result["min_ade_m"]], 3)
        assert _close(position["minFDE (m)"], [result["min_fde_m"]], 3)

    rows = _rows((report[1] / "realism.md").read_text(), "agent")
    assert [r["agent"] for r in rows] == ["`constant-velocity`", "`rules`"]
    for row in rows:
        result = json.loads(Path(row["file"].strip("`")).read_text())
        assert _close(row["realism"], [result["realism"]], 3)
        for group, value in result["groups"].items():
            assert _close(row[group], [value], 3)
        assert _close(row["swap rate (real)"], [result["swap_rate"], result["real_swap_rate"]], 1, 100)
        assert _close(row["collision rate (real)"], [result["collision_rate"], result["real_collision_rate"]], 1, 100)
        assert int(row["rollouts"]) == result["rollouts"] == 2


@pytest.mark.slow
def test_a_rerun_writes_the_same_bytes(runs, report, tmp_path):
    result, out = report
    before = {name: (out / name).read_bytes() for name in os.listdir(out)}
    again = render_report([str(p) for p in runs.values()], out)
    assert again == result and {name: (out / name).read_bytes() for name in os.listdir(out)} == before
    only_realism = render_report([str(runs["realism_rules"])], tmp_path / "one")
    assert only_realism["tables"] == [str(tmp_path / "one" / "realism.md")] and len(only_realism["figures"]) == 1


def _refused(runs: list, out, *expected: str) -> None:
    with pytest.raises(InputError) as caught:
        render_report(runs, out)
    message = str(caught.value)
    assert "\n" not in message and all(part in message for part in expected), message


def test_bad_inputs_are_refused_naming_the_path(runs, tmp_path):
    out = tmp_path / "out"
    _refused([], out, "non-empty list")
    _refused([str(tmp_path / "missing")], out, str(tmp_path / "missing"), "no such file or folder")
    (tmp_path / "empty").mkdir()
    _refused([str(tmp_path / "empty")], out, str(tmp_path / "empty"), "without summary.json")
    bad = tmp_path / "bad.json"
    for content, expected in (("{not json", "not valid JSON"), ("[1, 2]", "not an object"),
                              ('{"instances": 3, "nll_exact": NaN}', "NaN"), (b"\xff{}", "not UTF-8"),
                              ('{"instances": 3, "nll_exact": 1.0, "nll_is": null, "nll_naive": 2.0}',  # train --json
                               "without the keys")):
        bad.write_bytes(content if isinstance(content, bytes) else content.encode())
        _refused([str(bad)], out, str(bad), expected)
    summary = json.loads((runs["sim_synthetic"] / "summary.json").read_text())
    broken = tmp_path / "broken"
    broken.mkdir()
    for change, expected in (({"episodes": "2"}, "episodes is '2'"), ({"score": {"mean": 0.5}}, "no score.ci95"),
                             ({"success_rate": [1]}, "success_rate is [1] (expected an object)")):
        (broken / "summary.json").write_text(json.dumps({**summary, **change}))
        _refused([str(broken)], out, str(broken / "summary.json"), expected)
    realism = json.loads(runs["realism_rules"].read_text())
    bad.write_text(json.dumps({**realism, "groups": {"road": True}}))
    _refused([str(bad)], out, str(bad), "groups.road is True")
    _refused([str(runs["eval_0"]), str(runs["eval_0"])], out, str(runs["eval_0"]), "given twice")
    assert not out.exists()  # nothing written for a refused input


def test_an_output_folder_that_cannot_be_written_is_refused(runs, tmp_path):
    run = [str(runs["realism_rules"])]
    (tmp_path / "file").write_text("")
    _refused(run, tmp_path / "file", "--out", str(tmp_path / "file"), "is a file")
    _refused(run, tmp_path / "file" / "below", "--out", "not a folder")
    shutil.copy(runs["realism_rules"], tmp_path / "realism.md")  # an input named like an output
    _refused([str(tmp_path / "realism.md")], tmp_path, "would replace the input")
    if os.geteuid() != 0:
        locked = tmp_path / "locked"
        locked.mkdir(mode=0o500)
        _refused(run, locked / "out", "--out", str(locked / "out"), "cannot be written")
        locked.chmod(0o700)
    elif Path("/proc/self").is_dir():  # root writes into any folder, but nothing can be created in /proc
        _refused(run, "/proc/trafficweaving-report", "--out /proc/trafficweaving-report", "cannot be written")


def test_tick_labels_cut_paths_in_agent_specs_to_file_names():
    from trafficweaving.viz.result_figures import short_spec

    assert short_spec("model:authors:/a/b/weights.npz") == "model:authors:weights.npz"
    assert short_spec("replay:runs/hitl.parquet#3") == "replay:hitl.parquet#3"
    assert short_spec("model:driver") == "model:driver"
