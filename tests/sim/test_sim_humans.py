"""Human agents for closed loop (sim/humans.py): synthetic drivers with sampled styles, a human
model as a driver, a recorded human replayed; the spec factory and its errors."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st

from trafficweaving.data.trials import load_trials
from trafficweaving.dynamics import constant_acceleration_future, future_states, without_reversing
from trafficweaving.errors import InputError
from trafficweaving.model.registry import load_model
from trafficweaving.scenario import (CUTOFF_X, DT, HORIZON, LANE_CENTRE_Y, LANE_DIVIDER_Y, MIN_HISTORY, START_X,
                                   SWAP_THRESHOLD_Y, on_road, study_initial_conditions)
from trafficweaving.sim.drivers import DriverModel, DriverStyles
from trafficweaving.sim.generate import generate_trials
from trafficweaving.sim.humans import (ConstantVelocityDriver, ModelDriver, ReplayDriver, SampledDrivers, SyntheticDrivers,
                                      human_agent, keep_on_road, lateness)
from trafficweaving.sim.world import run_episodes


class LaneChangeRobot:
    """Test robot: holds its speed and steers into the other lane (a damped spring, m/s²). With a
    ``human`` (a :class:`ModelDriver` with ``robot_plan``), it tells the human its plan each step:
    its states when it holds zero acceleration (it acts before the human: car 0)."""

    def __init__(self, human: ModelDriver | None = None):
        self.human = human

    def reset(self, rng, start, me):
        self.me = me
        self.target = np.where(start[:, me, 1] > LANE_DIVIDER_Y, LANE_CENTRE_Y["right"], LANE_CENTRE_Y["left"])

    def act(self, history):
        now = history[:, self.me, -1]
        if self.human is not None:
            self.human.robot_future = future_states(now, np.zeros((len(now), HORIZON, 2)))
        ydd = np.clip(0.5 * (self.target - now[:, 1]) - 1.4 * now[:, 3], -2.0, 2.0)
        return np.stack([np.zeros(len(now)), ydd], axis=1)


def study_starts(*index):
    ics = study_initial_conditions()
    return np.stack([ics[i].start_states() for i in index])


def run(human, start, seed=0, robot=None):
    """Both cars' recorded states ``[m, 2, T, 6]`` with the robot as car 0, the human as car 1."""
    world = run_episodes(start, [robot or LaneChangeRobot(), human], np.random.default_rng(seed))
    return world.recorded()[0]


class Recorder:
    """Wraps a model driver's ``sample``: records each call's situations and the blocks drawn."""

    def __init__(self, agent: ModelDriver):
        self.calls, self.blocks, sample = [], [], agent.sample
        agent.sample = lambda histories, futures: (self.calls.append((np.array(histories), np.array(futures))),
                                                   self.blocks.append(sample(histories, futures)))[1] or self.blocks[-1]


@pytest.fixture(scope="module")
def default_model():
    return load_model("default")


@pytest.fixture(scope="module")
def replay_file(tmp_path_factory):
    """3 synthetic trials with agent 0 relabelled ``robot``, as a Parquet file."""
    trials, _ = generate_trials(3, seed=1)
    trials.roles[:, 0] = "robot"
    path = tmp_path_factory.mktemp("replay") / "trials.parquet"
    trials.write_parquet(path)
    return path


# ------------------------------------------------------------------ closed loop, every human
@pytest.fixture(params=["synthetic", "model:default", "replay"])
def spec(request, replay_file):
    return f"replay:{replay_file}" if request.param == "replay" else request.param


@pytest.mark.slow
def test_closed_loop_contract_and_determinism(spec):
    start = study_starts(0, 7)
    agent = human_agent(spec)
    agent.reset(np.random.default_rng(0), start, 1)
    history = np.repeat(start[:, :, None], MIN_HISTORY + 1, axis=2)
    actions = agent.act(history)
    assert actions.shape == (2, 2) and np.isfinite(actions).all()

    states = run(human_agent(spec), start, seed=4)
    assert states.shape[:2] == (2, 2) and states.shape[2] > 20 and np.isfinite(states).all()
    np.testing.assert_array_equal(states, run(human_agent(spec), start, seed=4))
    if not spec.startswith("replay:"):  # a replay of one drawn trial may draw the same one
        assert not np.array_equal(states, run(human_agent(spec), start, seed=5))


