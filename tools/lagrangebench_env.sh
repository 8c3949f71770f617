#!/usr/bin/env bash
# Set up a virtual environment in which LagrangeBench 0.2.0 (JAX + Haiku,
# tumaer/lagrangebench) imports and runs on a CPU-only Python 3.11 machine,
# beside (never inside) dispgns's own environment: LagrangeBench pins
# jax 0.4.29, dispgns needs a current JAX. Use it to check that exported
# datasets load with LagrangeBench's own H5Dataset and case_builder
# (tools/check_lagrangebench.py; pytest -m slow tests/test_lagrangebench.py).
#
# Environment variables:
#   LB_VENV   where to create the virtual environment   (default /tmp/lb-venv)
#   PYTHON    the interpreter used to create it         (default python3; 3.11 here)
#
# From scratch and idempotent: the venv carries a stamp holding the exact pin
# set below. If $LB_VENV exists without that stamp (another pin set, a
# half-finished install, an older attempt) it is deleted and rebuilt; if the
# stamp matches, the pip calls below are no-ops and only the versions are printed.
#
# Why the pins (lagrangebench 0.2.0's pyproject / poetry.lock, adapted):
#   - lagrangebench 0.2.0 and jax-sph 0.0.3 declare Requires-Python <=3.11,
#     which pip reads as excluding 3.11.7: installed with
#     --ignore-requires-python --no-deps (their dependencies are listed here).
#   - lagrangebench pins torch==2.3.1+cpu (only used for its DataLoader and
#     seeding); we use the CPU torch 2.13.0 wheel that pip finds locally, and
#     --no-deps keeps pip from ever resolving a (CUDA) torch for it.
#   - jax/jaxlib 0.4.29 as pinned by lagrangebench; numpy<2 for that jaxlib;
#     dm-haiku 0.0.12 pulls flax, hence flax 0.8.4 + orbax-checkpoint 0.5.20 +
#     chex 0.1.86 (the newest that still work with jax 0.4.29); ott-jax 0.4.6
#     with equinox/lineax/jaxopt versions that accept jax 0.4.29; matscipy
#     1.1.1 and pandas 3.0.6 (newer ones require numpy>=2); tensorstore/ml-dtypes pinned so the
#     resolver does not walk up to releases that need a newer jax.
set -euo pipefail

LB_VENV="${LB_VENV:-/tmp/lb-venv}"
PYTHON="${PYTHON:-python3}"

TORCH_PIN="torch==2.13.0"
PINS=(
    "jax[cpu]==0.4.29" "jaxlib==0.4.29" "numpy<2"
    "dm-haiku==0.0.12" "flax==0.8.4" "chex==0.1.86" "orbax-checkpoint==0.5.20"
    "ott-jax==0.4.6" "equinox==0.11.10" "lineax==0.0.7" "jaxopt==0.8.5"
    "optax==0.1.7" "e3nn-jax==0.20.3" "jraph==0.0.6.dev0" "jmp==0.0.4"
    "ml-dtypes==0.4.1" "tensorstore==0.1.74"
    "matscipy==1.1.1" "h5py==3.16.0" "PyYAML==6.0.3" "cloudpickle==3.1.2"
    "omegaconf==2.4.0" "wandb==0.31.0" "pyvista==0.49.1" "wget==3.2"
    "pandas==3.0.6" "absl-py==2.5.1"
)
NODEPS_PINS=("jax-sph==0.0.3" "lagrangebench==0.2.0")

STAMP_FILE="$LB_VENV/.lagrangebench_setup_stamp"
STAMP="$("$PYTHON" -c 'import sys; print(sys.version.split()[0])') ${TORCH_PIN} ${PINS[*]} ${NODEPS_PINS[*]}"

# 1. Fresh venv unless an identical one is already there.
if [ -e "$LB_VENV" ]; then
    if [ -f "$STAMP_FILE" ] && [ "$(cat "$STAMP_FILE")" = "$STAMP" ]; then
        echo "venv $LB_VENV already holds this pin set; re-checking"
    else
        if [ ! -f "$LB_VENV/pyvenv.cfg" ]; then
            echo "refusing to delete $LB_VENV: exists but is not a virtual environment" >&2
            exit 2
        fi
        echo "removing $LB_VENV (no matching setup stamp) and rebuilding from scratch"
        rm -rf "$LB_VENV"
    fi
fi
if [ ! -x "$LB_VENV/bin/python" ]; then
    "$PYTHON" -m venv "$LB_VENV"
fi
PIP=("$LB_VENV/bin/python" -m pip --quiet)

# 2. torch first, pinned: pip takes the local CPU wheel of 2.13.0 here; an
#    unpinned torch would pull a multi-GB CUDA build.
"${PIP[@]}" install "$TORCH_PIN"
# 3. everything lagrangebench and jax-sph need, resolved together.
"${PIP[@]}" install "$TORCH_PIN" "${PINS[@]}"
# 4. the two packages whose metadata pip would reject (python <=3.11,
#    torch==2.3.1+cpu), from PyPI, without their dependency lists.
"${PIP[@]}" install --no-deps --ignore-requires-python "${NODEPS_PINS[@]}"

# 5. Check: imports, CPU torch, and the versions.
"$LB_VENV/bin/python" - <<'EOF'
import importlib.metadata as md
import sys
import jax, jaxlib, haiku, numpy, torch
import lagrangebench, jax_sph
from lagrangebench import models, case_setup, Trainer  # noqa: F401  (full import chain)
assert torch.__version__.endswith("+cpu"), f"non-CPU torch {torch.__version__}"
assert jax.__version__ == "0.4.29" and numpy.__version__.startswith("1."), "wrong jax/numpy"
names = ["lagrangebench", "jax-sph", "jax", "jaxlib", "dm-haiku", "flax", "chex", "optax",
         "ott-jax", "orbax-checkpoint", "jraph", "e3nn-jax", "jmp", "numpy", "torch",
         "omegaconf", "wandb", "pyvista", "h5py", "matscipy"]
print("python", sys.version.split()[0], "|", " ".join(f"{n}=={md.version(n)}" for n in names))
print("jax devices:", jax.devices())
EOF
# pip check reports the known, deliberate mismatches (torch, python); show them.
"$LB_VENV/bin/python" -m pip check 2>&1 | sed 's/^/pip check: /' || true

echo "$STAMP" > "$STAMP_FILE"
echo "LagrangeBench venv ready: $LB_VENV"
