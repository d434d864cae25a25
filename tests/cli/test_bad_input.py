"""Bad input and faults, end to end through the console command: every case is one line on stderr
naming the option or file and what was expected, exit status 2, nothing written and nothing
replaced; interruptions clean up and end by their signal. Library-level cases live beside their
layer (test_trials*.py, test_import_*.py, test_checkpoint.py, test_planning_validation.py)."""

from __future__ import annotations

import contextlib
import functools
import io
import json
import math
import os
import signal
import subprocess
import sys
import time
import zipfile
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from trafficweaving.atomic import atomic_write
from trafficweaving.cli import build_parser, main
from trafficweaving.cli.common import SEED_MAX
from trafficweaving.model.crossval import MAX_FOLDS
from trafficweaving.model.metrics import MAX_SAMPLES
from trafficweaving.sim.generate import MAX_PAIRS, MAX_TRIALS


def run(capsys, *argv):
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def assert_one_line_error(code: int, out: str, err: str, *expected: str) -> None:
    assert code == 2, err
    assert out == "" and err.count("\n") == 1 and "Traceback" not in err, err
    for text in expected:
        assert text in err, err


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    """A small valid dataset (4 trials)."""
    path = tmp_path_factory.mktemp("data") / "d.parquet"
    assert main(["generate", "--trials", "4", "--seed", "1", "--out", str(path), "--json"]) == 0
    return path


def _with_dt(source: Path, target: Path, dt) -> Path:
    """A copy of dataset ``source`` whose metadata says time step ``dt`` (any JSON value)."""
    table = pq.read_table(source)
    metadata = dict(table.schema.metadata)
    fields = json.loads(metadata[b"trafficweaving"])
    metadata[b"trafficweaving"] = json.dumps({**fields, "dt": dt}).encode()
    pq.write_table(table.replace_schema_metadata(metadata), target)
    return target


# ---------------------------------------------------------------- numeric options
@pytest.mark.parametrize("argv, expected", [
    (["generate", "--trials", "0", "--out", "OUT"], "argument --trials: expected an integer in 1..100000, got 0"),
    (["generate", "--trials", "1.5", "--out", "OUT"], "argument --trials: expected an integer, got '1.5'"),
    (["generate", "--seed", "-1", "--out", "OUT"], "argument --seed: expected an integer in 0..4294967295, got -1"),
    (["generate", "--seed", str(2**64), "--out", "OUT"], "argument --seed"),
    (["generate", "--pairs", "0", "--out", "OUT"], "argument --pairs: expected an integer in 1..5555, got 0"),
    (["demo", "--trials", "0", "--out", "OUT"], "argument --trials"),
    (["evaluate", "--data", "DATA", "--samples", "0"], "argument --samples"),
    (["evaluate", "--data", "DATA", "--coverage-samples", "1"], "argument --coverage-samples: expected an integer in 2..25600"),
    (["evaluate", "--data", "DATA", "--ade-samples", "0"], "argument --ade-samples"),
    (["evaluate", "--data", "DATA", "--max-sampled-instances", "-1"], "argument --max-sampled-instances"),
    (["predict", "--data", "DATA", "--at", "0:5", "--samples", "0", "--out", "OUT"], "argument --samples"),
    (["calibrate", "--data", "DATA", "--folds", "F", "--model", "M", "--out", "OUT", "--samples", "1"], "argument --samples"),
    (["calibrate", "--data", "DATA", "--folds", "F", "--model", "M", "--out", "OUT", "--scales", "1,x"],
     "argument --scales: expected a number, got 'x' in the list '1,x'"),
    (["calibrate", "--data", "DATA", "--folds", "F", "--model", "M", "--out", "OUT", "--temperatures", "0"],
     "argument --temperatures: expected a finite number in (0, 100)"),
    (["train", "--data", "DATA", "--out", "OUT", "--hold-lr", "0"], "argument --hold-lr"),
    (["crossval", "--data", "DATA", "--workers", "0"], "argument --workers: expected an integer in 1.."),
    (["train", "--data", "DATA", "--out", "OUT", "--steps", "0"], "argument --steps: expected an integer >= 1"),
    (["train", "--data", "DATA", "--out", "OUT", "--lr", "nan"], "argument --lr: expected a finite number in (0, 1)"),
    (["train", "--data", "DATA", "--out", "OUT", "--lr", "2"], "argument --lr"),
    (["train", "--data", "DATA", "--out", "OUT", "--validation-fraction", "1"], "argument --validation-fraction"),
    (["train", "--data", "DATA", "--out", "OUT", "--patience", "-1"], "argument --patience"),
    (["crossval", "--data", "DATA", "--folds", "1"], "argument --folds: expected an integer in 2..100, got 1"),
    (["bench", "plan", "--threads", "0"], "argument --threads"),
    (["bench", "plan", "--threads", "50000"], "argument --threads"),
    (["bench", "plan", "--deadline", "nan"], "argument --deadline: expected a finite number"),
    (["bench", "plan", "--deadline", "inf"], "argument --deadline"),
    (["bench", "plan", "--deadline", "-1"], "argument --deadline"),
    (["bench", "plan", "--deadline", "0"], "argument --deadline"),
    (["bench", "plan", "--repeats", "0"], "argument --repeats"),
    (["bench", "plan", "--finalists", "0"], "argument --finalists"),
    (["nonsense"], "invalid choice"),
])
def test_malformed_numbers_are_refused_before_any_work(capsys, tmp_path, argv, expected):
    argv = [str(tmp_path / "out") if a == "OUT" else a for a in argv]
    code, out, err = run(capsys, *argv)
    assert_one_line_error(code, out, err, expected)
    assert not (tmp_path / "out").exists()