def test_authors_model_drives(authors_model_dir):
    states = run(human_agent(f"model:authors:{authors_model_dir / 'weights.npz'}"), study_starts(3))
    assert np.isfinite(states).all() and states.shape[2] > 20


# ------------------------------------------------------------------ synthetic
def test_sampled_drivers_are_synthetic_drivers_with_styles_from_the_rng():
    start = study_starts(1, 2, 9)
    rng = np.random.default_rng(11)
    styles = DriverStyles.sample(DriverModel(), len(start), rng)  # what reset draws first
    expected = run_episodes(start, [LaneChangeRobot(), SyntheticDrivers(styles)], rng).recorded()[0]
    np.testing.assert_array_equal(run(SampledDrivers(), start, seed=11), expected)


# ------------------------------------------------------------------ model
def test_constant_acceleration_future():
    present = np.array([[-100.0, -1.8, 29.0, 0.1, 0.5, -0.2], [-90.0, -6.1, 27.0, 0.0, 0.0, 0.0]])
    future = constant_acceleration_future(present)
    assert future.shape == (2, HORIZON, 6)
    np.testing.assert_allclose(constant_acceleration_future(torch.as_tensor(present)).numpy(), future)
    tau = DT * np.arange(1, HORIZON + 1)[:, None]  # s
    np.testing.assert_allclose(future[..., 4:6], np.repeat(present[:, None, 4:6], HORIZON, 1))
    np.testing.assert_allclose(future[..., 2:4], present[:, None, 2:4] + present[:, None, 4:6] * tau, atol=1e-12)
    np.testing.assert_allclose(future[..., 0:2], present[:, None, 0:2] + present[:, None, 2:4] * tau
                               + 0.5 * present[:, None, 4:6] * tau**2, atol=1e-12)


def test_model_driver_conditions_on_its_history_robot_first_and_the_guess(default_model):
    """The human as car 0: the model sees the robot (car 1) first, and the robot holding its
    present acceleration."""
    start = study_starts(4)
    agent = ModelDriver(default_model)
    recorder = Recorder(agent)
    world = run_episodes(start, [agent, LaneChangeRobot()], np.random.default_rng(2), max_steps=12)
    history = world.history[:, :, :MIN_HISTORY]
    ordered, futures = agent.conditioning(history)
    np.testing.assert_array_equal(ordered[0, :, 0], history[0, 1])
    np.testing.assert_array_equal(ordered[0, :, 1], history[0, 0])
    np.testing.assert_array_equal(futures, constant_acceleration_future(history[:, 1, -1]))
    seen_history, seen_future = recorder.calls[0]
    np.testing.assert_array_equal(seen_history, ordered)
    np.testing.assert_array_equal(seen_future, futures)


def test_model_driver_samples_every_3_steps_and_executes_the_sample(default_model):
    start = study_starts(0, 12)
    agent = ModelDriver(default_model)
    recorder = Recorder(agent)
    states = run(agent, start, seed=3)
    steps = states.shape[2]
    # holds its start acceleration until MIN_HISTORY steps exist; then one sample per block
    held = np.repeat(start[:, 1, None, 4:6], MIN_HISTORY - 1, 1)
    np.testing.assert_array_equal(states[:, 1, 1:MIN_HISTORY, 4:6], held)
    assert [h.shape[1] for h, _ in recorder.calls] == list(range(MIN_HISTORY, steps, 3))  # both episodes at once
    for k, first in enumerate(range(MIN_HISTORY, steps, 3)):
        for episode in (0, 1):
            done = min(3, steps - first)
            np.testing.assert_allclose(states[episode, 1, first:first + done, 4:6], recorder.blocks[k][episode, :done])
    assert not np.allclose(recorder.blocks[0], recorder.blocks[1])  # a new situation, a new block


def test_model_driver_with_the_robot_plan(default_model):
    agent = ModelDriver(default_model, robot_plan=True)
    recorder = Recorder(agent)
    states = run(agent, study_starts(5), robot=LaneChangeRobot(agent), seed=1)
    for history, future in recorder.calls:
        np.testing.assert_array_equal(future[0], future_states(history[0, -1, 0], np.zeros((HORIZON, 2))))
    assert np.isfinite(states).all()
    with pytest.raises(RuntimeError, match="robot_future"):
        run(ModelDriver(default_model, robot_plan=True), study_starts(5))


