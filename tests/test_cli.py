"""The console command: JSON contracts of DESIGN.md §5 and one-line errors on bad input."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

from trafficweaving.cli import main

HITL_DIR = Path(__file__).resolve().parents[2] / "shared/reference/hitl"


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


def test_human_readable_stats_show_table1(capsys, tmp_path):
    data = tmp_path / "d.parquet"
    run(capsys, "generate", "--trials", 40, "--out", data, "--json")
    code, out, _ = run(capsys, "stats", data)
    assert code == 0 and "Table I" in out and "paper 38.2%" in out


@pytest.mark.skipif(not HITL_DIR.is_dir(), reason="the authors' HITL recordings are not present")
def test_import_hitl_gives_30_trials_and_compares_behaviour(capsys, tmp_path):
    hitl = tmp_path / "hitl.parquet"
    code, out, _ = run(capsys, "import", "hitl", *sorted(HITL_DIR.glob("*.jld")), "--out", hitl, "--json")
    assert code == 0 and json.loads(out)["trials"] == 30
    data = tmp_path / "d.parquet"
    run(capsys, "generate", "--trials", 40, "--out", data, "--json")
    code, out, _ = run(capsys, "stats", data, "--reference", hitl, "--json")
    comparison = json.loads(out)["behaviour_vs_reference"]
    assert comparison["speed"]["real"]["count"] > 1000 and comparison["speed"]["wasserstein"] >= 0


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
    (["generate", "--trials", "0", "--out", "{tmp}/x.parquet"], "--trials must be a positive integer"),
    (["import", "hitl", "{tmp}/junk.parquet", "--out", "{tmp}/x.parquet"], "junk.parquet"),
    (["import", "rosbag", "{tmp}/nowhere", "--out", "{tmp}/x.parquet"], "nowhere"),
])
def test_bad_input_is_one_line_on_stderr_with_exit_2(capsys, tmp_path, argv, expected):
    (tmp_path / "junk.parquet").write_text("not parquet")
    code, out, err = run(capsys, *[a.format(tmp=tmp_path) for a in argv])
    assert code == 2 and out == ""
    assert expected in err and err.count("\n") == 1 and "Traceback" not in err


def test_python_dash_m_entry_point(tmp_path):
    result = subprocess.run([sys.executable, "-m", "trafficweaving", "generate", "--trials", "20",
                             "--out", str(tmp_path / "d.parquet"), "--json"], capture_output=True, text=True)
    assert result.returncode == 0 and json.loads(result.stdout)["trials"] == 20
