"""The Markdown tables of ``trafficweaving report``, one file per kind of input: a one-line
caption naming the inputs and their settings, the tables, a line of definitions and the figure.
Rows sorted as stated per table; numbers at fixed precision, so the same inputs give the same text."""

from __future__ import annotations

import re

from .runs import Run

RATES = {"swap": "swap", "off_road": "off-road", "collision": "collision", "at_fault_collision": "at-fault collision"}
"""The realism rates shown (``KEY_rate``, ``real_KEY_rate``) and their names in the table."""


def _code(text: str) -> str:
    """``text`` as a Markdown code span that a table row keeps whole (pipes escaped, line breaks
    as spaces)."""
    text = text.replace("\r", " ").replace("\n", " ")
    fence = "`" * (max((len(m) for m in re.findall(r"`+", text)), default=0) + 1)
    pad = " " if text.startswith("`") or text.endswith("`") else ""
    return f"{fence}{pad}{text}{pad}{fence}".replace("|", "\\|")


def _num(value, digits: int) -> str:
    return "n/a" if value is None else f"{value:.{digits}f}"


def _pct(value) -> str:
    return "n/a" if value is None else f"{100 * value:.1f} %"


def _with_interval(mean, ci95, digits: int, scale: float = 1.0) -> str:
    """``mean [low, high]`` (``scale``: 100 for percentages); n/a without a mean."""
    if mean is None:
        return "n/a"
    unit = " %" if scale == 100 else ""
    text = f"{scale * mean:.{digits}f}{unit}"
    return text if ci95 is None else f"{text} [{scale * ci95[0]:.{digits}f}, {scale * ci95[1]:.{digits}f}]"


