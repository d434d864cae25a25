"""The ``trafficweaving`` command's entry point: imports the package, then runs
:func:`trafficweaving.cli.main`.

Importing :mod:`trafficweaving` (Gymnasium and NumPy) happens before the CLI can install its own
handling of Ctrl-C, so this module, which imports nothing of the package's, answers a Ctrl-C during
that import with one line instead of the interpreter's traceback, and ends by SIGINT (status 130 in
a shell) as the CLI does.
"""

import os
import signal
import sys


def main() -> int:
    try:
        from trafficweaving.cli import main as run
    except KeyboardInterrupt:
        print("\ntrafficweaving: interrupted (SIGINT) while starting; nothing was written", file=sys.stderr)
        sys.stderr.flush()
        signal.signal(signal.SIGINT, signal.SIG_DFL)
        os.kill(os.getpid(), signal.SIGINT)
        return 128 + signal.SIGINT  # if the signal could not end the process
    return run()
