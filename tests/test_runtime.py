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

    for bad in (0, 2**31):
        with pytest.raises(ValueError, match="keep_free_bytes"):
            tune_host_allocator(bad)


def _uses_ynnpack(compiled_text: str) -> bool:
    return "__ynn_fusion" in compiled_text


def _dot(x):
    return jnp.tanh(x @ x.T) @ x


NO_YNNPACK = {"xla_cpu_experimental_ynn_fusion_type": ""}


@pytest.fixture(scope="module")
def jaxlib_uses_ynnpack():
    x = jnp.ones((64, 32))
    if not _uses_ynnpack(jax.jit(_dot).lower(x).compile().as_text()):
        pytest.skip("this jaxlib does not hand dots to YNNPACK: the option has nothing to show")
    return x


def test_cpu_jit_compiles_with_the_options_at_top_level_only(jaxlib_uses_ynnpack):
    x = jaxlib_uses_ynnpack
    f = runtime.cpu_jit(_dot, options=lambda x: NO_YNNPACK)
    assert not _uses_ynnpack(f.lower(x).compile().as_text())
    # Nested in the caller's jit it is a plain jit: the caller's (default) options hold.
    assert _uses_ynnpack(jax.jit(lambda y: f(y)).lower(x).compile().as_text())
    expected = np.asarray(jax.jit(_dot)(x))
    for got in (f(x), jax.jit(f)(x), jax.vmap(f)(x[None])[0]):
        np.testing.assert_allclose(np.asarray(got), expected, rtol=1e-5)
    grad = jax.grad(lambda y: jnp.sum(f(y)))(x)
    np.testing.assert_allclose(np.asarray(grad), np.asarray(jax.grad(lambda y: jnp.sum(_dot(y)))(x)), rtol=1e-5)


def test_physics_jit_drops_an_option_value_xla_refuses(monkeypatch):
    monkeypatch.setattr(runtime, "physics_compiler_options", lambda: {"xla_cpu_prefer_vector_width": "wide"})
    f = runtime.physics_jit(lambda x: jnp.sin(x) * 2.0)
    x = jnp.linspace(0.0, 1.0, 5)
    with pytest.warns(RuntimeWarning, match="xla_cpu_prefer_vector_width"):
        y = f(x)
    np.testing.assert_allclose(np.asarray(y), np.sin(np.asarray(x)) * 2.0, rtol=1e-6)


def test_this_jaxlib_accepts_the_real_options():
    from dispgns import ModelConfig

    for options in (runtime.physics_compiler_options(), runtime.network_compiler_options(ModelConfig())):
        items = tuple(sorted(options.items()))
        assert items and runtime._known_options(items) == items


def test_physics_jit_with_the_real_options_equals_plain_jit():
    f = lambda x: jnp.sum(jnp.exp(-x[:, None] * x[None, :]), axis=1)
    x = jnp.linspace(0.0, 2.0, 300)
    np.testing.assert_allclose(np.asarray(runtime.physics_jit(f)(x)), np.asarray(jax.jit(f)(x)), rtol=1e-6)


def test_network_compiler_options_depend_on_the_matmul_dtype():
    from dispgns import ModelConfig

    assert runtime.network_compiler_options(ModelConfig()) == {"xla_cpu_experimental_ynn_fusion_type": ""}
    assert runtime.network_compiler_options(None) == runtime.network_compiler_options(ModelConfig())
    assert runtime.network_compiler_options(ModelConfig(matmul_dtype="bfloat16")) == {}