def _table(header: list[str], rows: list[list[str]]) -> str:
    return "\n".join(["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
                     + ["| " + " | ".join(row) + " |" for row in rows])


def _caption(what: str, command: str, runs: list[Run], settings) -> str:
    """The one-line caption: what the table shows, from which inputs, with their settings."""
    inputs = "; ".join(f"{_code(run.path)} ({settings(run)})" for run in runs)
    return f"{what}, rendered by `trafficweaving report` from `{command}` output: {inputs}."


def _names(runs: list[Run], key) -> list[str]:
    """A display name per run: ``key(run)``, with the run's path added where two share it."""
    keys = [key(run) for run in runs]
    return [k if keys.count(k) == 1 else f"{k} ({run.path})" for k, run in zip(keys, runs)]


# ---------------------------------------------------------------- closed loop
CLOSED_LOOP_NOTES = (
    "Score: the closed-loop score (0 to 1), mean and Student-t 95 % interval over episodes; success with its Wilson "
    "95 % interval; near collisions: episodes with a step inside the paper's collision cost; smallest gap: the least "
    "longitudinal distance between the cars while they overlap laterally; lane reversals: the robot's sideways motion "
    "turning back, mean per episode; comfort: episodes with no step over nuPlan's comfort limits; safety overrides: "
    "episodes in which the planner's safety layer changed a window (docs/driving.md, Safety layer), in brackets the "
    "windows where no action was safe.")


def _simulate_settings(run: Run) -> str:
    """Seed, episodes, the planner's model and its budget or deadline, and a precision other than auto."""
    deadline = run.get("deadline", check="number or null", default=None)
    budget = run.get("budget", check="budget or null", default=None)
    precision = run.get("precision", check="text", default="auto")
    planning = ([f"budget {'/'.join(map(str, budget))} samples"] if budget is not None else []) + (
        [f"deadline {deadline:g} s"] if deadline is not None else [])
    return ", ".join([f"seed {run.get('seed', check='count')}", f"{run.get('episodes', check='count')} episodes",
                      f"model {_code(run.get('model', check='text', default='default'))}",
                      *(planning or ["full budget"]), *([f"precision {precision}"] if precision != "auto" else [])])


def _closed_loop_row(run: Run) -> list[str]:
    g = run.get
    at_fault = g("robot_at_fault_collisions", check="count or null")
    return [_code(g("robot", check="text")), _code(g("human", check="text")), str(g("episodes", check="count")),
            _with_interval(g("score", "mean", check="number or null"), g("score", "ci95", check="interval or null"), 3),
            _with_interval(g("success_rate", "rate", check="number or null"),
                           g("success_rate", "ci95", check="interval or null"), 1, 100),
            f"{g('collisions', check='count')} ({'n/a' if at_fault is None else at_fault})",
            str(g("near_collisions", check="count")), _num(g("min_gap_m", "min", check="number or null"), 2),
            _num(g("lane_reversals", "mean", check="number or null"), 2),
            _pct(g("score_parts", "comfort", "mean", check="number or null")), _safety_overrides(run), _code(run.path)]


def _safety_overrides(run: Run) -> str:
    """The episodes in which the safety layer changed a window, and the windows it changed with
    none safe (n/a for a run logged without them)."""
    overrides = run.get("safety_overrides", check="object or null", default=None)
    if overrides is None:
        return "n/a"
    return f"{run.get('safety_overrides', 'episodes', check='count')} ({run.get('safety_overrides', 'unresolved', check='count')})"


def closed_loop_table(runs: list[Run], figure: str) -> tuple[str, list[dict]]:
    """The closed-loop table file's text, rows sorted by robot, human and run path, and the
    figure's points (:func:`~trafficweaving.viz.result_figures.plot_scores_by_human`)."""
    pairs = {run.path: (run.get("robot", check="text"), run.get("human", check="text")) for run in runs}
    runs = sorted(runs, key=lambda run: (*pairs[run.path], run.path))
    points = []
    for run in runs:
        robot, human = pairs[run.path]
        shared = list(pairs.values()).count((robot, human)) > 1  # another run of this robot and human
        points.append({"series": f"{robot} ({run.path})" if shared else robot, "human": human,
                       "mean": run.get("score", "mean", check="number or null"),
                       "ci95": run.get("score", "ci95", check="interval or null")})
    header = ["robot", "human", "episodes", "score (95 % CI)", "success (95 % CI)", "collisions (robot at fault)",
              "near collisions", "smallest gap (m)", "lane reversals per episode", "comfort",
              "safety overrides: episodes (windows with none safe)", "run"]
    text = "\n\n".join([_caption("Closed loop", "simulate", runs, _simulate_settings),
                         _table(header, [_closed_loop_row(run) for run in runs]), CLOSED_LOOP_NOTES,
                         f"![closed-loop score per human]({figure})"])
    return text + "\n", points


# ---------------------------------------------------------------- models and agents
MODELS_NOTES = (
    "NLL: negative log-likelihood of the human's next 15 accelerations per direction (nats per instance, physical "
    "units): exact over the model's latent values, importance-sampled and naive from samples (n/a for a model without "
    "an encoder); x and y: exact, per direction; phases: of the human's lane change. Coverage: the share of true "
    "positions inside the samples' central intervals, per direction and horizon; minADE/minFDE: the best sample's "
    "average and final position errors.")
REALISM_NOTES = (
    "Realism (0 to 1): how likely the real driving is under the agent's rollouts, the weighted mean of its parts; "
    "rates: of the rollouts, the recordings' in brackets (at-fault collision: the human car at fault).")


def _keys(runs: list[Run], *keys: str) -> list[str]:
    """The keys of the objects at ``keys`` in the runs that have one, in first-seen order."""
    seen: dict[str, None] = {}
    for run in runs:
        seen.update(dict.fromkeys(run.get(*keys, check="object", default={})))
    return list(seen)


def _recorded(run: Run, fields: list[tuple[str, str, str]]) -> str:
    """``template`` filled with each field (``key``, ``check``, ``template``) the run records, joined."""
    return ", ".join(template.format(_code(value) if isinstance(value, str) else value)
                     for key, check, template in fields
                     if (value := run.get(key, check=check, default=None)) is not None)


def _evaluate_settings(run: Run) -> str:
    return _recorded(run, [("model", "text", "model {}"), ("variant", "text", "variant {}"),
                           ("data", "text", "data {}"), ("seed", "count", "seed {}"),
                           ("samples", "count", "{} position samples"),
                           ("ade_samples", "count", "minADE/minFDE best of {}")])


def _nll_row(run: Run, phases: list[str]) -> list[str]:
    g = run.get
    variant = g("variant", check="text", default=None)
    by_phase = [(g("nll_exact_by_phase", p, "nll_exact", check="number or null", default=None),
                 g("nll_exact_by_phase", p, "instances", check="count", default=None)) for p in phases]
    return [_code(run.label), "n/a" if variant is None else _code(variant), str(g("instances", check="count")),
            *(_num(g(key, check="number or null"), 3) for key in ("nll_exact", "nll_is", "nll_naive")),
            *(_num(g("nll_exact_by_direction", d, check="number or null", default=None), 3) for d in ("x", "y")),
            *(_num(nll, 3) + ("" if n is None else f" ({n})") for nll, n in by_phase), _code(run.path)]


def _position_row(run: Run, coverage: list[tuple[str, str, list[str]]]) -> list[str]:
    g = run.get
    covered = [" / ".join(_pct(g("coverage", d, h, level, check="number or null", default=None)) for level in levels)
               for d, h, levels in coverage]
    return [_code(run.label), _num(g("sampled_instances", check="count", default=None), 0), *covered,
            *(_num(g(key, check="number or null", default=None), 3) for key in ("min_ade_m", "min_fde_m")),
            _code(run.path)]


def models_table(runs: list[Run], figure: str) -> tuple[str, list[tuple[str, dict]]]:
    """The models' table file text, rows sorted by label and path (the NLLs; the sampled
    positions where recorded), and the figure's bars
    (:func:`~trafficweaving.viz.result_figures.plot_nll_by_direction`; none without NLL by direction)."""
    runs = sorted(runs, key=lambda run: (run.label, run.path))
    phases = _keys(runs, "nll_exact_by_phase")
    coverage = [(d, h, _keys(runs, "coverage", d, h)) for d in _keys(runs, "coverage")
                for h in _keys(runs, "coverage", d)]
    parts = [_caption("Human models", "evaluate --json", runs, _evaluate_settings),
             _table(["model", "variant", "instances", "exact", "importance-sampled", "naive", "x", "y",
                     *(f"{p} (instances)" for p in phases), "file"], [_nll_row(run, phases) for run in runs])]
    if coverage or any(run.get("min_ade_m", check="number or null", default=None) is not None for run in runs):
        parts.append(_table(["model", "sampled instances",
                             *(f"coverage {d} {h} s ({' / '.join(levels)} %)" for d, h, levels in coverage),
                             "minADE (m)", "minFDE (m)", "file"], [_position_row(run, coverage) for run in runs]))
    directions = [{d: run.get("nll_exact_by_direction", d, check="number or null", default=None) for d in ("x", "y")}
                  for run in runs]
    bars = [(name, nll) for name, nll in zip(_names(runs, lambda run: run.label), directions)
            if any(v is not None for v in nll.values())]
    parts += [MODELS_NOTES, *([f"![exact NLL by direction]({figure})"] if bars else [])]
    return "\n\n".join(parts) + "\n", bars


def _realism_row(run: Run, groups: list[str]) -> tuple[list[str], dict]:
    """The row and the figure's parts (realism, then its groups) of one agent."""
    g = run.get
    parts = {"realism": g("realism", check="number"),
             **{group: g("groups", group, check="number or null", default=None) for group in groups}}
    rates = [f"{_pct(g(f'{k}_rate', check='number or null', default=None))} "
             f"({_pct(g(f'real_{k}_rate', check='number or null', default=None))})" for k in RATES]
    row = [_code(run.label), *(_num(v, 3) for v in parts.values()), *rates,
           _num(g("trials", check="count", default=None), 0), str(g("rollouts", check="count")), _code(run.path)]
    return row, parts


def _realism_settings(run: Run) -> str:
    return _recorded(run, [("human", "text", "agent {}"), ("data", "text", "data {}"), ("seed", "count", "seed {}"),
                           ("trials", "count", "{} trials"), ("rollouts", "count", "{} rollouts")])


def realism_table(runs: list[Run], figure: str) -> tuple[str, list[tuple[str, dict]]]:
    """The realism table file text, rows sorted by label and path, and the figure's bars
    (:func:`~trafficweaving.viz.result_figures.plot_realism`)."""
    runs = sorted(runs, key=lambda run: (run.label, run.path))
    groups = _keys(runs, "groups")
    rows = [_realism_row(run, groups) for run in runs]
    header = ["agent", "realism", *groups, *(f"{name} rate (real)" for name in RATES.values()), "trials", "rollouts",
              "file"]
    text = "\n\n".join([_caption("Realism of human agents", "realism --json", runs, _realism_settings),
                         _table(header, [row for row, _ in rows]), REALISM_NOTES,
                         f"![realism and its parts]({figure})"])
    return text + "\n", [(name, parts) for name, (_, parts) in zip(_names(runs, lambda run: run.label), rows)]
