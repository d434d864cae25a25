"""The browser command: ``drive``."""

from __future__ import annotations

import os

from ..atomic import check_output_folder
from ..scenario import REPLAN_PERIOD_S
from ..model.spec import check_model_spec
from .common import _float_in, _int_at_least


def add_parsers(sub) -> None:
    """Add ``drive`` to the subparsers ``sub``."""
    from ..web.options import COUNTDOWN_S, PLAN_DEADLINE_S, ROOM_KINDS

    p = sub.add_parser("drive", help="drive the human car against the planner in the browser (or two people at "
                                     "two browsers: --mode human-human)")
    p.add_argument("--port", type=_int_at_least(0, 65535), default=8000, help="TCP port (default 8000; 0: any free port)")
    p.add_argument("--host", default="127.0.0.1", help="address to serve on (default 127.0.0.1: this machine only; "
                   "another address needs the printed link's key and each room's token)")
    p.add_argument("--allowed-host", action="append", default=[], metavar="NAME[:PORT]",
                   help="another name pages may use for this server (repeatable; default port: --port); requests "
                        "for any other host than the served address are refused")
    p.add_argument("--no-browser", action="store_true", help="do not open the page in the browser")
    p.add_argument("--mode", choices=ROOM_KINDS, default="robot",
                   help="robot: a person against the planner; human-human: rooms of two browsers, one person each")
    p.add_argument("--model", default="default", help="the planner's human model: checkpoint path, default, or authors:PATH")
    p.add_argument("--out", default="drives", help="folder the trials are recorded in (default: drives)")
    p.add_argument("--deadline", type=_float_in(0, REPLAN_PERIOD_S), default=PLAN_DEADLINE_S,
                   help=f"the planner's real-time deadline per plan, s, in (0, {REPLAN_PERIOD_S:g}) (default "
                        f"{PLAN_DEADLINE_S})")
    p.add_argument("--threads", type=_int_at_least(1, os.cpu_count() or 1),
                   help=f"planner CPU threads, 1..{os.cpu_count() or 1} (default: all cores but one)")
    p.add_argument("--countdown", type=_int_at_least(0, 10), default=COUNTDOWN_S,
                   help=f"seconds of countdown before a trial, 0..10 (default {COUNTDOWN_S})")
    p.set_defaults(func=cmd_drive, json=False)


def cmd_drive(args) -> None:
    """The browser human-in-the-loop app (:mod:`trafficweaving.web`)."""
    from ..web.room import DriveConfig
    from ..web.server import serve

    config = DriveConfig(mode=args.mode, countdown_s=args.countdown, model=check_model_spec(args.model, "--model"),
                         deadline=args.deadline, threads=args.threads)
    serve(config, args.host, args.port, check_output_folder(args.out, "--out"), allowed_hosts=args.allowed_host,
          open_browser=not args.no_browser)
