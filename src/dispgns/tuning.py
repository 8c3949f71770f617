"""Opt-in speed settings for the CPU, and the machine-dependent thresholds, in one place.

Nothing here runs by itself: ``import dispgns`` changes nothing outside
dispgns. Every setting is something a caller asks for by name, and none
changes a result beyond float rounding (another summation order).

* :func:`tune_host_allocator` (process-wide, Linux/glibc only): XLA:CPU
  allocates the temporary buffers of every execution as one block (about
  0.5 GB for a training step of the paper's network on 2 examples) and frees
  it at the end; glibc serves such a block with a fresh ``mmap``, so every
  step touches half a gigabyte of new pages (measured: ~125,000 page faults
  per training step, 15-20 % of its time). The tuning keeps those blocks in
  glibc's heap. The command line and the benchmarks call it first; a script
  may too, before its first JAX computation. Its full effect needs jaxlib
  0.10.2 or newer (measured on an 80 MB temporary buffer: 20,000 page faults
  per call untuned, none tuned); jaxlib 0.8.2 to 0.10.1 still map part of the
  buffer afresh (4,000-12,000 faults per call tuned).
* :func:`physics_compiler_options` and :func:`network_compiler_options`: XLA
  options for the CPU, for the host drivers that compile their own loops
  (``compiler_options=`` of :func:`dispgns.simulate`, :func:`dispgns.rollout`,
  the training loop, ...) or for the caller's own outermost ``jax.jit``.
* ``ModelConfig(kernels="fused")`` (in :mod:`dispgns.kernels`): the network's
  CPU kernels; :func:`tuned_model_config` sets it.
* :class:`Thresholds`: sizes at which one algorithm overtakes another on a
  given machine (all-pairs vs cell-list graphs, ...), measured on the 2-core
  machine of ``benchmarks/`` and tunable with :func:`use_thresholds`.

What each setting is worth is measured in ``benchmarks/README.md``.
"""

from __future__ import annotations

import contextlib
import contextvars
import ctypes
import dataclasses
import functools
import os
import sys
import warnings
from collections.abc import Callable, Iterator, Mapping
from typing import Any

# For annotations only (resolved lazily by ``typing.get_type_hints``): the model layer sits below this one.
import dispgns

__all__ = [
    "Thresholds",
    "host_allocator_tuned",
    "jitted",
    "network_compiler_options",
    "physics_compiler_options",
    "supported_compiler_options",
    "thresholds",
    "tune_host_allocator",
    "tuned_model_config",
    "use_thresholds",
]

# mallopt parameters (glibc malloc.h).
_M_TRIM_THRESHOLD = -1
_M_MMAP_MAX = -4
_M_ARENA_MAX = -8

_allocator_tuned = False


def _threads() -> int:
    """OS threads of this process (Linux), 0 when unknown."""
    try:
        return len(os.listdir("/proc/self/task"))
    except OSError:
        return 0


def tune_host_allocator(keep_free_bytes: int = 1 << 30, *, warn_if_late: bool = True) -> bool:
    """Keep XLA:CPU's per-execution buffers in glibc's heap (no fresh pages per call); process-wide.

    Sets, with glibc's ``mallopt``: one malloc arena for all threads (XLA's
    worker threads would otherwise get arenas of at most 64 MB, which hand
    large blocks to ``mmap`` whatever the settings), no ``mmap`` for large
    blocks, and a trim threshold of ``keep_free_bytes``. The price: up to
    ``keep_free_bytes`` of freed memory stays with the process instead of
    going back to the system.

    Call it before JAX starts its CPU backend (the first computation, or
    importing jax-md, which computes at import; ``import dispgns`` alone does
    not): threads that already allocated keep their own arenas, and the gain
    is then partial. Safe to call more than once; a no-op returning ``False``
    off Linux/glibc.

    Args:
      keep_free_bytes: freed memory at the top of the heap that is kept for
        reuse (1 GiB; at most 2**31 - 1).
      warn_if_late: warn when the process already runs more threads than
        ``import jax`` starts (a sign that XLA's thread pools exist).

    Returns:
      ``True`` if the settings are in effect (now or from an earlier call).
    """
    global _allocator_tuned
    if not 0 < keep_free_bytes < 2**31:
        raise ValueError(f"keep_free_bytes must be in (0, 2**31), got {keep_free_bytes!r}")
    if _allocator_tuned:
        return True
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(None)
        mallopt = libc.mallopt
        _ = libc.gnu_get_libc_version  # only glibc has it (musl's mallopt ignores these settings)
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
    threads = _threads()
    if warn_if_late and threads > 2:
        warnings.warn(
            f"dispgns.tuning.tune_host_allocator() called with {threads} threads running (JAX's CPU backend has "
            "probably started): threads that already allocated keep their own arenas, so the gain may be partial. "
            "Call it first, before any JAX computation or jax-md import.",
            RuntimeWarning,
            stacklevel=2,
        )
    settings = ((_M_ARENA_MAX, 1), (_M_MMAP_MAX, 0), (_M_TRIM_THRESHOLD, int(keep_free_bytes)))
    _allocator_tuned = all(mallopt(param, value) == 1 for param, value in settings)
    return _allocator_tuned


