"""Files of a training run: orbax checkpoints, the resolved configs, the JSONL log, exported models.

A run directory holds::

    config.json          model, training and dataset settings of the run (resolved)
    log.jsonl            one JSON object per logged step or validation
    checkpoints/<step>/  orbax checkpoints, the last ``keep_checkpoints``
    best/<step>/         the checkpoint with the best validation rollout MSE
    model/               the exported final model (params.msgpack + model.json)

An orbax checkpoint stores the :class:`~dispgns.training.TrainState` pytree
(``params``, ``opt_state``, ``step``, and ``ema`` when the run keeps a moving
average of the weights), the base PRNG key of the run and the
data-order position, plus the resolved configs as JSON, so a checkpoint
directory is self-describing. Orbax writes under a temporary name and
renames, so a checkpoint is either complete or absent.

An exported model (:func:`export_model`, :func:`load_model`) is what ships
and what ``evaluate``/``render``/``demo`` load: the parameters as msgpack
(flax.serialization: plain arrays, no pickle) and ``model.json`` with the
:class:`~dispgns.model.ModelConfig` and a free-form training record.

This module, :mod:`dispgns.data` and :mod:`dispgns.render` are the only
library modules that write files, and only at the paths they are given.
"""

from __future__ import annotations

import contextlib
import dataclasses
import errno
import json
import logging
import os
import re
import shutil
import signal
import threading
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import orbax.checkpoint as ocp
from flax import serialization

from dispgns.arrays import Params, PerAxis, PRNGKey
from dispgns.files import staged_directory, write_atomic
from dispgns.model import ModelConfig, init_params
from dispgns.training.loggers import json_safe
from dispgns.training.step import TrainConfig, TrainState, create_train_state

__all__ = [
    "BEST_DIR",
    "CHECKPOINT_DIR",
    "CONFIG_FILE",
    "CheckpointError",
    "Checkpointer",
    "JsonlLog",
    "LOG_FILE",
    "MODEL_DIR",
    "MODEL_FILE",
    "MODEL_FORMAT_VERSION",
    "PARAMS_FILE",
    "configs_from",
    "export_model",
    "load_model",
    "load_params",
    "read_json",
    "restore_template",
    "run_config",
    "write_json",
]

CONFIG_FILE = "config.json"
LOG_FILE = "log.jsonl"
CHECKPOINT_DIR = "checkpoints"
BEST_DIR = "best"
MODEL_DIR = "model"
PARAMS_FILE = "params.msgpack"
MODEL_FILE = "model.json"
MODEL_FORMAT_VERSION = 1


class CheckpointError(ValueError):
    """A run directory, checkpoint or exported model is missing, malformed or does not match.

    ``mismatch`` is true when a checkpoint is intact but belongs to another configuration.
    """

    def __init__(self, message: str, *, mismatch: bool = False):
        super().__init__(message)
        self.mismatch = mismatch


def _reason(error: BaseException) -> str:
    """The first line of a library's error, without its advice to library users (``strict=False`` ...)."""
    text = str(error).strip().splitlines()[0] if str(error).strip() else ""
    text = re.split(r"\s*(?:To restore|Please set|set `?strict|\bsee https?://)", text, maxsplit=1)[0].strip()
    text = re.sub(r"<[^>]{60,}>", "<...>", text)  # object reprs (TensorStore specs)
    return f"{type(error).__name__}: {text[:200]}" if text else type(error).__name__


def _remove_orbax_temporaries(run_dir: Path) -> list[Path]:
    """Remove orbax's temporary checkpoint folders under ``run_dir`` (left by a killed save); return them."""
    removed = []
    for folder in (run_dir / CHECKPOINT_DIR, run_dir / BEST_DIR):
        if not folder.is_dir():
            continue
        for path in sorted(folder.iterdir()):
            if ".orbax-checkpoint-tmp" in path.name:
                shutil.rmtree(path, ignore_errors=True)
                if not path.exists():
                    removed.append(path)
    return removed


# ----------------------------------------------------------------------------- small file helpers


