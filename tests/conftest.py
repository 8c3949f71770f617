"""Shared fixtures: a small generated dataset and a tiny model configuration."""

import pytest

from dispgns.model import ModelConfig

# A model small enough that a few hundred training steps take seconds.
TINY_MODEL = dict(latent_size=16, hidden_size=16, message_passing_steps=2)


@pytest.fixture(scope="session")
def tiny_dataset(tmp_path_factory):
    """The ``tiny`` preset (5 trajectories of 38-46 disks, 60 frames), generated once per test process."""
    from dispgns.data import generate_dataset, tiny_spec

    out = tmp_path_factory.mktemp("tiny-dataset") / "dataset"
    generate_dataset(tiny_spec(), out, seed=0)
    return out


@pytest.fixture(scope="session")
def tiny_model_config():
    return ModelConfig(connectivity_radius=0.4, **TINY_MODEL)
