"""The safety layer's overrides in episode records and run summaries (sim/episodes.py, sim/metrics.py)."""

import torch

from trafficweaving.planning.planner import Budget
from trafficweaving.sim.episodes import EpisodeSpec, run_episode
from trafficweaving.sim.metrics import aggregate


def test_every_window_the_safety_layer_changed_is_recorded_and_counted():
    torch.set_num_threads(1)
    spec = EpisodeSpec("planner-cv", "scenario:never-yield", seed=0, budget=Budget(1, 2, 4))
    robot, human = spec.agents()
    records = []
    for index in range(2):
        record = run_episode(spec, index, (robot, human)).record
        assert record["safety_overrides"] == [
            {"step": step, "proposed": d.proposed, "chosen": d.chosen, "any_safe": d.any_safe} for step, d in robot.safety_log]
        records.append(record)
    summary = aggregate(records)["safety_overrides"]
    logs = [r["safety_overrides"] for r in records]
    assert summary == {"windows": sum(map(len, logs)), "episodes": sum(map(bool, logs)),
                       "unresolved": sum(not o["any_safe"] for log in logs for o in log)}
    assert summary["episodes"] > 0  # the human swerves in from beside: nothing the plan chose is safe any more
    legacy = [{k: v for k, v in r.items() if k != "safety_overrides"} for r in records]
    assert aggregate(legacy)["safety_overrides"] is None