def host_allocator_tuned() -> bool:
    """Whether :func:`tune_host_allocator` has applied its settings in this process."""
    return _allocator_tuned


def _on_cpu() -> bool:
    import jax

    return jax.default_backend() == "cpu"


def physics_compiler_options() -> dict[str, Any]:
    """XLA options for the ground-truth physics on the CPU (``{}`` on other backends).

    XLA on CPU vectorises loops 256 bits wide unless told otherwise (some
    older CPUs lower their clock for 512-bit instructions). The physics' pair
    loops were ~2x faster at 512 bits on the AVX-512 Intel machine where this
    was measured, ~1.1x on the AMD EPYC of ``benchmarks/``; CPUs without
    AVX-512 keep their widest registers.

    Pass them to a host driver (``dispgns.simulate(..., compiler_options=...)``)
    or to your own outermost ``jax.jit`` around the pure core (JAX accepts
    options on the outermost jit only: ``jax.jit(jax.grad(loss), ...)``, not
    ``jax.grad`` of a jit with options).
    """
    if not _on_cpu():
        return {}
    return supported_compiler_options({"xla_cpu_prefer_vector_width": 512})


def network_compiler_options(model_config: dispgns.model.ModelConfig | None = None) -> dict[str, Any]:
    """XLA options for the learned simulator's network on the CPU (``{}`` on other backends).

    With float32 matmuls (``ModelConfig.matmul_dtype = "float32"``) the dots
    are left to XLA's own kernels instead of the YNNPACK library XLA hands
    them to by default (on the 2-core machine of ``benchmarks/``: paper
    network training step ~11 % and rollout step ~7 % faster). With bfloat16
    matmuls YNNPACK's kernels are the faster ones: no options. The physics
    keeps YNNPACK (it is 2x faster with it).

    Args:
      model_config: a :class:`dispgns.ModelConfig` (``None``: float32).
    """
    if not _on_cpu() or getattr(model_config, "matmul_dtype", "float32") != "float32":
        return {}
    return supported_compiler_options({"xla_cpu_experimental_ynn_fusion_type": ""})


def supported_compiler_options(options: Mapping[str, Any]) -> dict[str, Any]:
    """``options`` without those the installed jaxlib refuses (a warning names each one).

    XLA's option names change between releases: an option must never stop a
    computation. Each is tried alone on a trivial function (once per process).
    """
    return dict(_supported(tuple(sorted(options.items()))))


@functools.cache
def _supported(items: tuple[tuple[str, Any], ...]) -> tuple[tuple[str, Any], ...]:
    import jax

    kept = []
    for name, value in items:
        try:
            jax.jit(lambda x: x + 1, compiler_options={name: value}).lower(1.0).compile()
        except Exception as error:  # XLA raises its own runtime error types
            warnings.warn(
                f"dispgns: this jaxlib ({jax.__version__}) refuses the XLA option {name}={value!r} ({error}); "
                "compiling without it (same results, perhaps slower)",
                RuntimeWarning,
                stacklevel=3,
            )
            continue
        kept.append((name, value))
    return tuple(kept)


