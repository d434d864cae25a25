"""Benchmark: does the browser drive hold 10 Hz while the robot replans every 0.3 s?

Starts the real drive server (uvicorn, the app, the shipped model's planner in its background
thread, torch threads as `trafficweaving drive` sets them) on a free loopback port and drives
trial after trial against it until ``--seconds`` of simulated driving (60 by default) are done:
each trial from a random study start and robot car, the human car driven by a scripted person
who picks a throttle, then changes lanes at a random moment. The driver is either a WebSocket
client answering every state (``--driver websocket``, default) or headless Chromium showing the
real page, its keys pressed by Playwright (``--driver browser``; the page renders at its own
frame rate on the same cores, as a person's browser would).

From the recorded trials (their ``drive`` metadata) it prints the wall-clock period between
simulation steps (mean, p99, max; the target is 0.100 s), the planner's latencies (median, p99,
max), how many plans were late (a window started without its plan) and how many took longer than
the 0.3 s replanning period. One JSON object with ``--json``.

With ``--rooms N`` it measures human–human rooms instead: the server in ``human-human`` mode and
``N`` rooms of two pages each, all driving at once for ``--seconds`` of driving per room. The
pages are WebSocket clients in a separate process (as browsers would be), each sending its car's
controls 20 times a second as the page does (car A's person speeds up and changes lanes, car B's
brakes, then changes lanes behind it). It prints the step period of all rooms' trials (p50,
mean, p99, max).

    python benchmarks/bench_drive.py [--seconds 60] [--driver websocket|browser] [--threads N] [--seed 0] [--json]
    python benchmarks/bench_drive.py --rooms 20 [--seconds 60] [--seed 0] [--json]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import multiprocessing
import os
import tempfile
import threading
import time
from collections import Counter
from pathlib import Path

import numpy as np

from trafficweaving.data.trials import load_trials
from trafficweaving.scenario import DT, LANE_CENTRE_Y, LANE_DIVIDER_Y, REPLAN_PERIOD_S
from trafficweaving.web.protocol import CONTROL_INTERVAL_S
from trafficweaving.web.recording import recorded_files
from trafficweaving.web.room import DriveConfig
from trafficweaving.web.server import build_server, default_threads

CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = ["--no-sandbox", "--disable-gpu", "--disable-background-networking", "--disable-component-update",
                 "--disable-sync", "--no-first-run", "--disable-quic"]


class ScriptedPerson:
    """A driver for one trial: throttle ``throttle`` until ``throttle_steps``, then a light one;
    steering towards the other lane's centre from step ``swap_at`` on."""

    def __init__(self, rng: np.random.Generator, start_y: float):
        self.throttle = float(rng.uniform(0.0, 1.0))
        self.throttle_steps = int(rng.integers(5, 25))
        self.brake = float(rng.uniform(0.0, 0.4)) if rng.random() < 0.3 else 0.0
        self.swap_at = int(rng.integers(5, 30))
        self.target = LANE_CENTRE_Y["left"] if start_y < LANE_DIVIDER_Y else LANE_CENTRE_Y["right"]

    def controls(self, step: int, state) -> dict:
        steer = 0.0
        if step >= self.swap_at:
            steer = max(-1.0, min(1.0, 0.5 * (state[1] - self.target) + 0.3 * state[3]))
        early = step < self.throttle_steps
        return {"throttle": self.throttle if early else 0.15, "brake": self.brake if early else 0.0, "steer": steer}


def drive_websocket(url: str, seconds: float, rng: np.random.Generator) -> None:
    from websockets.sync.client import connect

    driven = 0.0
    with connect(url.replace("http://", "ws://") + "ws", max_size=None) as ws:
        json.loads(ws.recv(timeout=30))  # welcome
        while driven < seconds:
            ws.send(json.dumps({"type": "start"}))
            started = json.loads(ws.recv(timeout=30))
            car = started["roles"].index("human")
            person, seq = ScriptedPerson(rng, started["states"][car][1]), 0
            while True:
                message = json.loads(ws.recv(timeout=30))
                if message["type"] == "state":
                    seq += 1
                    ws.send(json.dumps({"type": "controls", "seq": seq, "car": car,
                                        **person.controls(message["step"], message["cars"][car])}))
                elif message["type"] == "ended":
                    driven += message["steps"] * DT
                    break


