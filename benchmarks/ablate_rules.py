"""Ablation of the default planner's driving rules: each rule removed in turn, against every human.

For each variant (``default``, then the default style with one rule removed, :data:`ABLATIONS`)
and each human spec, runs ``--episodes`` closed-loop episodes in real time (the planner's 0.3 s
deadline, as `trafficweaving simulate` runs them) and prints a Markdown table: score (mean),
success, collisions (robot at fault), near collisions, comfort, safety overrides, per variant
and human; ``--json`` prints the rows instead. Episodes are paired: every variant meets the same
humans and starts (the same seed and episode indices). Real-time runs depend on the machine's
speed: compare variants within one run, on an otherwise idle machine.

    python benchmarks/ablate_rules.py [--episodes 20] [--scenario-episodes 6] [--seed 4] [--workers 2]
        [--humans synthetic model:driver ...] [--rules default no-safety-layer ...] [--json]

The table in docs/driving.md (Ablation) is this script's output.
"""

from __future__ import annotations

import argparse
import json
import sys
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from pathlib import Path

from trafficweaving.planning.styles import STYLES, DrivingStyle
from trafficweaving.sim.scenarios import SCENARIOS


def _everywhere(style: DrivingStyle, **changes) -> DrivingStyle:
    """``style`` and its fallbacks with ``changes``."""
    fallbacks = {name: replace(getattr(style, name), **changes) if getattr(style, name) else None
                 for name in ("fallback", "safety_fallback")}
    return replace(style, **changes, **fallbacks)


ABLATIONS = {
    "default": lambda s: s,
    "no safety layer": lambda s: _everywhere(s, safety_layer=False),
    "no set-out rule": lambda s: _everywhere(s, set_out_gap=0.0),
    "no stand-off exit": lambda s: _everywhere(s, standoff_exit_cost=0.0),
    "no progress cost": lambda s: _everywhere(s, progress_cost=0.0),
    "no time fallback": lambda s: replace(s, fallback_within=0.0),
    "no stand-off fallback": lambda s: replace(s, standoff_within=0.0),
}
"""The variants by name: the default style (``planner``) with one rule removed."""

_WORKER: dict = {}


def _start_worker(rule: str, human: str, seed: int) -> None:
    import torch

    from trafficweaving.model.predictor import HumanPredictor
    from trafficweaving.model.registry import load_model
    from trafficweaving.planning.mpc import MPCPolicy
    from trafficweaving.planning.planner import Planner
    from trafficweaving.scenario import REPLAN_PERIOD_S
    from trafficweaving.sim.episodes import EpisodeSpec
    from trafficweaving.sim.humans import human_agent

    torch.set_num_threads(1)
    style = ABLATIONS[rule](STYLES["planner"])
    robot = MPCPolicy(Planner(HumanPredictor(load_model("default", "cpu")), style=style), deadline=REPLAN_PERIOD_S)
    _WORKER.update(agents=(robot, human_agent(human, "cpu")),
                   spec=EpisodeSpec("planner", human, seed, deadline=REPLAN_PERIOD_S))


def _episode(index: int) -> dict:
    from trafficweaving.sim.episodes import run_episode

    return run_episode(_WORKER["spec"], index, _WORKER["agents"]).record


def run(rule: str, human: str, episodes: int, seed: int, workers: int) -> dict:
    """One row: ``episodes`` episodes of the ``rule`` variant against ``human``."""
    from trafficweaving.sim.metrics import aggregate

    with ProcessPoolExecutor(workers, initializer=_start_worker, initargs=(rule, human, seed)) as pool:
        records = list(pool.map(_episode, range(episodes)))
    summary = aggregate(records)
    return {"rule": rule, "human": human, "episodes": episodes, "score": summary["score"]["mean"],
            "success": summary["success_rate"]["count"], "collisions": summary["collisions"],
            "at_fault": summary["robot_at_fault_collisions"], "near_collisions": summary["near_collisions"],
            "comfort": summary["score_parts"]["comfort"]["mean"],
            "safety_overrides": summary["safety_overrides"]["episodes"]}


def table(rows: list[dict]) -> str:
    """The rows as a Markdown table, one line per variant and human."""
    lines = ["| removed | human | episodes | score | success | collisions (at fault) | near collisions | comfort | "
             "safety overrides |", "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['rule']} | `{r['human']}` | {r['episodes']} | {r['score']:.3f} | {r['success']} | "
                     f"{r['collisions']} ({r['at_fault']}) | {r['near_collisions']} | {100 * r['comfort']:.0f} % | "
                     f"{r['safety_overrides']} |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=20, help="episodes per variant and human (default 20)")
    parser.add_argument("--scenario-episodes", type=int, default=6, help="episodes per scenario human (default 6)")
    parser.add_argument("--seed", type=int, default=4)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--data", default="hitl.parquet", help="the recorded trials the replayed humans replay "
                        "(`trafficweaving import hitl ... --out hitl.parquet`)")
    parser.add_argument("--humans", nargs="+", help="human specs (default: synthetic, model:driver, the authors' "
                        "model, the replays and their perturbations, every scenario)")
    parser.add_argument("--authors", default=str(Path(__file__).resolve().parents[2] / "shared/reference/authors_model/"
                                                 "weights.npz"), help="the authors' weights file")
    parser.add_argument("--rules", nargs="+", choices=list(ABLATIONS), default=list(ABLATIONS))
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    humans = args.humans or ["synthetic", "model:driver", f"model:authors:{args.authors}", f"replay:{args.data}",
                             f"replay:{args.data}@1.5,2", *(f"scenario:{name}" for name in SCENARIOS)]
    rows = []
    for human in humans:
        episodes = args.scenario_episodes if human.startswith("scenario:") else args.episodes
        for rule in args.rules:
            rows.append(run(rule, human, episodes, args.seed, args.workers))
            print(json.dumps(rows[-1]) if args.json else table(rows[-1:]).splitlines()[-1], file=sys.stderr, flush=True)
    print(json.dumps(rows) if args.json else table(rows))


if __name__ == "__main__":
    main()
