"""Property-based fuzzing of the validation boundary (hypothesis).

For ``rollout``, ``simulate`` and ``sample_initial_state``, random shapes, dtypes, NaN, inf, zero or negative radii
and centres anywhere either raise a ``ValueError`` naming the offending argument, or return finite results inside
the box. Nothing else: no other exception type, no NaN, no particle outside. The examples are derandomised (the
same ones every run) and few, with shapes drawn from small sets so that the valid ones reuse compiled programs.
"""

import jax
import numpy as np
import pytest

hypothesis = pytest.importorskip("hypothesis")
from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402
from hypothesis.extra import numpy as hnp  # noqa: E402

from dispgns.model import ModelConfig, init_params  # noqa: E402
from dispgns.physics import PhysicsConfig, PlacementError, sample_initial_state, simulate  # noqa: E402
from dispgns.simulator import rollout  # noqa: E402

TINY = ModelConfig(latent_size=8, hidden_size=8, message_passing_steps=1)
C = TINY.input_sequence_length
FUZZ = settings(
    max_examples=12,
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
# Mostly sensible numbers, sometimes anything: NaN, inf, huge, negative.
NUMBERS = st.one_of(
    st.floats(-1.0, 1.0, width=32),
    st.sampled_from([np.nan, np.inf, -np.inf, 0.0, 1e30, -1e-30]),
)


def _names_an_argument(error: ValueError, names) -> bool:
    return any(name in str(error) for name in names)


@pytest.fixture(scope="module")
def params():
    return init_params(jax.random.key(0), TINY)


# One way to get the inputs wrong per example (or none): valid inputs are drawn often enough to be checked too.
KINDS = ["valid", "valid", "valid", "value", "value", "radius", "frames", "dim", "radius length", "dtype", "empty"]


@st.composite
def rollout_inputs(draw):
    kind = draw(st.sampled_from(KINDS))
    n = 0 if kind == "empty" else 4
    frames = C - 1 if kind == "frames" else C
    dim = 3 if kind == "dim" else 2
    dtype = draw(st.sampled_from([np.float16, np.int32] if kind == "dtype" else [np.float32, np.float64]))
    # A valid window (particles on a line, moving slightly), anywhere in the box.
    centre = draw(hnp.arrays(np.float64, (dim,), elements=st.floats(-0.5, 0.5)))
    x = np.zeros((frames, n, dim))
    x[..., 0] = np.linspace(-0.3, 0.3, n)
    x = x + centre + 1e-3 * np.arange(frames)[:, None, None]
    radius = draw(hnp.arrays(np.float64, (n + (kind == "radius length"),), elements=st.floats(0.01, 0.05)))
    if kind == "value":
        x.flat[draw(st.integers(0, x.size - 1))] = draw(NUMBERS.filter(lambda v: not -1 <= v <= 1) | NUMBERS)
    if kind == "radius":
        radius[draw(st.integers(0, n - 1))] = draw(st.sampled_from([0.0, -0.03, np.nan, np.inf, 5.0]))
    with np.errstate(invalid="ignore", over="ignore"):
        return x.astype(dtype), radius.astype(dtype)


@FUZZ
@given(inputs=rollout_inputs())
def test_rollout_refuses_by_name_or_returns_finite_positions_inside_the_box(params, inputs):
    x, radius = inputs
    try:
        out = np.asarray(rollout(params, x, radius, 1, model_config=TINY))
    except ValueError as error:
        assert _names_an_argument(error, ["positions", "radius"]), str(error)
        return
    assert out.shape == (1, x.shape[1], 2)
    assert np.isfinite(out).all()
    bounds = np.asarray(TINY.bounds)
    assert np.all((out >= bounds[:, 0]) & (out <= bounds[:, 1]))


@st.composite
def physics_inputs(draw):
    kind = draw(st.sampled_from(KINDS))
    n = 0 if kind == "empty" else 3
    dim = draw(st.sampled_from([2, 3]))
    dtype = draw(st.sampled_from([np.int32] if kind == "dtype" else [np.float32, np.float64]))
    # Three disks or spheres 1 cm apart somewhere in the 0.1 m box, moving at up to 0.3 m/s.
    centre = draw(hnp.arrays(np.float64, (dim,), elements=st.floats(-0.08, 0.08)))
    x = np.zeros((n, dim))
    x[:, 0] = np.linspace(-0.01, 0.01, n)
    x = x + centre
    v = draw(hnp.arrays(np.float64, (n, dim), elements=st.floats(-0.3, 0.3)))
    radius = draw(hnp.arrays(np.float64, (n - (kind == "radius length"),), elements=st.floats(1e-3, 4e-3)))
    if kind in ("value", "frames"):
        array = x if kind == "value" else v
        array.flat[draw(st.integers(0, array.size - 1))] = draw(NUMBERS) * (0.2 if kind == "value" else 1e3)
    if kind in ("radius", "dim"):
        radius[draw(st.integers(0, n - 1))] = draw(st.sampled_from([0.0, -3e-3, np.nan, 0.5, 0.02]))
    with np.errstate(invalid="ignore", over="ignore"):
        return x.astype(dtype), v.astype(dtype), radius


@FUZZ
@given(inputs=physics_inputs())
def test_simulate_refuses_by_name_or_returns_finite_frames_inside_the_box(inputs):
    x, v, radius = inputs
    config = PhysicsConfig()
    try:
        out = np.asarray(simulate(x, v, radius, config, n_frames=2))
    except ValueError as error:
        assert _names_an_argument(error, ["x0", "v0", "radius"]), str(error)
        return
    assert out.shape == (2,) + x.shape
    assert np.isfinite(out).all()
    assert np.all(np.abs(out) <= config.box_half_size)


BAD_RADII = st.lists(st.sampled_from([0.0, -1e-3, np.nan, np.inf, 0.5, 3.0]), min_size=1, max_size=2)
GOOD_RADII = st.lists(st.sampled_from([1.5e-2, 2.5e-2]), min_size=1, max_size=2)


@FUZZ
@given(
    radii=st.one_of(BAD_RADII, st.tuples(GOOD_RADII, BAD_RADII).map(lambda t: t[0] + t[1]), st.just([])),
    count=st.sampled_from([None, 6, 0, -2, 2.5, 10**7]),
    dim=st.sampled_from([2, 3]),
)
def test_sample_initial_state_refuses_bad_radii_up_front(radii, count, dim):
    with pytest.raises(ValueError) as info:
        sample_initial_state(jax.random.key(0), radii, PhysicsConfig(), dim=dim, n_particles=count, max_particles=60)
    assert "radii_choices" in str(info.value) or "radius" in str(info.value), str(info.value)


@pytest.mark.slow  # each new particle count and grid compiles the placement anew (~3 s each)
@FUZZ
@given(
    radii=st.lists(
        # Valid radii from a short list: each new grid of the placement compiles anew.
        st.sampled_from([1.5e-2, 2.5e-2, 1.5e-2, 2.5e-2, 0.0, -1e-3, np.nan, np.inf, 1e-6, 0.5]),
        max_size=3,
    ),
    count=st.sampled_from([None, None, 6, 6, 0, -2, 2.5, 10**7]),
    dim=st.sampled_from([2, 2, 3]),
)
def test_sample_initial_state_refuses_by_name_or_places_inside_the_box(radii, count, dim):
    config = PhysicsConfig()
    try:
        state = sample_initial_state(jax.random.key(0), radii, config, dim=dim, n_particles=count, max_particles=60)
    except ValueError as error:
        assert _names_an_argument(error, ["radii_choices", "radius", "n_particles", "max_particles"]), str(error)
        return
    except PlacementError as error:  # the packing drawn is too dense for random placement: says what to pass
        assert "n_particles" in str(error) or "fewer particles" in str(error), str(error)
        return
    x, a = np.asarray(state.position), np.asarray(state.radius)
    assert x.shape == (a.size, dim) and a.size >= 1
    assert np.isfinite(x).all() and np.all(np.abs(x) + a[:, None] <= config.box_half_size + 1e-9)
    gaps = np.linalg.norm(x[:, None] - x[None], axis=-1) + np.diag(np.full(a.size, np.inf))
    assert np.all(gaps >= 0.999 * (a[:, None] + a[None]))
