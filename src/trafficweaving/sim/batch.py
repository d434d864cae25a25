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
interrupted batch resumes, first removing the temporary files of a killed run); a file made with
another spec, or whose record does not hold what the summary needs, is refused. A reused episode's metrics
are measured again from its states, and its file rewritten where they changed: a rerun brings the
logs of an earlier release up to this one's metrics. The summary is rebuilt from
the files of episodes ``0..episodes-1`` (others in the folder are left alone).

Engines: ``local`` runs the episodes in the calling process (``workers = 1``) or in a pool of
``workers`` spawned processes; ``ray`` runs them as Ray tasks, at most ``workers`` at a time, on
the running Ray instance, the cluster at ``address`` (checked to answer within
:data:`RAY_CONNECT_TIMEOUT_S` first) or a new local instance of ``workers`` CPUs.
Every worker uses one torch thread, so an episode is bitwise the same on either engine and any
number of workers (:mod:`.episodes`), unless the planner plans against a wall-clock deadline.
"""

from __future__ import annotations

import json
import logging
import math
import multiprocessing
import os
import re
import signal
import socket
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
from ..atomic import atomic_write, check_output_file, check_output_folder, remove_stale_temporaries
from ..data.trials import _short, load_trials
from ..errors import InputError
from ..model.device import choose_device
from ..planning.planner import Budget
from ..scenario import LANES
from .episodes import Episode, EpisodeSpec, run_episode
from .metrics import aggregate, episode_metrics

ENGINES = ("local", "ray")
RAY_MISSING = "`--engine ray` needs Ray: pip install 'trafficweaving[ray]'"

MAX_EPISODES = 100_000
"""Most episodes of one run: it keeps every episode's record (a few kB) in memory for the summary."""

WORKERS_PER_CPU = 4
"""Most workers per CPU core of this machine, where they run on it (the local engine, a new local
Ray instance): each is a process holding its own agents."""

RAY_CONNECT_TIMEOUT_S = 5.0
"""How long a Ray cluster's head may take to answer before its ``address`` is refused."""

RAY_ADDRESS_FORMS = "auto, local, HOST:PORT or ray://HOST:PORT"
"""The ``address`` forms ``ray.init`` takes (``ray://``: through Ray Client)."""

_RAY_ADDRESS = re.compile(r"(?:ray://)?(?P<host>\[[0-9A-Fa-f:.]+\]|[^\s:/\[\]@]+):(?P<port>[0-9]{1,5})")
_HTTP2_HELLO = b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n" + bytes([0, 0, 0, 4, 0, 0, 0, 0, 0])
"""An HTTP/2 client's first bytes: the connection preface and an empty SETTINGS frame (type 4)."""

EPISODE_NAME = re.compile(r"episode_(?P<index>[0-9]{6,})\.parquet")
"""The names of episode logs in ``out/episodes`` (:func:`episode_path`)."""


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


def max_workers(engine: str, address: str | None) -> int:
    """The most ``workers`` of a run: :data:`WORKERS_PER_CPU` per CPU core of this machine, or on
    a Ray cluster (an ``address`` other than ``local``) up to :data:`MAX_EPISODES` (one task per
    episode at most)."""
    if engine == "ray" and address not in (None, "local"):
        return MAX_EPISODES
    return WORKERS_PER_CPU * (os.cpu_count() or 1)


