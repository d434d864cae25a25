"""Bad input at the planner's boundaries (Planner.plan / score, MPCPolicy, Budget, the CVAE's
HumanPredictor, thread counts) raises InputError with one line that starts with the argument's name;
good edge cases pass."""

import numpy as np
import pytest
import torch

from trafficweaving.errors import InputError
from trafficweaving.model.cvae import CVAE, CVAEConfig
from trafficweaving.model.predictor import HumanPredictor
from trafficweaving.planning.candidates import N_ACTIONS, N_CANDIDATES, robot_candidates
from trafficweaving.planning.costs import PaperCost
from trafficweaving.planning.mpc import MPCPolicy
from trafficweaving.planning.planner import Budget, Planner, example_history
from trafficweaving.scenario import LANE_CENTRE_Y
from trafficweaving.validate import thread_count

COST = PaperCost(goal_y=LANE_CENTRE_Y["left"])
HISTORY = example_history()
TINY = Budget(1, 2, 2)


@pytest.fixture(scope="module")
def predictor():
    torch.manual_seed(0)
    return HumanPredictor(CVAE(CVAEConfig(history_units=8, future_units=8, decoder_units=16, p_z_hidden=4)))


@pytest.fixture(scope="module")
def planner(predictor):
    return Planner(predictor, TINY)


def rejects(name, call, *args, **kwargs) -> str:
    """``call(*args, **kwargs)`` raises InputError, a ValueError, whose one-line message starts with ``name``."""
    with pytest.raises(InputError) as info:
        call(*args, **kwargs)
    message = str(info.value)
    assert isinstance(info.value, ValueError) and message.startswith(name) and "\n" not in message, message
    return message


def _with(value, index):
    history = HISTORY.copy()
    history[index] = value
    return history


BAD_HISTORIES = [
    (_with(np.nan, (-1, 1, 0)), "NaN"),
    (_with(np.inf, (0, 0, 2)), "NaN or infinite"),
    (HISTORY[:3], "3 steps (expected at least 5)"),
    (HISTORY[:, :1], "shape [10, 1, 6]"),
    (HISTORY[..., :5], "shape [10, 2, 5]"),
    (HISTORY[0], "shape [2, 6]"),
    (HISTORY.reshape(10, 12), "shape [10, 12]"),
    (np.zeros((0, 2, 6)), "0 steps"),
    ("a history", "not an array of numbers"),
    ([[[1.0] * 6, [2.0] * 6]] * 4 + [[[1.0] * 6]], "not an array of numbers"),  # ragged
]
BAD_ACTIONS = [-1, N_ACTIONS, 8, True, False, 1.0, 3.0, "0", None]
BAD_DEADLINES = [float("nan"), float("inf"), -float("inf"), 0, 0.0, -1, True, "0.3"]


# ---------------------------------------------------------------- Planner.plan and Planner.score
@pytest.mark.parametrize("history, expected", BAD_HISTORIES)
def test_plan_and_score_refuse_bad_histories(planner, history, expected):
    assert expected in rejects("history", planner.plan, history, 0, COST)
    assert expected in rejects("history", planner.score, history, 0, COST, [0], 4)


@pytest.mark.parametrize("action", BAD_ACTIONS)
def test_plan_and_score_refuse_bad_first_actions(planner, action):
    assert f"must be an integer in 0..{N_ACTIONS - 1}" in rejects("first_action", planner.plan, HISTORY, action, COST)
    rejects("first_action", planner.score, HISTORY, action, COST, [0], 4)


@pytest.mark.parametrize("deadline", BAD_DEADLINES)
def test_plan_refuses_bad_deadlines(planner, deadline):
    assert "finite number of seconds > 0" in rejects("deadline", planner.plan, HISTORY, 0, COST, deadline=deadline)