def write_json(path: str | os.PathLike, values: Mapping[str, Any]) -> Path:
    """``values`` as indented JSON at ``path``, atomically."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_atomic(path, _dumps(values, indent=2) + "\n")
    return path


def read_json(path: str | os.PathLike, what: str) -> dict[str, Any]:
    """Read a JSON object; :class:`CheckpointError` naming the file when it is missing or malformed."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"{path}: not found; expected the {what}")
    try:
        values = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
        raise CheckpointError(f"{path}: cannot be read as JSON ({error}); expected the {what}") from None
    if not isinstance(values, dict):
        raise CheckpointError(f"{path}: holds a JSON {type(values).__name__}, expected an object ({what})")
    return values


def _dumps(value, **kwargs) -> str:
    """JSON text without NaN or infinities (``null`` instead; ``json`` would write the non-standard ``NaN``)."""
    return json.dumps(json_safe(value), allow_nan=False, default=_json_default, **kwargs)


def _json_default(value):
    if isinstance(value, (np.generic, jnp.ndarray, np.ndarray)):
        return np.asarray(value).tolist()
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")


class JsonlLog:
    """Append-only JSONL log (one object per line, flushed at once so a crash loses nothing)."""

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)

    def write(self, record: Mapping[str, Any]) -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        with self.path.open("a") as file:
            file.write(_dumps(record) + "\n")
            file.flush()

    def read(self) -> list[dict[str, Any]]:
        if not self.path.is_file():
            return []
        records = []
        lines = self.path.read_text().splitlines()
        for number, line in enumerate(lines, 1):
            if not line.strip():
                continue
            try:
                records.append(json.loads(line))
            except json.JSONDecodeError:
                # A run killed mid-write leaves at most one torn last line.
                if number != len(lines):
                    raise CheckpointError(f"{self.path}: line {number} is not JSON") from None
        return records

    def drop(self, *, kind: str, step: int) -> None:
        """Drop the records of ``kind`` at ``step`` (one that a resumed run redoes), atomically."""
        kept = [r for r in self.read() if not (r.get("kind") == kind and int(r.get("step", -1)) == step)]
        write_atomic(self.path, "".join(json.dumps(r, default=_json_default) + "\n" for r in kept))

    def truncate_after(self, step: int) -> None:
        """Drop records past ``step`` (a resumed run rewrites them), atomically."""
        kept = [r for r in self.read() if int(r.get("step", 0)) <= step]
        text = "".join(_dumps(r) + "\n" for r in kept)
        write_atomic(self.path, text)


# ----------------------------------------------------------------------------- run configuration


def run_config(
    model_config: ModelConfig,
    train_config: TrainConfig,
    normalization: Mapping[str, Any],
    dataset: Mapping[str, Any] | None = None,
) -> dict[str, Any]:
    """The resolved configuration of a run as a JSON-ready dict (what ``config.json`` holds)."""
    from dispgns import __version__

    return {
        "dispgns_version": __version__,
        "model": model_config.to_dict(),
        "train": train_config.to_dict(),
        "normalization": {k: np.asarray(v, np.float64).tolist() for k, v in normalization.items()},
        "dataset": dict(dataset or {}),
    }


def configs_from(values: Mapping[str, Any], where: str) -> tuple[ModelConfig, TrainConfig, dict[str, PerAxis]]:
    """``(ModelConfig, TrainConfig, normalization)`` from a :func:`run_config` dict."""
    try:
        model_config = ModelConfig.from_dict(values["model"])
        train_config = TrainConfig.from_dict(values["train"])
        normalization = {k: np.asarray(v, np.float32) for k, v in values["normalization"].items()}
    except KeyError as error:
        raise CheckpointError(
            f"{where}: missing field {error.args[0]!r}; expected 'model', 'train' and 'normalization'"
        ) from None
    except (TypeError, ValueError) as error:
        raise CheckpointError(f"{where}: {error}") from None
    return model_config, train_config, normalization


# ----------------------------------------------------------------------------- orbax checkpoints


