"""Command-line interface: ``trafficweaving <command> ...`` (also ``python -m trafficweaving``).

Every reporting command takes ``--json`` and then prints exactly one JSON object on stdout.
Bad input ends with a one-line message on stderr and exit status 2, never a traceback.
"""

from __future__ import annotations

import argparse
import signal
import sys

from ..errors import InputError
from . import data, demo, drive, model, planning, report, simulation
from .common import _die_by_signal, _Parser, _raise_terminated, _Terminated

GROUPS = (data, model, planning, simulation, drive, demo, report)
"""The command groups, in the order ``--help`` lists their commands; each adds its own."""


def build_parser() -> argparse.ArgumentParser:
    """The ``trafficweaving`` parser: one subcommand per command, added by its group's module."""
    parser = _Parser(prog="trafficweaving", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)
    for group in GROUPS:
        group.add_parsers(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run one command. Bad input: one line on stderr and status 2. SIGTERM and Ctrl-C (SIGINT):
    temporary files are removed, a one-line notice is printed, and the process ends by that
    signal (status 143 and 130 in a shell); also while the parser's imports (PyTorch) load."""
    previous = signal.signal(signal.SIGTERM, _raise_terminated)
    where = "trafficweaving"
    try:
        try:
            args = build_parser().parse_args(argv)
        except SystemExit as exc:  # --help (0) or a malformed option (2, one line printed)
            return int(exc.code or 0)
        where = f"trafficweaving {args.command}"
        args.func(args)
    except InputError as exc:
        print(f"{where}: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # unwritable output path, full disk, ...
        print(f"{where}: error: {exc.filename or ''}: {exc.strerror or exc}", file=sys.stderr)
        return 2
    except (KeyboardInterrupt, _Terminated) as exc:
        signum = signal.SIGINT if isinstance(exc, KeyboardInterrupt) else signal.SIGTERM
        print(f"\n{where}: interrupted ({signal.Signals(signum).name}); no partial output was left", file=sys.stderr)
        _die_by_signal(signum)
    finally:
        signal.signal(signal.SIGTERM, previous)
    return 0
