"""The closed-loop commands: ``simulate``, ``realism`` and ``plot-episode``."""

from __future__ import annotations

import os

from ..atomic import check_output_file
from ..errors import InputError
from ..scenario import REPLAN_PERIOD_S
from ..model.spec import check_model_spec
from .common import NON_NEGATIVE, POSITIVE, SEED, _emit, _float_in, _int_at_least


def add_parsers(sub) -> None:
    """Add the closed-loop commands to the subparsers ``sub``."""
    _add_simulate(sub)
    _add_realism(sub)
    _add_plot_episode(sub)


def _add_simulate(sub) -> None:
    """``simulate``."""
    from ..model.predictor import PRECISIONS
    from ..sim.batch import MAX_EPISODES, RAY_ADDRESS_FORMS, RAY_CONNECT_TIMEOUT_S, WORKERS_PER_CPU
    from ..sim.humans import HUMAN_SPECS

    p = sub.add_parser("simulate", help="closed-loop episodes of a robot against a human, with metrics and CIs")
    p.add_argument("--episodes", type=_int_at_least(1, MAX_EPISODES), required=True,
                   help=f"episodes 0..N-1 (each from --seed and its index), N in 1..{MAX_EPISODES}")
    p.add_argument("--robot", default="planner", help="planner (default: within nuPlan's comfort limits until time "
                                                      "runs short, the human beside brakes along with it or the "
                                                      "human ahead brakes hard, then decisive; makes room beside "
                                                      "the human), "
                                                      "planner-decisive (keeps to a lane change and settles on the "
                                                      "lane centre), planner-paper (the paper's exactly), "
                                                      "planner-comfort (within nuPlan's comfort limits), "
                                                      "planner-cautious (CVaR), planner-cv or rules")
    p.add_argument("--human", required=True, help=HUMAN_SPECS)
    p.add_argument("--seed", type=SEED, default=0)
    p.add_argument("--model", default="default", help="the planner's human model: checkpoint path, default, or authors:PATH")
    timing = p.add_mutually_exclusive_group()
    timing.add_argument("--deadline", type=_float_in(0, 3600), default=REPLAN_PERIOD_S,
                        help=f"the planner's real-time deadline: plan within this many seconds (default {REPLAN_PERIOD_S}, "
                             f"the replanning period)")
    timing.add_argument("--full-budget", dest="deadline", action="store_const", const=None,
                        help="plan with the paper's fixed sample counts however long it takes (on two CPU cores "
                             "~1-3 s a plan with default, 0.22-0.44 s with --model fast: docs/fast_model.md)")
    p.add_argument("--workers", type=POSITIVE, default=1, help=f"episodes run at once (default 1: in this process), "
                   f"at most {WORKERS_PER_CPU} per CPU core here ({WORKERS_PER_CPU * (os.cpu_count() or 1)}), or "
                   f"{MAX_EPISODES} on a Ray cluster")
    p.add_argument("--threads", type=_int_at_least(1, os.cpu_count() or 1), default=1,
                   help=f"torch threads of the episodes run in this process (--workers 1), 1..{os.cpu_count() or 1} "
                        f"(default 1; e.g. 2 for the full budget in real time on two cores, docs/planner.md)")
    p.add_argument("--engine", choices=("local", "ray"), default="local",
                   help="local: a process pool; ray: Ray tasks (pip install 'trafficweaving[ray]')")
    p.add_argument("--address", help=f"with --engine ray: the Ray cluster to join, {RAY_ADDRESS_FORMS}, its head "
                   f"answering within {RAY_CONNECT_TIMEOUT_S:g} s (default: a new local instance)")
    p.add_argument("--device", default="cpu", help="the models' device: cpu (default), auto, cuda, cuda:N")
    p.add_argument("--precision", choices=PRECISIONS, default="auto", help="the planner's sampling precision (default "
                   "auto: int8 or float32-compiled, fused and compiled, where a C++ compiler is found; docs/planner.md)")
    p.add_argument("--out", default="simulation", help="output folder (default ./simulation): "
                   "episodes/episode_NNNNNN.parquet and summary.json; a rerun resumes")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_simulate)


