"""The drive's kinds of room and defaults, in a module light enough for the command line's parser."""

ROOM_KINDS = ("robot", "human-human")
"""The kinds of room a drive server opens (its ``--mode``): ``robot``, a person against the planner
(each page its own room; the planner is shared in turn); ``human-human``, rooms of two pages, one
person at each, driving one car each."""
PLAN_DEADLINE_S = 0.25
"""The planner's real-time deadline while driving, s: the replanning period (0.3 s) less a margin
for handing the plan between threads and for the simulation's own step."""
COUNTDOWN_S = 3
"""Seconds of countdown before a trial starts."""
MAX_ROOMS = 64
"""Most rooms open at once; a page beyond them is told the server is full (a bound on what a flood
of pages can take)."""