def test_plan_refuses_bad_budgets_samples_and_costs(planner):
    rejects("budget", planner.plan, HISTORY, 0, COST, budget=(16, 32, 1024))
    for keep in (-1, 1.5, True):
        rejects("keep_samples", planner.plan, HISTORY, 0, COST, keep_samples=keep)
    rejects("cost", planner.plan, HISTORY, 0, None)
    rejects("cost", planner.score, HISTORY, 0, "paper", [0], 4)


@pytest.mark.parametrize("indices", [[-1], [N_CANDIDATES], [], [[0, 1]], [0.5], np.array([True]), "0"])
def test_score_refuses_bad_indices(planner, indices):
    assert f"integers in 0..{N_CANDIDATES - 1}" in rejects("indices", planner.score, HISTORY, 0, COST, indices, 4)


@pytest.mark.parametrize("samples", [0, -2, 2.0, True])
def test_score_refuses_bad_sample_counts(planner, samples):
    rejects("samples", planner.score, HISTORY, 0, COST, [0], samples)


@pytest.mark.slow
def test_good_edge_cases_plan(planner):
    plan = planner.plan(HISTORY[-5:].tolist(), np.int64(N_ACTIONS - 1), COST, keep_samples=0, deadline=None)
    assert plan.actions[0] == N_ACTIONS - 1 and plan.human.shape == (0, 15, 6)
    costs, human = planner.score(torch.as_tensor(HISTORY), 0, COST, np.array([0, N_CANDIDATES - 1]), 3)
    assert costs.shape == (2,) and human.shape == (3, 2, 15, 6)
    assert planner.plan(HISTORY, 0, COST, deadline=5).seconds <= 5


# ---------------------------------------------------------------- Budget and Planner
@pytest.mark.parametrize("counts, name", [((0, 32, 1024), "first_stage_samples"), ((-3, 32, 1024), "first_stage_samples"),
                                          ((16.0, 32, 1024), "first_stage_samples"), ((True, 32, 1024), "first_stage_samples"),
                                          ((16, 0, 1024), "finalists"), ((16, N_CANDIDATES + 1, 1024), "finalists"),
                                          ((16, 32, 0), "second_stage_samples"), ((16, 32, "1024"), "second_stage_samples")])
def test_budget_counts_are_positive_integers(counts, name):
    rejects(name, Budget, *counts)


def test_planner_refuses_bad_human_models_budgets_and_seeds(predictor):
    assert "HumanPredictor(cvae)" in rejects("human_model", Planner, predictor.model)
    rejects("budget", Planner, predictor, budget=16)
    for seed in (-1, 1.5, True, None):
        rejects("seed", Planner, predictor, seed=seed)
    assert Planner(predictor, budget=None).budget == Budget()


# ---------------------------------------------------------------- MPCPolicy
def test_mpc_refuses_bad_options(planner):
    for hold in (-1, 1.5, True):
        rejects("hold_steps", MPCPolicy, planner, hold_steps=hold)
    for deadline in BAD_DEADLINES:
        rejects("deadline", MPCPolicy, planner, deadline=deadline)
    rejects("budget", MPCPolicy, planner, budget=[1, 2, 2])
    rejects("cost", MPCPolicy, planner, cost=1000.0)


START = HISTORY[None, -1]  # one episode's start [1, 2, 6]: robot, human


def episode(history):
    """A robot-first history [t+1, 2, 6] as the world hands it to the robot as car 0: [1, 2, t+1, 6]."""
    return np.asarray(history).swapaxes(0, 1)[None]


@pytest.mark.parametrize("start, expected", [(_with(np.nan, (-1, 0, 1))[None, -1], "NaN"), (np.zeros((1, 2, 5)), "shape [1, 2, 5]"),
                                             (HISTORY[-2:], "shape [2, 2, 6]"), ("robot", "not an array of numbers")])
def test_mpc_reset_refuses_bad_starts(planner, start, expected):
    assert expected in rejects("start", MPCPolicy(planner).reset, np.random.default_rng(0), start, 0)