def _add_realism(sub) -> None:
    """``realism``."""
    from ..sim.humans import HUMAN_SPECS
    from ..sim.realism import MAX_ROLLOUTS, ROLLOUT_BYTES, ROLLOUTS

    p = sub.add_parser("realism", help="closed-loop realism of a human agent on recorded trials (WOSAC-style, docs/realism.md)")
    p.add_argument("--human", help=f"the agent: {HUMAN_SPECS}")
    p.add_argument("--folds", metavar="DIR", help="instead of --human: the fold models of `crossval --out DIR` on the "
                   "same data, each driving the trials it did not train on (out-of-fold)")
    p.add_argument("--data", required=True, help="recorded trials (Parquet); every car labelled human is rolled out")
    p.add_argument("--rollouts", type=_int_at_least(2, MAX_ROLLOUTS), default=ROLLOUTS,
                   help=f"rollouts per recorded human, 2..{MAX_ROLLOUTS} (default {ROLLOUTS}; each holds about "
                        f"{ROLLOUT_BYTES // 1000} kB while they run)")
    p.add_argument("--seed", type=SEED, default=0)
    p.add_argument("--device", default="cpu", help="a model agent's device: cpu (default), auto, cuda, cuda:N")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_realism)


def _add_plot_episode(sub) -> None:
    """``plot-episode``."""
    p = sub.add_parser("plot-episode", help="the paper's Fig. 6 of an episode (or any trial), and its animation")
    p.add_argument("data", help="an episode log (simulate's DIR/episodes/episode_K.parquet) or any dataset")
    p.add_argument("--trial", type=NON_NEGATIVE, default=0, help="which trial of the file (default 0)")
    p.add_argument("--out", required=True, help="output PNG (Fig. 6: accelerations over time and (x, y) paths)")
    p.add_argument("--gif", help="also an animated GIF; for a planner's episode with each plan's chosen future "
                                 "and sampled human futures (the episode is run again to recover them)")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_plot_episode)


def cmd_simulate(args) -> None:
    """Closed-loop episodes of a robot against a human (:mod:`trafficweaving.sim.batch`)."""
    from ..sim.batch import simulate, summary_table

    summary = simulate(args.episodes, args.robot, args.human, seed=args.seed, workers=args.workers,
                       engine=args.engine, address=args.address, out=args.out,
                       model=check_model_spec(args.model, "--model"), deadline=args.deadline, device=args.device,
                       precision=args.precision, progress=not args.json, threads=args.threads)
    _emit(args, summary, summary_table(summary))


def cmd_realism(args) -> None:
    """Closed-loop realism of a human agent on recorded trials (:mod:`trafficweaving.sim.realism`)."""
    from ..sim.realism import realism_of

    summary = realism_of(args.data, human=args.human, folds=args.folds, rollouts=args.rollouts, seed=args.seed,
                         device=args.device, progress=not args.json)
    groups = ", ".join(f"{g} {v:.3f}" for g, v in summary["groups"].items())
    rates = "; ".join(f"{k.replace('_', ' ')} {100 * summary[k + '_rate']:.1f} % (real {100 * summary['real_' + k + '_rate']:.1f} %)"
                      for k in ("swap", "off_road", "collision", "at_fault_collision"))
    _emit(args, summary, f"{summary['human']}: realism {summary['realism']:.3f} ({groups}) over {summary['streams']} "
                         f"recorded humans × {summary['rollouts']} rollouts\n{rates}")


def cmd_plot_episode(args) -> None:
    """The paper's Fig. 6 of one trial or episode, and optionally its animation."""
    from ..atomic import same_file
    from ..viz.episode_figures import episode_figures

    out = check_output_file(args.out, "--out")
    gif = check_output_file(args.gif, "--gif") if args.gif is not None else None
    if gif is not None and same_file(out, gif):
        raise InputError(f"--gif {gif}: the same file as --out {out} (expected another path: the animation would "
                         f"replace the figure)")
    payload = episode_figures(args.data, args.trial, out, gif)
    _emit(args, payload, "\n".join(f"wrote {path}" for key, path in payload.items() if key != "plans_drawn")
          + (f" ({payload['plans_drawn']} plans drawn)" if gif is not None else ""))
