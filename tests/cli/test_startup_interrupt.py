"""Ctrl-C while the ``trafficweaving`` command starts (importing Gymnasium, NumPy and PyTorch):
one line on stderr, no traceback, and the process ends by SIGINT."""

import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

COMMAND = Path(sys.executable).parent / "trafficweaving"


@pytest.mark.slow
@pytest.mark.skipif(not COMMAND.exists(), reason="the trafficweaving console script is not installed in this environment")
@pytest.mark.parametrize("delay_s", [0.15, 0.3, 1.0])
def test_ctrl_c_during_start_up_prints_one_line(delay_s, tmp_path):
    # `stats` of a missing file: cheap once started, but it imports the whole package first; SIGINT at its
    # default, as in a terminal, even when this test runs as a background job (started with SIGINT ignored)
    process = subprocess.Popen([str(COMMAND), "stats", str(tmp_path / "missing.parquet")], stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE, text=True,
                               preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    time.sleep(delay_s)
    process.send_signal(signal.SIGINT)
    out, err = process.communicate(timeout=60)
    lines = [line for line in err.splitlines() if line.strip()]
    assert "Traceback" not in err
    if process.returncode == 2:  # it finished before the signal: its own one-line error
        assert len(lines) == 1 and "missing.parquet" in lines[0]
        return
    assert process.returncode == -signal.SIGINT, err
    assert len(lines) == 1 and "interrupted (SIGINT)" in lines[0], err
    assert out == ""
