"""The two-stage planner (planning/planner.py): a toy model, budgets, risk, deadlines and screening."""

import numpy as np
import pytest
import torch

from trafficweaving.dynamics import future_states
from trafficweaving.errors import InputError
from trafficweaving.model.constant_velocity import ConstantVelocityHuman
from trafficweaving.model.cvae import CVAE
from trafficweaving.model.predictor import HumanPredictor
from trafficweaving.planning.candidates import N_ACTIONS, N_CANDIDATES, WINDOWS, Action, rollout
from trafficweaving.planning.costs import PaperCost
from trafficweaving.planning.planner import OWN_FUTURES_SHARE, SCREENING_SAMPLES, SHORTLIST, Budget, Planner, risk_cost
from trafficweaving.planning.styles import DrivingStyle

from helpers_planning import HISTORY_TOY, LEFT, ToyHuman, _accelerates_throughout, _history, toy_cost


@pytest.mark.slow
def test_two_stage_selection_finds_the_known_optimum():
    for seed in range(3):
        plan = Planner(ToyHuman(), seed=seed).plan(HISTORY_TOY, Action.of(0.0, "right").index, cost=toy_cost)
        assert _accelerates_throughout(plan)
        assert plan.futures == 4096 * 16 + 32 * 1024 and len(plan.finalists) == 32
        assert set(np.argsort(plan.first_stage_cost)[:32]) == set(plan.finalists)


@pytest.mark.slow
def test_second_stage_corrects_a_noisy_first_stage():
    corrected = 0
    for seed in range(6):
        plan = Planner(ToyHuman(), seed=seed).plan(HISTORY_TOY, Action.of(0.0, "right").index, cost=toy_cost)
        stage1_choice = plan.candidates.actions[int(np.argmin(plan.first_stage_cost))]
        corrected += not all(Action(int(a)).acceleration == 4.0 for a in stage1_choice[1:])
        assert _accelerates_throughout(plan)
    assert corrected >= 1  # stage 1 alone would have picked a worse sequence at least once


def test_budget_counts_are_configurable():
    plan = Planner(ToyHuman()).plan(HISTORY_TOY, 0, toy_cost, budget=Budget(2, 5, 7))
    assert plan.futures == 4096 * 2 + 5 * 7 and len(plan.finalists) == 5 and plan.second_stage_samples == 7


@pytest.mark.slow
def test_risk_judges_a_candidate_by_the_mean_of_its_worst_sampled_futures():
    scores = torch.tensor([[1.0, 10.0], [2.0, 20.0], [3.0, 30.0], [4.0, 40.0]])
    assert risk_cost(scores, 1.0).tolist() == [2.5, 25.0] and risk_cost(scores, 0.5).tolist() == [3.5, 35.0]
    assert risk_cost(scores, 0.1).tolist() == [4.0, 40.0]
    budget = Budget(8, 8, 8)
    plain = Planner(ToyHuman(), seed=0).plan(HISTORY_TOY, 0, toy_cost, budget=budget)
    cautious = Planner(ToyHuman(), seed=0, style=DrivingStyle(risk=0.25)).plan(HISTORY_TOY, 0, toy_cost, budget=budget)
    assert np.all(cautious.first_stage_cost >= plain.first_stage_cost - 1e-6)
    assert (cautious.first_stage_cost > plain.first_stage_cost + 1.0).mean() > 0.9
    for bad in (dict(risk=0.0), dict(risk=1.5), dict(turn_back_cost=-1.0), dict(turn_back_cost=float("inf")),
                dict(set_out_gap=-5.0), dict(set_out_until=0.5)):
        with pytest.raises(InputError, match="a driving style needs"):
            DrivingStyle(**bad)
    with pytest.raises(InputError, match="style must be a DrivingStyle"):
        Planner(ToyHuman(), style="paper")


@pytest.mark.slow
def test_a_real_time_plan_returns_within_the_deadline():
    torch.manual_seed(0)
    planner = Planner(HumanPredictor(CVAE()))
    history = _history()
    for deadline in (1.0, 0.6):
        plan = planner.plan(history, Action.of(0.0, "right").index, PaperCost(goal_y=LEFT), deadline=deadline)
        assert plan.seconds <= deadline
        assert plan.first_stage_samples >= 1 and np.isfinite(plan.first_stage_cost).any()


class _RecordingHuman(ConstantVelocityHuman):
    """The constant-velocity human, keeping the robot futures of every ``prepare``."""

    def __init__(self):
        super().__init__()
        self.prepared = []

    def prepare(self, history, robot_futures) -> None:
        super().prepare(history, robot_futures)
        self.prepared.append(np.asarray(robot_futures))


def test_real_time_screening_conditions_on_each_window_1_action_held_then_on_the_finalists():
    human = _RecordingHuman()
    history, fixed = _history(), Action.of(0.0, "right").index
    plan = Planner(human).plan(history, fixed, PaperCost(goal_y=LEFT), deadline=1e-3)
    held = np.array([[fixed] + [a] * (WINDOWS - 1) for a in range(N_ACTIONS)])
    screening, finalists = human.prepared
    np.testing.assert_array_equal(screening, rollout(history[-1, 0], held))
    np.testing.assert_array_equal(finalists, plan.candidates.states[plan.finalists])
    assert plan.first_stage_samples == SCREENING_SAMPLES and plan.second_stage_samples >= 1  # one round at least
    assert np.isfinite(plan.first_stage_cost).all()  # every candidate screened, however short the deadline


