"""Helpers shared by the subcommands: loading a model, formatting numbers."""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import os
import signal
import sys
import threading
from pathlib import Path

from dispgns.cli import CLIError


@contextlib.contextmanager
def sigterm_as_interrupt():
    """Inside the block a SIGTERM (a scheduler, ``timeout``) raises KeyboardInterrupt, as Ctrl-C does.

    The command's Ctrl-C handling (checkpoint, clean-up of temporary files)
    then runs for both. Only possible on the main thread; elsewhere a no-op.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGTERM, _raise_interrupt)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


# Signals turned into KeyboardInterrupt by this process, newest last (for the exit status).
_received: list[int] = []


def _raise_interrupt(signum, frame):
    _received.append(signum)
    raise KeyboardInterrupt


def interrupted_status() -> int:
    """The usual exit status of an interrupted command: 143 after a SIGTERM, 130 after Ctrl-C."""
    return 128 + last_signal()


def last_signal() -> int:
    """The signal behind the latest interrupt: SIGTERM when one was turned into it, else SIGINT."""
    return int(_received[-1] if _received else signal.SIGINT)


def reset_interrupts() -> None:
    """Forget earlier signals (``main()`` may run several commands in one process)."""
    _received.clear()


def clean_leftovers(*targets) -> None:
    """Remove (and say so) what an earlier, killed run of the command left beside its outputs ``targets``."""
    from dispgns.files import remove_leftovers

    for target in targets:
        for path, done in remove_leftovers(target):
            print(f"{path.name}: {done} (left by an interrupted earlier run)", file=sys.stderr)


def file_error(error: OSError, out) -> CLIError:
    """A :class:`CLIError` for an output that exists (``--overwrite``) or cannot be written (one line)."""
    if isinstance(error, FileExistsError):
        text = str(error)
        if "allow overwriting it" in text or "allow replacing it" in text:
            text += " (--overwrite)"
        return CLIError(text)
    where = error.filename or out
    if Path(str(where)).name.startswith(".") and ".tmp" in Path(str(where)).name:
        where = out  # a staging name of dispgns.files says nothing to the user: the output it was for does
    return CLIError(f"cannot write to {where}: {error.strerror or error}")


def check_writable_place(out) -> None:
    """Refuse ``--out`` up front when its nearest existing ancestor is not a writable directory."""
    parent = next((p for p in Path(out).absolute().parents if p.exists()), None)
    if parent is None or not parent.is_dir() or not os.access(parent, os.W_OK):
        raise CLIError(f"cannot write to {out}: {parent} is not a writable directory")


def check_output(out, *, overwrite: bool, marker: str, kind: str) -> None:
    """Refuse ``--out`` up front (before a long computation), as :func:`output_directory` would."""
    from dispgns.files import check_output_directory

    out = Path(out)
    if out.suffix.lower() in (".gif", ".mp4", ".png", ".json", ".h5"):
        raise CLIError(f"--out {out}: expected a directory (the files are written inside it), got a file name")
    try:
        check_output_directory(out, overwrite, marker, kind)
    except OSError as error:
        raise file_error(error, out) from None
    check_writable_place(out)


@contextlib.contextmanager
def output_directory(out, *, overwrite: bool, marker: str, kind: str):
    """Stage the output directory ``--out`` (see :func:`dispgns.files.staged_directory`) with CLI errors.

    Leftovers of a killed earlier run are removed first; an existing ``out``
    needs ``--overwrite`` and must hold ``marker``; an unwritable place or a
    failed write is one line. Yields the staging directory.
    """
    from dispgns.files import staged_directory

    out = Path(out)
    check_output(out, overwrite=overwrite, marker=marker, kind=kind)
    clean_leftovers(out)
    try:
        with staged_directory(out, overwrite=overwrite, marker=marker, kind=kind) as staging:
            yield staging
    except OSError as error:
        raise file_error(error, out) from None


def cpu_tuned(args) -> bool:
    """Whether the command runs with :mod:`dispgns.tuning`'s settings (all but ``--no-tuning``)."""
    return not getattr(args, "no_tuning", False)


def compute_config(args, model_config):
    """The model config the command computes with: the CPU kernels unless ``--no-tuning`` (same function)."""
    from dispgns import tuning

    return tuning.tuned_model_config(model_config) if cpu_tuned(args) else model_config


def network_options(args, model_config) -> dict:
    """XLA options for the network's compiled loops (``{}`` with ``--no-tuning``)."""
    from dispgns import tuning

    return tuning.network_compiler_options(model_config) if cpu_tuned(args) else {}


def physics_options(args) -> dict:
    """XLA options for the physics' compiled loops (``{}`` with ``--no-tuning``)."""
    from dispgns import tuning

    return tuning.physics_compiler_options() if cpu_tuned(args) else {}


def add_distributed_arguments(parser, description: str):
    """The ``--distributed`` options (JAX's multi-process runtime); returns their argument group."""
    group = parser.add_argument_group("devices and processes", description)
    group.add_argument(
        "--distributed",
        action="store_true",
        help="start JAX's distributed runtime (jax.distributed.initialize); the coordinator address, process "
        "count and id come from the options below or from what JAX reads itself (JAX_COORDINATOR_ADDRESS, "
        "JAX_NUM_PROCESSES, JAX_PROCESS_ID, SLURM)",
    )
    group.add_argument("--coordinator", metavar="HOST:PORT", help="address of process 0 (with --distributed)")
    group.add_argument("--num-processes", type=int, metavar="P", help="processes in all (with --distributed)")
    group.add_argument("--process-id", type=int, metavar="I", help="this process, 0 .. P-1 (with --distributed)")
    return group


