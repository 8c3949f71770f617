"""dispgns is a good citizen: nothing happens at import, tuning is opt-in and changes no result."""

import json
import os
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dispgns import tuning
from dispgns.graph import uses_cell_list
from dispgns.model import ModelConfig

SRC = Path(__file__).resolve().parents[1] / "src" / "dispgns"

# A fresh process that imports jax (whose own import sets two environment
# variables), then dispgns, rolls out the shipped model and reports what
# changed: environment, XLA flags, jax.config, any ctypes access to mallopt.
_GOOD_CITIZEN = r"""
import ctypes, json, os, sys
seen = []
class Spy(ctypes.CDLL):
    def __getattr__(self, name):
        seen.append(name)
        return super().__getattr__(name)
    def __getitem__(self, name):
        seen.append(name)
        return super().__getitem__(name)
ctypes.CDLL = Spy
import jax, jax_md, flax, optax, orbax.checkpoint, h5py  # their own import-time effects come first
env, config = dict(os.environ), {k: repr(v) for k, v in jax.config.values.items()}
import dispgns
params, model_config, _ = dispgns.load_pretrained()
x = jax.numpy.array([[[-0.5, 0.0], [0.5, 0.0]]] * 6) + 0.001 * jax.numpy.arange(6.0)[:, None, None]
out = dispgns.rollout(params, x, jax.numpy.array([0.03, 0.04]), 3, model_config=model_config)
changed_env = sorted(k for k in set(env) | set(os.environ) if env.get(k) != os.environ.get(k))
changed_config = sorted(k for k, v in jax.config.values.items() if config.get(k) != repr(v))
print(json.dumps({"env": changed_env, "config": changed_config, "ctypes": seen,
                  "tuned": dispgns.tuning.host_allocator_tuned(), "shape": list(out.shape)}))
"""


def _child(code: str, **env) -> str:
    environment = dict(os.environ, JAX_PLATFORMS="cpu", **env)
    return subprocess.run(
        [sys.executable, "-c", code], env=environment, capture_output=True, text=True, check=True
    ).stdout


def test_import_and_a_rollout_change_nothing_outside_dispgns():
    report = json.loads(_child(_GOOD_CITIZEN).splitlines()[-1])
    assert report == {"env": [], "config": [], "ctypes": [], "tuned": False, "shape": [3, 2, 2]}


def test_no_source_file_reads_private_jax_or_calls_mallopt_outside_tuning():
    for path in SRC.rglob("*.py"):
        text = path.read_text()
        assert "jax._src" not in text, path
        if path.name != "tuning.py":
            assert "mallopt" not in text, path


# A jitted function whose execution needs an ~80 MB temporary buffer: with
# glibc's defaults every call maps fresh pages for it (one page fault per
# 4 KiB page); with the tuning the heap block is reused.
_FAULTS = r"""
import resource, sys
import dispgns
if sys.argv[1] == "tuned":
    assert dispgns.tuning.tune_host_allocator()
import jax, jax.numpy as jnp
x = jnp.ones((5000, 64), jnp.float32)
w1 = jnp.full((64, 4096), 1e-3, jnp.float32)
w2 = jnp.full((4096, 8), 1e-3, jnp.float32)
f = jax.jit(lambda x: jnp.sum(jnp.tanh(x @ w1) @ w2))
for _ in range(3):
    f(x).block_until_ready()
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(5):
    f(x).block_until_ready()
print((resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before) / 5)
"""
TEMP_PAGES = 5000 * 4096 * 4 // 4096


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="mallopt is glibc's")
def test_the_host_allocator_tuning_is_opt_in_and_keeps_buffers():
    def faults(mode):
        environment = dict(os.environ, JAX_PLATFORMS="cpu")
        out = subprocess.run(
            [sys.executable, "-c", _FAULTS, mode], env=environment, capture_output=True, text=True, check=True
        )
        return float(out.stdout.split()[-1])

    import jaxlib

    # Default glibc (a plain import): the temporary buffer is faulted in afresh on every call.
    plain = faults("plain")
    assert plain > 0.5 * TEMP_PAGES
    if tuple(int(part) for part in jaxlib.__version__.split(".")[:3]) >= (0, 10, 2):
        assert faults("tuned") < 0.05 * TEMP_PAGES
    else:  # older jaxlib map part of the buffer afresh anyway (tuning.py's docstring): fewer faults, not none
        assert faults("tuned") < 0.8 * plain


def test_bad_keep_free_bytes_is_rejected():
    for bad in (0, 2**31):
        with pytest.raises(ValueError, match="keep_free_bytes"):
            tuning.tune_host_allocator(bad)


def _uses_ynnpack(compiled_text: str) -> bool:
    return "__ynn_fusion" in compiled_text


def _dot(x):
    return jnp.tanh(x @ x.T) @ x


def test_jitted_compiles_with_the_options_and_computes_the_same():
    x = jnp.ones((64, 32)) * jnp.linspace(0.0, 1.0, 32)
    if not _uses_ynnpack(jax.jit(_dot).lower(x).compile().as_text()):
        pytest.skip("this jaxlib does not hand dots to YNNPACK: the option has nothing to show")
    options = tuning.network_compiler_options(ModelConfig())
    tuned = tuning.jitted(_dot, options)
    assert tuned is tuning.jitted(_dot, dict(options))  # one jitted object (and cache) per (function, options)
    assert not _uses_ynnpack(tuned.lower(x).compile().as_text())
    np.testing.assert_allclose(np.asarray(tuned(x)), np.asarray(jax.jit(_dot)(x)), rtol=1e-5)