def check_ray_address(address) -> str:
    """``address`` if Ray can join it promptly: ``local`` (a new local instance), ``auto`` (the
    instance Ray finds running) or a cluster head's ``HOST:PORT`` (``ray://HOST:PORT``: Ray
    Client), which must answer as a gRPC server (an HTTP/2 handshake) within
    :data:`RAY_CONNECT_TIMEOUT_S` (``ray.init`` would wait minutes for a head that is not there,
    printing warnings). InputError naming the address otherwise."""
    if not isinstance(address, str) or not address:
        raise InputError(f"address {_short(address)} is not a Ray address (expected {RAY_ADDRESS_FORMS})")
    if address == "local":
        return address
    target = address
    if address == "auto":
        try:
            from ray._private.services import canonicalize_bootstrap_address  # Ray's own lookup; no public API
        except ImportError:  # another Ray release: ray.init looks it up
            return address
        try:
            target = canonicalize_bootstrap_address("auto")
        except (ConnectionError, ValueError) as exc:
            raise InputError(f"address 'auto': {(str(exc).splitlines() or [''])[0]}") from None
    match = _RAY_ADDRESS.fullmatch(target or "")
    if match is None or not 1 <= int(match["port"]) <= 65535:
        raise InputError(f"address {address!r} is not a Ray address (expected {RAY_ADDRESS_FORMS}, PORT in 1..65535)")
    expected = f"expected a running Ray cluster's head, e.g. from ray start --head, answering within {RAY_CONNECT_TIMEOUT_S:g} s"
    deadline = time.monotonic() + RAY_CONNECT_TIMEOUT_S
    reply = b""
    try:
        with socket.create_connection((match["host"].strip("[]"), int(match["port"])), RAY_CONNECT_TIMEOUT_S) as conn:
            conn.sendall(_HTTP2_HELLO)
            while len(reply) < 9:
                conn.settimeout(max(deadline - time.monotonic(), 0.01))
                chunk = conn.recv(9 - len(reply))
                if not chunk:
                    break
                reply += chunk
    except OSError as exc:  # refused, unreachable, an unknown host, timed out
        raise InputError(f"address {address!r}: {exc.strerror or str(exc) or type(exc).__name__} ({expected})") from None
    if len(reply) < 9 or reply[3] != 4:  # a gRPC server answers with its SETTINGS frame
        raise InputError(f"address {address!r}: what answers there is not a Ray cluster ({expected})")
    return address


def _check_outputs(out: str | Path, episodes: int) -> Path:
    """``out`` as a Path if every file a run of ``episodes`` writes there may be written (the
    folder, ``episodes/`` in it, each episode's log and ``summary.json``:
    :func:`~trafficweaving.atomic.check_output_file`); InputError naming ``--out`` otherwise."""
    out = check_output_folder(out, "--out")
    check_output_folder(out / "episodes", "--out")
    check_output_file(out / "summary.json", "--out")
    check_output_file(episode_path(out, 0), "--out")
    if (out / "episodes").is_dir():  # the logs there of episodes 0..episodes-1
        for entry in os.scandir(out / "episodes"):
            match = EPISODE_NAME.fullmatch(entry.name)
            if match and int(match["index"]) < episodes and entry.name == episode_path(out, int(match["index"])).name:
                check_output_file(entry.path, "--out")
    return out


_MISSING = object()


def _check_record(path: Path, trials, record: dict) -> None:
    """InputError naming ``path`` unless the episode record read back holds what the summary
    uses: one trial, ``robot_car`` 0 or 1 (the car labelled robot), an ``initial_condition`` with
    finite or null ``dv`` and ``tco`` (m/s, s) and the robot's lane, and ``latencies_s`` finite
    seconds ≥ 0."""
    def refuse(key: str, value, expected: str):
        shown = "missing" if value is _MISSING else _short(value)
        raise InputError(f"{path}: {key} {shown} in the episode record (expected {expected})")

    def number(value) -> bool:
        return type(value) is float and math.isfinite(value) or type(value) is int and abs(value) <= 2**53

    if len(trials) != 1:
        raise InputError(f"{path}: {len(trials)} trials (expected the one episode simulate logs per file)")
    car = record.get("robot_car", _MISSING)
    if type(car) is not int or car not in (0, 1) or list(trials.roles[0, [car, 1 - car]]) != ["robot", "human"]:
        refuse("robot_car", car, f"0 or 1, the car the roles label robot: {', '.join(map(str, trials.roles[0]))}")
    ic = record.get("initial_condition", _MISSING)
    if not isinstance(ic, dict):
        refuse("initial_condition", ic, "an object with dv, tco and robot_lane")
    for key in ("dv", "tco"):
        if key not in ic or not (ic[key] is None or number(ic[key])):
            refuse(f"initial_condition.{key}", ic.get(key, _MISSING), "a finite number or null")
    if ic.get("robot_lane") not in LANES:
        refuse("initial_condition.robot_lane", ic.get("robot_lane", _MISSING), " or ".join(LANES))
    latencies = record.get("latencies_s", _MISSING)
    if not isinstance(latencies, list) or not all(number(s) and s >= 0 for s in latencies):
        refuse("latencies_s", latencies, "a list of finite planner seconds >= 0")