def jitted(
    fun: Callable[..., Any],
    compiler_options: Mapping[str, Any] | None = None,
    *,
    static_argnames: tuple[str, ...] = (),
) -> Callable[..., Any]:
    """``jax.jit(fun, static_argnames=..., compiler_options=...)``, one jitted object per ``(fun, options)``.

    The host drivers compile their module-level functions through this, so
    that a call with the same options reuses the same compilation cache.
    """
    return _jitted(fun, tuple(sorted((compiler_options or {}).items())), tuple(static_argnames))


@functools.cache
def _jitted(fun, options: tuple[tuple[str, Any], ...], static_argnames: tuple[str, ...]):
    import jax

    return jax.jit(fun, static_argnames=static_argnames, compiler_options=dict(options) or None)


def tuned_model_config(model_config: dispgns.model.ModelConfig) -> dispgns.model.ModelConfig:
    """``model_config`` computed with the CPU kernels of :mod:`dispgns.kernels` (same parameters, same function)."""
    return dataclasses.replace(model_config, kernels="fused")


@dataclasses.dataclass(frozen=True)
class Thresholds:
    """Sizes at which one algorithm overtakes another (speed only: every choice gives the same result to float
    rounding; the same neighbours, found in another order).

    Measured on a 2-core Intel machine when they were set (``benchmarks/README.md``);
    another machine may prefer other values (:func:`use_thresholds`).

    Attributes:
      cell_list_min_particles: from this many particle slots on, learned-
        simulator graphs use a jax-md cell list instead of all ``N^2``
        candidate pairs (all pairs 0.19 vs cells 0.27 ms at N = 60, 0.40 vs
        0.44 at 120, 1.6 vs 0.7 at 220, 28 vs 7 at 1,000).
      slot_loop_max_pairs: up to this many neighbour slots (particles x list
        width) the physics' neighbour forces loop over slots; above, they
        use ``(Q, M)`` arrays (the loop is ~1.5x faster at 2,000 x 22 slots
        and at 20,000 x 22, slower at 50,000 x 22).
      generation_threads: trajectory groups simulated at the same time by
        :func:`dispgns.generate_dataset`, one thread each (two concurrent
        batches keep two cores busy: 1.3-1.5x faster than one). How the
        trajectories are grouped does not depend on it, so neither does the
        data.
    """

    cell_list_min_particles: int = 160
    slot_loop_max_pairs: int = 2**16
    generation_threads: int = 2

    def __post_init__(self):
        for field in dataclasses.fields(self):
            value = getattr(self, field.name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"Thresholds.{field.name} must be an integer >= 1, got {value!r}")


# A context variable, not a module global: a ``use_thresholds`` block in one thread (or asyncio task) is not seen by
# the others, and blocks that overlap in time restore in any order.
_DEFAULT_THRESHOLDS = Thresholds()  # frozen: one shared default is safe
_thresholds: contextvars.ContextVar[Thresholds] = contextvars.ContextVar(
    "dispgns_thresholds", default=_DEFAULT_THRESHOLDS
)


def thresholds() -> Thresholds:
    """The thresholds in effect in this context (read when a function sizes or picks an algorithm, on the host)."""
    return _thresholds.get()


@contextlib.contextmanager
def use_thresholds(**changes: int) -> Iterator[Thresholds]:
    """Within the ``with`` block, :func:`thresholds` has ``changes`` applied, in this thread (context) only.

    Example: ``with dispgns.tuning.use_thresholds(cell_list_min_particles=400): ...``.
    Compiled programs already cached keep the choice they were built with. A
    thread started inside the block does not inherit it unless it runs in a
    copy of the context (``contextvars.copy_context().run``), as
    :func:`dispgns.generate_dataset`'s workers do. A block must end in the
    context it began in (not across threads or event-loop tasks).
    """
    token = _thresholds.set(dataclasses.replace(_thresholds.get(), **changes))
    try:
        yield _thresholds.get()
    finally:
        _thresholds.reset(token)
