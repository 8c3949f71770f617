"""The host-allocator tuning that ``import dispgns`` applies (Linux/glibc only)."""

import os
import subprocess
import sys

import pytest

# A jitted function whose execution needs an ~80 MB temporary buffer: with
# glibc's defaults every call maps fresh pages for it (one page fault per
# 4 KiB page); with the tuning the heap block is reused.
_CHILD = r"""
import resource
import dispgns
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
faults = (resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before) / 5
print(dispgns.runtime._tuned, faults)
"""

TEMP_PAGES = 5000 * 4096 * 4 // 4096


def _run(env_value):
    env = dict(os.environ, DISPGNS_TUNE_ALLOCATOR=env_value, JAX_PLATFORMS="cpu")
    out = subprocess.run([sys.executable, "-c", _CHILD], env=env, capture_output=True, text=True, check=True)
    tuned, faults = out.stdout.split()
    return tuned == "True", float(faults)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="mallopt is glibc's")
def test_import_tunes_allocator_and_opt_out_restores_defaults():
    tuned, faults = _run("1")
    untuned, faults_default = _run("0")
    assert tuned and not untuned
    # Default glibc: the temporary buffer is faulted in afresh on every call.
    assert faults_default > 0.5 * TEMP_PAGES
    assert faults < 0.05 * TEMP_PAGES


def test_bad_keep_free_bytes_is_rejected():
    from dispgns.runtime import tune_host_allocator
    for bad in (0, 2 ** 31):
        with pytest.raises(ValueError, match="keep_free_bytes"):
            tune_host_allocator(bad)
