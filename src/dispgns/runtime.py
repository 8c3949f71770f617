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
physics is compiled with. Code that calls :func:`dispgns.simulate` inside
its own jit is compiled with that jit's options instead: pass these to the
outermost ``jax.jit`` (JAX refuses compiler options on a jit that is nested
in another or differentiated from outside, so put ``jax.grad`` inside it).
"""

from __future__ import annotations

import ctypes
import functools
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
    if not 0 < keep_free_bytes < 2 ** 31:
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
    applied = all(mallopt(param, value) == 1 for param, value in (
        (_M_ARENA_MAX, 1), (_M_MMAP_MAX, 0), (_M_TRIM_THRESHOLD, int(keep_free_bytes))))
    if applied and late and warn_if_late:
        warnings.warn("dispgns.tune_host_allocator() called after JAX started its CPU backend: threads that "
                      "already allocated keep their own arenas, so the speed-up may be partial. Call it "
                      "before the first JAX computation.", RuntimeWarning, stacklevel=2)
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


def _outside_transformations() -> bool:
    try:
        from jax._src import core
        return bool(core.trace_state_clean())
    except (ImportError, AttributeError):  # jax's private layout changed: the options are left out
        return False


def physics_jit(fun, **jit_kwargs):
    """``jax.jit(fun, **jit_kwargs)``, compiled with :func:`physics_compiler_options` on the CPU.

    JAX accepts compiler options only on a jit called outside every
    transformation; called inside one (the caller's ``jit``, ``vmap``,
    ``grad``), the function is an ordinary nested jit and gets the options of
    the outermost computation. Both versions compute the same function.
    """
    import jax  # here, not at the top: ``import dispgns`` stays light and tunes the allocator first

    with_options = jax.jit(fun, compiler_options=physics_compiler_options(), **jit_kwargs)
    plain = jax.jit(fun, **jit_kwargs)

    @functools.wraps(fun)
    def call(*args, **kwargs):
        tuned = _outside_transformations() and jax.default_backend() == "cpu"
        return (with_options if tuned else plain)(*args, **kwargs)

    return call

