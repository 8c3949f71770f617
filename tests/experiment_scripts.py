"""Shared by the tests of the scripts in experiments/accuracy: a loader and a model's normalisation statistics."""

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

EXPERIMENTS = Path(__file__).resolve().parents[1] / "experiments" / "accuracy"

NORM = {
    "velocity_mean": np.zeros(2),
    "velocity_std": np.full(2, 0.05),
    "acceleration_mean": np.zeros(2),
    "acceleration_std": np.full(2, 0.002),
}
"""Normalisation statistics for a randomly initialised 2-D model (:func:`dispgns.model.init_params`)."""


def load_experiment(name: str):
    """``experiments/accuracy/NAME.py`` as a module; its folder is on ``sys.path`` while it loads (sibling imports)."""
    sys.path.insert(0, str(EXPERIMENTS))
    try:
        spec = importlib.util.spec_from_file_location(name, EXPERIMENTS / f"{name}.py")
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
    finally:
        sys.path.remove(str(EXPERIMENTS))
    return module


def experiment_fixture(name: str, fixture: str | None = None):
    """A module-scoped pytest fixture (named ``fixture``, default ``name``) giving ``experiments/accuracy/NAME.py``."""
    return pytest.fixture(scope="module", name=fixture or name)(lambda: load_experiment(name))
