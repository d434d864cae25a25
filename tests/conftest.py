"""Shared test fixtures: the authors' reference data (their 30 human-in-the-loop recordings and
their trained model), found beside the repository in ``../shared/reference`` or in
``$TRAFFICWEAVING_SHARED/reference``.

A test that needs it takes one of these fixtures and is *skipped with the reason shown* when the
data is absent (``pytest -rs`` lists them); no test runs half of its checks without it. Markers
(registered in pyproject.toml): ``slow`` and ``browser``, both left out by ``make test-fast``.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

# Idle OpenMP threads sleep instead of spinning (set before torch loads; the processes the tests start inherit
# it): on cores busy with other work, torch's spinning threads make the model tests about ten times slower.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

REFERENCE = Path(os.environ.get("TRAFFICWEAVING_SHARED", Path(__file__).resolve().parents[2] / "shared")) / "reference"


@pytest.fixture(scope="session")
def hitl_dir() -> Path:
    """The folder of the authors' 30 human-in-the-loop ``.jld`` recordings (skips when absent)."""
    folder = REFERENCE / "hitl"
    if not sorted(folder.glob("*.jld")):
        pytest.skip(f"the authors' human-in-the-loop recordings are not present ({folder})")
    return folder


@pytest.fixture(scope="session")
def hitl_files(hitl_dir) -> list[Path]:
    """The 30 ``.jld`` files, sorted."""
    return sorted(hitl_dir.glob("*.jld"))


@pytest.fixture(scope="session")
def hitl_trials(hitl_files):
    """The 30 real trials imported once per test session (a :class:`TrialSet`; do not modify)."""
    from trafficweaving.data.hitl import read_hitl

    return read_hitl(hitl_files)


@pytest.fixture(scope="session")
def authors_model_dir() -> Path:
    """The folder of the authors' ``weights.npz`` and ``reference_outputs.npz`` (skips when absent)."""
    folder = REFERENCE / "authors_model"
    if not ((folder / "weights.npz").is_file() and (folder / "reference_outputs.npz").is_file()):
        pytest.skip(f"the authors' trained model and reference outputs are not present ({folder})")
    return folder


@pytest.fixture(scope="session")
def authors_evaluation(authors_model_dir, hitl_trials):
    """The authors' model as loaded (float32) evaluated on every instance of the 30 real trials, once
    per test session (an :class:`~trafficweaving.model.evaluate.Evaluation`; do not modify)."""
    from trafficweaving.model.authors import load_authors_model
    from trafficweaving.model.evaluate import evaluate
    from trafficweaving.model.exemplars import build_exemplars

    return evaluate(load_authors_model(authors_model_dir / "weights.npz"), build_exemplars(hitl_trials))


def pytest_collection_modifyitems(items):
    """Every test that takes the ``browser`` fixture (a real Chromium) is marked ``browser``, so
    ``pytest -m "not browser"`` (``make test-fast``) leaves it out."""
    for item in items:
        if "browser" in getattr(item, "fixturenames", ()):
            item.add_marker(pytest.mark.browser)