INTEGER_OPTIONS = {  # option: (command prefix, smallest valid value, largest or None)
    "--trials": (["generate", "--out", "x.parquet"], 1, MAX_TRIALS),
    "--pairs": (["generate", "--out", "x.parquet"], 1, MAX_PAIRS),
    "--seed": (["generate", "--out", "x.parquet"], 0, SEED_MAX),
    "--coverage-samples": (["evaluate", "--data", "d.parquet"], 2, MAX_SAMPLES),
    "--max-sampled-instances": (["evaluate", "--data", "d.parquet"], 0, None),
    "--folds": (["crossval", "--data", "d.parquet"], 2, MAX_FOLDS),
    "--threads": (["bench", "plan"], 1, os.cpu_count() or 1),
}


@functools.cache
def _parser():
    """The command's parser, built once for the hundreds of examples below (parsing leaves it as it is)."""
    return build_parser()


def _parse(argv: list[str]) -> tuple[int, str, object]:
    """(exit status, stderr, parsed namespace or None) of parsing ``argv`` without running it."""
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        try:
            return 0, "", _parser().parse_args(argv)
        except SystemExit as exc:
            return int(exc.code or 0), err.getvalue(), None


@pytest.mark.slow
@settings(max_examples=150, deadline=None, derandomize=True)
@given(option=st.sampled_from(sorted(INTEGER_OPTIONS)),
       value=st.one_of(st.integers(min_value=-2**70, max_value=2**70), st.floats(allow_nan=True, allow_infinity=True),
                       st.text(max_size=12)))
def test_integer_options_accept_exactly_their_range(option, value):
    prefix, low, high = INTEGER_OPTIONS[option]
    code, err, args = _parse([*prefix, f"{option}={value}"])
    try:
        number = int(str(value))
    except ValueError:
        number = None
    valid = number is not None and number >= low and (high is None or number <= high)
    if valid:
        assert code == 0 and getattr(args, option[2:].replace("-", "_")) == number
    else:
        assert code == 2 and err.count("\n") == 1 and option in err


@pytest.mark.slow
@settings(max_examples=150, deadline=None, derandomize=True)
@given(value=st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=12)))
def test_real_valued_options_accept_only_finite_numbers_in_their_interval(value):
    for option, prefix, inside in (
        ("--deadline", ["bench", "plan"], lambda v: 0 < v < 3600),
        ("--lr", ["train", "--data", "d", "--out", "m"], lambda v: 0 < v < 1),
        ("--validation-fraction", ["train", "--data", "d", "--out", "m"], lambda v: 0 <= v < 1),
    ):
        code, err, args = _parse([*prefix, f"{option}={value}"])
        try:
            number = float(str(value))
        except ValueError:
            number = None
        if number is not None and math.isfinite(number) and inside(number):
            assert code == 0 and getattr(args, option[2:].replace("-", "_")) == number
        else:
            assert code == 2 and err.count("\n") == 1 and option in err