def drive_browser(url: str, seconds: float, rng: np.random.Generator) -> None:
    """The same person at the page's keyboard: keys held for the throttle (pulsed for a partial
    one) and the steering (bang-bang around the wanted steering)."""
    from playwright.sync_api import sync_playwright

    driven = 0.0
    with sync_playwright() as playwright:
        browser = playwright.chromium.launch(executable_path=CHROMIUM, headless=True, args=CHROMIUM_ARGS)
        page = browser.new_page(viewport={"width": 1280, "height": 800})
        page.goto(url)
        while page.evaluate("window.drive.phase") != "idle":
            time.sleep(0.05)
        while driven < seconds:
            page.keyboard.press("Enter")
            while not page.evaluate("window.drive.phase === 'driving' || window.drive.phase === 'ended'"):
                time.sleep(0.01)
            started = page.evaluate("window.drive.started")
            car = started["roles"].index("human")
            person, held, tick = ScriptedPerson(rng, started["states"][car][1]), set(), 0
            while page.evaluate("window.drive.phase") == "driving":
                state = page.evaluate("window.drive.state")
                if state is not None:
                    c = person.controls(state["step"], state["cars"][car])
                    tick += 1
                    want = {key for key, on in (("ArrowUp", tick % 10 < 10 * c["throttle"]),
                                                ("ArrowDown", c["brake"] > 0),
                                                ("ArrowLeft", c["steer"] < -0.3), ("ArrowRight", c["steer"] > 0.3)) if on}
                    for key in held - want:
                        page.keyboard.up(key)
                    for key in want - held:
                        page.keyboard.down(key)
                    held = want
                time.sleep(0.03)
            for key in held:
                page.keyboard.up(key)
            while page.evaluate("window.drive.ended") is None:
                time.sleep(0.01)
            driven += page.evaluate("window.drive.ended.steps") * DT
        browser.close()


class PairPerson:
    """One of a pair's drivers for one trial: car A's (``leader``) holds a throttle for a while and
    changes lanes from an early step; car B's brakes at first and changes lanes later, behind it."""

    def __init__(self, rng: np.random.Generator, start_y: float, leader: bool):
        self.leader = leader
        self.pedal = float(rng.uniform(0.6, 1.0))
        self.pedal_steps = int(rng.integers(15, 26)) if leader else int(rng.integers(5, 10))
        self.swap_at = int(rng.integers(10, 15)) if leader else int(rng.integers(25, 31))
        self.target = LANE_CENTRE_Y["left"] if start_y < LANE_DIVIDER_Y else LANE_CENTRE_Y["right"]

    def controls(self, step: int, state) -> dict:
        steer = max(-1.0, min(1.0, 0.5 * (state[1] - self.target) + 0.3 * state[3])) if step >= self.swap_at else 0.0
        pedal = self.pedal if step < self.pedal_steps else 0.0
        return {"throttle": pedal if self.leader else 0.0, "brake": 0.0 if self.leader else pedal, "steer": steer}


