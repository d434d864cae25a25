"""The synthetic human–human generator: protocol, dynamics invariants, validity and statistics."""


import numpy as np
import pytest

from trafficweaving.data.behaviour import behaviour_samples, compare_behaviour
from trafficweaving.sim.drivers import FULL_THROTTLE, HARD_BRAKE, MAX_LATERAL_ACCEL
from trafficweaving.sim.generate import generate_trials, schedule
from trafficweaving.data.stats import TABLE1_PAPER, left_car_in_front, table1
from trafficweaving.scenario import (
    COLLISION_DX, COLLISION_DY, CUTOFF_X, DT, ROAD_Y_MAX, ROAD_Y_MIN, SWAP_THRESHOLD_Y,
)



@pytest.fixture(scope="module")
def big():
    return generate_trials(3000, seed=11)


def test_same_seed_same_data_other_seed_other_data():
    a, _ = generate_trials(40, seed=1)
    b, _ = generate_trials(40, seed=1)
    c, _ = generate_trials(40, seed=2)
    np.testing.assert_array_equal(a.states, b.states)
    assert not np.array_equal(a.lengths, c.lengths) or not np.allclose(a.states[:, :, :45], c.states[:, :, :45], equal_nan=True)


def test_protocol_rounds_of_18_and_pairs():
    ic, pair = schedule(18 * 19 * 2, 19, np.random.default_rng(0))
    for r in range(38):  # every round plays all 18 configurations once
        assert sorted(ic[18 * r: 18 * (r + 1)]) == list(range(18))
    assert np.bincount(pair).tolist() == [36] * 19


@pytest.mark.slow
def test_exactly_n_valid_trials_with_a_report(big):
    trials, report = big
    assert len(trials) == 3000 and report.kept == 3000
    assert report.simulated == 3000 + sum(report.rejected.values())
    assert sum(report.rejected.values()) / report.simulated < 0.06  # failures are rare
    assert set(trials.drivers.ravel()) == set(range(38))
    assert (trials.drivers[:, 1] == trials.drivers[:, 0] + 1).all()


def test_kept_trials_obey_the_validity_rules(big):
    trials, _ = big
    s, n = trials.states, trials.lengths
    rec = np.arange(s.shape[2])[None, :] < n[:, None]
    dx, dy = np.abs(s[:, 0, :, 0] - s[:, 1, :, 0]), np.abs(s[:, 0, :, 1] - s[:, 1, :, 1])
    assert not ((dx < COLLISION_DX) & (dy < COLLISION_DY) & rec).any()
    y = np.where(rec[:, None], s[..., 1], -4.0)
    assert ((y >= ROAD_Y_MIN) & (y <= ROAD_Y_MAX)).all()
    last = s[np.arange(len(n)), :, n - 1]  # [n, 2, 6]
    assert (last[..., 0] < CUTOFF_X).all()  # cut before the first car reaches the cutoff
    leader = last[..., 0].argmax(axis=1)
    y0 = s[np.arange(len(n)), leader, 0, 1]
    y_end = last[np.arange(len(n)), leader, 1]
    assert ((SWAP_THRESHOLD_Y - y0) * (SWAP_THRESHOLD_Y - y_end) < 0).all()  # the leader has swapped
    assert 40 <= n.mean() <= 56  # about 5 s, as the paper's trials


def test_dynamics_are_trapezoid_integrals_of_bounded_human_accelerations(big):
    trials, _ = big
    s = trials.states
    for p, v, a in ((0, 2, 4), (1, 3, 5)):
        dv = np.diff(s[..., v], axis=2) - 0.5 * DT * (s[..., a][..., 1:] + s[..., a][..., :-1])
        dp = np.diff(s[..., p], axis=2) - 0.5 * DT * (s[..., v][..., 1:] + s[..., v][..., :-1])
        assert np.nanmax(np.abs(dv)) < 1e-9 and np.nanmax(np.abs(dp)) < 1e-9
    xdd = s[..., 4][~np.isnan(s[..., 4])]
    assert xdd.min() >= -HARD_BRAKE - 1e-9 and xdd.max() <= FULL_THROTTLE + 1e-9
    speed = s[..., 2][~np.isnan(s[..., 2])]
    assert 10 < speed.min() and np.percentile(speed, 1) > 20 and speed.max() < 42
    # human-like lateral motion: bounded lateral acceleration, no lateral teleporting
    assert np.nanmax(np.abs(s[..., 5])) <= MAX_LATERAL_ACCEL + 1e-9


def test_table1_is_reproduced_and_outcomes_are_multimodal(big):
    trials, _ = big
    result = table1(trials)
    for dv, cells in TABLE1_PAPER.items():
        for k, target in cells.items():
            n = result["counts"][dv][k]
            se = np.sqrt(target * (1 - target) / n)
            # within 3 standard errors of the paper's value at this sample size, and within 8 pp
            assert abs(result["table1"][dv][k] - target) < max(3 * se, 0.02) and abs(result["table1"][dv][k] - target) < 0.08, (dv, k)
    front = left_car_in_front(trials)
    for dv in (-2, 0, 2):  # every initial condition shows both outcomes
        sel = np.round(trials.ic_dv) == dv
        assert 0 < front[sel].mean() < 1


def test_drivers_accelerate_brake_and_coast_like_people(big):
    trials, _ = big
    s = behaviour_samples(trials)
    accel = s["long_accel"]
    coasting = np.mean((accel > -0.6) & (accel < 0))
    assert coasting > 0.3  # feet off the pedals much of the time, as real drivers
    assert np.mean(accel > 2) > 0.05 and np.mean(accel < -2) > 0.03  # throttle and brake episodes
    assert -40 < np.percentile(s["lane_change_x"], 50) < -25  # real: -32 m; late lane changes fail this


def test_drivers_hold_their_controls_intermittently(big):
    """Real drivers hold lateral acceleration on 27 % of steps (runs: median 2, p90 7, max 19 steps)
    and longitudinal acceleration on 44 % (runs: median 2.5, p90 10); drivers adjusting every step
    (the old wobble model: 3 % lateral, runs of at most 3 steps) fail this."""
    s = behaviour_samples(big[0])
    assert 0.15 < s["lat_hold"].mean() < 0.45
    assert 0.35 < s["long_hold"].mean() < 0.6  # coasting as one long hold (60 %) fails this
    for direction in ("lat", "long"):
        runs = s[f"{direction}_hold_run"]
        assert np.percentile(runs, 90) >= 4 and runs.max() >= 15, direction
        assert 1 <= np.median(runs) <= 4, direction


def test_drivers_change_lane_slowly_and_press_around_it(big):
    s = behaviour_samples(big[0])
    assert 1.6 < np.median(s["lane_change_sideways_time"]) < 2.4  # real: 1.9 s
    assert np.median(s["long_accel_abs_near_crossing"]) > 1.15  # real: 1.8 m/s², old wobble model: 0.8
    # both cars are seen crossing the divider in most trials (real: every recorded human)
    assert len(s["lane_change_sideways_time"]) == len(s["lane_change_x"]) >= 2 * len(big[0]) * 0.88


@pytest.mark.slow
def test_marginals_are_close_to_the_real_human_drivers(big, hitl_trials):
    comparison = compare_behaviour(behaviour_samples(big[0]), behaviour_samples(hitl_trials))
    for name in ("speed", "long_accel", "lat_accel", "long_jerk", "lat_jerk", "lane_change_x", "long_hold",
                 "lat_hold", "long_hold_run", "lat_hold_run", "lane_change_sideways_time"):
        assert comparison[name]["wasserstein_over_std"] < 0.7, name
