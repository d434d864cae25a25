"""The main job, end to end on the shipped defaults (``trafficweaving demo``, ``make demo``).

1. a human–human dataset from the simulated drivers (the study's 1105 trials), its Table I next to
   the paper's, and its figures;
2. the authors' real human-in-the-loop recordings, when at hand, imported and compared with the
   simulated drivers;
3. the shipped human model: its scores on the real trials (in-sample, cross-validated and
   calibrated, as stored in the checkpoint) and a figure of its sampled futures (paper Fig. 3);
4. one full-budget plan of the paper's planner against that model, drawn;
5. closed loop: the planner with the shipped model against a real-time deadline (0.3 s per plan) drives
   against simulated drivers and against a model-driven human (the authors' model when at hand,
   else the shipped one), with the metrics of each batch, the paper's Fig. 6 of an episode and
   its animation (each plan's chosen future and the human futures it sampled).
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Callable

from .data.trials import TrialSet
from .errors import InputError
from .scenario import STUDY_TRIALS

DEFAULT_HITL_DIRS = ("../shared/reference/hitl", "shared/reference/hitl")
"""Where the demo looks for the authors' ``.jld`` recordings (relative to the working directory)."""
DEMO_REAL_PICKS = [(2, 1, 10), (7, 1, 20), (12, 1, 25)]
"""(trial, human agent, t) of the real trials drawn in the demo's prediction figure."""
DEMO_SYNTHETIC_PICKS = [(0, 0, 12), (1, 1, 20)]
"""(trial, human agent, t) drawn when no real trials are at hand."""
DEMO_EPISODES = 4
"""Closed-loop episodes per human in the demo (``trafficweaving simulate`` runs as many as asked)."""
DEMO_DEADLINE = 0.3
"""The demo's planner plans to a real-time deadline: each plan within the 0.3 s replanning period, s."""


def find_hitl_dir(explicit: str | Path | None) -> Path | None:
    """The folder of the authors' human-in-the-loop ``.jld`` files: ``explicit`` if given (it must
    be a folder), else the first of :data:`DEFAULT_HITL_DIRS` that exists, else None."""
    if explicit is not None:
        path = Path(explicit)
        if not path.is_dir():
            raise InputError(f"--hitl {path}: not a folder (expected the folder of the authors' .jld files)")
        if not any(path.glob("*.jld")):
            raise InputError(f"--hitl {path}: no .jld files in it (expected the authors' recordings)")
        return path
    return next((Path(d) for d in DEFAULT_HITL_DIRS if any(Path(d).glob("*.jld"))), None)


def run_demo(out: str | Path, trials: int = STUDY_TRIALS, seed: int = 0, hitl: str | Path | None = None,
             log: Callable[[str], None] = print) -> None:
    """Run the main job into folder ``out`` (datasets and ``figures/``), reporting through ``log``."""
    from .data.behaviour import behaviour_samples, compare_behaviour, format_comparison
    from .sim.generate import generate_trials
    from .data.stats import format_table1, format_table1_test, table1, table1_test
    from .viz.figures import write_dataset_figures

    out = Path(out)
    hitl_dir = find_hitl_dir(hitl)
    start = time.perf_counter()
    dataset, report = generate_trials(trials, seed=seed, progress=True)
    dataset.write_parquet(out / "human_human.parquet")
    log(f"generated {len(dataset)} valid human–human trials in {time.perf_counter() - start:.1f} s "
        f"({report.simulated} simulated, rejected {report.rejected}) -> {out / 'human_human.parquet'}")
    t1 = table1(dataset)
    log(format_table1(t1["table1"], t1["counts"]))
    log(format_table1_test(table1_test(t1["table1"], t1["counts"])))

    reference = None
    if hitl_dir is not None:
        from .data.hitl import read_hitl

        reference = read_hitl(sorted(hitl_dir.glob("*.jld")))
        reference.write_parquet(out / "hitl.parquet")
        comparison = compare_behaviour(behaviour_samples(dataset, "human"), behaviour_samples(reference, "human"))
        log(f"\nSimulated human drivers vs the {len(reference)} real human-in-the-loop trials in {hitl_dir}:")
        log(format_comparison(comparison))
    else:
        log("\n(authors' human-in-the-loop recordings not found; pass --hitl DIR to compare with real drivers)")
    for path in write_dataset_figures(dataset, out / "figures", reference):
        log(f"wrote {path}")
    _human_model_report(dataset, reference, out / "figures", log)
    _plan_figure(out / "figures", log)
    _closed_loop(out, hitl_dir, log)


def _score(value) -> str:
    return "n/a" if value is None else f"{value:.3f}"