async def _page(ws, starts: bool, seconds: float, rng: np.random.Generator) -> None:
    """One page of a room: trial after trial (``starts``: this page sends ``start``) until
    ``seconds`` of driving are done, its car's controls sent every ``CONTROL_INTERVAL_S``."""
    loop = asyncio.get_running_loop()
    driven = 0.0
    while driven < seconds:
        if starts:
            await ws.send(json.dumps({"type": "start"}))
        while (started := json.loads(await ws.recv()))["type"] != "started":
            pass
        car = started["cars"][0]
        person, state, seq = PairPerson(rng, started["states"][car][1], car == 0), None, 0
        next_send = loop.time()
        while True:
            try:
                message = json.loads(await asyncio.wait_for(ws.recv(), max(0.0, next_send - loop.time())))
            except asyncio.TimeoutError:
                if state is not None:
                    seq += 1
                    await ws.send(json.dumps({"type": "controls", "seq": seq, "car": car,
                                              **person.controls(state["step"], state["cars"][car])}))
                next_send += CONTROL_INTERVAL_S
                continue
            if message["type"] == "state":
                state = message
            elif message["type"] == "ended":
                driven += message["steps"] * DT
                break


async def _room(url: str, seconds: float, seed: int) -> None:
    from websockets.asyncio.client import connect

    ws_url = url.replace("http://", "ws://") + "ws"
    async with connect(ws_url, max_size=None) as first:
        await first.recv()  # welcome
        room = json.loads(await first.recv())
        async with connect(ws_url + "?" + room["join"].split("?", 1)[1], max_size=None) as second:
            await second.recv()  # welcome
            await asyncio.gather(_page(first, True, seconds, np.random.default_rng([seed, 0])),
                                 _page(second, False, seconds, np.random.default_rng([seed, 1])))


def drive_rooms(url: str, rooms: int, seconds: float, seed: int) -> None:
    """``rooms`` rooms of two pages at once (run in a process of its own, as browsers are)."""
    async def run() -> None:
        await asyncio.gather(*(_room(url, seconds, seed * 1000 + k) for k in range(rooms)))

    asyncio.run(run())


def summarise_rooms(files: list[Path]) -> dict:
    """The step periods of human–human trials (all rooms together)."""
    periods, steps, reasons = [], 0, Counter()
    for path in files:
        record = load_trials(path).metadata["drive"]
        periods += record["step_periods_s"]
        steps += record["step_period"]["steps"]
        reasons[record["reason"]] += 1
    periods = np.array(periods)
    return {
        "trials": len(files),
        "reasons": dict(reasons),
        "steps": steps,
        "driven_s": round(steps * DT, 1),
        "step_period_s": {"p50": float(np.median(periods)), "mean": float(periods.mean()),
                          "p99": float(np.percentile(periods, 99)), "max": float(periods.max()),
                          "over_110ms": int((periods > 0.11).sum())},
    }


def bench_rooms(args) -> dict:
    with tempfile.TemporaryDirectory() as scratch:
        out = Path(args.out or scratch)
        server = build_server(DriveConfig(mode="human-human", countdown_s=0), "127.0.0.1", 0, str(out))
        thread = threading.Thread(target=server.run, daemon=True)
        thread.start()
        while not server.server.started:
            time.sleep(0.02)
        began = time.perf_counter()
        pages = multiprocessing.get_context("spawn").Process(target=drive_rooms,
                                                             args=(server.url, args.rooms, args.seconds, args.seed))
        try:
            pages.start()
            pages.join()
        finally:
            server.server.should_exit = True
            thread.join(15)
            server.close()
        if pages.exitcode != 0:
            raise SystemExit(f"the pages' process failed (exit status {pages.exitcode})")
        return {"rooms": args.rooms, "cpus": os.cpu_count(), "wall_s": round(time.perf_counter() - began, 1),
                **summarise_rooms(recorded_files(out))}