# ---------------------------------------------------------------- output paths
def test_out_refuses_an_empty_path_a_folder_and_a_path_under_a_file(capsys, tmp_path):
    assert_one_line_error(*run(capsys, "generate", "--trials", 1, "--out", ""), "--out: empty path")
    assert_one_line_error(*run(capsys, "generate", "--trials", 1, "--out", tmp_path), "is a folder")
    (tmp_path / "file").write_text("x")
    assert_one_line_error(*run(capsys, "generate", "--trials", 1, "--out", tmp_path / "file" / "d.parquet"),
                          "is not a folder")
    assert_one_line_error(*run(capsys, "plot", "d.parquet", "--out", tmp_path / "file"), "--out", "is a file")


def test_out_never_replaces_a_symlink_or_its_target(capsys, tmp_path):
    target = tmp_path / "precious.txt"
    target.write_text("keep me")
    link = tmp_path / "link.parquet"
    link.symlink_to(target)
    assert_one_line_error(*run(capsys, "generate", "--trials", 1, "--out", link), "is a symbolic link")
    assert link.is_symlink() and target.read_text() == "keep me"


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="needs FIFOs")
def test_out_never_replaces_a_special_file(capsys, tmp_path):
    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    assert_one_line_error(*run(capsys, "generate", "--trials", 1, "--out", fifo), "is a special file")
    assert fifo.exists() and not fifo.is_file()
    assert_one_line_error(*run(capsys, "generate", "--trials", 1, "--out", os.devnull), "is a special file")
    assert Path(os.devnull).is_char_device()


def test_an_exception_or_interruption_inside_a_write_leaves_the_old_file_and_no_temporary(tmp_path):
    path = tmp_path / "d.bin"
    path.write_bytes(b"old")
    for exc in (RuntimeError("disk full"), KeyboardInterrupt()):
        with pytest.raises(type(exc)):
            with atomic_write(path) as f:
                f.write(b"half")
                raise exc
        assert path.read_bytes() == b"old" and sorted(p.name for p in tmp_path.iterdir()) == ["d.bin"]


# ---------------------------------------------------------------- files
@pytest.mark.slow
def test_malformed_dt_metadata_is_one_line(capsys, tmp_path, dataset):
    for value in ("abc", "0.1", None, [0.1], -0.1, 0, 1e400, float("nan")):
        bad = _with_dt(dataset, tmp_path / "bad.parquet", value)
        assert_one_line_error(*run(capsys, "stats", bad, "--json"), "bad.parquet")


def test_a_dataset_at_another_time_step_never_meets_the_model(capsys, tmp_path, dataset):
    from trafficweaving.data.trials import load_trials

    trials = load_trials(dataset)
    trials.dt = 0.2
    slow = tmp_path / "slow.parquet"
    trials.write_parquet(slow)
    for argv in (["evaluate", "--data", slow], ["train", "--data", slow, "--out", tmp_path / "m.pt", "--steps", 1],
                 ["predict", "--data", slow, "--at", "0:5", "--out", tmp_path / "f.png"]):
        assert_one_line_error(*run(capsys, *argv), "slow.parquet", "0.2", "0.1")
    assert not (tmp_path / "m.pt").exists() and not (tmp_path / "f.png").exists()


def test_stats_json_holds_no_nan_or_infinity_even_for_a_single_trial(capsys, tmp_path):
    data = tmp_path / "one.parquet"
    run(capsys, "generate", "--trials", 1, "--out", data, "--json")
    code, out, _ = run(capsys, "stats", data, "--reference", data, "--json")

    def refuse(constant):
        raise AssertionError(f"JSON holds {constant}")

    assert code == 0 and json.loads(out, parse_constant=refuse)["trials"] == 1