# ------------------------------------------------------------------ replay
def test_replay_reproduces_the_recording(replay_file):
    trials = load_trials(replay_file)
    agent = human_agent(f"replay:{replay_file}#2")
    start = agent.start_states(2)
    np.testing.assert_array_equal(start, trials.states[2, :, 0])  # robot (agent 0) first
    np.testing.assert_array_equal(agent.start_states([2, 2], me=0), trials.states[[2, 2]][:, ::-1, 0])
    states = run(agent, start[None], seed=8)
    recorded, length = trials.states[2, 1], trials.lengths[2]
    assert states.shape[2] > length
    np.testing.assert_array_equal(states[0, 1, :length, 4:6], recorded[:length, 4:6])
    last = np.repeat(recorded[None, length - 1, 4:6], states.shape[2] - length, 0)
    np.testing.assert_array_equal(states[0, 1, length:, 4:6], last)  # the last acceleration is kept
    assert agent.played.tolist() == [2]


def test_replay_draws_trials_from_the_rng(replay_file):
    agent = human_agent(f"replay:{replay_file}")
    agent.reset(np.random.default_rng(0), study_starts(*range(12)), 1)
    played = agent.played.copy()
    agent.reset(np.random.default_rng(0), study_starts(*range(12)), 1)
    np.testing.assert_array_equal(agent.played, played)
    assert set(played) == {0, 1, 2}


def test_replay_of_real_human_in_the_loop_trials(hitl_trials):
    agent = ReplayDriver(hitl_trials, trial=int(hitl_trials.trial_ids[0]))
    human = int(np.flatnonzero(hitl_trials.roles[0] == "human")[0])
    states = run(agent, agent.start_states(agent.trial)[None])
    length = min(hitl_trials.lengths[0], states.shape[2])
    np.testing.assert_array_equal(states[0, 1, 0], hitl_trials.states[0, human, 0])
    np.testing.assert_array_equal(states[0, 1, :length, 4:6], hitl_trials.states[0, human, :length, 4:6])


# ------------------------------------------------------------------ bad specs
@pytest.mark.parametrize("spec", ["", "robot", "model:", "replay:", "Synthetic", "model"])
def test_unknown_spec(spec):
    with pytest.raises(InputError, match="expected one of: synthetic, model:SPEC"):
        human_agent(spec)


def test_missing_files_and_bad_trials(tmp_path, replay_file):
    for spec in (f"model:{tmp_path / 'none.pt'}", f"model:authors:{tmp_path / 'none.npz'}",
                 f"replay:{tmp_path / 'none.parquet'}"):
        with pytest.raises(InputError, match="none"):
            human_agent(spec)
    with pytest.raises(InputError, match=r"no trial 7 .*trial ids 0\.\.2"):
        human_agent(f"replay:{replay_file}#7")
    with pytest.raises(InputError, match="robot_plan applies only to model"):
        human_agent("synthetic", robot_plan=True)


def test_replay_without_a_human(tmp_path):
    trials, _ = generate_trials(1, seed=2)
    trials.roles[:] = "robot"
    path = tmp_path / "robots.parquet"
    trials.write_parquet(path)
    with pytest.raises(InputError, match=f"{path}: .*expected a dataset with an agent labelled human"):
        human_agent(f"replay:{path}")


def _proposing(driver, *accelerations):
    """A stand-in for ``driver.sample_futures``: samples holding these ``(xdd, ydd)`` (m/s²) for 1.5 s."""
    physical = torch.zeros(len(accelerations), 1, HORIZON, 2, dtype=torch.float64)
    physical[:] = torch.tensor(accelerations, dtype=torch.float64)[:, None, None, :]
    return lambda batch, k, generator: driver.actions_to_standard(physical.to(torch.float32))


def _driver_situation():
    """A human car 100 m behind the robot in the other lane, both at 29 m/s: robot-first histories
    ``[1, 5, 2, 6]`` and the robot's guessed future."""
    human = np.array([-100.0, LANE_CENTRE_Y["left"], 29.0, 0.0, 0.0, 0.0])
    robot = np.array([0.0, LANE_CENTRE_Y["right"], 29.0, 0.0, 0.0, 0.0])
    histories = np.repeat(np.stack([robot, human])[None, None], MIN_HISTORY, axis=1)
    return histories, constant_acceleration_future(histories[:, -1, 0])


