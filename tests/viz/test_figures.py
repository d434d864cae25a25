"""Each figure function writes a readable PNG atomically, on small hand-built trial sets."""

import numpy as np
import pytest
from matplotlib.image import imread

from trafficweaving.data.behaviour import behaviour_samples
from trafficweaving.data.stats import table1
from trafficweaving.data.trials import TrialSet
from trafficweaving.scenario import DT, LANE_CENTRE_Y
from trafficweaving.viz import plot_behaviour, plot_profiles, plot_table1, plot_trajectories

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def weaving_trials(n: int = 6, steps: int = 45) -> TrialSet:
    """``n`` two-car trials: both cars swap lanes along a half cosine; the left-lane car is faster
    in odd trials (so it passes in front) and slower in even ones. Trial 0 is shorter (padded)."""
    t = np.arange(steps) * DT
    states = np.full((n, 2, steps, 6), np.nan)
    lengths = np.full(n, steps)
    lengths[0] = steps - 5
    y_l, y_r = LANE_CENTRE_Y["left"], LANE_CENTRE_Y["right"]
    for i in range(n):
        dv = 2.0 if i % 2 else -2.0
        for agent, (v, y0, y1, t0) in enumerate([(29.0 + dv, y_l, y_r, 1.0 + 0.1 * i), (29.0, y_r, y_l, 1.5)]):
            phase = np.clip((t - t0) / 2.0, 0.0, 1.0)
            y = y0 + (y1 - y0) * 0.5 * (1.0 - np.cos(np.pi * phase))
            xdd = 0.5 * dv * np.sin(np.pi * t / t[-1])
            xd = v + np.concatenate([[0.0], np.cumsum(0.5 * DT * (xdd[1:] + xdd[:-1]))])
            x = -120.0 - 3.0 * agent + np.concatenate([[0.0], np.cumsum(0.5 * DT * (xd[1:] + xd[:-1]))])
            yd = np.gradient(y, DT)
            states[i, agent, : lengths[i]] = np.stack([x, y, xd, yd, xdd, np.gradient(yd, DT)], -1)[: lengths[i]]
    return TrialSet(
        states=states, lengths=lengths, trial_ids=np.arange(n, dtype=np.int32),
        roles=np.array([["robot", "human"]] * n), start_lanes=np.array([["left", "right"]] * n),
        drivers=np.full((n, 2), -1, dtype=np.int32),
        ic_dv=np.array([2.0 if i % 2 else -2.0 for i in range(n - 1)] + [0.0]),
        ic_tco=np.array([1.0 + i % 3 for i in range(n - 1)] + [np.nan]),
        sources=np.array(["test"] * n),
    )


def assert_png(path, folder):
    """``path`` is a non-empty PNG that matplotlib reads back as an RGB(A) image, and ``folder``
    holds no leftover temporary file."""
    data = path.read_bytes()
    assert data[:8] == PNG_SIGNATURE
    image = imread(path)
    assert image.ndim == 3 and image.shape[0] > 100 and image.shape[1] > 100 and image.shape[2] in (3, 4)
    assert image[..., :3].std() > 0  # something was drawn
    assert [p.name for p in folder.iterdir() if p.name.startswith(".")] == []


@pytest.fixture(scope="module")
def trials():
    return weaving_trials()


def test_plot_trajectories(trials, tmp_path):
    out = plot_trajectories(trials, tmp_path / "sub" / "traj.png", max_trials=4)
    assert out == tmp_path / "sub" / "traj.png"
    assert_png(out, tmp_path / "sub")


@pytest.mark.slow
def test_plot_profiles(trials, tmp_path):
    assert_png(plot_profiles(trials, tmp_path / "profiles.png"), tmp_path)


@pytest.mark.slow
def test_plot_table1_with_empty_cells(trials, tmp_path):
    result = table1(trials)
    assert result["table1"]["0"]["all"] is not None
    assert_png(plot_table1(result["table1"], tmp_path / "t1.png", counts=result["counts"]), tmp_path)
    empty = {"-2": {"1": None, "2": None, "3": None}, "0": {"all": None}, "2": {"1": None, "2": None, "3": None}}
    assert_png(plot_table1(empty, tmp_path / "t1_empty.png"), tmp_path)


@pytest.mark.slow
def test_plot_behaviour_overwrites_atomically(trials, tmp_path):
    sim, real = behaviour_samples(trials, "robot"), behaviour_samples(trials, "human")
    real["lane_change_duration"] = np.array([])  # a statistic with no real sample still gets a panel
    path = tmp_path / "behaviour.png"
    path.write_bytes(b"old")
    assert_png(plot_behaviour(sim, real, path, labels=("robot", "human")), tmp_path)


def test_empty_trial_set_is_refused(trials, tmp_path):
    with pytest.raises(ValueError, match="no trials"):
        plot_trajectories(trials.subset(np.zeros(len(trials), bool)), tmp_path / "x.png")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.slow
def test_planner_figures(tmp_path):
    import torch

    from helpers_model import SMALL_UNITS
    from trafficweaving.model.cvae import CVAE, CVAEConfig
    from trafficweaving.model.predictor import HumanPredictor
    from trafficweaving.planning.candidates import Action
    from trafficweaving.planning.costs import PaperCost
    from trafficweaving.planning.planner import Budget, Planner, example_history
    from trafficweaving.scenario import LANE_CENTRE_Y
    from trafficweaving.viz.planning_figures import plot_candidates, plot_plan

    present = example_history()[-1, 0]
    fig4 = plot_candidates([(present, Action.of(0.0, "right").index, "right lane")], tmp_path / "fig4.png")
    torch.manual_seed(0)
    planner = Planner(HumanPredictor(CVAE(CVAEConfig(**SMALL_UNITS))), Budget(1, 4, 8))
    fig5 = plot_plan(planner, example_history(), Action.of(0.0, "right").index, PaperCost(goal_y=LANE_CENTRE_Y["left"]),
                     tmp_path / "fig5.png", samples=8, scoring_samples=16)
    for path in (fig4, fig5):
        assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and path.stat().st_size > 20_000
