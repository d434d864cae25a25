"""The planner: lateral steering (boundary-value problem), candidate dynamics, costs, the fast
sampler against the model's own, two-stage selection on a toy model, deadlines and MPC."""

from dataclasses import replace

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from trafficweaving.dynamics import future_states, integrate_trapezoid
from trafficweaving.errors import InputError
from trafficweaving.model.constant_velocity import ConstantVelocityHuman
from trafficweaving.model.cvae import CVAE, CVAEConfig
from trafficweaving.model.registry import load_model
from trafficweaving.model.fused_decoder import INT8_RANGE, FusedDecoder, decode_step, quantize_rows
from trafficweaving.model.predictor import HumanPredictor, resolve_precision
from trafficweaving.model.sampler import BatchedRollout
from trafficweaving.planning.candidates import (ACCELERATIONS, KINEMATICS, N_ACTIONS, N_CANDIDATES, SETTLING_TIME, WINDOWS,
                                                Action, acceleration_indices, action_sequences, robot_candidates, rollout)
from trafficweaving.planning.costs import PaperCost
from trafficweaving.planning.mpc import HOLD_STEPS, MPCPolicy
from trafficweaving.planning.planner import (OWN_FUTURES_SHARE, SCREENING_SAMPLES, SHORTLIST, Budget, Planner,
                                             example_history, risk_cost)
from trafficweaving.planning.styles import (FOLLOW_COST, FOLLOW_LATERAL, HUMAN_ACCELERATION_HELD, PROGRESS_COST,
                                            SET_OUT_COST, SET_OUT_GAP, STANDOFF_EXIT_COST, STYLES, YIELD_MARGIN,
                                            YIELD_SPEED_FLOOR, DrivingStyle, brakes_along, set_outs, standoff_exit,
                                            stopping_shortfall, turn_backs)
from trafficweaving.planning.steering import jerk_limited_steer, optimal_time, steer, steering_cost
from trafficweaving.scenario import COLLISION_DX, CAR_WIDTH, CUTOFF_X, DT, HORIZON, LANE_CENTRE_Y, LANE_DIVIDER_Y
from trafficweaving.sim.world import World

LEFT, RIGHT = LANE_CENTRE_Y["left"], LANE_CENTRE_Y["right"]
STATES = np.array([[RIGHT, 0.0, 0.0], [LEFT, 0.4, -0.5], [-3.5, -1.2, 2.0], [-5.0, 0.8, 0.3]])
TARGETS = np.array([LEFT, RIGHT, RIGHT, LEFT])


# ---------------------------------------------------------------- steering
def test_steering_reaches_the_target_at_rest_and_holds_it():
    T = optimal_time(STATES, TARGETS)
    end = steer(STATES, TARGETS, np.stack([T, T + 0.5, T + 3.0], axis=-1))
    np.testing.assert_allclose(end[..., 0], TARGETS[:, None].repeat(3, 1), atol=1e-9)
    np.testing.assert_allclose(end[..., 1:], 0.0, atol=1e-9)


def test_steering_time_minimises_the_cost():
    T = optimal_time(STATES, TARGETS)
    for k in range(len(T)):
        grid = np.linspace(0.05, 12.0, 120_001)
        brute = steering_cost(np.repeat(STATES[k:k + 1], len(grid), 0), np.full(len(grid), TARGETS[k]), grid)
        assert steering_cost(STATES[k], TARGETS[k], T[k]) <= brute.min() + 1e-9
        assert abs(T[k] - grid[brute.argmin()]) < 1e-3


def test_steering_is_the_minimum_energy_jerk_and_integrates_consistently():
    state, target = STATES[2], TARGETS[2]
    T = float(optimal_time(state, target))
    times = np.linspace(0.0, T, 20_001)[:-1]  # up to the final time, where the hold begins
    path = steer(state, target, times)  # [K, 4]: y, yd, ydd, yddd
    dt = times[1] - times[0]
    for lower, upper in ((2, 3), (1, 2), (0, 1)):  # integrate each derivative (trapezoid) and compare
        integrated = path[0, lower] + np.concatenate([[0.0], np.cumsum(0.5 * dt * (path[1:, upper] + path[:-1, upper]))])
        np.testing.assert_allclose(integrated, path[:, lower], atol=1e-6)
    energy = np.trapezoid(path[:, 3] ** 2, times)
    assert T + energy / 1000.0 == pytest.approx(float(steering_cost(state, target, T)), rel=1e-4)
    # any other jerk profile reaching the same final state differs by a perturbation orthogonal to
    # (T-t)²/2, T-t and 1 (the final state is linear in exactly these moments) and costs more
    basis = np.stack([(T - times) ** 2 / 2, T - times, np.ones_like(times)], axis=1)
    bump = np.sin(3 * np.pi * times / T) + 0.5 * np.cos(7 * times)
    bump -= basis @ np.linalg.lstsq(basis, bump, rcond=None)[0]
    assert np.abs(np.trapezoid(basis * bump[:, None], times, axis=0)).max() < 1e-3
    for scale in (0.05, 0.5, 2.0):
        assert np.trapezoid((path[:, 3] + scale * bump) ** 2, times) > energy


def test_at_target_means_no_motion():
    path = steer(np.array([LEFT, 0.0, 0.0]), np.array(LEFT), np.array([0.1, 0.2, 0.3]))
    np.testing.assert_allclose(path[:, 0], LEFT)
    np.testing.assert_allclose(path[:, 1:], 0.0)


def test_jerk_limited_steering_keeps_to_its_limits_reaches_the_target_and_is_faster_than_minimum_energy():
    """From every test state, and a lane change from rest: within 4.5 m/s² and 7 m/s³ (the jerk
    also as sampled every 0.1 s), at rest on the target after it, re-solving from a state on the way
    continues the same path, and the lane change ends sooner than the minimum-energy one whose
    sampled jerk peaks at the same 7 m/s³ (ρ = 60: 3.2 s); a small correction given a shortest
    time takes that long, gently."""
    times = np.arange(1, 81) * DT  # 0.1 .. 8 s
    path = jerk_limited_steer(STATES, TARGETS, times, 4.5, 7.0)  # [4, K, 3]
    acc = np.concatenate([STATES[:, None, 2], path[..., 2]], axis=1)
    assert np.abs(path[..., 2]).max() <= 4.5 + 1e-9 and np.abs(np.diff(acc, axis=1) / 0.1).max() <= 7.0 + 1e-9
    np.testing.assert_allclose(path[:, -1], np.stack([TARGETS, 0 * TARGETS, 0 * TARGETS], 1), atol=1e-9)
    again = jerk_limited_steer(path[:, 9], TARGETS, times[:20], 4.5, 7.0)  # from 1 s on
    np.testing.assert_allclose(again, path[:, 10:30], atol=1e-6)
    lane_change = jerk_limited_steer(np.array([RIGHT, 0.0, 0.0]), np.array(LEFT), times, 4.5, 7.0)
    done = times[np.argmax(np.abs(lane_change[:, 0] - LEFT) < 1e-6)]
    gentle = steer(np.array([RIGHT, 0.0, 0.0]), np.array(LEFT), times, 60.0)
    assert done < 2.8 and times[np.argmax(np.abs(gentle[:, 0] - LEFT) < 1e-3)] > 3.0
    assert np.abs(np.diff(np.r_[0.0, gentle[:, 2]]) / 0.1).max() > 7.0
    nudge = jerk_limited_steer(np.array([LEFT - 0.01, 0.02, 0.1]), np.array(LEFT), times, 4.5, 7.0, min_time=0.6)
    assert np.abs(nudge[:5, 0] - LEFT).min() > 1e-4 and np.abs(nudge[5:, 0] - LEFT).max() < 1e-9  # there at 0.6 s
    assert np.abs(nudge[..., 2]).max() < np.abs(jerk_limited_steer(np.array([LEFT - 0.01, 0.02, 0.1]), np.array(LEFT),
                                                                     times, 4.5, 7.0)[..., 2]).max() / 4
    with pytest.raises(ValueError, match="no jerk-limited steering"):
        jerk_limited_steer(np.array([RIGHT, np.nan, 0.0]), np.array(LEFT), times, 4.5, 7.0)


# ---------------------------------------------------------------- candidates
PRESENT = np.array([-90.0, RIGHT, 29.0, 0.0, 0.0, 0.0])


