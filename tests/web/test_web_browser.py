"""End to end in a real browser: headless Chromium (Debian's ``chromium``, driven by Playwright
through its ``executable_path``) opens the drive page of a real server, starts a trial, holds keys
to drive the human car through a lane change, sees the robot plan, finishes the trial and finds
its recording valid; and two Chromium pages join one human–human room, drive a trial of the
study protocol together, and its recording loads with `stats` and fine-tunes a model
(`train --init`). It saves a screenshot; with ``TRAFFICWEAVING_DRIVE_SCREENSHOT=PATH`` set it
also writes it there (``docs/figures/drive.png`` is made so, see docs/drive.md)."""

import json
import os
import shutil
import time
from pathlib import Path

import pytest

from helpers_web import drive_server
from trafficweaving.cli import main
from trafficweaving.data.trials import load_trials
from trafficweaving.scenario import LANE_CENTRE_Y, LANE_DIVIDER_Y, MIN_TRIAL_STEPS, SWAP_THRESHOLD_Y

CHROMIUM = Path("/usr/bin/chromium")
CHROMIUM_ARGS = ["--no-sandbox", "--disable-gpu", "--disable-background-networking", "--disable-component-update",
                 "--disable-sync", "--no-first-run", "--disable-quic"]
IC = 4  # car B starts in the right lane at 27 m/s, 6 m ahead of car A (left lane, 29 m/s)
SCREENSHOT_ENV = "TRAFFICWEAVING_DRIVE_SCREENSHOT"


@pytest.fixture(scope="module")
def browser():
    if not CHROMIUM.is_file():
        pytest.skip(f"Chromium is not installed at {CHROMIUM} (Debian: apt-get install chromium)")
    sync_api = pytest.importorskip("playwright.sync_api", reason="playwright is not installed (pip install -e '.[test]')")
    with sync_api.sync_playwright() as playwright:
        browser = playwright.chromium.launch(executable_path=str(CHROMIUM), headless=True, args=CHROMIUM_ARGS)
        yield browser
        browser.close()


def wait_for(page, expression: str, timeout: float = 20.0):
    """Poll ``expression`` (JavaScript) until it is truthy; returns its value."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        value = page.evaluate(expression)
        if value:
            return value
        time.sleep(0.05)
    raise AssertionError(f"timed out waiting for {expression}")


@pytest.mark.slow
def test_drive_a_trial_in_the_browser(browser, tmp_path):
    with drive_server(tmp_path / "drives", countdown=1) as url:
        page = browser.new_page(viewport={"width": 1280, "height": 740})
        errors = []
        page.on("pageerror", lambda error: errors.append(str(error)))
        page.goto(url)
        wait_for(page, "window.drive.phase === 'idle'")
        assert page.locator("#mode").inner_text() == "you vs the robot"
        assert page.locator("#ic option").count() == 19  # the study's 18 starts and random
        page.select_option("#ic", str(IC))
        page.select_option("#car", "1")  # you drive car B: the robot drives car A
        assert "You: right lane at 27 m/s, 6 m ahead of the robot" in page.locator("#ic-text").inner_text()
        assert page.locator("#show-plan").is_checked()

        page.keyboard.press("Enter")
        started = wait_for(page, "window.drive.started")
        assert started["roles"] == ["robot", "human"]
        assert wait_for(page, "document.getElementById('overlay').textContent") in ("1", "GO")
        wait_for(page, "window.drive.phase === 'driving'")
        start_x = started["states"][1][0]

        # hold the throttle for 2 s, then change lanes with the steering keys (a driver watching
        # the car: steer left until across the divider, then let the car straighten into the lane)
        page.keyboard.down("ArrowUp")
        target = LANE_CENTRE_Y["left"]
        screenshot = tmp_path / "drive.png"
        shot = False
        steering = None
        top_speed = 0.0
        while page.evaluate("window.drive.phase") == "driving":
            state = page.evaluate("window.drive.state")
            if state is None:
                time.sleep(0.05)
                continue
            x, y, xd = state["cars"][1][:3]
            top_speed = max(top_speed, xd)
            if state["step"] >= 20:
                page.keyboard.up("ArrowUp")
            want = "ArrowLeft" if state["step"] >= 12 and y < target - 2.0 else None
            if want != steering:
                if steering:
                    page.keyboard.up(steering)
                if want:
                    page.keyboard.down(want)
                steering = want
            if not shot and state["step"] >= 28 and page.evaluate("window.drive.plans") > 0:
                page.screenshot(path=str(screenshot))
                shot = True
            time.sleep(0.05)
        if steering:
            page.keyboard.up(steering)

        ended = wait_for(page, "window.drive.ended")
        final = page.evaluate("window.drive.state")
        final_plans = final["planner"]
        assert page.locator("#result").is_visible()
        assert page.locator("#outcome").inner_text()
        assert ended["reason"] in ("finished", "collision"), ended
        # the robot planned, and the page received every plan it executed (on a machine this busy
        # elsewhere, some plans may be late: they are counted, not executed)
        assert page.evaluate("window.drive.plans") == final_plans["plans"] >= 1
        plan = page.evaluate("window.drive.plan")
        assert len(plan["robot"]) == 15 and len(plan["humans"]) > 0
        assert top_speed > 31.0  # the throttle key sped the car up from 27 m/s
        assert final["cars"][1][0] - start_x > 100  # the car moved
        assert not errors, errors

        # the recording is a valid trial of the dataset format with what the page showed
        assert ended["file"]
        trials = load_trials(ended["file"])
        assert trials.lengths[0] == ended["steps"] >= MIN_TRIAL_STEPS
        assert list(trials.roles[0]) == ["robot", "human"]
        human = trials.states[0, 1, : trials.lengths[0]]
        assert abs(human[-1, 0] - final["cars"][1][0]) < 1e-9
        assert human[:, 2].max() > 31.0
        if ended["reason"] == "finished":
            assert human[-1, 1] > SWAP_THRESHOLD_Y  # the keys changed lanes
        assert page.locator("#file").inner_text() == f"Recorded: {ended['file']}"

        # next trial, stopped with Escape: too short to record, and the page says so
        page.click("#next")
        wait_for(page, "window.drive.phase === 'driving'")
        page.keyboard.press("Escape")
        wait_for(page, "window.drive.phase === 'ended'")
        assert page.evaluate("window.drive.ended.reason") == "aborted"
        assert "not recorded" in page.locator("#file").inner_text()
        page.close()

    assert shot and screenshot.stat().st_size > 10_000
    if os.environ.get(SCREENSHOT_ENV):
        shutil.copyfile(screenshot, os.environ[SCREENSHOT_ENV])


def steer_key(y: float, start_y: float) -> str | None:
    """The arrow key a driver holds to move from the lane it started in (``start_y``) into the other
    lane's centre, none once within 2 m of it (the car then straightens into the lane)."""
    target = LANE_CENTRE_Y["left"] if start_y < LANE_DIVIDER_Y else LANE_CENTRE_Y["right"]
    if abs(y - target) <= 2.0:
        return None
    return "ArrowLeft" if target > y else "ArrowRight"


