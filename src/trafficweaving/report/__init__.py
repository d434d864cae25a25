"""Results tables (Markdown) and figures (PNG) rendered from what ``simulate``, ``evaluate --json``
and ``realism --json`` wrote: results pages made this way cannot drift from the code, and a user's
own runs give the same tables.

An input is recognised by what it holds (:func:`.runs.read_run`): a folder with the ``summary.json``
that :func:`~trafficweaving.sim.batch.simulate` writes (or that summary saved from ``simulate
--json``); a JSON object with ``evaluate``'s keys (:data:`.runs.EVALUATE_KEYS`) or ``realism``'s
(:data:`.runs.REALISM_KEYS`). Written into the output folder, for the kinds given (:data:`OUTPUTS`;
files of kinds not given are left alone):

* ``closed_loop.md``, ``closed_loop_score.png``: one row per simulate run (robot, human), sorted
  by robot, human and run path; the score per human, one marker series per robot;
* ``models.md``, ``models_nll_by_direction.png``: one row per evaluate file, sorted by label and
  path; the exact NLL by direction;
* ``realism.md``, ``realism.png``: one row per realism file, sorted by label and path; the
  realism score and its parts.

A table file starts with a one-line caption naming the inputs and their settings, and ends with
its figure. Rates are percentages with their 95 % Wilson interval, means with their Student-t
95 % interval (none below 2 values), as ``simulate`` measures them (:mod:`.tables`). No
timestamps: the same inputs give the same bytes.
"""

from __future__ import annotations

import os
import re
import sys
from pathlib import Path

from tqdm import tqdm

from ..atomic import atomic_write, check_output_file, check_output_folder, remove_stale_temporaries
from ..data.trials import _short
from ..errors import InputError
from ..viz.result_figures import plot_nll_by_direction, plot_realism, plot_scores_by_human
from .runs import EXPECTED, Run, read_run
from .tables import closed_loop_table, models_table, realism_table

OUTPUTS = {"simulate": ("closed_loop.md", "closed_loop_score.png"),
           "evaluate": ("models.md", "models_nll_by_direction.png"),
           "realism": ("realism.md", "realism.png")}
"""Per kind of input, its table and figure in the output folder."""
RENDERERS = {"simulate": (closed_loop_table, plot_scores_by_human), "evaluate": (models_table, plot_nll_by_direction),
             "realism": (realism_table, plot_realism)}
"""Per kind of input, what renders its table and what draws its figure."""

_OUTPUT_NAMES = re.compile("|".join(re.escape(name) for names in OUTPUTS.values() for name in names))


def render_report(runs: list[str | Path], out: str | Path, progress: bool = False) -> dict:
    """Render the tables and figures of ``runs`` (simulate run folders, evaluate and realism
    ``--json`` files; module docstring) into the folder ``out``. Returns ``runs`` (per input, in
    the order given: ``path``, ``kind``, ``label``), ``tables`` and ``figures`` (the files
    written). Every input is read and checked, and every output path, before anything is
    written; InputError naming the path for a bad input, an input given twice, an empty list or
    an output folder that cannot be written. ``progress``: a tqdm bar on stderr while reading."""
    if isinstance(runs, (str, os.PathLike)) or not isinstance(runs, (list, tuple)) or not runs:
        raise InputError(f"runs {_short(runs)}: expected a non-empty list of run paths ({EXPECTED})")
    out = check_output_folder(out, "--out")
    read: list[Run] = []
    sources: dict[str, str] = {}
    for path in tqdm(runs, desc="runs", unit="run", file=sys.stderr, disable=not progress, leave=False):
        run = read_run(path)
        real = os.path.realpath(run.source)
        if real in sources:
            raise InputError(f"{run.path}: given twice (also as {sources[real]}; expected each run once)")
        sources[real] = run.path
        read.append(run)
    rendered = []
    for kind, (table, plot) in RENDERERS.items():
        mine = [run for run in read if run.kind == kind]
        if mine:
            text, figure_data = table(mine, OUTPUTS[kind][1])
            rendered.append((out / OUTPUTS[kind][0], text, out / OUTPUTS[kind][1], plot, figure_data))
    for table_path, _, figure_path, _, _ in rendered:
        for path in (table_path, figure_path):
            check_output_file(path, "--out")
            if os.path.realpath(path) in sources:
                raise InputError(f"--out {out}: would replace the input {sources[os.path.realpath(path)]} "
                                 f"(expected another folder)")
    tables, figures = [], []
    try:
        out.mkdir(parents=True, exist_ok=True)
        remove_stale_temporaries(out, _OUTPUT_NAMES)
        for table_path, text, figure_path, plot, figure_data in rendered:
            with atomic_write(table_path) as f:
                f.write(text.encode())
            tables.append(str(table_path))
            if figure_data:
                figures.append(str(plot(figure_data, figure_path)))
    except OSError as exc:
        raise InputError(f"--out {out}: cannot be written ({exc.strerror or exc}; expected a folder this user may "
                         f"write)") from None
    return {"runs": [{"path": run.path, "kind": run.kind, "label": run.label} for run in read],
            "tables": tables, "figures": figures}