@pytest.mark.slow
def test_real_time_stage_1_samples_every_candidates_own_futures_where_two_each_fit_in_time():
    human = _RecordingHuman()
    planner, history, fixed = Planner(human), _history(), Action.of(0.0, "right").index
    planner.rows_per_second = 2.05 * N_CANDIDATES / (OWN_FUTURES_SHARE * 0.3)  # two each fit in 0.3 s
    plan = planner.plan(history, fixed, PaperCost(goal_y=LEFT), deadline=0.3)
    assert plan.first_stage_samples == 2 and len(human.prepared[0]) == N_CANDIDATES  # own futures, no screening
    assert len(human.prepared) == 1 and plan.futures == (2 * N_CANDIDATES + plan.shortlist_samples * SHORTLIST
                                                        + plan.second_stage_samples * 32)
    human.prepared.clear()
    planner.rows_per_second = 1.9 * N_CANDIDATES / (OWN_FUTURES_SHARE * 0.3)  # fewer than two: screening
    plan = planner.plan(history, fixed, PaperCost(goal_y=LEFT), deadline=0.3)
    assert plan.first_stage_samples == SCREENING_SAMPLES and len(human.prepared[0]) == N_ACTIONS


class _NoisyHuman(_RecordingHuman):
    """Random longitudinal accelerations (m/s², standard deviation 2), keeping every draw
    (candidate indices, accelerations)."""

    def __init__(self):
        super().__init__()
        self.draws, self.rng = [], torch.Generator().manual_seed(0)

    def sample(self, candidates, n, generator=None):
        accelerations = super().sample(candidates, n, generator).clone()
        accelerations[..., 0] = 2.0 * torch.randn(accelerations.shape[:-1], generator=self.rng)
        self.draws.append((torch.as_tensor(candidates).clone(), accelerations))
        return accelerations


@pytest.mark.slow
def test_real_time_finalists_are_the_best_of_the_shortlist_by_all_their_samples():
    human, history, fixed, cost = _NoisyHuman(), _history(), Action.of(0.0, "right").index, PaperCost(goal_y=LEFT)
    planner = Planner(human)
    planner.rows_per_second = 2.05 * N_CANDIDATES / (OWN_FUTURES_SHARE * 2.0)  # two each fit in 2 s
    plan = planner.plan(history, fixed, cost, deadline=2.0)
    (everyone, first), (shortlist, more), *_ = human.draws
    assert plan.first_stage_samples == 2 and len(everyone) == N_CANDIDATES
    assert plan.shortlist_samples == len(more) >= 1
    assert set(shortlist.tolist()) == set(np.argsort(plan.first_stage_cost)[:SHORTLIST].tolist())
    present = torch.as_tensor(history[-1, 1], dtype=torch.float32)
    robot = torch.as_tensor(plan.candidates.states[shortlist.numpy()], dtype=torch.float32)
    costs = cost(robot.unsqueeze(0), future_states(present, torch.cat([first[:, shortlist], more]))).mean(0)
    assert set(plan.finalists.tolist()) == set(shortlist[torch.topk(costs, 32, largest=False).indices].tolist())
    assert plan.futures == 2 * N_CANDIDATES + plan.shortlist_samples * SHORTLIST + plan.second_stage_samples * 32
    full = planner.plan(history, fixed, cost, budget=Budget(2, 32, 4))  # the paper's stages: no shortlist
    assert full.shortlist_samples == 0 and full.futures == 2 * N_CANDIDATES + 4 * 32
    planner.rows_per_second = 2.05 * N_CANDIDATES / (OWN_FUTURES_SHARE * 1e-4)  # own futures, no time left after
    late = planner.plan(history, fixed, cost, deadline=1e-4)
    assert late.first_stage_samples >= 2 and late.shortlist_samples == 0 and late.second_stage_samples >= 1


@pytest.mark.slow
def test_screening_is_exact_for_a_human_that_ignores_the_robot():
    # the constant-velocity human's future does not depend on the robot's: the shared futures are
    # every candidate's own, so the screened stage 1 costs what the paper's stage 1 costs
    planner, history, cost = Planner(ConstantVelocityHuman()), _history(), PaperCost(goal_y=LEFT)
    fixed = Action.of(0.0, "right").index
    planner.rows_per_second = 1.0  # too slow for own futures in real time: it screens
    screened = planner.plan(history, fixed, cost, deadline=1.0)
    assert screened.first_stage_samples == SCREENING_SAMPLES
    full = planner.plan(history, fixed, cost, budget=Budget(1, 32, 1))
    assert full.first_stage_samples == 1 and full.futures == N_CANDIDATES + 32
    np.testing.assert_allclose(screened.first_stage_cost, full.first_stage_cost, rtol=1e-5, atol=1e-3)
    assert screened.index == full.index
