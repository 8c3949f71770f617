"""Settings that make XLA on CPU faster: glibc's allocator (process-wide) and compiler options.

XLA:CPU allocates the temporary buffers of every execution of a compiled
function as one block (about 0.5 GB for a training step of the paper's
network on 2 examples) and frees it when the execution ends. glibc serves a
block that large with a fresh ``mmap`` and returns it with ``munmap``, so
every step touches half a gigabyte of new pages: measured here, ~125,000
page faults per training step, 15-20 % of its time. :func:`tune_host_allocator`
makes glibc keep such blocks in its heap and reuse them.

``import dispgns`` calls it first (before any module that starts JAX's CPU
backend, e.g. jax-md's), so scripts, notebooks and the command line all get
it; set the environment variable ``DISPGNS_TUNE_ALLOCATOR=0`` to leave glibc's
defaults alone. It changes no result, only where memory comes from; the price
is that up to ``keep_free_bytes`` of freed memory stays with the process
instead of going back to the system. It only takes full effect before the
first JAX computation of the process (import dispgns first, or call it
yourself at the top of a script).

:func:`physics_compiler_options` are the XLA options the ground-truth
physics is compiled with, :func:`network_compiler_options` those of the
learned simulator's training step and rollouts (both on the CPU only). Code
that calls :func:`dispgns.simulate`, :func:`dispgns.rollout` or
:func:`dispgns.train_step` inside its own jit is compiled with that jit's
options instead: pass these to the outermost ``jax.jit`` (JAX refuses
compiler options on a jit that is nested in another or differentiated from
outside, so put ``jax.grad`` inside it).
"""

from __future__ import annotations

import ctypes
import functools
import inspect
import os
import sys
import warnings

# mallopt parameters (glibc malloc.h).
_M_TRIM_THRESHOLD = -1
_M_MMAP_MAX = -4
_M_ARENA_MAX = -8

_tuned = False


def _jax_backends_initialized() -> bool:
    try:
        from jax._src import xla_bridge
    except ImportError:  # jax's private layout changed: assume the worst (only a warning depends on it)
        return True
    check = getattr(xla_bridge, "backends_are_initialized", None)
    return True if check is None else bool(check())


def tune_host_allocator(keep_free_bytes: int = 1 << 30, *, warn_if_late: bool = True) -> bool:
    """Keep XLA:CPU's per-execution buffers in glibc's heap (no fresh pages per call).

    Sets, with ``mallopt``: one malloc arena for all threads (XLA's worker
    threads would otherwise get arenas of at most 64 MB, which hand large
    blocks to ``mmap`` whatever the settings), no ``mmap`` for large blocks,
    and a trim threshold of ``keep_free_bytes``.

    Call it before the first JAX computation of the process: threads that
    already allocated keep their arenas (a warning says so). Safe to call
    more than once; a no-op returning ``False`` off Linux/glibc.

    Args:
      keep_free_bytes: freed memory at the top of the heap that is kept for
        reuse instead of being returned to the system (1 GiB; at most
        2**31 - 1).
      warn_if_late: warn when JAX's backend is already running.

    Returns:
      ``True`` if the settings were applied (now or by an earlier call).
    """
    global _tuned
    if not 0 < keep_free_bytes < 2**31:
        raise ValueError(f"keep_free_bytes must be in (0, 2**31), got {keep_free_bytes!r}")
    if _tuned:
        return True
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(None)
        mallopt = libc.mallopt
        libc.gnu_get_libc_version  # only glibc has it (musl's mallopt ignores these settings)
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
    late = _jax_backends_initialized()
    applied = all(
        mallopt(param, value) == 1
        for param, value in ((_M_ARENA_MAX, 1), (_M_MMAP_MAX, 0), (_M_TRIM_THRESHOLD, int(keep_free_bytes)))
    )
    if applied and late and warn_if_late:
        warnings.warn(
            "dispgns.tune_host_allocator() called after JAX started its CPU backend: threads that "
            "already allocated keep their own arenas, so the speed-up may be partial. Call it "
            "before the first JAX computation.",
            RuntimeWarning,
            stacklevel=2,
        )
    _tuned = applied
    return applied


def host_allocator_tuned() -> bool:
    """Whether :func:`tune_host_allocator` has applied its settings in this process."""
    return _tuned


def tune_at_import() -> bool:
    """What ``import dispgns`` does: :func:`tune_host_allocator` unless ``DISPGNS_TUNE_ALLOCATOR=0``."""
    if os.environ.get("DISPGNS_TUNE_ALLOCATOR", "1").strip().lower() in ("0", "false", "no", "off"):
        return False
    return tune_host_allocator(warn_if_late=False)


def physics_compiler_options() -> dict[str, int]:
    """XLA options for the physics' ``jax.jit`` s: ``jax.jit(f, compiler_options=physics_compiler_options())``.

    XLA on CPU vectorises its loops 256 bits wide unless told otherwise (some
    older CPUs lower their clock for 512-bit instructions). The pair-force
    loops of the physics are 1.6x faster at 512 bits on the AVX-512 machine
    of ``benchmarks/simulate.py`` (Euler step at N = 220: 0.061 vs 0.100 ms).
    It is a preference: CPUs without AVX-512 keep their widest registers
    (:func:`physics_jit` passes it only when JAX's default backend is the
    CPU). It changes no formula, only how loops are vectorised (float32
    results may differ in the last bits).
    """
    return {"xla_cpu_prefer_vector_width": 512}