def test_network_compiler_options_depend_on_the_matmul_dtype():
    assert tuning.network_compiler_options(ModelConfig()) == {"xla_cpu_experimental_ynn_fusion_type": ""}
    assert tuning.network_compiler_options(None) == tuning.network_compiler_options(ModelConfig())
    assert tuning.network_compiler_options(ModelConfig(matmul_dtype="bfloat16")) == {}
    assert tuning.physics_compiler_options() == {"xla_cpu_prefer_vector_width": 512}


def test_options_unknown_to_jaxlib_are_dropped_with_a_warning():
    asked = {"xla_cpu_option_that_does_not_exist": 1, "xla_cpu_prefer_vector_width": 512}
    with pytest.warns(RuntimeWarning, match="xla_cpu_option_that_does_not_exist"):
        kept = tuning.supported_compiler_options(asked)
    assert kept == {"xla_cpu_prefer_vector_width": 512}
    f = tuning.jitted(lambda x: jnp.tanh(x) * 3.0, kept)
    x = jnp.linspace(-1.0, 1.0, 7)
    np.testing.assert_allclose(np.asarray(f(x)), np.tanh(np.asarray(x)) * 3.0, rtol=1e-6)


def test_thresholds_are_validated_and_tunable_within_a_block():
    assert uses_cell_list(200, 2, connectivity_radius=0.2)
    with tuning.use_thresholds(cell_list_min_particles=1000) as changed:
        assert changed.cell_list_min_particles == 1000 and tuning.thresholds() is changed
        assert not uses_cell_list(200, 2, connectivity_radius=0.2)
    assert tuning.thresholds() == tuning.Thresholds()
    for bad in (0, -1, 1.5, True):
        with pytest.raises(ValueError, match="cell_list_min_particles"):
            tuning.Thresholds(cell_list_min_particles=bad)


def test_a_thresholds_block_is_its_threads_own_and_overlapping_blocks_restore_in_any_order():
    import threading

    entered, exit_a, exit_b = threading.Barrier(3, timeout=60), threading.Event(), threading.Event()
    seen = {}

    def block(name, value, leave):
        with tuning.use_thresholds(cell_list_min_particles=value):
            entered.wait()
            leave.wait(timeout=60)
            seen[name] = tuning.thresholds().cell_list_min_particles

    # Daemons, and every wait bounded: a failing assertion below must not leave the test waiting for them.
    a = threading.Thread(target=block, args=("a", 10, exit_a), daemon=True)
    b = threading.Thread(target=block, args=("b", 20, exit_b), daemon=True)
    a.start()
    b.start()
    entered.wait()
    try:
        assert tuning.thresholds() == tuning.Thresholds()  # both blocks are open, in other threads
    finally:
        # a leaves first, b after: the order in which a module global's restores went wrong
        exit_a.set()
        a.join(timeout=60)
        exit_b.set()
        b.join(timeout=60)
    assert seen == {"a": 10, "b": 20} and tuning.thresholds() == tuning.Thresholds()


def test_generate_datasets_workers_run_with_the_callers_thresholds(monkeypatch, tmp_path):
    import threading

    import dispgns.data.generate as generate
    from dispgns.data import tiny_spec

    seen = set()
    simulate_batch = generate.simulate_batch

    def spy(*args, **kwargs):  # what the physics would read, in the thread that runs it
        worker = threading.current_thread().name.startswith("dispgns-simulate")
        seen.add((worker, tuning.thresholds().slot_loop_max_pairs))
        return simulate_batch(*args, **kwargs)

    # A regression guard for the context variable (a module global reached every thread). The value differs from
    # the default without changing the physics' choice of code path (the jit cache does not know the thresholds).
    value = tuning.Thresholds().slot_loop_max_pairs + 7
    monkeypatch.setattr(generate, "simulate_batch", spy)
    with tuning.use_thresholds(slot_loop_max_pairs=value, generation_threads=2):
        generate.generate_dataset(tiny_spec(), tmp_path / "data", seed=0, batch_size=2)  # 3 groups, 2 threads
    assert seen == {(True, value)}


# A child process calls the command line's main in-process (a command that fails at once, as a notebook's call
# with a typo would): it must leave the process's allocator as it was.
_CLI_IN_PROCESS = (
    _GOOD_CITIZEN.split("import dispgns\n")[0]
    + r"""
import dispgns.cli, dispgns.tuning
status = dispgns.cli.main(["evaluate", "--data", "/nonexistent-dispgns-data", "--no-progress"])
print(json.dumps({"status": status, "ctypes": seen, "tuned": dispgns.tuning.host_allocator_tuned()}))
"""
)


def test_the_command_lines_main_called_in_process_leaves_the_allocator_alone():
    report = json.loads(_child(_CLI_IN_PROCESS).splitlines()[-1])
    assert report == {"status": 2, "ctypes": [], "tuned": False}


def test_no_tuning_is_not_abbreviated():
    # The program reads --no-tuning from argv before parsing (to tune the allocator first): argparse must not
    # accept an abbreviation that the early check would not see.
    from dispgns.cli import main

    with pytest.raises(SystemExit) as exit_info:
        main(["--no-tun", "evaluate", "--data", "/nonexistent-dispgns-data"])
    assert exit_info.value.code == 2