def test_a_driver_model_executes_a_safe_sample_or_the_one_unsafe_latest():
    driver = load_model("driver")
    agent = ModelDriver(driver, anticipation=0)
    assert ModelDriver(driver).proposals == 8 and ModelDriver(load_model("default")).proposals == 1
    histories, futures = _driver_situation()
    proposing = lambda *lateral: _proposing(driver, *((0.0, a) for a in lateral))  # noqa: E731

    agent.proposals = 3
    agent.model.sample_futures = proposing(5.0, 1.0, 0.0)  # off the road at once, off the road late, safe
    np.testing.assert_allclose(agent.sample(histories, futures)[0, :, 1], 0.0, atol=1e-5)
    # none safe: the one leaving the road latest, its pedal kept and its wheel steering back to the lane's centre
    agent.model.sample_futures = _proposing(driver, (0.3, 5.0), (0.6, 1.0), (0.9, 5.0))
    executed = agent.sample(histories, futures)[0]
    np.testing.assert_allclose(executed[:, 0], 0.6, atol=1e-5)
    np.testing.assert_allclose(executed[:, 1], 0.0, atol=1e-5)  # already on the centre line, at rest


@given(v0=st.floats(0.0, 40.0), a0=st.floats(-8.0, 5.0),
       accelerations=st.lists(st.floats(-8.0, 5.0), min_size=1, max_size=15))
def test_braking_stops_a_car_and_never_reverses_it(v0, a0, accelerations):
    guarded = without_reversing(v0, a0, np.array(accelerations))
    speeds = v0 + np.cumsum(0.5 * DT * (np.concatenate([[a0], guarded[:-1]]) + guarded))  # the trapezoid rule
    assert (speeds >= -1e-9).all() and (guarded >= np.array(accelerations)).all()
    kept = v0 + np.cumsum(0.5 * DT * (np.concatenate([[a0], accelerations[:-1]]) + np.array(accelerations)))
    if (kept >= 0).all():  # nothing to guard: unchanged
        np.testing.assert_array_equal(guarded, accelerations)


class _Braking:
    """Brakes at 6 m/s² every step, whatever its speed."""

    def reset(self, rng, start, me):
        pass

    def act(self, history):
        return np.tile([-6.0, 0.0], (len(history), 1))


def test_a_car_braking_to_a_stop_in_the_world_does_not_roll_backwards():
    start = np.array([[[START_X, LANE_CENTRE_Y["right"], 2.0, 0.0, 0.0, 0.0],
                       [START_X, LANE_CENTRE_Y["left"], 29.0, 0.0, 0.0, 0.0]]])
    world = run_episodes(start, [_Braking(), ConstantVelocityDriver()], np.random.default_rng(0), max_steps=20,
                         until_max_steps=True)
    speeds, accelerations = world.states[0, 0, :, 2], world.states[0, 0, :, 4]
    assert (speeds >= -1e-9).all() and speeds[-1] == pytest.approx(0.0, abs=1e-9)
    assert accelerations[1] == -6.0 and (accelerations[1:] >= -6.0).all()  # braked as asked until it stopped
    np.testing.assert_allclose(world.states[0, 1, :, 2], 29.0)  # the other car untouched


@pytest.mark.slow
def test_a_driver_model_judges_its_proposals_by_the_other_cars_predicted_futures():
    driver = load_model("driver")
    agent = ModelDriver(driver)
    assert agent.anticipation == 8 and ModelDriver(load_model("default")).anticipation == 0
    histories, futures = _driver_situation()
    agent.proposals = 2
    agent.model.sample_futures = _proposing(driver, (0.0, 0.0), (-6.0, 0.0))  # keep the speed; brake
    keep = future_states(histories[0, -1, 1], np.zeros((HORIZON, 2)))  # [15, 6]
    predicted = np.repeat(futures[None], 2, axis=0)  # [2, 1, 15, 6]: the robot as guessed ...
    predicted[1, 0, 12:] = keep[12:]  # ... or, in one of two predictions, where the human keeps its speed in 1.3 s
    agent.others = lambda h: predicted
    agent.reset(np.random.default_rng(0), histories[:, 0], me=1)
    np.testing.assert_allclose(agent.sample(histories, futures)[0, :, 0], -6.0, atol=1e-5)  # braking is clear of both
    agent.anticipation = 0  # the guess alone: keeping the speed is safe
    np.testing.assert_allclose(agent.sample(histories, futures)[0, :, 0], 0.0, atol=1e-5)


