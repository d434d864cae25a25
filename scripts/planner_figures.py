"""Write the planner's figures into ``docs/figures``: the paper's Fig. 4 (candidate robot futures
from three initial states) and Fig. 5 (a full-budget plan with the shipped model, beside braking
and accelerating alternatives).

    python scripts/planner_figures.py [--model default] [--out docs/figures]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from trafficweaving.model.registry import load_model
from trafficweaving.model.predictor import HumanPredictor
from trafficweaving.planning.candidates import Action
from trafficweaving.planning.costs import PaperCost
from trafficweaving.planning.planner import Planner, example_history
from trafficweaving.scenario import LANE_CENTRE_Y
from trafficweaving.viz.planning_figures import plot_candidates, plot_plan


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", default="default")
    parser.add_argument("--out", default="docs/figures")
    args = parser.parse_args()
    out = Path(args.out)
    right, left = LANE_CENTRE_Y["right"], LANE_CENTRE_Y["left"]
    starts = [
        (np.array([-100.0, right, 29.0, 0.0, 0.0, 0.0]), Action.of(0.0, "right").index, "in the right lane at 29 m/s"),
        (np.array([-60.0, -4.6, 27.0, 1.2, 0.4, 0.0]), Action.of(-3.0, "left").index, "changing lanes at 27 m/s, braking"),
        (np.array([-30.0, left, 33.0, 0.0, 0.0, 0.0]), Action.of(4.0, "left").index, "in the left lane at 33 m/s, accelerating"),
    ]
    print(plot_candidates(starts, out / "fig4_candidates.png"))
    planner = Planner(HumanPredictor(load_model(args.model), precision="auto"), seed=0)
    for gap, name in ((2.0, "fig5_plan_side_by_side.png"), (-8.0, "fig5_plan_human_behind.png")):
        print(plot_plan(planner, example_history(gap=gap), Action.of(0.0, "right").index, PaperCost(goal_y=left), out / name))


if __name__ == "__main__":
    main()