def _state_tree(state: TrainState, key: jax.Array, data_position: int) -> dict[str, Any]:
    # The moving average only when the run keeps one: checkpoints of runs without it keep their layout.
    average = {} if state.ema is None else {"ema": state.ema}
    return {
        **average,
        "params": state.params,
        "opt_state": state.opt_state,
        "step": state.step,
        # numpy, not a jax.Array: the key lives on one device, and in a multi-process run orbax saves only
        # global or numpy arrays.
        "key": np.asarray(jax.random.key_data(key)),
        "data_position": np.asarray(data_position, np.int32),
    }


class _DropThreadFailures(logging.Filter):
    """Drops orbax's log records of a failed save thread (with their tracebacks): the save raises it anyway."""

    def filter(self, record: logging.LogRecord) -> bool:
        return not (record.levelno >= logging.ERROR and "raised an exception" in record.getMessage())


@contextlib.contextmanager
def _quiet_orbax_threads():
    """While saving, orbax's worker threads log a failure (a read-only or full disk) with a traceback.

    The failure reaches the caller as one ``OSError`` (:meth:`Checkpointer._save`);
    only those records of orbax's logger (``absl``) are dropped, and only
    during the save.
    """
    logger = logging.getLogger("absl")
    quiet = _DropThreadFailures()
    logger.addFilter(quiet)
    try:
        yield
    finally:
        logger.removeFilter(quiet)


