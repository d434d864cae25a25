"""The command-line package: it starts without PyTorch, every function in it is short, and the
``report`` command prints what it wrote (the tables themselves are tested in test_report.py)."""

import ast
import json
import subprocess
import sys
from pathlib import Path

import pytest

import trafficweaving.cli
from trafficweaving.cli import build_parser, main
from trafficweaving.sim.batch import simulate

CLI = Path(trafficweaving.cli.__file__).parent


@pytest.mark.slow
def test_importing_the_cli_does_not_import_torch():
    code = "import sys, trafficweaving.cli; print('torch' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "False"


@pytest.mark.slow
def test_no_function_of_the_cli_is_over_80_lines():
    long = [(path.name, node.name, node.end_lineno - node.lineno + 1)
            for path in CLI.glob("*.py") for node in ast.walk(ast.parse(path.read_text()))
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and node.end_lineno - node.lineno >= 80]
    assert long == []


def test_every_group_adds_its_commands_in_order():
    commands = list(build_parser()._subparsers._group_actions[0].choices)
    assert commands == ["generate", "import", "stats", "plot", "train", "crossval", "distil", "calibrate", "mix", "evaluate",
                        "predict", "bench", "simulate", "realism", "plot-episode", "drive", "demo", "report"]


@pytest.fixture(scope="module")
def run_folder(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("sim") / "rules"
    simulate(2, "rules", "synthetic", seed=0, out=out)
    return out


@pytest.mark.slow
def test_report_json_names_the_files_it_wrote(capsys, run_folder, tmp_path):
    assert main(["report", str(run_folder), "--out", str(tmp_path / "report"), "--json"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert [run["kind"] for run in result["runs"]] == ["simulate"]
    assert result["tables"] and all(Path(p).is_file() for p in result["tables"] + result["figures"])


def test_report_text_is_one_line_per_written_file(capsys, run_folder, tmp_path):
    assert main(["report", str(run_folder), "--out", str(tmp_path / "report")]) == 0
    lines = capsys.readouterr().out.splitlines()
    written = sorted(str(p) for p in (tmp_path / "report").iterdir())
    assert sorted(line.removeprefix("wrote ") for line in lines) == written and all(line.startswith("wrote ") for line in lines)


def test_report_of_a_missing_run_is_one_line(capsys, tmp_path):
    code = main(["report", str(tmp_path / "missing"), "--out", str(tmp_path / "report"), "--json"])
    out, err = capsys.readouterr()
    assert code == 2 and out == "" and err.count("\n") == 1 and "missing" in err
    assert not (tmp_path / "report").exists()
