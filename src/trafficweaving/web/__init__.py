"""Human-in-the-loop driving in the browser (``trafficweaving drive``, ``docs/drive.md``).

A person drives the human car against the robot's planner — or two people drive both cars —
on a local web page; the server simulates the step-6 world at 0.1 s with the person as one more
agent, and records every trial in the dataset format.

Modules: :mod:`.options` (modes and defaults), :mod:`.controls` (controls → accelerations, the
driving limits), :mod:`.person` (the person as an agent), :mod:`.trial` (one trial: world,
agents, end rule, record), :mod:`.recording` (files), :mod:`.protocol` (client messages and their
checks), :mod:`.session` (a page's trials in real time), :mod:`.app` (FastAPI app and WebSocket),
:mod:`.server` (uvicorn, the command), ``static/`` (the page).
"""