def test_the_candidate_counts_follow_from_the_horizon_and_the_actions():
    assert (WINDOWS, N_ACTIONS, N_CANDIDATES) == (5, 8, 4096) and WINDOWS * 3 == HORIZON
    assert Budget().futures == 4096 * 16 + 32 * 1024


def test_4096_distinct_candidates_with_the_first_window_fixed():
    first = Action.of(4.0, "right").index
    c = robot_candidates(PRESENT, first)
    assert c.states.shape == (4096, 15, 6) and c.actions.shape == (4096, 5)
    assert (c.actions[:, 0] == first).all() and len({tuple(a) for a in c.actions}) == 4096
    same = c.states[:, :3].copy()
    same[:, 2, 4] = 0.0  # the xdd stored at the window's last step is the next window's acceleration
    np.testing.assert_allclose(same, np.broadcast_to(same[:1], (4096, 3, 6)))
    assert Action(first).acceleration == 4.0 and Action(first).lane == "right"


def test_candidate_longitudinal_dynamics_euler_velocity_trapezoid_position():
    c = robot_candidates(PRESENT, Action.of(0.0, "right").index)
    for k in (0, 1234, 4095):
        acc = np.repeat([ACCELERATIONS[a // 2] for a in c.actions[k]], 3)  # applied from t .. t+14
        xd = np.concatenate([[PRESENT[2]], c.states[k, :, 2]])
        x = np.concatenate([[PRESENT[0]], c.states[k, :, 0]])
        np.testing.assert_allclose(np.diff(xd), DT * acc, atol=1e-12)
        np.testing.assert_allclose(np.diff(x), 0.5 * DT * (xd[1:] + xd[:-1]), atol=1e-12)
        np.testing.assert_allclose(c.states[k, :-1, 4], acc[1:])  # xdd stored at a step = applied from it


def test_candidate_lateral_motion_follows_the_steering_window_by_window():
    actions = np.array([[Action.of(0.0, "right").index, Action.of(0.0, "left").index, Action.of(4.0, "left").index,
                         Action.of(-3.0, "right").index, Action.of(0.0, "left").index]])
    states = rollout(PRESENT, actions)[0]
    lateral = PRESENT[[1, 3, 5]]
    for w, a in enumerate(actions[0]):
        window = steer(lateral, np.array(LANE_CENTRE_Y[Action(int(a)).lane]), DT * np.arange(1, 4))
        np.testing.assert_allclose(states[3 * w:3 * w + 3][:, [1, 3, 5]], window[:, :3], atol=1e-12)
        lateral = window[-1, :3]
    hold = rollout(PRESENT, np.full((1, 5), Action.of(0.0, "right").index))[0]
    np.testing.assert_allclose(hold[:, 1], RIGHT)
    np.testing.assert_allclose(hold[:, 2], PRESENT[2])


def test_action_sequences_order():
    seqs = action_sequences(3)
    assert seqs.shape == (4096, 5) and (seqs[:8, -1] == np.arange(8)).all() and (seqs[-1] == [3, 7, 7, 7, 7]).all()


# ---------------------------------------------------------------- costs
def _pair(robot_xy_v, human_xy_v, steps=15):
    r, h = torch.zeros(steps, 6, dtype=torch.float64), torch.zeros(steps, 6, dtype=torch.float64)
    r[:, [0, 1, 2, 4]] = torch.tensor(robot_xy_v, dtype=torch.float64)
    h[:, [0, 1, 2, 4]] = torch.tensor(human_xy_v, dtype=torch.float64)
    return r, h


def test_cost_terms_by_hand():
    cost = PaperCost(goal_y=LEFT)
    # 3 m behind and 1 m beside: collision zone; robot 2 m/s slower and behind: moving apart rewarded
    r, h = _pair([-60.0, LEFT - 1.0, 27.0, 2.0], [-57.0, LEFT, 29.0, 0.0])
    terms = cost.terms(r, h)
    assert terms["collision"][0].item() == pytest.approx(1000 * (9.25 - np.sqrt(10.0)))
    assert terms["effort"][0].item() == pytest.approx(4.0)
    assert terms["lane"][0].item() == pytest.approx(500 * min(1.5 - 60 / 150, 1.0) * 1.0)
    assert terms["separation"][0].item() == pytest.approx(-100 * min(max(-3.0 * -2.0, 0), 1))
    total = sum(v[0].item() for v in terms.values())
    assert cost(r, h).item() == pytest.approx(total * sum(0.9 ** i for i in range(1, 16)))
    # far apart, on goal, closing in: only effort
    r, h = _pair([-200.0, LEFT, 29.0, 0.0], [-100.0, RIGHT, 27.0, 0.0])
    terms = cost.terms(r, h)
    assert terms["collision"].abs().sum() == 0 and terms["lane"].abs().sum() == 0 and terms["separation"].abs().sum() == 0
    # lane urgency ramps: weight 1.5 + x/150, capped at 1
    r, _ = _pair([-150.0, RIGHT, 29.0, 0.0], [0.0, 0.0, 0.0, 0.0])
    assert cost.terms(r, h)["lane"][0].item() == pytest.approx(500 * 0.5 * (LEFT - RIGHT))


def test_cost_broadcasts_over_samples_and_candidates():
    cost = PaperCost(goal_y=LEFT)
    robot = torch.randn(1, 7, 15, 6, dtype=torch.float64)
    human = torch.randn(5, 7, 15, 6, dtype=torch.float64)
    out = cost(robot, human)
    assert out.shape == (5, 7)
    assert out[2, 3].item() == pytest.approx(cost(robot[0, 3], human[2, 3]).item())


def test_human_integration_is_the_trapezoid_rule():
    present = torch.tensor([-80.0, RIGHT, 28.0, 0.3, 1.0, -0.2], dtype=torch.float64)
    actions = torch.randn(4, 15, 2, dtype=torch.float64)
    states = future_states(present, actions)
    for axis in (0, 1):
        p, v = integrate_trapezoid(np.full(4, present[axis].item()), np.full(4, present[2 + axis].item()),
                                   np.concatenate([np.full((4, 1), present[4 + axis].item()), actions[..., axis].numpy()], 1))
        np.testing.assert_allclose(states[..., axis].numpy(), p[:, 1:], atol=1e-10)
        np.testing.assert_allclose(states[..., 2 + axis].numpy(), v[:, 1:], atol=1e-10)


# ---------------------------------------------------------------- fast sampler
@pytest.mark.parametrize("variant, calibration", [("cvae", None), ("mixture-lstm", None), ("lstm", None),
                                                  ("cvae-hold", None), ("cvae-hold", (3.0, 1.7))])
def test_fast_sampler_equals_the_models_sampling_given_the_same_random_numbers(variant, calibration):
    torch.manual_seed(0)
    model = CVAE(CVAEConfig.variant(variant)).double().eval()
    if calibration:
        model.set_calibration(*calibration)
    history = torch.randn(9, 12, dtype=torch.float64)
    futures = torch.randn(6, 15, 6, dtype=torch.float64)
    present = torch.randn(2, dtype=torch.float64)  # the human's present action
    fast = BatchedRollout(model, chunk_rows=5)  # chunks that split candidates
    context = fast.encode(history, futures, present)
    g = torch.Generator().manual_seed(1)
    latents = fast.sample_latents(context, 4, g)
    noise = (torch.rand(4, 6, 15, generator=g, dtype=torch.float64), torch.randn(4, 6, 15, 2, generator=g, dtype=torch.float64))
    ours = fast.sample(context, latents, noise=noise)
    with torch.no_grad():
        x = torch.cat([model.encode_history(history[None], torch.tensor([8])).expand(6, -1),
                       model.encode_robot_future(futures, history[-1, :6].expand(6, -1))], -1)
        zx = torch.cat([model.latent_onehots[latents], x.expand(4, -1, -1)], -1)
        robot_inputs = torch.cat([history[-1, :6].expand(6, 1, -1), futures[:, :-1]], 1)
        reference = model.sample_actions(zx, robot_inputs, present.expand(6, -1), noise=noise)
    torch.testing.assert_close(ours, reference, rtol=0, atol=1e-10)


@pytest.mark.parametrize("variant, calibration", [("cvae", None), ("lstm", None), ("cvae-hold", None),
                                                  ("cvae-hold", (3.0, 1.7))])
def test_fused_decoder_steps_equal_the_fast_sampler_given_the_same_random_numbers(variant, calibration):
    """The fused steps of precision int8, with its weights left unquantised, are the
    batched sampler's decoder (float64, run eagerly)."""
    torch.manual_seed(0)
    model = CVAE(CVAEConfig.variant(variant)).double().eval()
    if calibration:
        model.set_calibration(*calibration)
    fast = BatchedRollout(model)
    fused = FusedDecoder(fast.w_step, fast.latent_gates, fast.latent_init, fast.w_head, fast.head_bias, fast.output_scale,
                         fast.hold_sigma if model.config.hold else None, fast.modes, fast.components,
                         quantize=False, compiled=False)
    context = fast.encode(torch.randn(9, 12, dtype=torch.float64), torch.randn(6, 15, 6, dtype=torch.float64),
                          torch.randn(2, dtype=torch.float64))
    g = torch.Generator().manual_seed(1)
    cand, z = torch.randint(6, (40,), generator=g), torch.randint(len(model.latent_onehots), (40,), generator=g)
    uniform, normal = torch.rand(40, 15, generator=g, dtype=torch.float64), torch.randn(40, 15, 2, generator=g, dtype=torch.float64)
    ours = fused.decode(context, cand, z, context["present_action"], uniform, normal)
    reference = fast.decode_rows(context, cand, z, uniform, normal)
    torch.testing.assert_close(ours, reference, rtol=0, atol=1e-10)


def test_int8_weights_round_trip_within_half_a_step():
    w = torch.randn(64, 32) * torch.logspace(-3, 1, 64)[:, None]  # rows of very different sizes
    codes, scale = quantize_rows(w)
    assert codes.dtype == torch.int8 and codes.abs().max() == INT8_RANGE
    assert ((codes * scale - w).abs() <= scale / 2 * (1 + 1e-6)).all()


def test_int8_precision_compiles_and_samples_what_float32_samples_to_quantisation_error():
    """precision int8 (compiled) against the same steps run eagerly (the same numbers to float
    rounding, but for rare draws on a component boundary) and against float32 with the same random
    numbers, on a trained model: the first step's draws agree to within the quantisation, and over
    the 15 steps (where a draw that picks another mixture component makes the rest of its future
    differ) about as closely as bfloat16's."""
    model = load_model("default")
    history = example_history()
    futures = robot_candidates(history[-1, 0], 0).states[:64]
    coarse = HumanPredictor(model, precision="int8")
    assert coarse.precision == "int8"
    a, b = HumanPredictor(model, precision="float32").predict(history, futures, n=8, seed=3), coarse.predict(history, futures, n=8, seed=3)
    bf16 = HumanPredictor(model, precision="bfloat16").predict(history, futures, n=8, seed=3)
    assert torch.equal(a.latents, b.latents)
    difference = (a.actions - b.actions).abs()  # m/s²
    assert difference[:, :, 0].median() < 0.01
    assert difference.mean() < 2 * (a.actions - bf16.actions).abs().mean()
    coarse.rollout.fused.step = decode_step  # eagerly
    eager = coarse.predict(history, futures, n=8, seed=3)
    torch.testing.assert_close(eager.actions[:, :, 0], b.actions[:, :, 0], rtol=0, atol=1e-4)
    # compiled multiply-adds round differently, so a draw on the boundary of two mixture components
    # (or hold modes) may take the other one at a later step, and the rest of its future differs
    agree = ((eager.actions - b.actions).abs() <= 1e-3).all(-1).float()  # [n, B, 15]
    assert agree.mean() > 0.99 and agree[:, :, :5].mean() > 0.998
    with pytest.raises(InputError, match="CPU only"):
        resolve_precision("int8", "cuda")


def test_the_predictors_one_shot_prediction_is_its_planning_protocol():
    torch.manual_seed(0)
    predictor = HumanPredictor(CVAE(CVAEConfig.variant("cvae-hold")))
    history = example_history()
    futures = robot_candidates(history[-1, 0], 0).states[:6]
    prediction = predictor.predict(history, futures, n=3, seed=5)
    predictor.prepare(history, futures)
    actions = predictor.sample(torch.arange(6), 3, torch.Generator().manual_seed(5))
    assert prediction.actions.shape == (3, 6, 15, 2) and prediction.log_p_z.shape == (6, 25)
    torch.testing.assert_close(actions, prediction.actions, rtol=0, atol=0)
    subset = predictor.sample(torch.tensor([4, 1]), 2, torch.Generator().manual_seed(1))
    assert subset.shape == (2, 2, 15, 2) and torch.isfinite(subset).all()
    assert predictor.precision == "float32"


@pytest.mark.parametrize("variant", ["cvae", "cvae-hold"])
def test_common_random_numbers_give_every_candidate_each_samples_draws(variant):
    """Sample i of every candidate is drawn with the same random numbers: identical robot futures get
    identical futures, a candidate's futures do not depend on which others are sampled with it, and
    they have the distribution of independent draws (mean and spread of 4000 samples)."""
    torch.manual_seed(0)
    model = CVAE(CVAEConfig.variant(variant))
    history = example_history()
    candidates = robot_candidates(history[-1, 0], 0).states
    futures = np.concatenate([candidates[:1], candidates[:1], candidates[-1:]])  # 0 and 1 the same
    common, independent = HumanPredictor(model), HumanPredictor(model, common_random_numbers=False)
    for predictor in (common, independent):
        predictor.prepare(history, futures)
    shared = common.sample(torch.arange(3), 4000, torch.Generator().manual_seed(3))
    torch.testing.assert_close(shared[:, 0], shared[:, 1], rtol=0, atol=0)
    alone = common.sample(torch.tensor([2]), 4000, torch.Generator().manual_seed(3))
    torch.testing.assert_close(alone[:, 0], shared[:, 2], rtol=0, atol=0)
    apart = independent.sample(torch.arange(3), 4000, torch.Generator().manual_seed(3))
    assert not torch.equal(apart[:, 0], apart[:, 1])
    torch.testing.assert_close(shared.mean(0), apart.mean(0), rtol=0, atol=0.15)
    torch.testing.assert_close(shared.std(0), apart.std(0), rtol=0.1, atol=0.05)


# ---------------------------------------------------------------- two-stage planner on a toy model
class ToyHuman:
    """Human accelerations ``N(0, 1)`` per step, independent of the robot: with :func:`toy_cost`
    each candidate's expected cost is known exactly."""

    device, dtype = torch.device("cpu"), torch.float32

    def prepare(self, history, robot_futures):
        pass

    def sample(self, candidates, n, generator):
        return torch.randn((n, len(candidates), 15, 2), generator=generator, dtype=torch.float64)


def toy_cost(robot, human):
    """Expected value: 200 per free window whose acceleration is not 4 m/s² (the 16 candidates that
    accelerate throughout are optimal); noise: sd 800 per sampled future, so 16 samples (sd 200)
    often rank one of the 192 candidates 200 worse first, 1024 samples (sd 25) do not."""
    windows = robot[..., [3, 6, 9, 12], 4]  # acceleration of windows 1..4
    return 200.0 * (windows != 4.0).sum(-1) + 3100.0 * human[..., 4].mean(-1)


class GoalToyCost:
    """:func:`toy_cost` for a robot heading to the lane centre ``goal_y``, which it ignores."""

    def __init__(self, goal_y: float):
        self.goal_y = goal_y

    def __call__(self, robot, human):
        return toy_cost(robot, human)


PRESENT_TOY = np.array([0.0, RIGHT, 30.0, 0.0, 0.0, 0.0])
HISTORY_TOY = np.repeat(np.stack([PRESENT_TOY, PRESENT_TOY + [0, 4.26, 0, 0, 0, 0]])[None], 6, axis=0)


def _accelerates_throughout(plan):
    return all(Action(int(a)).acceleration == 4.0 for a in plan.actions[1:])


def test_two_stage_selection_finds_the_known_optimum():
    for seed in range(3):
        plan = Planner(ToyHuman(), seed=seed).plan(HISTORY_TOY, Action.of(0.0, "right").index, cost=toy_cost)
        assert _accelerates_throughout(plan)
        assert plan.futures == 4096 * 16 + 32 * 1024 and len(plan.finalists) == 32
        assert set(np.argsort(plan.first_stage_cost)[:32]) == set(plan.finalists)


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


def test_turning_back_from_a_lane_change_under_way_costs_and_setting_out_does_not():
    """HISTORY_TOY's robot is in the right lane; window 0 sets out for the goal, the left lane."""
    fixed, cost = Action.of(0.0, "left").index, GoalToyCost(LEFT)
    history = HISTORY_TOY.copy()
    history[-1, 0, 1] = RIGHT + 1.5  # 1.5 m under way
    plain = Planner(ToyHuman(), seed=0).plan(history, fixed, cost)
    committed = Planner(ToyHuman(), seed=0, style=DrivingStyle(turn_back_cost=1000.0, commit_offset=1.0)).plan(history, fixed, cost)
    backs = turn_backs(plain.candidates.actions, "left")  # the toy cost ignores the lane
    assert backs.max() == 2 and (backs == 0).sum() == N_CANDIDATES // 2 ** (WINDOWS - 1)  # left, right, left, right, left
    np.testing.assert_allclose(committed.first_stage_cost - plain.first_stage_cost, 1000.0 * backs, atol=1e-3)
    assert backs[committed.index] == 0 and _accelerates_throughout(committed)
    probing = Planner(ToyHuman(), seed=0, style=DrivingStyle(turn_back_cost=1000.0, commit_offset=2.0)).plan(history, fixed, cost)
    np.testing.assert_array_equal(probing.first_stage_cost, plain.first_stage_cost)  # not yet committed: free
    free = Planner(ToyHuman(), seed=0, style=DrivingStyle(turn_back_cost=1000.0)).plan(history, fixed, toy_cost)
    np.testing.assert_array_equal(free.first_stage_cost, plain.first_stage_cost)  # a cost without a goal lane
    lanes = lambda *names: [Action.of(0.0, n).index for n in names]  # noqa: E731
    sequences = np.array([lanes("right", "left", "left", "left", "left"), lanes("left", "right", "left", "right", "left"),
                          lanes("right", "right", "right", "right", "right"), lanes("left", "left", "right", "right", "right")])
    assert turn_backs(sequences, "left").tolist() == [0, 2, 0, 1]


def test_setting_out_beside_the_human_costs_and_with_room_in_its_lane_or_under_way_does_not():
    """HISTORY_TOY's cars are side by side, the robot in the right lane; the goal is the left lane."""
    keep, cost, style = Action.of(0.0, "right").index, GoalToyCost(LEFT), DrivingStyle(set_out_gap=5.0)
    plain = Planner(ToyHuman(), seed=0).plan(HISTORY_TOY, keep, cost)
    beside = Planner(ToyHuman(), seed=0, style=style).plan(HISTORY_TOY, keep, cost)
    starts = set_outs(plain.candidates.actions, "left")
    assert starts.sum() == N_CANDIDATES // 2
    np.testing.assert_allclose(beside.first_stage_cost - plain.first_stage_cost, SET_OUT_COST * starts, atol=0.1)
    assert not starts[beside.index]

    def costs_of_the_rule(history):
        return (Planner(ToyHuman(), seed=0, style=style).plan(history, keep, cost).first_stage_cost
                - Planner(ToyHuman(), seed=0).plan(history, keep, cost).first_stage_cost)

    apart = HISTORY_TOY.copy()
    apart[:, 1, 0] -= 5.5  # the human 5.5 m behind at the same speed: room to set out, unless braking in front of it
    accelerations = np.array([[Action(int(a)).acceleration for a in row] for row in plain.candidates.actions])
    never_braking, braking_hard = (accelerations[:, 1:] >= 0).all(1), (accelerations[:, 1:3] == -6.0).all(1)
    apart_costs = costs_of_the_rule(apart)
    np.testing.assert_array_equal(apart_costs[never_braking], 0.0)
    np.testing.assert_allclose(apart_costs[braking_hard], SET_OUT_COST * starts[braking_hard], atol=0.1)
    pulling_away = HISTORY_TOY.copy()
    pulling_away[:, 1, 0] -= 2.0  # 2 m behind but 6 m/s slower: 5.6 m apart by the time the robot is across
    pulling_away[:, 1, 2] -= 6.0
    np.testing.assert_array_equal(costs_of_the_rule(pulling_away), 0.0)
    closing = apart.copy()
    closing[:, 1, 2] += 3.0  # 5 m behind but 3 m/s faster: 3.2 m behind 0.6 s from now
    np.testing.assert_allclose(costs_of_the_rule(closing), SET_OUT_COST * starts, atol=0.1)
    in_lane = HISTORY_TOY.copy()
    in_lane[:, 1] = HISTORY_TOY[:, 0] + [3.0, 0, 0, 0, 0, 0]  # 3 m ahead in the robot's lane: setting out moves away
    np.testing.assert_array_equal(costs_of_the_rule(in_lane), 0.0)
    going = Action.of(0.0, "left").index  # window 0 already sets out: nothing to start
    np.testing.assert_array_equal(Planner(ToyHuman(), seed=0, style=style).plan(HISTORY_TOY, going, cost).first_stage_cost,
                                  Planner(ToyHuman(), seed=0).plan(HISTORY_TOY, going, cost).first_stage_cost)
    lanes = lambda *names: [Action.of(0.0, n).index for n in names]  # noqa: E731
    sequences = np.array([lanes("right", "left", "left", "left", "left"), lanes("left", "left", "left", "left", "left"),
                          lanes("right", "right", "left", "left", "left"), lanes("left", "right", "left", "right", "left")])
    assert set_outs(sequences, "left").tolist() == [True, False, False, False]


def test_the_set_out_rule_moves_the_robot_as_each_candidate_does():
    """The human 1 m behind the robot and 6 m/s slower is 4.6 m behind 0.6 s from now if the robot
    keeps its speed: too close to set out; 5.3 m behind if the robot accelerates at 4 m/s² from now
    (the decisive kinematics reach it at once): room; 3.5 m if it brakes at 6 m/s². A candidate that
    holds its speed is judged as the robot keeping it (:meth:`DrivingStyle.blocks_set_out`)."""
    style = STYLES["planner-decisive"]
    robot = np.array([-120.0, RIGHT, 30.0, 0.0, 0.0, 0.0])
    human = robot + [-1.0, LEFT - RIGHT, -6.0, 0.0, 0.0, 0.0]
    assert style.blocks_set_out(robot, human)
    for acceleration, blocked in ((0.0, True), (4.0, False), (-6.0, True)):
        first, across = Action.of(acceleration, "right").index, Action.of(acceleration, "left").index
        states = robot_candidates(robot, first, style.kinematics).states
        sequence = (action_sequences(first)[:, 1:] == across).all(1)
        assert style.blocks_set_out_along(states[sequence], robot, human).tolist() == [blocked], acceleration
    holding = robot_candidates(robot, Action.of(0.0, "right").index, style.kinematics)
    held = (acceleration_indices(holding.actions) == 0).all(1)
    for gap in (-6.0, -4.0, 0.0, 4.9, 5.1, 8.0):
        for speed in (24.0, 30.0, 33.0):
            other = robot + [gap, LEFT - RIGHT, speed - 30.0, 0.0, 0.0, 0.0]
            along = style.blocks_set_out_along(holding.states[held], robot, other)
            assert (along == style.blocks_set_out(robot, other)).all()
    in_lane = robot + [-1.0, 0.0, -6.0, 0.0, 0.0, 0.0]  # the human in the robot's lane: nothing to wait for
    assert not style.blocks_set_out_along(holding.states, robot, in_lane).any()
    assert not STYLES["planner-paper"].blocks_set_out_along(holding.states, robot, human).any()


def _shortfall_by_simulation(robot, states, human, human_braking, kinematics, dt=1e-3):
    """:func:`stopping_shortfall` of one candidate ``states [15, 6]`` the long way: both cars'
    speeds integrated on a fine time grid, the gap checked at each step where the robot is in the
    human's way and, braking, at every point after the horizon if it still is."""
    if human[0] <= robot[0]:
        return 0.0
    b_h, b_r = max(human_braking, -human[4]), -min(kinematics.accelerations)
    t = np.arange(0.0, 30.0, dt)
    human_x = human[0] + np.concatenate([[0.0], np.cumsum(dt * np.maximum(human[2] - b_h * (t[:-1] + dt / 2), 0.0))])
    in_way = np.abs(states[:, 1] - human[1]) < FOLLOW_LATERAL
    gaps = [human_x[round(k * DT / dt)] - states[k - 1, 0] - COLLISION_DX for k in range(1, 7) if in_way[k - 1]]
    delay = 0.0 if kinematics.jerk is None else max(states[5, 4] + b_r, 0.0) / (2 * kinematics.jerk)
    braking = t >= 0.6 - dt / 2
    s = t[braking] - t[braking][0]
    v = max(states[5, 2], 0.0)  # braking to a stop, not reversing
    speed = np.where(s < delay, v, np.maximum(v - b_r * (s - delay), 0.0))
    robot_x = states[5, 0] + np.concatenate([[0.0], np.cumsum(dt * (speed[1:] + speed[:-1]) / 2)])
    gap = human_x[braking] - robot_x - COLLISION_DX
    gaps += [gap[round((k * DT - 0.6) / dt)] for k in range(6, 16) if in_way[k - 1]]
    if in_way[-1]:
        gaps.append(gap[s >= 0.9 - dt / 2].min())
    return max(-min(gaps, default=np.inf), 0.0)


@settings(max_examples=60, deadline=None)
@given(gap=st.floats(-2.0, 30.0), robot_speed=st.floats(0.0, 35.0), human_speed=st.floats(0.0, 35.0),
       human_acceleration=st.floats(-9.0, 2.0), offset=st.floats(-5.0, 5.0), first=st.integers(0, 7),
       kinematics=st.sampled_from(["settled", "comfort"]))
def test_the_stopping_shortfall_is_the_least_gap_of_both_cars_braking(gap, robot_speed, human_speed, human_acceleration,
                                                                      offset, first, kinematics):
    """The closed form (the least gap at the ends of the speeds' pieces or where they are equal)
    against both cars braked on a 1 ms grid, for candidates moving as each kinematics."""
    kinematics = KINEMATICS[kinematics]
    robot = np.array([0.0, RIGHT, robot_speed, 0.0, 0.0, 0.0])
    human = np.array([gap, RIGHT + offset, human_speed, 0.0, human_acceleration, 0.0])
    candidates = robot_candidates(robot, first, kinematics).states[::97]
    short = stopping_shortfall(robot, candidates, human, 6.0, kinematics)
    expected = [_shortfall_by_simulation(robot, c, human, 6.0, kinematics) for c in candidates]
    np.testing.assert_allclose(short, expected, atol=0.03)


def test_the_following_rule_keeps_a_gap_the_robot_can_stop_in():
    """A human 20 m ahead in the robot's lane, both at 20 m/s: holding the speed leaves room to stop
    behind it braking at 6 m/s² (0.6 s and a car length: 16.5 m), not once it brakes at 8 m/s²;
    braking harder in window 1 comes shorter by less;
    the rule is silent for a human behind or in the other lane, and the planner's rule cost is
    FOLLOW_COST per metre."""
    style = STYLES["planner-decisive"]
    robot = np.array([0.0, RIGHT, 20.0, 0.0, 0.0, 0.0])
    cruising = robot + [20.0, 0.0, 0.0, 0.0, 0.0, 0.0]
    braking = cruising + [0.0, 0.0, 0.0, 0.0, -8.0, 0.0]
    in_lane = [Action.of(a, "right").index for a in ACCELERATIONS]
    sequences = np.array([[in_lane[0], a, a, a, a] for a in in_lane])  # window 1 at 0, 4, -3, -6 m/s², held
    states = rollout(robot, sequences, style.kinematics)
    held, faster, slower, hardest = stopping_shortfall(robot, states, braking, style.follow_braking, style.kinematics)
    assert held > 0 and faster > held > slower > hardest
    assert stopping_shortfall(robot, states[:1], cruising, style.follow_braking, style.kinematics)[0] == 0.0
    behind = braking - [40.0, 0.0, 0.0, 0.0, 0.0, 0.0]
    other_lane = braking + [0.0, LEFT - RIGHT, 0.0, 0.0, 0.0, 0.0]
    for human in (behind, other_lane):
        np.testing.assert_array_equal(stopping_shortfall(robot, states, human, style.follow_braking, style.kinematics), 0.0)
    ramped = stopping_shortfall(robot, states, braking, style.follow_braking, KINEMATICS["comfort"])
    assert ramped[0] > held  # the comfort kinematics' braking ramps up at its jerk limit: it needs more room

    history = np.repeat(np.stack([robot, braking])[None], 6, axis=0)
    history[:, :, 0] += 20.0 * DT * np.arange(-5, 1)[:, None]
    keep, cost = in_lane[0], GoalToyCost(RIGHT)
    ruled = Planner(ToyHuman(), seed=0, style=style).plan(history, keep, cost)
    plain = Planner(ToyHuman(), seed=0, style=replace(style, follow_braking=0.0)).plan(history, keep, cost)
    expected = FOLLOW_COST * stopping_shortfall(robot, ruled.candidates.states, braking, style.follow_braking, style.kinematics)
    np.testing.assert_allclose(ruled.first_stage_cost - plain.first_stage_cost, expected, rtol=1e-5, atol=0.1)
    assert Action(int(ruled.actions[1])).acceleration == -6.0  # toy_cost alone prefers 4 m/s² in every window
    with pytest.raises(InputError):
        DrivingStyle(follow_braking=-1.0)


def test_in_its_goal_lane_the_robot_gets_going_again_where_nothing_holds_it():
    """Stopped in its goal lane 8 m short of the cutoff, a slow human 7 m ahead beside it: the paper's
    cost pays the robot for staying behind (separation reward) and ``planner``'s styles still
    accelerate (PROGRESS_COST per m/s of the horizon's end speed short of the floor: the rule costs
    exactly that), without the progress cost they stay; in the start lane, or faster than the
    floor, the cost is silent."""
    robot = np.array([CUTOFF_X - 8.0, RIGHT, 0.0, 0.0, 0.0, 0.0])
    human = np.array([CUTOFF_X - 1.0, LEFT + 0.5, 1.5, 0.0, 0.0, 0.0])
    history = np.repeat(np.stack([robot, human])[None], 6, axis=0)
    history[:, 1, 0] += 1.5 * DT * np.arange(-5, 1)
    keep, cost = Action.of(0.0, "right").index, PaperCost(goal_y=RIGHT)
    first = STYLES["planner"]
    for style in (first, first.fallback, first.safety_fallback):
        assert style.progress_cost == PROGRESS_COST
        ruled = Planner(ConstantVelocityHuman(), Budget(1, 8, 1), style=style).plan(history, keep, cost)
        plain = Planner(ConstantVelocityHuman(), Budget(1, 8, 1), style=replace(style, progress_cost=0.0)).plan(
            history, keep, cost)
        short = np.maximum(YIELD_SPEED_FLOOR - ruled.candidates.states[:, -1, 2], 0.0)
        np.testing.assert_allclose(ruled.first_stage_cost - plain.first_stage_cost, PROGRESS_COST * short, rtol=1e-5)
        assert Action(int(ruled.actions[1])).acceleration > 0 and ruled.robot[-1, 2] > 1.5
        assert plain.robot[-1, 2] < 0.5  # the paper's cost alone keeps it behind the human
    fast = history.copy()
    fast[:, 0, 2] = YIELD_SPEED_FLOOR + 0.5  # its braking candidates end the horizon below the floor
    for situation, goal_y in ((history, LEFT), (fast, RIGHT)):  # in the start lane; not slower than the floor
        ruled = Planner(ConstantVelocityHuman(), Budget(1, 8, 1), style=first).plan(situation, keep, PaperCost(goal_y))
        plain = Planner(ConstantVelocityHuman(), Budget(1, 8, 1), style=replace(first, progress_cost=0.0)).plan(
            situation, keep, PaperCost(goal_y))
        np.testing.assert_allclose(ruled.first_stage_cost, plain.first_stage_cost)
    with pytest.raises(InputError, match="progress_cost"):
        DrivingStyle(progress_cost=-1.0)


def _seconds_to_clear(robot, human, acceleration, gap, ahead, floor=-np.inf):
    """How long the robot holding ``acceleration`` from its state ``robot [6]`` (its speed kept at
    ``floor`` or above once it is) takes to get ``gap`` ahead of (or behind) the human ``human
    [6]``, holding its acceleration for HUMAN_ACCELERATION_HELD s and then its speed, on a 1 ms
    grid (20 s)."""
    t = np.arange(0, 20_001) * 1e-3
    integral = lambda speed: np.concatenate([[0.0], np.cumsum(0.5 * 1e-3 * (speed[1:] + speed[:-1]))])  # noqa: E731
    human_x = human[0] + integral(human[2] + human[4] * np.minimum(t, HUMAN_ACCELERATION_HELD))
    robot_x = robot[0] + integral(np.maximum(robot[2] + acceleration * t, min(floor, robot[2])))
    dx = robot_x - human_x
    clear = dx >= gap if ahead else dx <= -gap
    return t[np.argmax(clear)] if clear.any() else np.inf


@settings(max_examples=300, deadline=None)
@given(st.floats(-12.0, 12.0), st.floats(-4.0, 4.0), st.floats(-8.0, 4.0), st.floats(14.0, 32.0),
       st.sampled_from(["settled", "comfort"]), st.sampled_from(["holding", "accelerating", "braking"]))
def test_the_standoff_exit_takes_the_sooner_way_out_and_keeps_to_the_present_one_in_doubt(
        dx, dv, human_acceleration, speed, kinematics_name, present):
    """Against brute force, the robot braking to YIELD_SPEED_FLOOR and no slower: in doubt (neither
    way out YIELD_MARGIN s sooner) it yields, unless it is accelerating already."""
    kinematics = KINEMATICS[kinematics_name]
    robot_acceleration = {"holding": 0.0, "accelerating": max(kinematics.accelerations),
                          "braking": -kinematics.hardest_braking}[present]
    human = np.array([-100.0, LEFT, speed, 0.0, human_acceleration, 0.0])
    robot = np.array([-100.0 + dx, RIGHT, speed + dv, 0.0, robot_acceleration, 0.0])
    ahead = _seconds_to_clear(robot, human, max(kinematics.accelerations), SET_OUT_GAP, True)
    behind = _seconds_to_clear(robot, human, -kinematics.hardest_braking, SET_OUT_GAP, False, YIELD_SPEED_FLOOR)
    way_out = kinematics.accelerations[standoff_exit(robot, human, kinematics, SET_OUT_GAP)]
    doubt = ahead + YIELD_MARGIN > behind + 2e-3 and behind + YIELD_MARGIN > ahead + 2e-3  # neither clearly sooner
    if ahead + YIELD_MARGIN < behind - 2e-3 or doubt and present == "accelerating":
        assert way_out == max(kinematics.accelerations)
    elif behind + YIELD_MARGIN < ahead - 2e-3 or (doubt or ahead == behind == np.inf) and present != "accelerating":
        assert way_out == -kinematics.hardest_braking


def test_the_standoff_exit_yields_down_to_the_speed_floor_and_no_further():
    """2 m behind a human at the same speed, the robot drops behind (hardest braking) at 29 m/s;
    at YIELD_SPEED_FLOOR it cannot brake any more, so it goes ahead instead."""
    kinematics = KINEMATICS["settled"]
    for speed, way_out in ((29.0, -6.0), (YIELD_SPEED_FLOOR, 4.0)):
        human = np.array([-60.0, LEFT, speed, 0.0, 0.0, 0.0])
        robot = human + [-2.0, RIGHT - LEFT, 0.0, 0.0, 0.0, 0.0]
        assert kinematics.accelerations[standoff_exit(robot, human, kinematics, SET_OUT_GAP)] == way_out


def _side_by_side(robot_accelerations, human_accelerations, dx=0.0):
    """Both cars' states ``[t+1, 2, 6]`` from 29 m/s side by side (the robot ``dx`` m ahead),
    moving with the accelerations ``[t+1]`` (m/s²) of each (trapezoid rule, as the world)."""
    cars = []
    for x, y, acceleration in ((-160.0 + dx, RIGHT, robot_accelerations), (-160.0, LEFT, human_accelerations)):
        acceleration = np.asarray(acceleration, dtype=float)
        position, speed = integrate_trapezoid(x, 29.0, acceleration)
        zeros = np.zeros_like(position)
        cars.append(np.stack([position, zeros + y, speed, zeros, acceleration, zeros], axis=-1))
    return np.stack(cars, axis=1)


def test_the_way_out_goes_ahead_once_the_human_has_braked_along():
    """Side by side, the robot has braked at 4 m/s² for a second, then held its speed: the present
    states alone say drop behind. A human that braked as hard (brakes_along) makes the robot go
    ahead, also 2 s later, and makes comfort first fall back on the decisive style; one that kept
    its speed, braked at half the robot's rate or at twice it (the speeds part: the way ahead opens
    by itself), or braked along while far ahead (no stand-off), does not."""
    first = replace(STYLES["planner"], standoff_within=0.0)  # beside the human yielding, not time, makes it fall back
    style = first.fallback
    keep = Action.of(0.0, "right").index
    braking = [0.0] * 5 + [-4.0] * 10 + [0.0]
    for human, along in ((braking, True), ([0.0] * 16, False), ([0.0] * 5 + [-2.0] * 10 + [0.0], False)):
        history = _side_by_side(braking, human, dx=2.0 * along - 1.0)  # 1 m behind or ahead: no way ahead before
        assert brakes_along(history) == along
        assert style.kinematics.accelerations[standoff_exit(*history[-1], style.kinematics, SET_OUT_GAP)] == -6.0
        assert style.human_yields(history) == along
        assert style.kinematics.accelerations[style.way_out(history)] == (4.0 if along else -6.0)
        assert first.fallback_for(history, keep, LEFT) is (style if along else None)
    harder = _side_by_side(braking, [0.0] * 5 + [-8.0] * 10 + [0.0], dx=1.0)  # the human braking twice as hard
    assert not brakes_along(harder) and not style.human_yields(harder) and first.fallback_for(harder, keep, LEFT) is None
    assert style.way_out(harder) == standoff_exit(*harder[-1], style.kinematics, SET_OUT_GAP)  # ahead opens by itself
    later = _side_by_side(braking + [0.0] * 20, braking + [0.0] * 20, dx=1.0)
    assert not brakes_along(later) and style.human_yields(later) and first.fallback_for(later, keep, LEFT) is style
    assert style.kinematics.accelerations[style.way_out(later)] == 4.0
    far = _side_by_side(braking, braking, dx=-30.0)
    assert brakes_along(far) and not style.human_yields(far) and first.fallback_for(far, keep, LEFT) is None
    assert not brakes_along(_side_by_side([0.0] * 3 + [-4.0] * 3, [0.0] * 3 + [-4.0] * 3))  # too short a history


def test_the_standoff_exit_makes_room_beside_the_human():
    """2 m behind the human at the same speed, the robot yields (hardest braking); 4 m ahead, or
    beside a human braking at 8 m/s², it goes ahead. The planner costs every other window-1
    acceleration ``standoff_exit_cost`` while the set-out rule holds the robot in its lane, and
    only then."""
    style = STYLES["planner"].fallback
    assert style.standoff_exit_cost == STYLES["planner"].standoff_exit_cost == STANDOFF_EXIT_COST
    history = _history()
    robot, human = history[-1]
    assert style.blocks_set_out(robot, human)  # the human 2 m ahead at the same speed
    assert style.kinematics.accelerations[standoff_exit(robot, human, style.kinematics, SET_OUT_GAP)] == -6.0
    ahead = robot + [6.0, 0.0, 0.0, 0.0, 0.0, 0.0]
    assert style.kinematics.accelerations[standoff_exit(ahead, human, style.kinematics, SET_OUT_GAP)] == 4.0
    braking = human + [0.0, 0.0, 0.0, 0.0, -8.0, 0.0]  # a human that yields too: the robot goes ahead
    assert style.kinematics.accelerations[standoff_exit(robot, braking, style.kinematics, SET_OUT_GAP)] == 4.0
    keep, cost = Action.of(0.0, "right").index, GoalToyCost(LEFT)
    ruled = Planner(ToyHuman(), seed=0, style=style).plan(history, keep, cost)
    plain = Planner(ToyHuman(), seed=0, style=replace(style, standoff_exit_cost=0.0)).plan(history, keep, cost)
    exits = np.array([Action(int(a)).acceleration for a in ruled.candidates.actions[:, 1]]) == -6.0
    np.testing.assert_allclose(ruled.first_stage_cost - plain.first_stage_cost, STANDOFF_EXIT_COST * ~exits, atol=0.1)
    assert Action(int(ruled.actions[1])).acceleration == -6.0 and Action(int(plain.actions[1])).acceleration == 4.0
    clear = history.copy()
    clear[:, 1, 0] += 30.0  # the human 32 m ahead: no stand-off, no exit cost
    ruled = Planner(ToyHuman(), seed=0, style=style).plan(clear, keep, cost)
    plain = Planner(ToyHuman(), seed=0, style=replace(style, standoff_exit_cost=0.0)).plan(clear, keep, cost)
    np.testing.assert_allclose(ruled.first_stage_cost, plain.first_stage_cost)
    with pytest.raises(InputError, match="standoff_exit_cost"):
        DrivingStyle(standoff_exit_cost=-1.0)


def test_the_set_out_rule_watches_the_gap_while_each_styles_lane_change_crosses_the_divider():
    """With half a second or more to spare either side, for the lane change from rest set out in
    window 1 (0.3 s from now); the styles' fallbacks too."""
    times = np.arange(1, 61) * DT
    for name, style in [(name, style) for name, top in STYLES.items()
                       for style in (top, top.fallback, top.safety_fallback) if style is not None]:
        if style.set_out_gap:
            y = style.kinematics.steer(np.array([RIGHT, 0.0, 0.0]), np.array(LEFT), times)[:, 0]
            over = np.abs(y - LANE_DIVIDER_Y) < CAR_WIDTH / 2  # the robot's body over the divider
            first, last = 0.3 + times[over][[0, -1]]
            assert style.set_out_times[0] <= first - 0.45 and style.set_out_times[-1] >= last + 0.45, name


def test_a_style_falls_back_when_time_runs_short_or_the_human_ahead_brakes_harder_than_it_can():
    """The fallback plans from the first window the robot, settled in its start lane, would reach the
    cutoff within ``fallback_within`` s, or ``standoff_within`` s while the set-out rule holds it
    and would still hold it ``fallback_within`` s before the cutoff (not while a lane change is
    under way), or, in either lane or moving between them, the human ahead in its way brakes harder
    than the style's kinematics can."""
    comfort, quick = STYLES["planner-comfort"], STYLES["planner-decisive"]
    style = replace(comfort, fallback=quick, fallback_within=2.0, standoff_within=3.0)
    keep, go = Action.of(0.0, "right").index, Action.of(0.0, "left").index

    def car(seconds_to_cutoff, speed=30.0, y=RIGHT, yd=0.0):
        return np.array([CUTOFF_X - 30.0 * seconds_to_cutoff, y, speed, yd, 0.0, 0.0])

    def fallback(style, robot, human, first_action, goal_y):  # from the present states alone
        return style.fallback_for(np.stack([robot, human])[None], first_action, goal_y)

    far = car(5.0, y=LEFT)
    assert fallback(style, car(1.95), far, keep, LEFT) is quick and fallback(style, car(2.05), far, keep, LEFT) is None
    assert fallback(style, car(1.0), far, go, LEFT) is None  # set out: window 0 heads for the goal lane
    assert fallback(style, car(1.0, y=RIGHT + 0.5), far, keep, LEFT) is None  # turning back, not yet settled
    assert fallback(style, car(1.0, yd=0.5), far, keep, LEFT) is None
    assert fallback(style, car(1.0), far, keep, None) is None  # a cost without a goal lane
    assert fallback(style, car(1.0, speed=0.0), far, keep, LEFT) is None  # standing still
    assert fallback(comfort, car(0.5), far, keep, LEFT) is None  # no fallback
    # a stand-off: beside the human at its speed 2.9 s before the cutoff; not when drifting apart, or earlier
    assert style.blocks_set_out(car(2.9), car(2.9, y=LEFT)) and not style.blocks_set_out(car(2.9), far)
    assert not style.blocks_set_out(car(2.9), car(2.9))  # the human in the robot's lane
    assert fallback(style, car(2.9), car(2.9, y=LEFT), keep, LEFT) is quick
    assert fallback(style, car(2.9), car(2.9, speed=25.0, y=LEFT), keep, LEFT) is None  # clear in time
    assert style.blocks_set_out(car(2.9), car(2.9, speed=25.0, y=LEFT))
    assert fallback(style, car(3.1), car(3.1, y=LEFT), keep, LEFT) is None
    # settled in the goal lane behind a human that brakes harder than the comfort kinematics can: braking is not held to comfort
    ahead = car(4.0, y=LEFT) + [20.0, 0.0, 0.0, 0.0, -(comfort.kinematics.hardest_braking + 0.5), 0.0]
    assert fallback(style, car(5.0, y=LEFT), ahead, go, LEFT) is quick
    assert fallback(style, car(5.0, y=LEFT), ahead + [0, 0, 0, 0, 1.0, 0], go, LEFT) is None  # within the kinematics' braking
    assert fallback(style, car(5.0, y=LEFT, yd=0.5), ahead, go, LEFT) is quick  # not settled: nor put off
    assert fallback(style, car(5.0, y=(LEFT + RIGHT) / 2, yd=1.5), ahead, go, LEFT) is quick  # moving across
    assert fallback(style, car(5.0), ahead, keep, LEFT) is None  # in the other lane: not in the robot's way
    assert fallback(style, car(5.0), ahead, go, LEFT) is quick  # the robot heading into its lane
    assert fallback(style, car(3.0, y=LEFT), ahead, go, LEFT) is None  # behind the robot
    # with a safety fallback, braking for safety alone falls back on it; time, or both, on the fallback
    safe = replace(style, safety_fallback=replace(comfort, kinematics=KINEMATICS["safety"]))
    assert fallback(safe, car(5.0, y=(LEFT + RIGHT) / 2, yd=1.5), ahead, go, LEFT) is safe.safety_fallback
    assert fallback(safe, car(1.95), far, keep, LEFT) is quick
    braking_ahead = car(1.5) + [0.0, 0.0, 0.0, 0.0, -(comfort.kinematics.hardest_braking + 0.5), 0.0]  # in the robot's lane
    assert fallback(safe, car(3.0), braking_ahead, keep, LEFT) is safe.safety_fallback
    assert fallback(safe, car(1.95), braking_ahead, keep, LEFT) is quick
    for fallbacks in ({"fallback": style}, {"safety_fallback": style}, {"safety_fallback": replace(comfort, safety_fallback=quick)}):
        with pytest.raises(InputError):
            DrivingStyle(**fallbacks)  # a fallback has none of its own
    with pytest.raises(InputError):
        DrivingStyle(standoff_within=-1.0)

    # the planner plans in the style it is given, moving as that style
    planner, cost = Planner(ToyHuman(), seed=0, style=style), GoalToyCost(LEFT)
    for given, kinematics in ((None, comfort.kinematics), (quick, quick.kinematics)):
        plan = planner.plan(HISTORY_TOY, keep, cost, style=given)
        assert plan.style is (given or style)
        np.testing.assert_array_equal(plan.robot, robot_candidates(PRESENT_TOY, keep, kinematics).states[plan.index])
    with pytest.raises(InputError):
        planner.plan(HISTORY_TOY, keep, cost, style="decisive")


def test_mpc_plans_in_the_fallback_from_the_first_plan_that_needs_it_to_the_end_of_the_episode():
    """A robot 3 s before the cutoff beside a slower human (4 m ahead, 5 m/s slower) it cannot set
    out beside yet, the fallback within 2.5 s: the first plans are comfortable, then every plan
    falls back, also once the lane change is under way; a new episode starts over."""
    torch.manual_seed(0)
    style = replace(STYLES["planner-comfort"], fallback=STYLES["planner-decisive"], fallback_within=2.5)
    policy = MPCPolicy(Planner(ConstantVelocityHuman(), Budget(1, 2, 2), style=style))
    start = np.array([[[CUTOFF_X - 29.0 * 3.0 - 29.0 * DT * (HOLD_STEPS - 1), RIGHT, 29.0, 0, 0, 0],
                       [CUTOFF_X - 29.0 * 3.0 - 29.0 * DT * (HOLD_STEPS - 1) + 4.0, LEFT, 24.0, 0, 0, 0]]])
    for _ in range(2):
        world = World(start)
        policy.reset(np.random.default_rng(0), world.states[:, :, 0], 0)
        for _ in range(HOLD_STEPS + 30):
            world.step(np.stack([policy.act(world.history), np.zeros((1, 2))], axis=1))
        seconds = [(CUTOFF_X - world.history[0, 0, t, 0]) / world.history[0, 0, t, 2] for t in policy.plan_steps]
        fell = next(k for k, s in enumerate(seconds) if s < 2.5)
        assert fell > 0 and all(p.style is style for p in policy.plans[:fell])
        assert all(p.style is STYLES["planner-decisive"] for p in policy.plans[fell:]) and policy.fallen_back
        assert any(Action(int(p.actions[0])).lane == "left" for p in policy.plans[fell:])  # under way, still
        assert world.history[0, 0, -1, 1] > LANE_DIVIDER_Y  # across


def test_mpc_keeps_to_the_safety_fallback_until_time_asks_for_the_fallback():
    """Comfort first: a human braking hard ahead while the robot moves across switches to the safety
    fallback (the decisive braking, the comfort steering), which stays when the human stops braking;
    time running short switches to the decisive fallback, which stays to the end of the episode."""
    first = STYLES["planner"]
    policy = MPCPolicy(Planner(ConstantVelocityHuman(), Budget(1, 2, 2), style=first))
    keep, go = Action.of(0.0, "right").index, Action.of(0.0, "left").index

    def car(seconds_to_cutoff, y=RIGHT, yd=0.0, xdd=0.0):
        return np.array([CUTOFF_X - 30.0 * seconds_to_cutoff, y, 30.0, yd, xdd, 0.0])

    policy.reset(np.random.default_rng(0), np.stack([car(8.0), car(8.0, y=LEFT)])[None], 0)
    braking = np.stack([car(5.0, y=(LEFT + RIGHT) / 2, yd=1.5), car(4.5, y=LEFT, xdd=-5.0)])[None]
    assert policy.plan_style(np.stack([car(6.0), car(2.0, y=LEFT)])[None], keep) is first and policy.fallen_back is None
    assert policy.plan_style(braking, go) is first.safety_fallback
    assert first.safety_fallback.kinematics == KINEMATICS["safety"] and first.safety_fallback.follow_braking == 6.0
    assert policy.plan_style(np.stack([car(6.0), car(2.0, y=LEFT)])[None], keep) is first.safety_fallback
    assert policy.plan_style(np.stack([car(1.9), car(5.0, y=LEFT)])[None], keep) is first.fallback
    assert policy.plan_style(braking, go) is first.fallback
    policy.reset(np.random.default_rng(0), np.stack([car(8.0), car(8.0, y=LEFT)])[None], 0)
    assert policy.fallen_back is None and policy.plan_style(braking, go) is first.safety_fallback


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


# ---------------------------------------------------------------- deadlines and MPC
def _history(steps=10):
    robot = np.array([-120.0, RIGHT, 29.0, 0.0, 0.0, 0.0])
    human = np.array([-118.0, LEFT, 29.0, 0.0, 0.0, 0.0])
    t = DT * np.arange(steps)[:, None]
    return np.stack([robot + t * [29.0, 0, 0, 0, 0, 0], human + t * [29.0, 0, 0, 0, 0, 0]], axis=1)


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


def test_mpc_holds_then_replans_every_window_with_the_fixed_first_window():
    torch.manual_seed(0)
    policy = MPCPolicy(Planner(HumanPredictor(CVAE())), budget=Budget(1, 2, 2))
    world = World(_history(1))  # one episode; the robot is car 0, the human keeps its speed
    policy.reset(np.random.default_rng(0), world.states[:, :, 0], 0)
    for _ in range(HOLD_STEPS + 9):
        world.step(np.stack([policy.act(world.history), np.zeros((1, 2))], axis=1))
    robot = world.history[0, 0]
    np.testing.assert_allclose(robot[: HOLD_STEPS + 1, 1], RIGHT)
    np.testing.assert_allclose(robot[: HOLD_STEPS + 1, 2], 29.0)
    assert len(policy.plans) == len(policy.latencies) == 3  # at t = 8, 11, 14
    assert policy.plans[0].actions[0] == Action.of(0.0, "right").index
    for previous, current in zip(policy.plans, policy.plans[1:]):
        assert current.actions[0] == previous.actions[1]
    # what the robot executed in window t = 11..14 is the first plan's window 1, from its state at t = 11
    executed = rollout(robot[11], policy.plans[0].actions[1:2][None])[0]
    np.testing.assert_allclose(robot[12:15, 5], executed[:, 5])
    np.testing.assert_allclose(robot[12:14, 4], executed[:2, 4])


def test_settled_steering_comes_to_rest_on_the_lane_centre_where_the_papers_keeps_chattering():
    """Executed as the world executes a plan (one acceleration a step, trapezoid rule), the paper's
    steering re-solves the sampling's residue on the lane centre every window into ±0.7 m/s²; with
    lateral manoeuvres of at least SETTLING_TIME the same lane change comes to rest."""
    from trafficweaving.dynamics import trapezoid_step

    def executed(kinematics, windows=30):
        state, accelerations = np.array([-300.0, RIGHT, 30.0, 0.0, 0.0, 0.0]), []
        for _ in range(windows):
            for planned in rollout(state, np.array([[Action.of(0.0, "left").index]]), kinematics)[0]:
                y, yd = trapezoid_step(state[1], state[3], state[5], planned[5])
                state = np.array([planned[0], y, planned[2], yd, planned[4], planned[5]])
                accelerations.append(planned[5])
        return np.array(accelerations), state

    paper, _ = executed(KINEMATICS["paper"])
    settled, end = executed(KINEMATICS["settled"])
    assert np.abs(paper[-30:]).max() > 0.5 and np.abs(settled[-30:]).max() < 0.01
    assert abs(end[1] - LANE_CENTRE_Y["left"]) < 0.01 and abs(end[3]) < 0.01
    assert np.abs(settled).max() == pytest.approx(np.abs(paper[:30]).max(), rel=0.1)  # the same lane change
    assert float(optimal_time(np.array([LEFT + 0.01, 0.0, 0.0]), np.array(LEFT), min_time=SETTLING_TIME)) >= SETTLING_TIME


def test_comfort_candidates_keep_to_the_comfort_limits_from_every_state_they_reach():
    """From the right lane towards the left one, lane changes turned back included; the paper's
    candidates break the limits in most sequences."""
    from trafficweaving.sim.score import comfort_violations  # the closed loop's own definition

    def onward(present, first, kinematics):  # per candidate: a step over the limits (the present included)
        states = robot_candidates(present, first, kinematics).states
        acc = np.concatenate([np.broadcast_to(present[4:6], (len(states), 1, 2)), states[..., 4:6]], 1)
        return np.array([comfort_violations(a).any() for a in acc]), states

    start = np.array([-100.0, RIGHT, 30.0, 0.0, 0.0, 0.0])
    rng = np.random.default_rng(0)
    presents = [start]
    for first in (0, 1, 3, 6):  # states after a window and after two, as the MPC executes them
        _, states = onward(start, first, KINEMATICS["comfort"])
        picks = rng.choice(len(states), 3, replace=False)
        presents += [states[i, 2] for i in picks] + [states[i, 5] for i in picks]
    assert max(p[3] for p in presents) > 0.5  # some of them under way
    checked = 0
    for present in presents:
        for first in (0, 3, N_ACTIONS - 1):
            violations, _ = onward(present, first, KINEMATICS["comfort"])
            assert not violations.any()
            checked += len(violations)
    assert checked == 3 * len(presents) * N_CANDIDATES
    assert onward(start, 0, KINEMATICS["paper"])[0].mean() > 0.5
    comfort = robot_candidates(presents[-1], 0, KINEMATICS["comfort"]).states
    np.testing.assert_allclose(np.diff(comfort[..., 2], axis=1), DT * comfort[:, :-1, 4], atol=1e-12)  # Euler velocity


def test_a_comfort_planner_drives_the_closed_loop_within_the_limits():
    from trafficweaving.sim.score import comfort_violations

    torch.manual_seed(0)
    policy = MPCPolicy(Planner(HumanPredictor(CVAE()), style=STYLES["planner-comfort"]), budget=Budget(1, 2, 2))
    world = World(_history(1))
    policy.reset(np.random.default_rng(0), world.states[:, :, 0], 0)
    for _ in range(40):
        world.step(np.stack([policy.act(world.history), np.zeros((1, 2))], axis=1))
    assert len(policy.plans) >= 10 and not comfort_violations(world.history[0, 0, :, 4:6]).any()