def test_a_corrupted_checkpoint_is_refused_not_silently_loaded(capsys, tmp_path, dataset):
    from trafficweaving.model.checkpoint import save_checkpoint
    from trafficweaving.model.cvae import CVAE

    model = tmp_path / "m.pt"
    save_checkpoint(model, CVAE())
    with zipfile.ZipFile(model) as archive:  # the largest stored tensor's bytes
        info = max((i for i in archive.infolist() if "/data/" in i.filename), key=lambda i: i.file_size)
    raw = bytearray(model.read_bytes())
    with open(model, "rb") as f:
        f.seek(info.header_offset + 26)
        name_length, extra_length = np.frombuffer(f.read(4), dtype="<u2")
    offset = info.header_offset + 30 + int(name_length) + int(extra_length) + info.file_size // 2
    raw[offset] ^= 0xFF
    model.write_bytes(bytes(raw))
    assert_one_line_error(*run(capsys, "evaluate", "--model", model, "--data", dataset), "m.pt", "SHA-256")


def test_a_hand_edited_authors_npz_is_refused(capsys, tmp_path, dataset):
    junk = tmp_path / "weights.npz"
    junk.write_bytes(os.urandom(2000))
    assert_one_line_error(*run(capsys, "evaluate", "--model", f"authors:{junk}", "--data", dataset), "weights.npz")


def test_a_bad_reference_fails_before_any_fold_trains(capsys, tmp_path, dataset):
    start = time.perf_counter()
    assert_one_line_error(*run(capsys, "crossval", "--data", dataset, "--folds", 2, "--reference", tmp_path / "nope.pt"),
                          "--reference", "nope.pt")
    junk = tmp_path / "junk.pt"
    junk.write_bytes(os.urandom(500))
    assert_one_line_error(*run(capsys, "crossval", "--data", dataset, "--folds", 2, "--reference", junk), "junk.pt")
    assert time.perf_counter() - start < 30


def test_unusable_devices_are_refused(capsys, dataset):
    for device in ("meta", "tpu9", "cuda:99", ""):
        assert_one_line_error(*run(capsys, "evaluate", "--data", dataset, "--device", device), "device")


def test_a_random_bytes_bag_is_rejected_not_fatal(capsys, tmp_path):
    bags = tmp_path / "bags"
    bags.mkdir()
    (bags / "noise.bag").write_bytes(os.urandom(4096))
    code, out, err = run(capsys, "import", "rosbag", bags, "--out", tmp_path / "r.parquet", "--json")
    assert "Traceback" not in err
    if code == 0:  # the bag is counted as rejected
        assert json.loads(out)["rejected"] == 1
    else:  # or, with no bag left at all, one line naming the folder
        assert_one_line_error(code, out, err, "bags")


# ---------------------------------------------------------------- signals
def _start(tmp_path: Path, *argv: str) -> subprocess.Popen:
    """The command as a person starts it in a terminal: SIGINT at its default even when this test
    runs as a background job (a shell starts those with SIGINT ignored, and children inherit that)."""
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    return subprocess.Popen([sys.executable, "-m", "trafficweaving", *argv], cwd=tmp_path, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))


def _wait_until_busy(process: subprocess.Popen, cpu_seconds: float, timeout: float = 60.0) -> None:
    """Wait until ``process`` has used ``cpu_seconds`` of CPU (read from /proc; 4 s of wall time
    where there is no /proc)."""
    stat = Path(f"/proc/{process.pid}/stat")
    if not stat.exists():
        time.sleep(4)
        return
    ticks, began = os.sysconf("SC_CLK_TCK"), time.monotonic()
    while time.monotonic() - began < timeout:
        fields = stat.read_text().rsplit(")", 1)[1].split()  # after "pid (name)": state is field 3
        if (int(fields[11]) + int(fields[12])) / ticks >= cpu_seconds:  # utime + stime (fields 14, 15)
            return
        time.sleep(0.2)
    raise AssertionError(f"the command used less than {cpu_seconds} s of CPU in {timeout} s")


@pytest.mark.slow
@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT])
def test_sigterm_and_ctrl_c_end_quietly_by_their_signal_and_leave_no_file(tmp_path, signum):
    process = _start(tmp_path, "generate", "--trials", str(MAX_TRIALS), "--out", "big.parquet")  # minutes of work
    _wait_until_busy(process, cpu_seconds=3.0)  # imports done, generating (however loaded the machine is)
    process.send_signal(signum)
    _, err = process.communicate(timeout=60)
    assert process.returncode == -signum  # ended by the signal itself: the shell reports 128 + signum
    assert "Traceback" not in err and "interrupted" in err
    assert list(tmp_path.iterdir()) == []
