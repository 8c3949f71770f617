"""The host-allocator tuning that ``import dispgns`` applies (Linux/glibc only) and the physics' compiler options."""

import os
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dispgns import runtime

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


def test_physics_jit_compiles_with_the_options_at_top_level_only(monkeypatch):
    # An option value XLA rejects shows which calls compile with the options.
    monkeypatch.setattr(runtime, "physics_compiler_options", lambda: {"xla_cpu_prefer_vector_width": "wide"})
    rejected = runtime.physics_jit(lambda x: jnp.sin(x) * 2.0)
    x = jnp.linspace(0.0, 1.0, 5)
    with pytest.raises(Exception, match="xla_cpu_prefer_vector_width"):
        rejected(x)
    # Inside the caller's transformations it is a plain nested jit.
    expected = np.sin(np.asarray(x)) * 2.0
    np.testing.assert_allclose(np.asarray(jax.jit(rejected)(x)), expected, rtol=1e-6)
    np.testing.assert_allclose(np.asarray(jax.vmap(rejected)(x)), expected, rtol=1e-6)
    np.testing.assert_allclose(np.asarray(jax.grad(lambda y: jnp.sum(rejected(y)))(x)), 2.0 * np.cos(np.asarray(x)),
                               rtol=1e-6)


def test_physics_jit_with_the_real_options_equals_plain_jit():
    f = lambda x: jnp.sum(jnp.exp(-x[:, None] * x[None, :]), axis=1)
    x = jnp.linspace(0.0, 2.0, 300)
    np.testing.assert_allclose(np.asarray(runtime.physics_jit(f)(x)), np.asarray(jax.jit(f)(x)), rtol=1e-6)



def test_network_compiler_options_depend_on_the_matmul_dtype():
    from dispgns import ModelConfig
    assert runtime.network_compiler_options(ModelConfig()) == {"xla_cpu_experimental_ynn_fusion_type": ""}
    assert runtime.network_compiler_options(None) == runtime.network_compiler_options(ModelConfig())
    assert runtime.network_compiler_options(ModelConfig(matmul_dtype="bfloat16")) == {}


def test_network_jit_takes_the_options_of_the_calls_config_at_top_level_only(monkeypatch):
    from dispgns import ModelConfig
    seen = []

    def options(model_config):
        seen.append(model_config.matmul_dtype)
        return {"xla_cpu_prefer_vector_width": "wide"} if model_config.matmul_dtype == "float32" else {}

    monkeypatch.setattr(runtime, "network_compiler_options", options)
    f = runtime.network_jit(lambda x, *, model_config: jnp.cos(x) + model_config.latent_size,
                            static_argnames=("model_config",))
    x = jnp.linspace(0.0, 1.0, 4)
    with pytest.raises(Exception, match="xla_cpu_prefer_vector_width"):
        f(x, model_config=ModelConfig())
    expected = np.cos(np.asarray(x)) + 128.0
    np.testing.assert_allclose(np.asarray(f(x, model_config=ModelConfig(matmul_dtype="bfloat16"))), expected,
                               rtol=1e-6)
    np.testing.assert_allclose(np.asarray(jax.jit(lambda y: f(y, model_config=ModelConfig()))(x)), expected,
                               rtol=1e-6)
    assert seen == ["float32", "bfloat16"]  # the nested call asks for no options
    lowered = runtime.network_jit(lambda x, model_config: x * 2, static_argnums=(1,))
    assert lowered.lower(x, ModelConfig(matmul_dtype="bfloat16")).compile()(x).shape == (4,)


def test_options_unknown_to_jaxlib_are_dropped_with_a_warning():
    f = runtime.cpu_jit(lambda x: jnp.tanh(x) * 3.0, options=lambda x: {"xla_cpu_option_that_does_not_exist": 1,
                                                                           "xla_cpu_prefer_vector_width": 512})
    x = jnp.linspace(-1.0, 1.0, 7)
    with pytest.warns(RuntimeWarning, match="xla_cpu_option_that_does_not_exist"):
        y = f(x)
    np.testing.assert_allclose(np.asarray(y), np.tanh(np.asarray(x)) * 3.0, rtol=1e-6)
    assert runtime._known_options((("xla_cpu_option_that_does_not_exist", 1), ("xla_cpu_prefer_vector_width", 512))) \
        == (("xla_cpu_prefer_vector_width", 512),)
