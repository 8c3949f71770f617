#!/usr/bin/env bash
# Install dispgns with OLDER versions of its core dependencies in a fresh venv and run a part of the test
# suite with them: evidence for the lower bounds in pyproject.toml (the newest releases are what CI runs).
#
#   bash tools/check_lower_bounds.sh                       # the default older combination below
#   PINS="jax==0.9.0 jaxlib==0.9.0 flax==0.12.1" bash tools/check_lower_bounds.sh
#   VENV=/tmp/lb-bounds TESTS="tests/test_model.py" bash tools/check_lower_bounds.sh
#
# Prints the installed versions, then pytest's summary; exits with pytest's code.
#
# Combinations checked (with optax 0.2.5, orbax-checkpoint 0.11.25, h5py 3.11.0, jax-md 0.2.29, numpy 2.4):
# - jax 0.8.2, flax 0.12.0: the default TESTS pass.
# - jax 0.9.0, flax 0.12.0: fails at import: jax-md imports flax.nnx, which needs
#   jax._src.core.mutable_array (gone in jax 0.9); flax 0.12.0 still allows jax >= 0.9, hence flax >= 0.12.1.
# - jax 0.9.0, flax 0.12.1, jaxtyping 0.2.36: the default TESTS (test_annotations included) pass (367 tests,
#   2026-12-02).
# - jax 0.8.2, flax 0.12.1, jaxtyping 0.2.36: test_package, test_annotations, test_model pass (261 tests,
#   2026-12-02).
set -euo pipefail
ROOT="$(cd "$(dirname "$0")/.." && pwd)"
VENV="${VENV:-/tmp/dispgns-lower-bounds}"
PYTHON="${PYTHON:-python3}"
PINS="${PINS:-jax==0.8.2 jaxlib==0.8.2 flax==0.12.1 optax==0.2.5 orbax-checkpoint==0.11.25 h5py==3.11.0 jaxtyping==0.2.36}"
TESTS="${TESTS:-tests/test_package.py tests/test_layers.py tests/test_annotations.py tests/test_model.py tests/test_simulator.py tests/test_training_step.py tests/test_data_format.py tests/test_formats.py tests/test_lagrangebench.py}"
rm -rf "$VENV"
"$PYTHON" -m venv "$VENV"
# shellcheck disable=SC2086
"$VENV/bin/python" -m pip install --quiet "$ROOT[test]" $PINS
"$VENV/bin/python" -m pip list 2>/dev/null | grep -i -E "^(jax|jaxlib|flax|optax|orbax-checkpoint|jax-md|numpy|h5py) "
cd "$ROOT"
# shellcheck disable=SC2086
exec "$VENV/bin/python" -m pytest -q -p no:cacheprovider --import-mode=importlib $TESTS