@contextlib.contextmanager
def _interrupts_held():
    """Hold Ctrl-C and SIGTERM back until the block is done, then deliver the first one received.

    Orbax finishes a save in a background thread: an interrupt in the middle
    would leave it running while the caller's interrupt handling saves the
    same step again. Only possible on the main thread; elsewhere a no-op.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    received = []
    held = (signal.SIGINT, signal.SIGTERM)
    previous = {signum: signal.signal(signum, lambda signum, frame: received.append(signum)) for signum in held}
    try:
        yield
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)
    if received:
        # Delivered again now, to the handler that was in place (a SIGTERM keeps its meaning and status).
        signal.raise_signal(received[0])
        raise KeyboardInterrupt


class Checkpointer:
    """Orbax checkpoints of one run: the last ``keep`` in ``checkpoints/``, the best one in ``best/``.

    Args:
      run_dir: the run directory.
      keep: how many of the latest checkpoints to keep.
      config: the resolved run configuration (:func:`run_config`), stored in
        every checkpoint.
    """

    def __init__(
        self,
        run_dir: str | os.PathLike,
        *,
        keep: int = 3,
        config: Mapping[str, Any] | None = None,
        remove_leftovers: bool = False,
    ):
        self.run_dir = Path(run_dir)
        self.config = dict(config or {})
        # Orbax saves under "<step>.orbax-checkpoint-tmp*" and renames; a killed save leaves that behind.
        # Only a writer (the training run) removes them: a reader may run beside a live save.
        self.removed: list[Path] = _remove_orbax_temporaries(self.run_dir) if remove_leftovers else []
        options = dict(create=True, enable_async_checkpointing=False)
        self._last = ocp.CheckpointManager(
            self.run_dir.absolute() / CHECKPOINT_DIR, options=ocp.CheckpointManagerOptions(max_to_keep=keep, **options)
        )
        self._best = ocp.CheckpointManager(
            self.run_dir.absolute() / BEST_DIR, options=ocp.CheckpointManagerOptions(max_to_keep=1, **options)
        )
        self.best_value = self._read_best_value()
        # The newest checkpoint known complete (found at start or saved since): what a failed save leaves.
        self.last_saved: int | None = self._last.latest_step()

    def _read_best_value(self) -> float:
        step = self._best.latest_step()
        if step is None:
            return float("inf")
        extra = self._best.restore(step, args=ocp.args.Composite(extra=ocp.args.JsonRestore()))["extra"]
        value = extra.get("validation_value")
        return float("inf") if value is None else float(value)

    def latest_step(self) -> int | None:
        return self._last.latest_step()

    def save(
        self,
        state: TrainState,
        key: PRNGKey,
        *,
        data_position: int,
        validation: Mapping[str, Any] | None = None,
        validation_value: float | None = None,
    ) -> None:
        """Save ``state`` (and, if ``validation_value`` beats every earlier one, as the best too).

        Args:
          key: the run's base PRNG key (per-step keys are folded from it).
          data_position: batches consumed so far (the data-order position).
          validation: the latest validation metrics (stored as JSON).
          validation_value: the number "best" is judged by (lower is better).
        """
        step = int(state.step)
        extra = json_safe(
            {
                "config": self.config,
                "step": step,
                "data_position": int(data_position),
                "validation": dict(validation or {}),
                "validation_value": validation_value,
            }
        )
        tree = _state_tree(state, key, data_position)
        args = ocp.args.Composite(state=ocp.args.StandardSave(tree), extra=ocp.args.JsonSave(extra))
        with _interrupts_held():
            if self._last.latest_step() != step:
                self._save(self._last, step, args)
                self.last_saved = step
            if validation_value is not None and np.isfinite(validation_value) and validation_value < self.best_value:
                if self._best.latest_step() != step:
                    self._save(self._best, step, args)
                self.best_value = float(validation_value)

    @staticmethod
    def _save(manager, step: int, args) -> None:
        """One orbax save; a failed write becomes an ``OSError`` naming the checkpoint folder.

        Orbax and TensorStore raise ``OSError`` without a file name (a
        read-only file system) or other types carrying the system's message
        (a full disk); the caller needs the place and the reason in one line.
        """
        where = str(Path(manager.directory) / str(step))
        try:
            with _quiet_orbax_threads():
                manager.save(step, args=args)
                manager.wait_until_finished()
        except OSError as error:
            raise OSError(error.errno or errno.EIO, error.strerror or _reason(error), where) from None
        except Exception as error:  # TensorStore's write errors are ValueErrors carrying the OS error's code
            code = re.search(r"os_error_code='?(\d+)", str(error))
            if code is not None:
                raise OSError(int(code.group(1)), os.strerror(int(code.group(1))), where) from None
            raise OSError(errno.EIO, f"the checkpoint could not be written ({_reason(error)})", where) from None

    def restore(
        self, template: TrainState, key: PRNGKey, *, step: int | None = None, best: bool = False
    ) -> tuple[TrainState, PRNGKey, dict[str, Any]]:
        """Restore into the structure of ``template`` (e.g. a fresh :func:`create_train_state`).

        Returns:
          ``(state, key, extra)``; ``extra`` holds ``data_position``,
          ``validation``, ``config``.
        """
        manager = self._best if best else self._last
        if step is not None:
            return self._restore_step(manager, step, template, key)
        steps = sorted(manager.all_steps(), reverse=True)
        if not steps:
            raise CheckpointError(f"{manager.directory}: no checkpoint to restore")
        # The newest checkpoint that reads back; the damaged ones after it are reported, not hidden.
        skipped = []
        for candidate in steps:
            try:
                state, key_out, extra = self._restore_step(manager, candidate, template, key)
            except CheckpointError as error:
                if error.mismatch:  # every checkpoint of the run would disagree: no fallback
                    raise
                skipped.append(str(error))
                continue
            extra["skipped"] = skipped
            return state, key_out, extra
        raise CheckpointError(f"{manager.directory}: no checkpoint can be read: " + "; ".join(skipped))

    def _restore_step(self, manager, step: int, template: TrainState, key: jax.Array):
        where = f"{manager.directory}/{step}"
        abstract = jax.tree_util.tree_map(ocp.utils.to_shape_dtype_struct, _state_tree(template, key, 0))
        mismatch = self._config_mismatch(manager, step, averaged=template.ema is not None)
        if mismatch:
            raise CheckpointError(f"{where}: written for another configuration ({mismatch})", mismatch=True)
        try:
            restored = manager.restore(
                step, args=ocp.args.Composite(state=ocp.args.StandardRestore(abstract), extra=ocp.args.JsonRestore())
            )
        except Exception as error:  # orbax and tensorstore raise many types (bare Exception too) on damage
            raise CheckpointError(f"{where}: cannot be read, the checkpoint is damaged ({_reason(error)})") from None
        tree, extra = restored["state"], restored["extra"]
        state = template.replace(
            params=tree["params"], opt_state=tree["opt_state"], step=tree["step"], ema=tree.get("ema")
        )
        return state, jax.random.wrap_key_data(np.asarray(tree["key"])), dict(extra)

    def _config_mismatch(self, manager, step: int, *, averaged: bool) -> str:
        """How checkpoint ``step``'s stored config differs from the run's ('' if it does not, or is unknown).

        The model fields must agree with the run's config.json, and the stored
        training config must keep a weight average exactly when the restoring
        state does (``averaged``): the two trees differ in shape otherwise, which
        orbax would report as damage, and every checkpoint of the run would then
        be tried in turn. A stored config without a training part (not written
        by :func:`run_config`) is not checked for the average.
        """
        try:
            extra = manager.restore(step, args=ocp.args.Composite(extra=ocp.args.JsonRestore()))["extra"]
            stored = extra["config"]
        except Exception:  # a damaged checkpoint: the full restore reports it
            return ""
        if not isinstance(stored, Mapping):
            return ""
        diff = []
        theirs_train = stored.get("train")
        if isinstance(theirs_train, Mapping):
            # A checkpoint written before TrainConfig.ema_decay existed had no average.
            decay = theirs_train.get("ema_decay", 0.0)
            if bool(decay) != averaged:
                diff.append(
                    f"ema_decay: checkpoint {decay!r} ({'with' if decay else 'without'} a weight average), "
                    f"the restoring state {'with' if averaged else 'without'} one"
                )
        mine, theirs = self.config.get("model"), stored.get("model")
        if isinstance(mine, Mapping) and isinstance(theirs, Mapping):
            ignored = {"kernels"}  # a speed setting, the same function
            # A field missing on either side was added to ModelConfig after that side was written: it then had
            # the field's default behaviour, so a checkpoint of an older version still resumes a run.
            defaults = {field.name: field.default for field in dataclasses.fields(ModelConfig)}

            def value(config, name):
                return config.get(name, defaults.get(name))

            diff += [
                f"{name}: checkpoint {value(theirs, name)!r}, config.json {value(mine, name)!r}"
                for name in sorted(set(mine) | set(theirs))
                if name not in ignored and value(theirs, name) != value(mine, name)
            ]
        return "; ".join(diff)

    def close(self) -> None:
        self._last.close()
        self._best.close()


# ----------------------------------------------------------------------------- exported models


def export_model(
    directory: str | os.PathLike, params: Params, model_config: ModelConfig, record: Mapping[str, Any] | None = None
) -> Path:
    """Write a model directory (``params.msgpack`` + ``model.json``), replacing it atomically.

    Args:
      directory: the model directory to create or replace.
      params: ``{"network", "normalization"}`` from a trained state.
      model_config: its :class:`ModelConfig`.
      record: JSON-ready provenance (training config, steps, dataset, metrics).
    """
    from dispgns import __version__

    directory = Path(directory).absolute()
    host = jax.tree_util.tree_map(lambda x: np.asarray(x, np.float32), jax.device_get(params))
    info = {
        "format_version": MODEL_FORMAT_VERSION,
        "dispgns_version": __version__,
        "model": model_config.to_dict(),
        "record": dict(record or {}),
    }
    with staged_directory(directory, overwrite=True, marker=MODEL_FILE, kind="model") as staging:
        (staging / PARAMS_FILE).write_bytes(serialization.msgpack_serialize(serialization.to_state_dict(host)))
        (staging / MODEL_FILE).write_text(_dumps(info, indent=2) + "\n")
    return directory


def load_model(directory: str | os.PathLike) -> tuple[Params, ModelConfig, dict[str, Any]]:
    """Read a model directory written by :func:`export_model`.

    Returns:
      ``(params, model_config, info)``; ``info`` is ``model.json`` (with the
      training ``record``).

    Raises:
      CheckpointError: a file is missing or malformed, or the parameters do
        not have the shapes the stored config implies.
    """
    directory = Path(directory)
    info = read_json(directory / MODEL_FILE, "model description of an exported dispgns model")
    where = str(directory / MODEL_FILE)
    if info.get("format_version") != MODEL_FORMAT_VERSION:
        raise CheckpointError(
            f"{where}: 'format_version' is {info.get('format_version')!r}, expected {MODEL_FORMAT_VERSION}"
        )
    try:
        model_config = ModelConfig.from_dict(info["model"])
    except KeyError:
        raise CheckpointError(f"{where}: missing field 'model'") from None
    except (TypeError, ValueError) as error:
        raise CheckpointError(f"{where}: 'model' is not a valid ModelConfig: {error}") from None
    path = directory / PARAMS_FILE
    if not path.is_file():
        raise CheckpointError(f"{path}: not found; expected the parameters of the exported model")
    try:
        raw = serialization.msgpack_restore(path.read_bytes())
    except Exception as error:  # msgpack raises several unrelated types on corrupt input
        raise CheckpointError(f"{path}: cannot be read as msgpack parameters ({error})") from None
    template = jax.eval_shape(lambda: init_params(jax.random.key(0), model_config))
    params = _match_template(template, raw, str(path))
    return params, model_config, info


def _match_template(template, raw, where: str, path: str = ""):
    """``raw`` (nested dicts of arrays) checked against ``template``'s structure and shapes."""
    if isinstance(template, Mapping):
        if not isinstance(raw, Mapping):
            raise CheckpointError(
                f"{where}: '{path or '/'}' is not a mapping, expected one with keys {sorted(template)}"
            )
        missing = sorted(set(template) - set(raw))
        extra = sorted(set(raw) - set(template))
        if missing or extra:
            raise CheckpointError(
                f"{where}: '{path or '/'}' has keys missing {missing} / unexpected {extra} for the stored model config"
            )
        return {k: _match_template(template[k], raw[k], where, f"{path}/{k}") for k in template}
    array = np.asarray(raw)
    if array.shape != tuple(template.shape):
        raise CheckpointError(f"{where}: '{path}' has shape {array.shape}, expected {tuple(template.shape)}")
    return jnp.asarray(array, template.dtype)


