"""Human-in-the-loop driving in the browser (``trafficweaving drive``, ``docs/drive.md``).

A person drives the human car against the robot's planner — or two people at two browsers drive
both cars, the study's human–human data collection — on a web page; the server simulates the
scenario's world at 0.1 s with each person as one more agent, and records every trial in the
dataset format.

Modules, bottom up: :mod:`.options` (kinds of room and defaults), :mod:`.controls` (controls →
accelerations, the driving limits), :mod:`.person` (the person as an agent), :mod:`.trial` (one
trial: world, agents, end rule, record), :mod:`.recording` (files), :mod:`.study` (the study
protocol for a pair, a folder's progress), :mod:`.protocol` (the WebSocket messages both ways),
:mod:`.room` (a room's pages and trials in real time, the shared planner's queue), :mod:`.lobby`
(the server's rooms, tokens and key), :mod:`.hosts` (the hosts and origins served), :mod:`.limits`
(bounds on connections), :mod:`.app` (FastAPI app and WebSocket), :mod:`.server` (uvicorn, the
command), ``static/`` (the page: ``drive.js`` shared state, ``draw.js``,
``input.js``, ``connection.js``).
"""
