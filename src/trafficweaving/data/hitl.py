"""Import of the authors' human-in-the-loop recordings (Julia JLD files).

Each file is HDF5 holding datasets ``car1`` (the robot, driven by the authors' planner) and
``car2`` (the human), float32 ``[6, T, 1]``: rows ``x, y, xd, yd, xdd, ydd`` (m, m/s, m/s²), one
column per ``DT`` step. Every recorded step is kept: no cutting, no validity filtering; but a
file with a value outside :data:`.trials.PLAUSIBLE_RANGES` (no real car does that) is refused.
"""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np

from ..errors import InputError
from ..scenario import DELTA_V_VALUES, DT, MIN_TRIAL_STEPS, STATE_NAMES, lane_of
from .trials import TrialSet, first_implausible, implausible_text

CARS = ("car1", "car2")
"""Dataset names, in agent order (agent 0 = robot, agent 1 = human)."""
AGENT_ROLES = ("robot", "human")
"""Role of agent 0 (``car1``) and agent 1 (``car2``) in these files (labels from :data:`.trials.ROLES`)."""
EXPECTED = "a Julia JLD (HDF5) file with datasets car1 and car2 of shape [6, T, 1]"


def read_hitl(paths: list[str | Path]) -> TrialSet:
    """Read human-in-the-loop trials, one per file, numbered 0..n-1 in the order given.

    Agent 0 is ``car1`` (role ``robot``), agent 1 is ``car2`` (role ``human``); drivers are unknown
    (-1). ``ic_dv`` is ``v_left - v_right`` at step 0 (the left car is the one with the larger
    ``y``) and ``ic_tco = -(x_left - x_right) / ic_dv`` (NaN when ``ic_dv`` is 0); a ``Δv`` within 0.25 m/s of a study value
    (``DELTA_V_VALUES``) is snapped to it.

    Raises :class:`InputError` (one line naming the file) on a missing file, a file that is not
    HDF5, a missing or malformed ``car1``/``car2``, cars of different lengths, NaN/inf values, a
    value outside :data:`.trials.PLAUSIBLE_RANGES` (message: the car, the quantity, the value and
    the plausible range), or fewer than ``MIN_TRIAL_STEPS`` steps. ``source_path`` is the file when
    one is given, else their common folder (None if they lie in several).
    """
    if not paths:
        raise InputError(f"no files given (expected one or more .jld files: {EXPECTED})")
    trajectories = [_read_file(Path(p)) for p in paths]  # each [2, T, 6]
    n = len(trajectories)
    lengths = np.array([s.shape[1] for s in trajectories], dtype=np.int64)
    states = np.full((n, 2, int(lengths.max()), len(STATE_NAMES)), np.nan)
    for i, s in enumerate(trajectories):
        states[i, :, : s.shape[1]] = s

    x0, y0, xd0 = states[:, :, 0, 0], states[:, :, 0, 1], states[:, :, 0, 2]  # [n, 2]
    left = np.argmax(y0, axis=1)
    rows = np.arange(n)
    ic_dv = xd0[rows, left] - xd0[rows, 1 - left]
    # speeds within 0.25 m/s of a study value (recordings start a few steps in) snap to it
    grid = np.array(DELTA_V_VALUES)
    nearest = grid[np.argmin(np.abs(ic_dv[:, None] - grid[None, :]), axis=1)]
    ic_dv = np.where(np.abs(ic_dv - nearest) < 0.25, nearest, ic_dv)
    gap = x0[rows, left] - x0[rows, 1 - left]
    with np.errstate(divide="ignore", invalid="ignore"):
        ic_tco = np.where(ic_dv == 0.0, np.nan, -gap / ic_dv)

    return TrialSet(
        states=states,
        lengths=lengths,
        trial_ids=np.arange(n, dtype=np.int32),
        roles=np.tile(np.array(AGENT_ROLES), (n, 1)),
        start_lanes=lane_of(y0),
        drivers=np.full((n, 2), -1, dtype=np.int32),
        ic_dv=ic_dv,
        ic_tco=ic_tco,
        sources=np.array([Path(p).name for p in paths]),
        dt=DT,
        metadata={"importer": "hitl"},
        source_path=_common_source([Path(p) for p in paths]),
    )


def _common_source(paths: list[Path]) -> Path | None:
    """The one file read, or the folder all files lie in; None when they are spread out."""
    if len(paths) == 1:
        return paths[0]
    folders = {p.parent for p in paths}
    return folders.pop() if len(folders) == 1 else None


def _read_file(path: Path) -> np.ndarray:
    """Both cars' states from one file, ``[2, T, 6]`` float64, validated."""
    if not path.is_file():
        raise InputError(f"{path}: {'is a folder' if path.is_dir() else 'no such file'} (expected {EXPECTED})")
    if not h5py.is_hdf5(path):
        raise InputError(f"{path}: not an HDF5 file (expected {EXPECTED})")
    try:
        with h5py.File(path, "r") as f:
            cars = [_read_car(f, name, path) for name in CARS]
    except OSError as exc:
        raise InputError(f"{path}: unreadable HDF5 file ({str(exc).splitlines()[0]}; expected {EXPECTED})") from None
    if cars[0].shape != cars[1].shape:
        raise InputError(f"{path}: car1 has {cars[0].shape[0]} steps but car2 has {cars[1].shape[0]} (expected equal lengths)")
    steps = cars[0].shape[0]
    if steps < MIN_TRIAL_STEPS:
        raise InputError(f"{path}: only {steps} steps (expected at least {MIN_TRIAL_STEPS})")
    return np.stack(cars)


def _read_car(f: h5py.File, name: str, path: Path) -> np.ndarray:
    """One car's states ``[T, 6]`` float64 from dataset ``name`` (stored ``[6, T, 1]``)."""
    ds = f.get(name)
    if not isinstance(ds, h5py.Dataset):
        raise InputError(f"{path}: missing dataset {name} (expected {EXPECTED})")
    if ds.dtype.kind not in "fiu":
        raise InputError(f"{path}: dataset {name} has dtype {ds.dtype} (expected float numbers)")
    if ds.ndim != 3 or ds.shape[0] != len(STATE_NAMES) or ds.shape[2] != 1:
        raise InputError(f"{path}: dataset {name} has shape {list(ds.shape)} (expected [6, T, 1])")
    states = np.asarray(ds[()], dtype=np.float64)[:, :, 0].T
    bad = ~np.isfinite(states)
    if bad.any():
        step, row = np.argwhere(bad)[0]
        raise InputError(f"{path}: dataset {name} has a NaN or infinite {STATE_NAMES[row]} at step {step} (expected finite numbers)")
    implausible = first_implausible(states)
    if implausible is not None:
        (step,), quantity, value = implausible
        role = AGENT_ROLES[CARS.index(name)]
        text = implausible_text(quantity, value, where=f" at step {step}")
        raise InputError(f"{path}: {name} ({role}) has {text}")
    return states