def _reusable(path: Path, spec: EpisodeSpec, index: int) -> dict | None:
    """The JSON record of episode ``index`` logged at ``path``, its metrics measured again from its
    states (the file rewritten where they changed), or None when there is no readable log (to
    compute); InputError when it was made with another spec (a field the log predates counts as
    its default: a run of an earlier release resumes) or its record is malformed
    (:meth:`EpisodeSpec.from_dict`, :func:`_check_record`)."""
    try:
        trials = load_trials(path)
    except InputError:
        return None
    record = trials.metadata.get("episode")
    if not isinstance(record, dict) or type(record.get("index")) is not int or record["index"] != index:
        return None
    if EpisodeSpec.from_dict(record.get("spec"), str(path)) != spec:
        raise InputError(f"{path}: an episode of another run ({json.dumps(record.get('spec'))}; expected "
                         f"{json.dumps(spec.as_dict())}: use another --out folder)")
    _check_record(path, trials, record)
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


def _run_inline(spec: EpisodeSpec, agents: tuple, indices: list[int], done: Callable[[Episode], None],
                threads: int = 1) -> None:
    with _torch_threads(threads):
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
        options = ({"address": address} if address not in (None, "local")
                   else {"address": address, "num_cpus": workers, "include_dashboard": False})
        try:
            ray.init(**options, log_to_driver=False, logging_level=logging.WARNING)
        except (ConnectionError, ValueError, RuntimeError) as exc:  # e.g. ray:// without Ray Client installed
            raise InputError(f"address {address!r}: Ray could not start or join it: "
                             f"{(str(exc).splitlines() or [type(exc).__name__])[0]}") from None
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
             precision: str = "auto", progress: bool = False, threads: int = 1) -> dict:
    """Run (or resume) episodes ``0..episodes-1`` of robot ``robot`` against human ``human`` and
    return the summary written to ``out/summary.json`` (module docstring; keys of
    :func:`~.metrics.aggregate`, plus ``computed`` and ``reused`` episode counts, the settings and
    ``seconds``). ``progress``: a tqdm bar on stderr. ``threads``: the torch threads of episodes
    run in this process (``workers`` 1; a worker process runs one), e.g. 2 for a planner that has
    the machine's two cores to itself.

    Every argument is checked before an episode runs (InputError: ``episodes`` in
    1..:data:`MAX_EPISODES`, ``workers`` in 1..:func:`max_workers`, seed 0..2³²−1, the engine, Ray
    installed for ``engine="ray"``, ``address`` only with Ray and answering
    (:func:`check_ray_address`), every output path (:func:`_check_outputs`), the ``device``
    (``auto`` resolved here), and the specs, model and ``precision``, by building the agents
    once); then the temporary files a killed run left in the folder are removed and the episodes
    logged there read back (:func:`_reusable`). An episode that raises stops the batch with
    :class:`EpisodeFailed` (finished episodes stay logged; no summary is written). With Ray
    already initialised in this process, its instance is used (``address`` ignored) and left
    running.
    """
    episodes = validate.integer("episodes", episodes, 1, MAX_EPISODES)
    if engine not in ENGINES:
        raise InputError(f"engine {engine!r} is unknown (expected one of {', '.join(ENGINES)})")
    if engine == "ray" and find_spec("ray") is None:
        raise InputError(RAY_MISSING)
    if address is not None and engine != "ray":
        raise InputError(f"address {address!r} applies only to the ray engine (expected engine 'ray' or no address)")
    workers = validate.integer("workers", workers, 1, max_workers(engine, address))
    threads = validate.thread_count("threads", threads)
    if threads > 1 and (workers > 1 or engine == "ray"):
        raise InputError(f"threads {threads} applies to episodes run in this process (expected workers 1 and the local "
                         f"engine; a worker runs one thread)")
    out = _check_outputs(out, episodes)
    device = str(choose_device(device))
    spec = EpisodeSpec(robot, human, seed, model, None if deadline is None else float(deadline), budget, device, precision)
    agents = spec.agents()
    if address is not None:
        check_ray_address(address)

    began = time.perf_counter()
    (out / "episodes").mkdir(parents=True, exist_ok=True)  # an unwritable place fails here, before any episode
    remove_stale_temporaries(out / "episodes", EPISODE_NAME)
    remove_stale_temporaries(out, re.compile(r"summary\.json"))
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
            _run_inline(spec, agents, todo, done, threads)
    finally:
        bar.close()

    summary = {**aggregate([records[index] for index in range(episodes)]), "computed": len(todo),
               "reused": episodes - len(todo), **spec.as_dict(), "engine": engine, "workers": workers, "threads": threads,
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

