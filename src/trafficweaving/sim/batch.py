"""Batch closed-loop evaluation: many independent episodes (:mod:`.episodes`), run in parallel,
logged one Parquet file each and summarised with confidence intervals (:mod:`.metrics`).

Output folder ``out``:

* ``episodes/episode_000042.parquet``: episode 42 in the dataset format (one trial, roles
  ``robot``/``human``, source ``episode-000042``), its JSON record (metrics, latencies, initial
  condition, spec) in the file's metadata under ``episode``; written atomically as it finishes;
* ``summary.json``: :func:`~.metrics.aggregate` of episodes ``0..episodes-1`` plus the run's
  settings, written last.

A rerun into the same folder reuses every episode whose file loads and was made with the same
spec (robot, human, seed, model, deadline, budget, device), recomputing only the missing ones (an
interrupted batch resumes); a file made with another spec is refused. A reused episode's metrics
are measured again from its states, and its file rewritten where they changed: a rerun brings the
logs of an earlier release up to this one's metrics. The summary is rebuilt from
the files of episodes ``0..episodes-1`` (others in the folder are left alone).

Engines: ``local`` runs the episodes in the calling process (``workers = 1``) or in a pool of
``workers`` spawned processes; ``ray`` runs them as Ray tasks, at most ``workers`` at a time, on
the running Ray instance, the cluster at ``address`` or a new local instance of ``workers`` CPUs.
Every worker uses one torch thread, so an episode is bitwise the same on either engine and any
number of workers (:mod:`.episodes`), unless the planner plans against a wall-clock deadline.
"""

from __future__ import annotations

import json
import logging
import multiprocessing
import signal
import sys
import threading
import time
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from contextlib import contextmanager
from dataclasses import replace
from importlib.util import find_spec
from pathlib import Path
from typing import Callable, Iterator

import torch
from tqdm import tqdm

from .. import validate
from ..atomic import atomic_write, check_output_folder
from ..data.trials import load_trials
from ..errors import InputError
from ..model.checkpoint import choose_device
from ..planning.planner import Budget
from .episodes import Episode, EpisodeSpec, run_episode
from .metrics import aggregate, episode_metrics

ENGINES = ("local", "ray")
RAY_MISSING = "`--engine ray` needs Ray: pip install 'trafficweaving[ray]'"


class EpisodeFailed(InputError):
    """An episode raised: the batch stopped. One line naming the episode and the error (an
    :class:`InputError`, so the command line reports it with exit status 2)."""

    def __init__(self, index: int, error: BaseException):
        reason = (str(error).splitlines() or [""])[0]
        super().__init__(f"episode {index} failed: {type(error).__name__}: {reason}")
        self.index = index


def episode_path(out: Path, index: int) -> Path:
    """Where episode ``index`` is logged: ``out/episodes/episode_000042.parquet``."""
    return out / "episodes" / f"episode_{index:06d}.parquet"


def _reusable(path: Path, spec: EpisodeSpec, index: int) -> dict | None:
    """The JSON record of episode ``index`` logged at ``path``, its metrics measured again from its
    states (the file rewritten where they changed), or None when there is no readable log (to
    compute); InputError when it was made with another spec (a field the log predates counts as
    its default: a run of an earlier release resumes)."""
    try:
        trials = load_trials(path)
    except InputError:
        return None
    record = trials.metadata.get("episode")
    if not isinstance(record, dict) or record.get("index") != index:
        return None
    stored = record.get("spec")
    try:
        same = isinstance(stored, dict) and EpisodeSpec.from_dict(stored) == spec
    except TypeError:  # fields this release does not know
        same = False
    if not same:
        raise InputError(f"{path}: an episode of another run ({json.dumps(record.get('spec'))}; expected "
                         f"{json.dumps(spec.as_dict())}: use another --out folder)")
    metrics = episode_metrics(trials.states[0], int(trials.lengths[0]), record["robot_car"])
    if metrics != record.get("metrics"):  # logged by a release that measured differently
        record = {**record, "metrics": metrics}
        replace(trials, metadata={**trials.metadata, "episode": record}).write_parquet(path)
    return record


@contextmanager
def _torch_threads(count: int) -> Iterator[None]:
    """Run with ``count`` torch threads, then restore the caller's setting."""
    before = torch.get_num_threads()
    torch.set_num_threads(count)
    try:
        yield
    finally:
        torch.set_num_threads(before)


_worker_agents: dict[EpisodeSpec, tuple] = {}
"""In a worker process: the agents of the spec it last ran (built once, reset per episode)."""


def _worker_episode(spec: EpisodeSpec, index: int) -> Episode:
    """Episode ``index`` in a worker process (pool or Ray), one torch thread, agents reused."""
    torch.set_num_threads(1)
    if spec not in _worker_agents:
        _worker_agents.clear()
        _worker_agents[spec] = spec.agents()
    return run_episode(spec, index, _worker_agents[spec])