def restore_template(
    model_config: ModelConfig, train_config: TrainConfig, normalization: Mapping[str, Any]
) -> TrainState:
    """A fresh state of the right structure to restore a checkpoint into."""
    return create_train_state(jax.random.key(0), model_config, train_config, normalization)


def load_params(
    path: str | os.PathLike, *, best: bool = False, averaged: bool = True
) -> tuple[Params, ModelConfig, dict[str, Any]]:
    """Parameters from an exported model directory or a training run directory.

    Args:
      path: a directory with ``model.json`` (:func:`export_model`), or a run
        directory with ``config.json`` (then its exported ``model/``, or its
        latest checkpoint when the run has not exported one yet).
      best: from a run directory, take the best checkpoint by validation.
      averaged: from a checkpoint of a run that keeps a moving average of
        the weights (``TrainConfig.ema_decay > 0``), the average (True, what
        the run validates and exports) or the raw weights (False, read from
        the checkpoint even when the run has exported a model). No effect
        on runs without an average.

    Returns:
      ``(params, model_config, info)``; ``info["source"]`` says what was loaded.
    """
    path = Path(path)
    if (path / MODEL_FILE).is_file() and not best:
        params, model_config, info = load_model(path)
        return params, model_config, {**info, "source": str(path)}
    if not (path / CONFIG_FILE).is_file():
        raise CheckpointError(f"{path}: neither an exported model ({MODEL_FILE}) nor a training run ({CONFIG_FILE})")
    if not best and averaged and (path / MODEL_DIR / MODEL_FILE).is_file():
        params, model_config, info = load_model(path / MODEL_DIR)
        return params, model_config, {**info, "source": str(path / MODEL_DIR)}
    values = read_json(path / CONFIG_FILE, "configuration of the run")
    model_config, train_config, normalization = configs_from(values, str(path / CONFIG_FILE))
    checkpointer = Checkpointer(path, config=values)
    try:
        state, _, extra = checkpointer.restore(
            restore_template(model_config, train_config, normalization), jax.random.key(0), best=best
        )
    finally:
        checkpointer.close()
    where = path / (BEST_DIR if best else CHECKPOINT_DIR) / str(int(state.step))
    return (
        state.eval_params if averaged else state.params,
        model_config,
        {
            "model": model_config.to_dict(),
            "source": str(where),
            "record": {
                "steps": int(state.step),
                "train": train_config.to_dict(),
                "validation": extra.get("validation", {}),
            },
        },
    )