def network_compiler_options(model_config=None) -> dict[str, str]:
    """XLA options for the jits that run the learned simulator's network on the CPU.

    For float32 matmuls (``ModelConfig.matmul_dtype = "float32"``, the
    default) the dots are left to XLA's own kernels instead of the YNNPACK
    library that XLA hands them to by default: measured on the 2-core AMD
    EPYC machine of ``benchmarks/gnn.py``, in-process A/B over interleaved
    rounds, the paper network's training step 187 -> 167 ms and rollout step
    24.0 -> 22.3 ms, the shipped network's 52.9 -> 49.0 ms and 4.43 -> 4.08
    ms. For bfloat16 matmuls YNNPACK's kernels are the faster ones (rollout
    step 16.7 vs 24.0 ms without them), so there are no options. The
    ground-truth physics keeps YNNPACK too (its Euler step at N = 220 is 2x
    faster with it: 0.023 vs 0.050 ms). Float32 results may differ in the
    last bits (another summation order), as between any two matmul kernels.

    Args:
      model_config: a :class:`dispgns.ModelConfig` (``None``: float32).

    Returns:
      the options, for ``jax.jit(..., compiler_options=...)`` on the CPU.
    """
    matmul_dtype = getattr(model_config, "matmul_dtype", "float32")
    if matmul_dtype == "float32":
        return {"xla_cpu_experimental_ynn_fusion_type": ""}
    return {}


def _outside_transformations() -> bool:
    try:
        from jax._src import core

        return bool(core.trace_state_clean())
    except (ImportError, AttributeError):  # jax's private layout changed: the options are left out
        return False


@functools.cache
def _known_options(items: tuple[tuple[str, object], ...]) -> tuple[tuple[str, object], ...]:
    """``items`` without the options this jaxlib refuses (a warning names each one).

    XLA's option names and values change between releases: an option must
    never stop a computation. Each is tried alone on a trivial function.
    """
    import jax

    kept = []
    for name, value in items:
        try:
            jax.jit(lambda x: x + 1, compiler_options={name: value}).lower(1.0).compile()
        except Exception as error:  # XLA raises its own runtime error types
            warnings.warn(
                f"dispgns: this jaxlib ({jax.__version__}) refuses the XLA option {name}={value!r} "
                f"({error}); compiling without it (same results, perhaps slower)",
                RuntimeWarning,
                stacklevel=4,
            )
            continue
        kept.append((name, value))
    return tuple(kept)


class CpuJit:
    """``jax.jit(fun, **jit_kwargs)`` that, on the CPU, compiles with per-call XLA options.

    ``options(*args, **kwargs)`` returns the compiler options for a call
    (e.g. from its static model config). They are used only for calls outside
    every transformation: JAX refuses compiler options on a jit nested in the
    caller's ``jit`` or differentiated by ``grad``, so inside any
    transformation (``jit``, ``vmap``, ``grad``, ``scan``) this is an ordinary
    nested jit and gets the options of the outermost computation. Both compute
    the same function. Options the installed jaxlib refuses are dropped with a
    warning. ``lower`` works as ``jax.jit(...).lower``.
    """

    def __init__(self, fun, options, **jit_kwargs):
        import jax  # here, not at the top: ``import dispgns`` stays light and tunes the allocator first

        functools.update_wrapper(self, fun)
        self._fun, self._options, self._jit_kwargs = fun, options, jit_kwargs
        self._plain = jax.jit(fun, **jit_kwargs)
        self._tuned: dict = {}

    def _pick(self, args, kwargs):
        import jax

        if not (_outside_transformations() and jax.default_backend() == "cpu"):
            return self._plain
        items = _known_options(tuple(sorted(self._options(*args, **kwargs).items())))
        if not items:
            return self._plain
        if items not in self._tuned:
            self._tuned[items] = jax.jit(self._fun, compiler_options=dict(items), **self._jit_kwargs)
        return self._tuned[items]

    def __call__(self, *args, **kwargs):
        return self._pick(args, kwargs)(*args, **kwargs)

    def lower(self, *args, **kwargs):
        return self._pick(args, kwargs).lower(*args, **kwargs)


def cpu_jit(fun=None, *, options, **jit_kwargs):
    """:class:`CpuJit` of ``fun``; without ``fun``, a decorator."""
    if fun is None:
        return functools.partial(cpu_jit, options=options, **jit_kwargs)
    return CpuJit(fun, options, **jit_kwargs)


def physics_jit(fun, **jit_kwargs):
    """``jax.jit(fun, **jit_kwargs)`` with :func:`physics_compiler_options` on the CPU (see :class:`CpuJit`)."""
    return CpuJit(fun, lambda *args, **kwargs: physics_compiler_options(), **jit_kwargs)


def network_jit(fun=None, *, config_arg: str = "model_config", **jit_kwargs):
    """``jax.jit`` compiled with :func:`network_compiler_options` of the call's model config on the CPU.

    ``config_arg`` names the parameter of ``fun`` that holds the
    :class:`dispgns.ModelConfig`, or an object with a ``model_config``
    attribute (a ``TrainState``). See :class:`CpuJit`.
    """
    if fun is None:
        return functools.partial(network_jit, config_arg=config_arg, **jit_kwargs)
    signature = inspect.signature(fun)
    if config_arg not in signature.parameters:
        raise ValueError(
            f"network_jit: {fun.__qualname__} has no parameter {config_arg!r} "
            f"(parameters: {list(signature.parameters)})"
        )

    def options(*args, **kwargs):
        bound = signature.bind(*args, **kwargs)  # a TypeError for a call that lacks arguments, as Python's own
        bound.apply_defaults()
        config = bound.arguments[config_arg]
        return network_compiler_options(getattr(config, "model_config", config))

    return CpuJit(fun, options, **jit_kwargs)