@pytest.mark.slow
def test_two_browsers_drive_a_trial_in_one_room_and_it_trains(browser, tmp_path, capsys):
    out = tmp_path / "drives"
    with drive_server(out, mode="human-human") as url:
        first = browser.new_context(viewport={"width": 1000, "height": 700}).new_page()
        second = browser.new_context(viewport={"width": 1000, "height": 700}).new_page()
        errors = []
        for page in (first, second):
            page.on("pageerror", lambda error: errors.append(str(error)))
        first.goto(url)
        wait_for(first, "window.drive.room")
        assert first.locator("#mode").inner_text() == "human–human room"
        link = first.locator("#join-link").input_value()
        assert "room=" in link and "token=" in link and "token=" in first.url  # a reload rejoins the room
        assert first.locator("#start").is_disabled()  # alone in the room
        second.goto(link)
        wait_for(first, "window.drive.room.seats.every((taken) => taken)")
        for page, person in ((first, "11"), (second, "22")):
            page.fill("#driver0", person)
            page.press("#driver0", "Tab")
        wait_for(second, "JSON.stringify(window.drive.room.participants) === '[11,22]'")
        study = second.evaluate("window.drive.room.study")
        assert "Round 1, trial 1 of 18" in second.locator("#study-text").inner_text()

        second.click("#start")  # either person starts; the protocol picks the start and the cars
        for page in (first, second):
            wait_for(page, "window.drive.phase === 'driving'")
        started = first.evaluate("window.drive.started")
        assert started["initial_condition"]["index"] == study["next_initial_condition"]
        assert first.evaluate("window.drive.started.cars") == [0] and second.evaluate("window.drive.started.cars") == [1]
        start_y = [car[1] for car in started["states"]]
        # car A (first page) speeds up and changes lanes first; car B (second page) brakes, then changes lanes
        held = {first: set(), second: set()}
        while first.evaluate("window.drive.phase") == "driving":
            state = first.evaluate("window.drive.state")
            if state is not None:
                step, cars = state["step"], state["cars"]
                wanted = {first: {"ArrowUp" if step < 25 else None, steer_key(cars[0][1], start_y[0]) if step >= 12 else None},
                          second: {"ArrowDown" if step < 8 else None, steer_key(cars[1][1], start_y[1]) if step >= 25 else None}}
                for page, keys in wanted.items():
                    keys.discard(None)
                    for key in held[page] - keys:
                        page.keyboard.up(key)
                    for key in keys - held[page]:
                        page.keyboard.down(key)
                    held[page] = keys
            time.sleep(0.05)
        ended = wait_for(first, "window.drive.ended")
        assert wait_for(second, "window.drive.ended") == ended
        assert ended["reason"] in ("finished", "collision", "off_road"), ended
        assert "Recorded:" in second.locator("#file").inner_text()
        wait_for(first, "window.drive.room.study.done === 1")  # a completed trial of the protocol
        assert not errors, errors

    trials = load_trials(ended["file"])
    assert list(trials.roles[0]) == ["human", "human"] and list(trials.drivers[0]) == [11, 22]
    record = trials.metadata["drive"]
    assert record["room"]["round"] == 0 and record["room"]["participants"] == [11, 22]
    controls = record["controls"]["log"]
    assert max(used[0] for used in controls["0"]) == 1.0 and max(used[1] for used in controls["1"]) == 1.0  # the keys

    assert main(["stats", str(out), "--json"]) == 0
    stats = json.loads(capsys.readouterr().out)
    assert stats["pairs"][0]["participants"] == [11, 22] and stats["pairs"][0]["trials"] == 1
    assert main(["train", "--data", ended["file"], "--init", "default", "--steps", "1", "--validation-fraction", "0",
                 "--device", "cpu", "--out", str(tmp_path / "fine_tuned.pt"), "--json"]) == 0
    trained = json.loads(capsys.readouterr().out)
    assert trained["init"] == "default" and (tmp_path / "fine_tuned.pt").is_file()
