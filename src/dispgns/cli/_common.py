"""Helpers shared by the subcommands: loading a model, formatting numbers."""

from __future__ import annotations

import contextlib
import dataclasses
import signal
import threading

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


def _raise_interrupt(signum, frame):
    raise KeyboardInterrupt


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


def add_model_argument(parser) -> None:
    parser.add_argument(
        "--model",
        metavar="PATH",
        help="an exported model directory (model.json) or a training run directory "
        "(default: the model shipped with dispgns)",
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


def load_model_argument(args):
    """``(params, model_config, info)`` for ``--model``/``--best``/``--keep-inside-box`` (default: shipped model).

    The config is the one to compute with (:func:`compute_config`).
    """
    params, model_config, info = _load(args)
    if getattr(args, "keep_inside_box", None) is not None:
        model_config = dataclasses.replace(model_config, keep_inside_box=args.keep_inside_box == "on")
    return params, compute_config(args, model_config), info


def _load(args):
    from dispgns.training.checkpoint import CheckpointError, load_params

    if args.model is None:
        if args.best:
            raise CLIError("--best needs --model RUN (a training run directory)")
        from dispgns.pretrained import load_pretrained

        try:
            return load_pretrained()
        except (FileNotFoundError, CheckpointError) as error:
            raise CLIError(f"the shipped model cannot be loaded: {error}; pass --model PATH") from None
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