def start_distributed(args) -> None:
    """Start JAX's distributed runtime for ``--distributed``, before anything starts JAX's backend."""
    if not args.distributed:
        if any(value is not None for value in (args.coordinator, args.num_processes, args.process_id)):
            raise CLIError("--coordinator, --num-processes and --process-id need --distributed")
        return
    import jax

    try:
        jax.distributed.initialize(
            coordinator_address=args.coordinator, num_processes=args.num_processes, process_id=args.process_id
        )
    except (RuntimeError, ValueError) as error:
        raise CLIError(f"--distributed: cannot start JAX's distributed runtime: {error}") from None


def local_mesh():
    """A 1-D mesh of this process's devices (axis ``"data"``), or ``None`` with one device."""
    import jax

    devices = jax.local_devices()
    return None if len(devices) == 1 else jax.make_mesh((len(devices),), ("data",), devices=devices)


def add_model_argument(parser) -> None:
    parser.add_argument(
        "--model",
        metavar="PATH|NAME",
        help="an exported model directory (model.json), a training run directory, or the name of a shipped "
        "model ('paper': trained on the paper's 16 trajectories; default: the model shipped with dispgns for the "
        "data's dimension, sedimentation-2d in 2-D)",
    )
    parser.add_argument(
        "--best",
        action="store_true",
        help="with a run directory: the best checkpoint by validation instead of the final model",
    )
    parser.add_argument(
        "--keep-inside-box",
        choices=("on", "off"),
        default=None,
        help="project predicted centres that cross a wall back onto it (default: as the model's config says)",
    )
    parser.add_argument(
        "--symmetrize",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="average every prediction over the symmetries of the box floor (8 in 3-D, the mirror image in 2-D): "
        "exactly equivariant whatever the weights, 8 network evaluations per step in 3-D (2 in 2-D); "
        "--no-symmetrize turns it off (default: as the model's config says; sedimentation-2d ships with it on)",
    )


def load_model_argument(args, dim: int = 2):
    """``(params, model_config, info)`` for ``--model``/``--best``/``--keep-inside-box`` (default: shipped model).

    Without ``--model`` it is the shipped model for ``dim``-D data (``sedimentation-2d`` in 2-D,
    ``sedimentation-3d`` in 3-D); ``--model NAME`` with the name of a shipped model (e.g. ``paper``)
    and no such path loads that one. The config is the one to compute with (:func:`compute_config`).
    """
    params, model_config, info = _load(args, dim)
    if getattr(args, "keep_inside_box", None) is not None:
        model_config = dataclasses.replace(model_config, keep_inside_box=args.keep_inside_box == "on")
    if getattr(args, "symmetrize", None) is not None:
        try:
            model_config = dataclasses.replace(model_config, symmetrize=args.symmetrize)
        except ValueError as error:
            raise CLIError(f"--symmetrize: {error}") from None
    return params, compute_config(args, model_config), info


def may_name_a_shipped_model(source: str) -> bool:
    """Whether ``--model``/``--init-from SOURCE`` is read as a shipped model's name (e.g. ``paper``).

    An existing path always wins, and anything with a path separator is a path.
    """
    return not Path(source).exists() and "/" not in source and "\\" not in source


def _load(args, dim: int = 2):
    from dispgns.training.checkpoint import CheckpointError, load_params

    if args.model is None:
        if args.best:
            raise CLIError("--best needs --model RUN (a training run directory)")
        from dispgns.pretrained import default_model_name, load_pretrained, shipped_models

        name = default_model_name(dim)
        if name not in shipped_models():
            raise CLIError(
                f"no {dim}-D model ships with this installation of dispgns (dispgns.pretrained has "
                f"{shipped_models()}, not {name!r}); pass --model PATH to a {dim}-D training run or exported model"
            )
        try:
            return load_pretrained(name)
        except (FileNotFoundError, CheckpointError) as error:
            raise CLIError(f"the shipped model cannot be loaded: {error}; pass --model PATH") from None
    source = str(args.model)
    if may_name_a_shipped_model(source):
        from dispgns.pretrained import load_pretrained, shipped_models

        if source in shipped_models():
            if args.best:
                raise CLIError(f"--best needs --model RUN (a training run directory), not the shipped model {source!r}")
            return load_pretrained(source)
    try:
        return load_params(args.model, best=args.best)
    except CheckpointError as error:
        raise CLIError(str(error)) from None


def fmt(value, digits: int = 3) -> str:
    """A number for tables: ``1.23e-04`` when small or large, ``2.61`` otherwise, ``-`` when missing."""
    if value is None:
        return "-"
    if isinstance(value, int) and not isinstance(value, bool):
        return str(value)
    value = float(value)
    if value != value:
        return "nan"
    if value != 0 and (abs(value) < 1e-2 or abs(value) >= 1e4):
        return f"{value:.{digits - 1}e}"
    return f"{value:.{digits}g}"


def mean_std(summary, key: str) -> str:
    """``mean ± std`` of a :func:`dispgns.metrics.summarize` entry, ``-`` when missing."""
    entry = summary.get(key)
    if not isinstance(entry, dict) or not isinstance(entry.get("mean"), float):
        return "-"
    return f"{fmt(entry['mean'])} ± {fmt(entry['std'], 2)}"
