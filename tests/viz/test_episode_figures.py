"""Episode figures: the paper's Fig. 6, the animation, and `trafficweaving plot-episode` (which
runs a planner's episode again to draw its plans)."""

import json

import numpy as np
import pytest
from PIL import Image

from trafficweaving.cli import main
from trafficweaving.planning.planner import Budget
from trafficweaving.sim.episodes import EpisodeSpec, rerun_with_plans, run_episode
from trafficweaving.sim.generate import generate_trials
from trafficweaving.viz.episode_figures import animate_episode, plot_episode

PNG = b"\x89PNG\r\n\x1a\n"


@pytest.fixture(scope="module")
def episode_log(tmp_path_factory):
    """A short planner episode (constant-velocity human model, tiny budget) logged as simulate does."""
    path = tmp_path_factory.mktemp("episode") / "episode_000002.parquet"
    run_episode(EpisodeSpec("planner-cv", "synthetic", seed=4, budget=Budget(1, 4, 8)), 2).trials.write_parquet(path)
    return path


@pytest.mark.slow
def test_fig6_and_animation_of_any_trial(tmp_path):
    trials, _ = generate_trials(2, seed=1)
    assert plot_episode(trials, 1, tmp_path / "fig6.png").read_bytes()[:8] == PNG
    steps = 12  # a frame per step (test_plot_episode_command animates a whole episode)
    gif = animate_episode(trials.states[0, :, 20:20 + steps], ("human", "human"), tmp_path / "a.gif")
    with Image.open(gif) as image:
        assert image.n_frames == steps and image.size == (800, 300)
    with pytest.raises(ValueError, match="index 2 is outside 0..1"):
        plot_episode(trials, 2, tmp_path / "x.png")


@pytest.mark.slow
def test_rerunning_an_episode_recovers_its_plans_and_refuses_an_edited_log(episode_log, tmp_path):
    from trafficweaving.data.trials import load_trials

    trials = load_trials(episode_log)
    plans = rerun_with_plans(trials)
    steps = [t for t, _, _ in plans]
    assert steps[0] == 8 and np.all(np.diff(steps) == 3)  # hold 8 steps, then plan every 0.3 s
    t, robot_future, human_futures = plans[0]
    assert robot_future.shape == (15, 6) and human_futures.shape[1:] == (15, 6)
    robot = int(np.flatnonzero(trials.roles[0] == "robot")[0])
    executed = trials.states[0, robot, t + 1: t + 4, 4:6]  # the accelerations the robot then applied
    np.testing.assert_allclose(executed, robot_future[:3, 4:6])
    trials.states[0, :, 20:, 0] += 1.0  # not what this episode does: no plans are claimed for it
    assert rerun_with_plans(trials) is None


@pytest.mark.slow
def test_plot_episode_command(episode_log, tmp_path, capsys):
    code = main(["plot-episode", str(episode_log), "--out", str(tmp_path / "f.png"), "--gif", str(tmp_path / "a.gif"),
                 "--json"])
    report = json.loads(capsys.readouterr().out)
    assert code == 0 and report["plans_drawn"] > 5
    assert (tmp_path / "f.png").read_bytes()[:8] == PNG and (tmp_path / "a.gif").stat().st_size > 10_000
    code = main(["plot-episode", str(episode_log), "--trial", "1", "--out", str(tmp_path / "g.png")])
    err = capsys.readouterr().err
    assert code == 2 and "--trial 1" in err and err.count("\n") == 1 and not (tmp_path / "g.png").exists()