def _human_model_report(dataset: TrialSet, reference: TrialSet | None, figures: Path, log: Callable[[str], None]) -> None:
    """The shipped human model on the real trials (when at hand) and its predictions as a figure."""
    from .model.checkpoint import load_checkpoint
    from .model.evaluate import evaluate
    from .model.exemplars import build_exemplars
    from .model.mixture import describe
    from .model.registry import default_model_path
    from .viz.model_figures import plot_predictions

    model, payload = load_checkpoint(default_model_path())
    if reference is not None:
        result = evaluate(model, build_exemplars(reference)).summary()
        log(f"\nShipped human model ({describe(model)}: {payload.get('summary', 'see docs/model.md')}) on the "
            f"{len(reference)} real trials: {result['instances']} instances, NLL exact {result['nll_exact']:.3f}, "
            f"IS {_score(result['nll_is'])}, naive {result['nll_naive']:.3f} nats (the authors' model: -12.717)")
        calibration = payload.get("calibration") or {}
        nested = calibration.get("nested")
        if nested:  # trained on these trials: the honest score is the nested cross-validated one
            cov = nested["coverage_90"]
            log(f"  in-sample: the model was fine-tuned on these trials. Nested {len(nested['folds'])}-fold cross-validation "
                f"by trial (every choice of the recipe and calibration made without the fold it scores): NLL "
                f"{nested['fold_mean_nll_exact']:.3f} per fold (per instance x {nested['nll_exact_by_direction']['x']:.2f}, "
                f"y {nested['nll_exact_by_direction']['y']:.2f}); 90 % position intervals 1.5 s ahead cover "
                f"{100 * cov['x']:.0f} % (x) and {100 * cov['y']:.0f} % (y) of real positions")
        cv = payload.get("crossval")
        if cv and cv.get("reference"):
            log(f"  the authors' model on the same folds: {cv['reference']['nll_exact']:.3f}")
        picks, data, name = DEMO_REAL_PICKS, reference, "predictions_real.png"
    else:
        picks, data, name = DEMO_SYNTHETIC_PICKS, dataset, "predictions_synthetic.png"
    log(f"wrote {plot_predictions(model.to('cpu'), data, picks, figures / name, title='shipped human model: 50 sampled futures')}")


def _plan_figure(figures: Path, log: Callable[[str], None]) -> None:
    """One full-budget plan with the shipped model, drawn beside braking and accelerating alternatives."""
    from .model.predictor import HumanPredictor
    from .model.registry import load_model
    from .planning.candidates import Action
    from .planning.costs import PaperCost
    from .planning.planner import Planner, example_history
    from .scenario import LANE_CENTRE_Y
    from .viz.planning_figures import plot_plan

    planner = Planner(HumanPredictor(load_model("default"), precision="auto"))
    path = plot_plan(planner, example_history(), Action.of(0.0, "right").index, PaperCost(goal_y=LANE_CENTRE_Y["left"]),
                     figures / "plan.png")
    budget = planner.budget
    log(f"\nplanned against {budget.futures} sampled human futures (every candidate × {budget.first_stage_samples}, "
        f"best {budget.finalists} × {budget.second_stage_samples}); wrote {path}")


def _closed_loop(out: Path, hitl_dir: Path | None, log: Callable[[str], None]) -> None:
    """A few real-time closed-loop episodes against simulated and model-driven humans, their
    metrics, and Fig. 6 and the animation of one of them."""
    from .sim.batch import simulate, summary_table
    from .sim.episodes import EpisodeSpec, run_episode
    from .viz.episode_figures import animate_episode, plot_episode

    authors = None if hitl_dir is None else hitl_dir.parent / "authors_model" / "weights.npz"
    model_human = f"model:authors:{authors}" if authors is not None and authors.is_file() else "model:default"
    for human, name in (("synthetic", "synthetic"), (model_human, "model")):
        log(f"\nclosed loop: the planner (shipped model, {DEMO_DEADLINE:g} s per plan) vs {human}")
        summary = simulate(DEMO_EPISODES, "planner", human, seed=0, out=out / "closed_loop" / name,
                           deadline=DEMO_DEADLINE, progress=True)
        log(summary_table(summary))
    spec = EpisodeSpec("planner", "synthetic", seed=0, deadline=DEMO_DEADLINE)
    robot, human = agents = spec.agents()
    episode = run_episode(spec, 0, agents)
    trials, length = episode.trials, int(episode.trials.lengths[0])
    figures = out / "figures"
    log(f"wrote {plot_episode(trials, 0, figures / 'episode.png', title='planner (blue) vs a simulated driver (red)')}")
    plans = [(t, plan.robot, plan.human[:32]) for t, plan in zip(robot.plan_steps, robot.plans)]
    roles = tuple(str(r) for r in trials.roles[0])
    log(f"wrote {animate_episode(trials.states[0, :, :length], roles, figures / 'episode.gif', plans, title='planner vs simulated driver')}")