def summarise(files: list[Path]) -> dict:
    periods, latencies, late, windows, steps = [], [], 0, 0, 0
    for path in files:
        record = load_trials(path).metadata["drive"]
        periods += record["step_periods_s"]
        steps += record["step_period"]["steps"]
        planner = record["planner"]
        latencies += planner["latencies_s"]
        late += len(planner["late_windows"])
        windows += len(planner["plans"]) + len(planner["late_windows"])
    periods, latencies = np.array(periods), np.array(latencies)
    return {
        "trials": len(files),
        "steps": steps,
        "driven_s": round(steps * DT, 1),
        "step_period_s": {"mean": float(periods.mean()), "p99": float(np.percentile(periods, 99)),
                          "max": float(periods.max()), "over_110ms": int((periods > 0.11).sum())},
        "plan_latency_s": {"plans": len(latencies), "median": float(np.median(latencies)),
                           "p99": float(np.percentile(latencies, 99)), "max": float(latencies.max()),
                           "over_replanning_period": int((latencies > REPLAN_PERIOD_S).sum())},
        "windows_planned": windows,
        "late_plans": late,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=60.0, help="simulated driving to do, s (default 60)")
    parser.add_argument("--driver", choices=("websocket", "browser"), default="websocket")
    parser.add_argument("--threads", type=int, default=default_threads(),
                        help="planner torch threads (default: as trafficweaving drive, all cores but one)")
    parser.add_argument("--seed", type=int, default=0, help="the scripted person's choices")
    parser.add_argument("--out", help="keep the recorded trials in this folder (default: a temporary one)")
    parser.add_argument("--rooms", type=int, help="measure this many human-human rooms at once instead (two "
                                                  "scripted pages each)")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    if args.rooms is not None:
        if args.rooms < 1:
            parser.error(f"argument --rooms: expected an integer >= 1, got {args.rooms}")
        result = bench_rooms(args)
        if args.json:
            print(json.dumps(result))
            return
        period = result["step_period_s"]
        print(f"{result['rooms']} human-human rooms at once on {result['cpus']} CPUs: {result['trials']} trials, "
              f"{result['steps']} steps ({result['driven_s']} s driven; ends: "
              f"{', '.join(f'{k} {v}' for k, v in sorted(result['reasons'].items()))})")
        print(f"step period: p50 {1000 * period['p50']:.1f} ms, mean {1000 * period['mean']:.1f} ms, "
              f"p99 {1000 * period['p99']:.1f} ms, max {1000 * period['max']:.1f} ms "
              f"({period['over_110ms']} over 110 ms)")
        return

    with tempfile.TemporaryDirectory() as scratch:
        out = Path(args.out or scratch)
        config = DriveConfig(countdown_s=0, threads=args.threads)
        server = build_server(config, "127.0.0.1", 0, str(out))
        thread = threading.Thread(target=server.run, daemon=True)
        thread.start()
        while not server.server.started:
            time.sleep(0.02)
        began = time.perf_counter()
        try:
            (drive_browser if args.driver == "browser" else drive_websocket)(server.url, args.seconds,
                                                                             np.random.default_rng(args.seed))
        finally:
            server.server.should_exit = True
            thread.join(15)
            server.close()
        result = {"driver": args.driver, "threads": args.threads, "cpus": os.cpu_count(),
                  "deadline_s": config.deadline, "wall_s": round(time.perf_counter() - began, 1),
                  **summarise(recorded_files(out))}
    if args.json:
        print(json.dumps(result))
        return
    period, plan = result["step_period_s"], result["plan_latency_s"]
    print(f"{result['trials']} trials, {result['steps']} steps ({result['driven_s']} s driven), driver "
          f"{args.driver}, {args.threads} planner thread(s) on {result['cpus']} CPUs, deadline {config.deadline} s")
    print(f"step period: mean {1000 * period['mean']:.1f} ms, p99 {1000 * period['p99']:.1f} ms, "
          f"max {1000 * period['max']:.1f} ms ({period['over_110ms']} over 110 ms)")
    print(f"plans: {plan['plans']}, latency median {1000 * plan['median']:.0f} ms, p99 {1000 * plan['p99']:.0f} ms, "
          f"max {1000 * plan['max']:.0f} ms ({plan['over_replanning_period']} over {REPLAN_PERIOD_S:g} s)")
    print(f"late plans: {result['late_plans']} of {result['windows_planned']} windows")


if __name__ == "__main__":
    main()
