"""Shared fixtures: a small generated dataset and a tiny model configuration."""

import gc

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
def tiny_pair(tiny_dataset):
    """``(metadata, [two trajectories])``: the first two of the tiny dataset's ``train`` split."""
    from dispgns.data import load_dataset

    metadata, splits = load_dataset(tiny_dataset, ["train"])
    return metadata, splits["train"][:2]


@pytest.fixture(scope="session")
def tiny_model_config():
    return ModelConfig(connectivity_radius=0.4, **TINY_MODEL)


@pytest.fixture(autouse=True, scope="module")
def _compiled_code_released_after_each_module():
    """Drop JAX's compiled functions after each test module.

    Every executable XLA:CPU compiles keeps several memory mappings, and JAX's
    caches keep every executable alive: the whole suite in one process (plain
    ``pytest``, no ``-n``) reached Linux's limit of 65,530 mappings per process
    (``vm.max_map_count``) about 720 tests in, and XLA then crashed while
    compiling (a segmentation fault or an abort). Cleared per module, the count
    stays near its baseline (~2,700 before a clear, ~1,100 after).
    """
    yield
    import jax

    jax.clear_caches()
    gc.collect()