def test_a_driver_model_predicts_the_other_car_with_the_seats_swapped():
    agent = ModelDriver(load_model("driver"))
    histories, _ = _driver_situation()
    agent.reset(np.random.default_rng(0), histories[:, 0], me=1)
    others = agent.others(histories)
    assert others.shape == (8, 1, HORIZON, 6) and np.isfinite(others).all()
    np.testing.assert_allclose(others[:, 0, 0, 0], histories[0, -1, 0, 0] + 0.1 * 29.0, atol=0.1)  # from the robot's state
    assert np.abs(others[..., 1] - LANE_CENTRE_Y["right"]).max() < 3.0  # the robot's lane, give or take its lane change


def test_a_driver_model_near_the_cutoff_prefers_a_proposal_that_swaps_lanes_in_time():
    driver = load_model("driver")
    agent = ModelDriver(driver)
    histories, futures = _driver_situation()  # the human 100 m behind the robot, in the left lane
    agent.reset(np.random.default_rng(0), histories[:, 0], me=1)
    agent.others = lambda h: np.repeat(futures[None], agent.anticipation, axis=0)
    agent.proposals = 2
    agent.model.sample_futures = _proposing(driver, (0.0, 0.0), (0.0, -3.0))  # keep the lane; change it
    far = histories.copy()
    far[:, :, 1, 0] = CUTOFF_X - 150.0  # 150 m to the cutoff: either will do, the first is taken
    np.testing.assert_allclose(agent.sample(far, futures)[0, :, 1], 0.0, atol=1e-5)
    near = histories.copy()
    near[:, :, 1, 0] = CUTOFF_X - 90.0  # still in its lane in 1.5 s, 46 m (1.6 s) short of the cutoff: late
    np.testing.assert_allclose(agent.sample(near, futures)[0, :, 1], -3.0, atol=1e-5)


def test_lateness_is_zero_on_time_and_grows_with_the_distance_left_to_the_divider():
    start_y = np.array([LANE_CENTRE_Y["left"], LANE_CENTRE_Y["right"]])
    def end(x, y):  # states [2, 6] of both cars at x (m) and lateral positions y (m), at 29 m/s
        return np.array([[x, yk, 29.0, 0.0, 0.0, 0.0] for yk in y])
    np.testing.assert_allclose(lateness(start_y, end(CUTOFF_X - 100.0, start_y)), 0.0)  # 3.4 s from the cutoff
    near = CUTOFF_X - 40.0  # 1.4 s from the cutoff
    np.testing.assert_allclose(lateness(start_y, end(near, start_y)), 1.0)  # still on the lane's centre line
    np.testing.assert_allclose(lateness(start_y, end(near, [SWAP_THRESHOLD_Y + 1e-6, SWAP_THRESHOLD_Y - 1e-6])), 0.5, atol=1e-6)
    np.testing.assert_allclose(lateness(start_y, end(near, start_y[::-1])), 0.0)  # across: not late
    halfway = (start_y + SWAP_THRESHOLD_Y) / 2
    np.testing.assert_allclose(lateness(start_y, end(near, halfway)), 0.75)


def test_a_late_driver_model_takes_the_proposal_that_gets_farthest_across():
    driver = load_model("driver")
    agent = ModelDriver(driver)
    histories, futures = _driver_situation()
    histories[:, :, 1, 0] = CUTOFF_X - 90.0  # late whatever it does: none of these crosses within 1.5 s
    agent.reset(np.random.default_rng(0), histories[:, 0], me=1)
    agent.others = lambda h: np.repeat(futures[None], agent.anticipation, axis=0)
    agent.proposals = 3
    agent.model.sample_futures = _proposing(driver, (0.0, 0.0), (0.0, -1.5), (0.0, -0.5))
    np.testing.assert_allclose(agent.sample(histories, futures)[0, :, 1], -1.5, atol=1e-5)


def test_keeping_on_the_road_steers_a_drifting_car_back_to_its_lane_and_keeps_the_pedal():
    present = np.array([[-50.0, -1.2, 29.0, 0.6, 0.0, 0.3],    # drifting out over the left edge
                        [-50.0, -7.4, 29.0, -0.8, 0.0, -1.0]])  # and over the right edge
    held = np.repeat(present[:, None, 4:6], HORIZON, axis=1)  # [2, 15, 2]: holding on leaves the road
    assert not on_road(future_states(present, held)[..., 1]).all()
    kept = keep_on_road(present, held)
    np.testing.assert_array_equal(kept[..., 0], held[..., 0])
    y = future_states(present, kept)[..., 1]
    assert on_road(y).all()
    np.testing.assert_allclose(y[:, -1], [LANE_CENTRE_Y["left"], LANE_CENTRE_Y["right"]], atol=0.2)