def _init_worker() -> None:
    """A pool worker leaves Ctrl-C to the main process, which stops it, and holds no semaphore
    that stopping it would leak (tqdm's default lock is one; the resource tracker would warn)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    tqdm.set_lock(threading.RLock())


def _run_inline(spec: EpisodeSpec, agents: tuple, indices: list[int], done: Callable[[Episode], None]) -> None:
    with _torch_threads(1):
        for index in indices:
            try:
                episode = run_episode(spec, index, agents)
            except Exception as exc:
                raise EpisodeFailed(index, exc) from exc
            done(episode)


def _run_pool(spec: EpisodeSpec, indices: list[int], workers: int, done: Callable[[Episode], None]) -> None:
    pool = ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn"), initializer=_init_worker)
    pending = {pool.submit(_worker_episode, spec, index): index for index in indices}
    try:
        while pending:
            finished, _ = wait(pending, return_when=FIRST_COMPLETED)
            for future in sorted(finished, key=pending.get):
                index = pending.pop(future)
                try:
                    episode = future.result()
                except Exception as exc:
                    raise EpisodeFailed(index, exc) from exc
                done(episode)
    except BaseException:
        for future in pending:
            future.cancel()
        for process in list(pool._processes.values()):  # no public API to stop workers before Python 3.14
            process.terminate()  # their running episodes are dropped
        raise
    finally:
        pool.shutdown(wait=True, cancel_futures=True)


def _run_ray(spec: EpisodeSpec, indices: list[int], workers: int, address: str | None,
             done: Callable[[Episode], None]) -> None:
    import ray

    started = not ray.is_initialized()
    if started:
        options = {"address": address} if address else {"num_cpus": workers, "include_dashboard": False}
        ray.init(**options, log_to_driver=False, logging_level=logging.WARNING)
    task = ray.remote(num_cpus=1, max_retries=0)(_worker_episode)
    queue = iter(indices)
    pending: dict = {}
    try:
        for index in queue:
            pending[task.remote(spec, index)] = index
            if len(pending) == workers:
                break
        while pending:
            finished, _ = ray.wait(list(pending), num_returns=1)
            index = pending.pop(finished[0])
            try:
                episode = ray.get(finished[0])
            except Exception as exc:
                raise EpisodeFailed(index, getattr(exc, "cause", None) or exc) from exc
            done(episode)
            for following in queue:
                pending[task.remote(spec, following)] = following
                break
    except BaseException:
        for ref in pending:
            ray.cancel(ref, force=True)
        raise
    finally:
        if started:
            ray.shutdown()


def simulate(episodes: int, robot: str, human: str, seed: int = 0, workers: int = 1, engine: str = "local",
             address: str | None = None, out: str | Path = "simulate", model: str = "default",
             deadline: float | None = None, budget: Budget | None = None, device: str = "cpu",
             precision: str = "auto", progress: bool = False) -> dict:
    """Run (or resume) episodes ``0..episodes-1`` of robot ``robot`` against human ``human`` and
    return the summary written to ``out/summary.json`` (module docstring; keys of
    :func:`~.metrics.aggregate`, plus ``computed`` and ``reused`` episode counts, the settings and
    ``seconds``). ``progress``: a tqdm bar on stderr.

    Every argument is checked before an episode runs (InputError: counts ≥ 1, seed 0..2³²−1, the
    engine, Ray installed for ``engine="ray"``, ``address`` only with Ray, the output folder, the
    ``device`` (``auto`` resolved here), and the specs, model and ``precision``, by building the
    agents once). An episode that raises stops the batch with :class:`EpisodeFailed` (finished
    episodes stay logged; no summary is written). With Ray already initialised in this process, its instance is used
    (``address`` ignored) and left running.
    """
    episodes = validate.integer("episodes", episodes, 1)
    workers = validate.integer("workers", workers, 1)
    seed = validate.integer("seed", seed, 0, 2**32 - 1)
    if engine not in ENGINES:
        raise InputError(f"engine {engine!r} is unknown (expected one of {', '.join(ENGINES)})")
    if engine == "ray" and find_spec("ray") is None:
        raise InputError(RAY_MISSING)
    if address is not None and engine != "ray":
        raise InputError(f"address {address!r} applies only to the ray engine (expected engine 'ray' or no address)")
    out = check_output_folder(out, "--out")
    device = str(choose_device(device))
    spec = EpisodeSpec(robot, human, seed, model, None if deadline is None else float(deadline), budget, device, precision)
    agents = spec.agents()

    began = time.perf_counter()
    records: dict[int, dict] = {}
    for index in range(episodes):
        path = episode_path(out, index)
        if path.is_file() and (record := _reusable(path, spec, index)) is not None:
            records[index] = record
    todo = [index for index in range(episodes) if index not in records]
    bar = tqdm(total=episodes, initial=episodes - len(todo), desc="episodes", unit="episode", file=sys.stderr,
               disable=not progress, leave=False)

    def done(episode: Episode) -> None:
        episode.trials.write_parquet(episode_path(out, episode.index))
        records[episode.index] = episode.record
        bar.update()

    try:
        if todo and engine == "ray":
            _run_ray(spec, todo, workers, address, done)
        elif todo and min(workers, len(todo)) > 1:
            _run_pool(spec, todo, min(workers, len(todo)), done)
        else:
            _run_inline(spec, agents, todo, done)
    finally:
        bar.close()

    summary = {**aggregate([records[index] for index in range(episodes)]), "computed": len(todo),
               "reused": episodes - len(todo), **spec.as_dict(), "engine": engine, "workers": workers,
               "out": str(out), "seconds": time.perf_counter() - began}
    with atomic_write(out / "summary.json") as f:
        f.write(json.dumps(summary, indent=2, allow_nan=False).encode())
    return summary


def _episodes_by_limit(by_limit: dict | None) -> str:
    """How many episodes break each comfort limit, for :func:`summary_table` (nothing for logs that
    predate the breakdown)."""
    if by_limit is None:
        return ""
    return " (episodes over each limit: " + ", ".join(f"{k} {v['episodes']}" for k, v in by_limit.items()) + ")"


def summary_table(summary: dict) -> str:
    """The summary as readable text: the overall rates and a table by initial condition."""
    def pct(r: dict) -> str:
        if r["rate"] is None:
            return "n/a"
        return f"{100 * r['rate']:.1f} % [{100 * r['ci95'][0]:.1f}, {100 * r['ci95'][1]:.1f}]"

    def num(value, digits: int = 2) -> str:
        return "n/a" if value is None else f"{value:.{digits}f}"

    def interval(m: dict, digits: int = 2) -> str:
        if m["mean"] is None:
            return "n/a"
        return num(m["mean"], digits) + ("" if m["ci95"] is None else f" [{num(m['ci95'][0], digits)}, {num(m['ci95'][1], digits)}]")

    lat, parts = summary["planner_latency_s"], summary["score_parts"]
    gap = summary["min_gap_m"]
    lines = [
        f"{summary['episodes']} episodes, robot {summary['robot']} vs human {summary['human']}, seed {summary['seed']} "
        f"({summary['computed']} computed, {summary['reused']} reused) -> {summary['out']}",
        f"success {pct(summary['success_rate'])}   collisions {summary['collisions']} ({pct(summary['collision_rate'])}; "
        f"robot at fault {num(summary['robot_at_fault_collisions'], 0)})   "
        f"near collisions {summary['near_collisions']} ({pct(summary['near_collision_rate'])})",
        f"robot first {pct(summary['robot_first_rate'])}   human swapped {pct(summary['human_swap_rate'])}   "
        f"time to swap {num(summary['time_to_swap_s']['mean'])} s",
        f"score {interval(summary['score'], 3)} (ttc {num(parts['ttc']['mean'])}, progress "
        f"{num(parts['progress']['mean'])}, comfort {num(parts['comfort']['mean'])})   lane reversals "
        f"{num(summary['lane_reversals']['mean'])} per episode, at most one in {pct(summary['lane_reversals']['at_most_one'])}   "
        f"lateral swings {num(summary['lateral_swings']['mean'])} per episode   "
        f"comfort violations {summary['comfort_violation_steps']['count']} of {summary['comfort_violation_steps']['steps']} steps"
        + _episodes_by_limit(summary['comfort_violation_steps']['by_limit']),
        f"longitudinal gap while overlapping laterally: min {num(gap['min'])} m, mean of episodes {num(gap['mean'])} m; "
        f"closest centres: mean of episodes {num(summary['min_distance_m']['mean'])} m",
        (f"planner latency median {num(lat['median'], 3)} s, p99 {num(lat['p99'], 3)} s over {lat['plans']} plans; "
         f"deadline misses (over the {summary['planning_period_s']:g} s period) {summary['deadline_misses']}"
         if lat["plans"] else "no plans (a robot without a planner)"),
        "",
        f"{'Δv (m/s)':>8} {'tco (s)':>7} {'robot':>6} {'episodes':>8}  {'success (95 % CI)':<24} {'collisions':>10} "
        f"{'near':>5} {'min gap (m)':>11}",
    ]
    for row in summary["by_initial_condition"]:
        tco = "all" if row["tco"] is None else f"{row['tco']:g}"
        dv = "?" if row["dv"] is None else f"{row['dv']:g}"
        lines.append(f"{dv:>8} {tco:>7} {row['robot_lane']:>6} {row['episodes']:>8}  "
                     f"{pct(row['success_rate']):<24} {row['collisions']:>10} {row['near_collisions']:>5} "
                     f"{num(row['min_gap_m']['min']):>11}")
    return "\n".join(lines)

