"""The ``dispgns`` command line: the only place that parses arguments and prints.

Exit status: 0 on success, 2 for a user error (one line on stderr), 130
after Ctrl-C and 143 after SIGTERM (the command checkpoints or cleans up
first).

Each subcommand lives in its own module exposing ``register(subparsers)``,
which adds its parser and sets ``func`` to a callable taking the parsed
arguments and returning an exit code.
"""

from __future__ import annotations

import importlib
import os
import sys

TYPE_CHECKING = False  # typing's, without importing typing (start-up time: see _start_up)
if TYPE_CHECKING:
    import argparse

# Subcommand modules, in the order shown by --help.
_COMMANDS = ("demo", "generate", "import_npz", "import_files", "train", "evaluate", "render", "export")


class CLIError(Exception):
    """A user-facing error: printed as one message, exit code 2."""


def build_parser() -> argparse.ArgumentParser:
    import argparse

    from dispgns import __version__

    parser = argparse.ArgumentParser(
        prog="dispgns",
        description="Learned simulation of finite-size particle suspensions (graph network simulator).",
        # _start_up reads --no-tuning from argv before parsing: no abbreviation may mean it here and not there
        allow_abbrev=False,
    )
    parser.add_argument("--version", action="version", version=f"dispgns {__version__}")
    parser.add_argument(
        "--no-tuning",
        action="store_true",
        help="run without dispgns.tuning's CPU settings (host allocator, XLA options, fused kernels): "
        "the same results to float rounding, slower",
    )
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in _COMMANDS:
        try:
            module = importlib.import_module(f"dispgns.cli.{name}")
        except ModuleNotFoundError as error:
            if error.name == f"dispgns.cli.{name}":
                continue
            raise
        module.register(subparsers)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run one ``dispgns`` command in this process; its exit status.

    The caller's host allocator is left as it was: its tuning
    (:func:`dispgns.tuning.tune_host_allocator`, process-wide and permanent) is
    done by the ``dispgns`` program (:func:`entry`) before anything starts,
    not here; an in-process caller who wants it calls it first.
    """
    parser = build_parser()
    args = parser.parse_args(argv)
    if getattr(args, "func", None) is None:
        parser.print_help()
        return 2
    from dispgns.cli._common import interrupted_status, reset_interrupts

    reset_interrupts()
    previous_hook = sys.unraisablehook
    sys.unraisablehook = _without_closed_loop_reports(previous_hook)
    try:
        return int(args.func(args) or 0)
    except CLIError as error:
        print(f"dispgns {args.command}: error: {error}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"dispgns {args.command}: interrupted", file=sys.stderr)
        return interrupted_status()
    except ImportError as error:
        if not _caused_by_interrupt(error):
            raise
        # A Ctrl-C inside a C extension's initialisation (a library a command imports late) comes out as
        # its ImportError.
        print(f"dispgns {args.command}: interrupted", file=sys.stderr)
        return interrupted_status()
    finally:
        sys.unraisablehook = previous_hook


def _caused_by_interrupt(error: BaseException) -> bool:
    """Whether a ``KeyboardInterrupt`` is among ``error``'s causes or contexts."""
    seen = set()
    while error is not None and id(error) not in seen:
        if isinstance(error, KeyboardInterrupt):
            return True
        seen.add(id(error))
        error = error.__cause__ or error.__context__
    return False


def _without_closed_loop_reports(hook):
    """``hook`` (``sys.unraisablehook``), silent for TensorStore's reports of a closed event loop.

    When a checkpoint write fails part-way (a file system turned read-only),
    orbax closes its per-operation event loop at the first error while
    TensorStore still completes the other writes; each completion then finds
    the loop closed and TensorStore prints ``RuntimeError: Event loop is
    closed`` as an unraisable exception (tens of tracebacks before the one
    error line the command prints). Nothing is lost: the save has failed
    already and says so. Every other report reaches ``hook``.
    """

    import threading

    def report(unraisable):
        if isinstance(unraisable.exc_value, RuntimeError) and str(unraisable.exc_value) == "Event loop is closed":
            return
        if isinstance(unraisable.exc_value, KeyboardInterrupt):
            # A Ctrl-C (or SIGTERM made one) that landed in a callback whose errors are ignored, e.g. JAX's
            # garbage-collection callback (often during start-up): without this the command ran on to its end.
            # Sent again from a helper thread a moment later: sent from here, it would be handled inside this
            # hook and ignored again.
            from dispgns.cli._common import last_signal

            threading.Timer(0.01, os.kill, (os.getpid(), last_signal())).start()
            return
        hook(unraisable)

    return report


def entry() -> None:
    """The ``dispgns`` program (console script and ``python -m dispgns``): :func:`main`, then a clean exit.

    The exit skips the interpreter's teardown, once every file is closed and
    every output flushed: threads of the libraries underneath (XLA's thread
    pools, TensorStore's and orbax's workers) may still run while Python
    finalises, and a SIGTERM'd run then sometimes died at exit with "pure
    virtual method called" (status 134) or a segmentation fault (139)
    instead of its usual 143, after everything had been saved.
    """
    import contextlib
    import logging

    interrupt = _start_up()
    if interrupt:
        print("dispgns: interrupted", file=sys.stderr)
        code = 128 + interrupt
    else:
        code = main()
    if "jax" in sys.modules:
        import jax

        with contextlib.suppress(Exception):
            jax.distributed.shutdown()  # what its atexit hook would do (no-op without --distributed)
    logging.shutdown()
    with contextlib.suppress(Exception):
        sys.stdout.flush()
    with contextlib.suppress(Exception):
        sys.stderr.flush()
    os._exit(code)


# Imported while Ctrl-C and SIGTERM wait: a signal landing inside a C extension's initialisation (jaxlib's,
# h5py's) left an ImportError traceback or a segmentation fault instead of the command's usual exit.
_START_UP_MODULES = ("jax", "h5py")


def _start_up() -> int:
    """Tune the host allocator (unless ``--no-tuning``; the only place that does), then import what every command
    needs, with Ctrl-C and SIGTERM held; the first signal received, or 0.

    A signal that arrives meanwhile is answered after the imports (a second or
    so at most) with the usual status, 130 or 143, and one line. A signal the
    caller ignores (``nohup``, a background job) stays ignored.
    """
    import signal

    received: list[int] = []
    held = {}
    for signum in (signal.SIGINT, signal.SIGTERM):
        if signal.getsignal(signum) is not signal.SIG_IGN:
            held[signum] = signal.signal(signum, lambda number, frame: received.append(number))
    try:
        if "--no-tuning" not in sys.argv[1:]:
            from dispgns.tuning import tune_host_allocator

            tune_host_allocator(warn_if_late=False)  # before any thread of XLA's allocates
        for name in _START_UP_MODULES:
            importlib.import_module(name)
        build_parser()  # the subcommands' modules
    finally:
        for signum, handler in held.items():
            signal.signal(signum, handler)
    return received[0] if received else 0


if __name__ == "__main__":
    entry()