def test_network_jit_takes_the_options_of_the_calls_config_at_top_level_only(monkeypatch, jaxlib_uses_ynnpack):
    from dispgns import ModelConfig

    x = jaxlib_uses_ynnpack
    seen = []

    def options(model_config):
        seen.append(model_config.matmul_dtype)
        return NO_YNNPACK if model_config.matmul_dtype == "float32" else {}

    monkeypatch.setattr(runtime, "network_compiler_options", options)
    f = runtime.network_jit(
        lambda x, *, model_config: _dot(x) + model_config.latent_size, static_argnames=("model_config",)
    )
    assert not _uses_ynnpack(f.lower(x, model_config=ModelConfig()).compile().as_text())
    assert _uses_ynnpack(f.lower(x, model_config=ModelConfig(matmul_dtype="bfloat16")).compile().as_text())
    assert _uses_ynnpack(jax.jit(lambda y: f(y, model_config=ModelConfig())).lower(x).compile().as_text())
    assert seen == ["float32", "bfloat16"]  # the nested call asks for no options
    expected = np.asarray(_dot(x)) + 128.0
    np.testing.assert_allclose(np.asarray(f(x, model_config=ModelConfig())), expected, rtol=1e-5)
    positional = runtime.network_jit(lambda x, model_config: x * 2, static_argnums=(1,))
    assert positional.lower(x, ModelConfig()).compile()(x).shape == x.shape
    with pytest.raises(ValueError, match="no parameter 'config'"):
        runtime.network_jit(lambda x, model_config: x, config_arg="config")


def test_every_network_entry_point_compiles_with_the_options(jaxlib_uses_ynnpack):
    """train_step, the validation loss, one step and the (batched) rollout chunks: no YNNPACK dot at float32."""
    from types import SimpleNamespace

    from dispgns import ModelConfig
    from dispgns.data.examples import BatchStream
    from dispgns.graph import GraphCapacity
    from dispgns.simulator import _rollout_chunk, _rollout_chunk_batch, _step_jit
    from dispgns.training import TrainConfig, create_train_state, train_step
    from dispgns.training.loop import _clean_loss

    config = ModelConfig(latent_size=16, hidden_size=16, message_passing_steps=1)
    rng = np.random.default_rng(0)
    traj = SimpleNamespace(
        position=(rng.uniform(-0.5, 0.5, (1, 6, 2)) + 1e-3 * np.arange(9)[:, None, None]).astype(np.float32),
        radius=np.full((6,), 0.04, np.float32),
    )
    train_config = TrainConfig(standardize=False)
    state = create_train_state(jax.random.key(0), config, train_config)
    batch = BatchStream([traj], input_sequence_length=6, batch_size=1, connectivity_radius=0.2).batch(0)
    window, radius = jnp.asarray(traj.position[:6]), jnp.asarray(traj.radius)
    mask, capacity = jnp.ones((6,), bool), GraphCapacity(30)
    lowered = {
        "train_step": train_step.lower(state, batch, jax.random.key(1)),
        "_clean_loss": _clean_loss.lower(state.params, batch, config, train_config),
        "_step_jit": _step_jit.lower(state.params, window, radius, mask, capacity=capacity, model_config=config),
        "_rollout_chunk": _rollout_chunk.lower(
            state.params, window, radius, mask, jnp.int32(2), length=2, capacity=capacity, model_config=config
        ),
        "_rollout_chunk_batch": _rollout_chunk_batch.lower(
            state.params,
            window[None],
            radius[None],
            mask[None],
            jnp.int32(2),
            length=2,
            capacity=capacity,
            model_config=config,
        ),
    }
    for name, low in lowered.items():
        assert not _uses_ynnpack(low.compile().as_text()), name
    bf16 = ModelConfig(latent_size=16, hidden_size=16, message_passing_steps=1, matmul_dtype="bfloat16")
    assert _uses_ynnpack(
        _step_jit.lower(state.params, window, radius, mask, capacity=capacity, model_config=bf16).compile().as_text()
    )


def test_options_unknown_to_jaxlib_are_dropped_with_a_warning():
    runtime._known_options.cache_clear()
    f = runtime.cpu_jit(
        lambda x: jnp.tanh(x) * 3.0,
        options=lambda x: {"xla_cpu_option_that_does_not_exist": 1, "xla_cpu_prefer_vector_width": 512},
    )
    x = jnp.linspace(-1.0, 1.0, 7)
    with pytest.warns(RuntimeWarning, match="xla_cpu_option_that_does_not_exist"):
        y = f(x)
    np.testing.assert_allclose(np.asarray(y), np.tanh(np.asarray(x)) * 3.0, rtol=1e-6)
    assert runtime._known_options(
        (("xla_cpu_option_that_does_not_exist", 1), ("xla_cpu_prefer_vector_width", 512))
    ) == (("xla_cpu_prefer_vector_width", 512),)
