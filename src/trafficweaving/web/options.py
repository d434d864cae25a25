"""The drive's modes and defaults, in a module light enough for the command line's parser."""

MODES = ("robot", "human-human")
"""``robot``: a person against the planner; ``human-human``: two people on one keyboard."""
PLAN_DEADLINE_S = 0.25
"""The planner's real-time deadline while driving, s: the replanning period (0.3 s) less a margin
for handing the plan between threads and for the simulation's own step."""
COUNTDOWN_S = 3
"""Seconds of countdown before a trial starts."""