def test_mpc_reset_refuses_bad_rngs_and_cars(planner):
    policy = MPCPolicy(planner)
    for rng in (0, None, np.random.RandomState(0)):
        rejects("rng", policy.reset, rng, START, 0)
    for me in (-1, 2, 0.0, True):
        rejects("me", policy.reset, np.random.default_rng(0), START, me)


def test_mpc_act_refuses_bad_or_out_of_step_histories(planner):
    policy = MPCPolicy(planner, budget=TINY)
    with pytest.raises(RuntimeError, match="reset"):
        policy.act(episode(HISTORY))
    policy.reset(np.random.default_rng(0), START, 0)
    for bad, expected in ((episode(_with(np.nan, (-1, 1, 0))), "NaN"), (HISTORY, "shape [10, 2, 6]"),
                          (np.repeat(episode(HISTORY), 2, axis=0), "shape [2, 2, 10, 6]"), ("a history", "not an array")):
        assert expected in rejects("history", policy.act, bad)
    assert policy.act(episode(HISTORY[-1:]).astype(np.float32)).shape == (1, 2)  # one step of history while holding


def test_mpc_without_hold_plans_at_once_and_then_needs_enough_history(planner):
    policy = MPCPolicy(planner, budget=TINY, hold_steps=0)
    policy.reset(np.random.default_rng(0), HISTORY[None, 2], 0)
    assert "expected at least 5" in rejects("history", policy.act, episode(HISTORY[:3]))
    policy.reset(np.random.default_rng(0), START, 0)
    assert policy.act(episode(HISTORY)).shape == (1, 2) and len(policy.plans) == 1


# ---------------------------------------------------------------- HumanPredictor (the CVAE's sampling)
def test_predictor_refuses_bad_inputs(predictor):
    futures = robot_candidates(HISTORY[-1, 0], 0).states[:4]
    for history, expected in BAD_HISTORIES:
        assert expected in rejects("history", predictor.predict, history, futures, 2)
        rejects("history", predictor.prepare, history, futures)
    for bad, expected in ((futures[:, :14], "shape [4, 14, 6]"), (futures[:0], "shape [0, 15, 6]"),
                          (_with_future(futures), "NaN"), (futures[0], "shape [15, 6]")):
        assert expected in rejects("robot_futures", predictor.predict, HISTORY, bad, 2)
    for n in (0, -1, 2.0, True, None):
        rejects("n", predictor.predict, HISTORY, futures, n)
    for seed in (-1, 0.5):
        rejects("seed", predictor.predict, HISTORY, futures, 2, seed=seed)
    predictor.prepare(HISTORY, futures)
    generator = torch.Generator()
    for candidates in ([4], [-1], [], torch.tensor([0.0]), [[0]]):
        assert "integers in 0..3" in rejects("candidates", predictor.sample, candidates, 2, generator)
    rejects("n", predictor.sample, torch.arange(4), 0, generator)
    assert predictor.sample([3, 0], 2, generator).shape == (2, 2, 15, 2)


def _with_future(futures):
    bad = futures.copy()
    bad[1, 7, 3] = np.nan
    return bad


def test_predictor_needs_a_prepared_situation_and_known_options():
    model = CVAE(CVAEConfig(history_units=8, future_units=8, decoder_units=16, p_z_hidden=4))
    with pytest.raises(RuntimeError, match="prepare"):
        HumanPredictor(model).sample(torch.arange(2), 2, torch.Generator())
    assert "auto, float32, bfloat16" in rejects("precision", HumanPredictor, model, precision="fp16")
    rejects("chunk_rows", HumanPredictor, model, chunk_rows=0)
    assert HumanPredictor(model, precision="bfloat16").precision == "bfloat16"


# ---------------------------------------------------------------- thread counts (bench)
def test_thread_counts():
    import os

    for threads in (0, -1, (os.cpu_count() or 1) + 1, 50_000, 1.5, True):
        assert "must be an integer in 1.." in rejects("--threads", thread_count, "--threads", threads)
    assert thread_count("--threads", 1) == 1
