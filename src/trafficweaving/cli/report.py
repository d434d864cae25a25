"""The results command: ``report``."""

from __future__ import annotations

from .common import _emit


def add_parsers(sub) -> None:
    """Add ``report`` to the subparsers ``sub``."""
    p = sub.add_parser("report", help="results tables (Markdown) and figures (PNG) from simulate, evaluate and "
                                      "realism outputs")
    p.add_argument("runs", nargs="+", metavar="RUN", help="a simulate run folder (with its summary.json), or an "
                   "evaluate --json or realism --json output file")
    p.add_argument("--out", required=True, help="output folder for the tables and figures")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_report)


def cmd_report(args) -> None:
    """Render the results of the runs (:mod:`trafficweaving.report`)."""
    from ..report import render_report

    result = render_report(args.runs, args.out, progress=not args.json)
    _emit(args, result, "\n".join(f"wrote {path}" for path in [*result["tables"], *result["figures"]]))
