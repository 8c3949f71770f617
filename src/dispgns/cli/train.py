"""``dispgns train``: train a learned simulator on a dataset directory, with checkpoints and exact resume."""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import os
import shutil
import statistics
import sys
from collections.abc import Mapping
from pathlib import Path
from typing import Any, NamedTuple

from dispgns.cli import CLIError
from dispgns.cli._common import (
    add_distributed_arguments,
    clean_leftovers,
    compute_config,
    file_error,
    interrupted_status,
    may_name_a_shipped_model,
    network_options,
    sigterm_as_interrupt,
    start_distributed,
)

DEFAULT_CONFIG = "cpu"  # dispgns.pretrained.DEFAULT_CONFIG (not imported here: --help stays fast)

# Training fields that may change when a run is resumed: they decide how long
# and how often, not what is learned.
RESUMABLE_TRAIN_FIELDS = (
    "num_steps",
    "log_every",
    "validate_every",
    "checkpoint_every",
    "keep_checkpoints",
    "validation_examples",
    "validation_trajectories",
    "validation_rollout_frames",
)


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "train",
        help="train a learned simulator on a dataset",
        description="Train the graph network simulator on DATA's train split, validating on its valid split. "
        "Writes RUN/config.json, RUN/log.jsonl, orbax checkpoints (RUN/checkpoints, RUN/best), "
        "the final model (RUN/model) and RUN/training_curve.png. Ctrl-C checkpoints and stops; "
        "--resume continues exactly where the run stopped.",
    )
    parser.add_argument("--data", required=True, metavar="DIR", help="dataset directory (from dispgns generate)")
    parser.add_argument("--out", required=True, metavar="RUN", help="run directory to create (or resume)")
    parser.add_argument(
        "--config",
        metavar="NAME|YAML",
        help=f"a shipped configuration: '{DEFAULT_CONFIG}' (default: the 'paper' model's, sized for a CPU, "
        "about 4 h on 2 cores), 'paper_gpu' (the paper's 2.6 M-parameter network and 2 M steps with "
        "dispgns's fixes: for a GPU) or 'paper' (the authors' exact recipe, for a GPU); or a YAML file with "
        "'model:' and 'train:' sections (ModelConfig / TrainConfig fields; unset fields take the dataclass "
        "defaults)",
    )
    parser.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="SECTION.FIELD=VALUE",
        dest="overrides",
        help="override one field, e.g. --set model.latent_size=64 --set train.noise_std=3e-4 "
        "(repeatable; applied after --config)",
    )
    parser.add_argument("--steps", type=int, metavar="N", help="train up to step N (train.num_steps)")
    parser.add_argument("--resume", action="store_true", help="continue the run in RUN from its latest checkpoint")
    parser.add_argument(
        "--init-from",
        metavar="MODEL",
        help="start a new run from a trained model's parameters and normalisation instead of random weights "
        "(fine-tuning): an exported model directory, a run directory (its exported model, else its latest "
        "checkpoint), or the name of a shipped model (e.g. 'paper'). The network is the model's (--config/--set "
        "may change training fields and the model's keep_inside_box, symmetrize, bounds, kernels and matmul_dtype "
        "only), or a larger one computing the same function "
        "if model.hidden_size or model.message_passing_steps ask for more (dispgns.model.grow_network); the "
        "optimiser and the learning-rate schedule start afresh",
    )
    parser.add_argument("--overwrite", action="store_true", help="replace an existing run in RUN")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.add_argument(
        "--logger",
        action="append",
        choices=("jsonl", "tensorboard", "wandb"),
        default=[],
        help="also log to TensorBoard (RUN/tensorboard, needs tensorboardX) or Weights & Biases (needs wandb; "
        "offline unless --wandb-mode online or WANDB_MODE says otherwise); repeatable. RUN/log.jsonl is always "
        "written",
    )
    parser.add_argument("--wandb-project", default="dispgns", metavar="NAME", help="W&B project (default dispgns)")
    parser.add_argument(
        "--wandb-mode", choices=("offline", "online", "disabled"), help="W&B mode (default: WANDB_MODE, else offline)"
    )
    parallel = add_distributed_arguments(
        parser,
        "Every batch is split over all devices JAX sees (data parallelism; train.batch_size is the global batch, "
        "a multiple of the device count); with --distributed, over the devices of every process.",
    )
    parallel.add_argument(
        "--one-device", action="store_true", help="train on the first device only, even when JAX sees more"
    )
    parser.set_defaults(func=run)


# ----------------------------------------------------------------------------- configuration


def _read_yaml(path: str) -> dict[str, Any]:
    import yaml

    try:
        text = Path(path).read_text()
    except OSError as error:
        raise CLIError(f"{path}: cannot be read ({error.strerror or error})") from None
    try:
        values = yaml.safe_load(text) or {}
    except yaml.YAMLError as error:
        raise CLIError(f"{path}: not valid YAML ({error})") from None
    if not isinstance(values, dict):
        raise CLIError(
            f"{path}: expected a mapping with 'model:' and/or 'train:' sections, got {type(values).__name__}"
        )
    unknown = sorted(set(values) - {"model", "train"})
    if unknown:
        raise CLIError(f"{path}: unknown section(s) {unknown}, expected 'model' and/or 'train'")
    for section in ("model", "train"):
        if not isinstance(values.get(section, {}), dict):
            raise CLIError(f"{path}: section {section!r} must be a mapping of field: value")
    return {section: dict(values.get(section) or {}) for section in ("model", "train")}


def _config_values(config: str) -> dict[str, dict[str, Any]]:
    """``{"model": ..., "train": ...}`` of ``--config``: a shipped name (``cpu``, ``paper_gpu``, ``paper``) or YAML."""
    from dispgns.pretrained import CONFIG_NAMES, named_config

    if config in CONFIG_NAMES and not Path(config).is_file():
        named = named_config(config)
        return {section: dict(fields) for section, fields in named.values.items()}
    if not Path(config).exists() and not config.endswith((".yaml", ".yml")):
        raise CLIError(
            f"--config {config}: neither a shipped configuration ({', '.join(CONFIG_NAMES)}) nor a YAML file"
        )
    return _read_yaml(config)


def _apply_overrides(values: dict[str, dict[str, Any]], overrides: list[str]) -> None:
    import yaml

    for text in overrides:
        name, sep, raw = text.partition("=")
        section, dot, field = name.strip().partition(".")
        if not sep or not dot or section not in ("model", "train") or not field:
            raise CLIError(
                f"--set {text!r}: expected SECTION.FIELD=VALUE with SECTION 'model' or 'train', "
                f"e.g. --set model.latent_size=64"
            )
        try:
            values[section][field] = yaml.safe_load(raw)
        except yaml.YAMLError:
            values[section][field] = raw


def resolve_configs(args: argparse.Namespace, default_connectivity_radius: float | None):
    """``(ModelConfig, TrainConfig, explicit)`` from defaults, ``--config``, ``--set`` and ``--steps``.

    ``explicit`` holds the fields the user set (``{"model": {...}, "train": {...}}``).
    """
    from dispgns.model import ModelConfig
    from dispgns.training import TrainConfig

    values = _config_values(args.config) if args.config else {"model": {}, "train": {}}
    _apply_overrides(values, args.overrides)
    if args.steps is not None:
        values["train"]["num_steps"] = args.steps
    explicit = {section: dict(fields) for section, fields in values.items()}
    if not args.config:
        # No --config: the `paper` model's configuration, under what the user set (not "explicit":
        # a resumed run keeps the configuration it was started with).
        base = _config_values(DEFAULT_CONFIG)
        values = {section: {**base[section], **values[section]} for section in ("model", "train")}
    model_values = dict(values["model"])
    if "connectivity_radius" not in model_values and default_connectivity_radius is not None:
        model_values["connectivity_radius"] = float(default_connectivity_radius)
    flags = [flag for flag, used in (("--set", args.overrides), ("--steps", args.steps is not None)) if used]
    # Name every source the values came from: the YAML file may not be the culprit.
    where = " + ".join([f"--config {args.config or DEFAULT_CONFIG}"] + flags)
    try:
        model_config = ModelConfig.from_dict(model_values)
    except (TypeError, ValueError) as error:
        raise CLIError(f"{where}: invalid model config: {error}") from None
    try:
        train_config = TrainConfig.from_dict(values["train"])
    except (TypeError, ValueError) as error:
        raise CLIError(f"{where}: invalid train config: {error}") from None
    return model_config, train_config, explicit


def _differences(stored, requested, fields) -> list[str]:
    return [
        f"{name}: checkpoint {getattr(stored, name)!r}, requested {getattr(requested, name)!r}"
        for name in fields
        if getattr(stored, name) != getattr(requested, name)
    ]


def validation_fingerprint(trajectories) -> str | None:
    """A digest of the validation trajectories' positions and radii (``None`` without any).

    Two runs' validation scores compare only on the same files. A dataset regenerated
    with the same command on another machine starts from the same states but is not
    bit-identical (float rounding, then chaos), so the digest is of the arrays.
    """
    import numpy as np

    if not trajectories:
        return None
    digest = hashlib.sha256()
    for trajectory in trajectories:
        for array in (trajectory.position, trajectory.radius):
            array = np.ascontiguousarray(array)
            digest.update(f"{array.dtype.str}{array.shape}".encode())
            digest.update(array)  # the buffer, not a copy
    return digest.hexdigest()[:16]


# Resumable training fields that change what a validation scores (the others change how long and how often).
VALIDATION_FIELDS = ("validation_examples", "validation_trajectories", "validation_rollout_frames")


def _warn_if_validation_changed(validated: Mapping, dataset_info: dict, train, data: Path, step: int) -> None:
    """Say so when a resumed run validates otherwise than up to ``step``: other files or other settings.

    ``validated`` is the run config stored in the restored checkpoint: the files and
    settings the run had when that checkpoint was saved (config.json is rewritten as
    soon as a run resumes, so a second resume before the next checkpoint would compare
    with the new ones). ``dataset_info`` is the dataset record about to be written,
    ``train`` the training config from here on. What the record lacks is not compared:
    runs of older versions recorded no fingerprint, and a checkpoint written by
    :class:`Checkpointer` without a run config has no training settings.
    """
    reasons = []
    before = (validated.get("dataset") or {}).get("valid_fingerprint")
    now = dataset_info["valid_fingerprint"]
    if before and now and before != now:  # without a validation split nothing is validated from here on
        reasons.append(
            f"{data / 'valid.h5'}: not the validation trajectories this run was validated on up to step {step} "
            f"(fingerprint {now}, was {before}; regenerated on another machine?)"
        )
    stored_train = validated.get("train")
    stored_train = stored_train if isinstance(stored_train, Mapping) else {}
    changed = [
        f"train.{name} {stored_train[name]!r} -> {getattr(train, name)!r}"
        for name in VALIDATION_FIELDS
        if name in stored_train and stored_train[name] != getattr(train, name)
    ]
    if changed and now:  # likewise
        reasons.append(f"the validation settings changed after step {step} ({', '.join(changed)})")
    if reasons:
        print(
            f"warning: {'; '.join(reasons)}: the validations logged from here on do not compare with the earlier "
            "ones, and the best checkpoint is replaced only by a validation better than the best earlier one",
            file=sys.stderr,
        )


def resumed_configs(stored_model, stored_train, explicit: dict[str, dict[str, Any]], run_dir: Path):
    """The configs of a resumed run: the stored ones, with only the resumable training fields changed."""
    model_changes = {k: v for k, v in explicit["model"].items()}
    if model_changes:
        try:
            requested = dataclasses.replace(stored_model, **model_changes)
        except (TypeError, ValueError) as error:
            raise CLIError(f"invalid model config: {error}") from None
        diff = _differences(stored_model, requested, [f.name for f in dataclasses.fields(stored_model)])
        if diff:
            raise CLIError(
                f"{run_dir / 'config.json'}: the requested model does not match the checkpoint ("
                + "; ".join(diff)
                + "); a run resumes with the model it was started with"
            )
    try:
        train = dataclasses.replace(stored_train, **explicit["train"])
    except (TypeError, ValueError) as error:
        raise CLIError(f"invalid train config: {error}") from None
    fixed = [f.name for f in dataclasses.fields(stored_train) if f.name not in RESUMABLE_TRAIN_FIELDS]
    diff = _differences(stored_train, train, fixed)
    if diff:
        raise CLIError(
            f"{run_dir / 'config.json'}: the requested training config does not match the checkpoint ("
            + "; ".join(diff)
            + f"); on resume only {', '.join(RESUMABLE_TRAIN_FIELDS)} may change"
        )
    return stored_model, train


class _InitialModel(NamedTuple):
    params: dict
    model_config: Any
    normalization: dict
    record: dict


# Model fields a fine-tuning run may set: they change what is done with the network, not its weights.
_FINE_TUNE_MODEL_FIELDS = ("keep_inside_box", "symmetrize", "bounds", "kernels", "matmul_dtype")


def _initial_model(source: str, explicit: dict[str, dict[str, Any]], requested: Any, seed: int) -> _InitialModel:
    """The parameters, network configuration and normalisation that ``--init-from SOURCE`` starts from.

    A configuration asking for more hidden units or interaction blocks than the source has grows the source's
    network into that size (:func:`dispgns.model.grow_network`, fresh weights drawn from ``seed``).
    ``requested`` is the :class:`~dispgns.model.ModelConfig` resolved from ``explicit`` (its values parsed).
    """
    import jax
    import numpy as np

    from dispgns.model import GROWABLE_FIELDS, grow_network
    from dispgns.pretrained import pretrained_path
    from dispgns.training.checkpoint import CheckpointError, load_params

    path = Path(source)
    if may_name_a_shipped_model(source):
        try:
            path = pretrained_path(source)
        except FileNotFoundError as error:
            raise CLIError(f"--init-from {source}: neither a directory nor a shipped model ({error})") from None
    try:
        params, model_config, info = load_params(path)
    except CheckpointError as error:
        raise CLIError(f"--init-from {source}: {error}") from None
    fixed = sorted(set(explicit["model"]) - set(_FINE_TUNE_MODEL_FIELDS))
    differ = [f for f in fixed if getattr(requested, f) != getattr(model_config, f)]
    grows = [f for f in differ if f in GROWABLE_FIELDS and getattr(requested, f) > getattr(model_config, f)]
    differ = [f for f in differ if f not in grows]
    if differ:
        raise CLIError(
            f"--init-from {source}: the model's network is fixed by its parameters, but the configuration sets "
            + "; ".join(
                f"model.{f} = {getattr(requested, f)!r} (the model has {getattr(model_config, f)!r})" for f in differ
            )
            + f"; only {', '.join('model.' + f for f in _FINE_TUNE_MODEL_FIELDS)} may change, and "
            + " and ".join(f"model.{f}" for f in GROWABLE_FIELDS)
            + " may grow (never shrink)"
        )
    changes = {f: v for f, v in explicit["model"].items() if f in _FINE_TUNE_MODEL_FIELDS}
    changes.update({f: getattr(requested, f) for f in grows})
    source_config = model_config
    # Trained as the network alone: the position guard and the floor-symmetry average are rollout-time choices of
    # the export (a shipped model may have them on), unless the configuration asks for them.
    changes.setdefault("keep_inside_box", False)
    changes.setdefault("symmetrize", False)
    try:
        model_config = dataclasses.replace(model_config, **changes)
    except (TypeError, ValueError) as error:
        raise CLIError(f"--init-from {source}: invalid model config: {error}") from None
    normalization = {k: np.asarray(v, np.float32) for k, v in params["normalization"].items()}
    record = {"model": source, "source": info.get("source", str(path)), "steps": info.get("record", {}).get("steps")}
    if grows:
        network = grow_network(jax.random.key(seed), params["network"], source_config, model_config)
        params = {"network": network, "normalization": params["normalization"]}
        record["grown"] = {f: [getattr(source_config, f), getattr(model_config, f)] for f in grows}
    return _InitialModel(params, model_config, normalization, record)


# ----------------------------------------------------------------------------- output directory


def _unfinished_start(run_dir: Path) -> list[Path]:
    """What a run killed during its start left in ``run_dir``, if that is all it holds; else ``[]``.

    A start writes ``config.json`` (atomically: a temporary first) and the
    checkpointer's empty ``best/`` and ``checkpoints/``; killed in between
    (SIGKILL), it leaves those without ``config.json``, a folder neither
    ``--resume`` nor ``--overwrite`` could take. Temporaries of a process that
    still runs are not leftovers, so a live run's folder is never one.
    """
    from dispgns.files import leftovers
    from dispgns.training.checkpoint import CONFIG_FILE, LOG_FILE, MODEL_DIR

    if not run_dir.is_dir() or (run_dir / CONFIG_FILE).exists():
        return []
    ours = {p.name for name in (CONFIG_FILE, LOG_FILE, MODEL_DIR) for p in leftovers(run_dir / name)}
    entries = list(run_dir.iterdir())
    for entry in entries:
        empty_folder = entry.name in ("best", "checkpoints") and entry.is_dir() and not any(entry.iterdir())
        if entry.name not in ours and not empty_folder:
            return []
    return entries


def _check_fresh_run_dir(run_dir: Path, *, overwrite: bool) -> None:
    from dispgns.training.checkpoint import CONFIG_FILE

    if _unfinished_start(run_dir):
        return  # removed by _create_run_dir, which says so
    if run_dir.exists() and (not run_dir.is_dir() or any(run_dir.iterdir())):
        if not overwrite:
            raise CLIError(
                f"{run_dir} exists and is not empty; use --resume to continue the run in it, "
                f"--overwrite to replace it, or another --out"
            )
        if not (run_dir / CONFIG_FILE).is_file():
            raise CLIError(f"refusing to overwrite {run_dir}: it is not a dispgns run ({CONFIG_FILE} not found)")
    parent = next((p for p in run_dir.absolute().parents if p.exists()), None)
    if parent is None or not parent.is_dir() or not os.access(parent, os.W_OK):
        raise CLIError(f"cannot create the run directory {run_dir}: {parent} is not a writable directory")


def _create_run_dir(run_dir: Path, *, overwrite: bool) -> None:
    unfinished = _unfinished_start(run_dir)
    if unfinished:
        for entry in unfinished:
            if entry.is_dir():
                shutil.rmtree(entry)
            else:
                entry.unlink()
        print(
            f"{run_dir}: removed {', '.join(sorted(e.name for e in unfinished))} (left by a run killed as it started)",
            file=sys.stderr,
        )
    elif overwrite and run_dir.is_dir():
        shutil.rmtree(run_dir)
    try:
        run_dir.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise CLIError(f"cannot create the run directory {run_dir}: {error.strerror or error}") from None


# ----------------------------------------------------------------------------- progress


class _Progress:
    def __init__(self, first: int, last: int, enabled: bool):
        self.bar = None
        if enabled:
            from tqdm import tqdm

            self.bar = tqdm(
                total=last,
                initial=first,
                desc="training",
                unit=" steps",
                dynamic_ncols=True,
                file=sys.stderr,
                smoothing=0.05,
            )

    def step(self, step: int, metrics) -> None:
        if self.bar is not None:
            self.bar.update(step - self.bar.n)
            if step % 10 == 0:
                self.bar.set_postfix(loss=f"{metrics['loss']:.3g}", lr=f"{metrics['learning_rate']:.2g}", refresh=False)

    def write(self, text: str) -> None:
        if self.bar is not None:
            self.bar.write(text, file=sys.stderr)
        else:
            print(text, file=sys.stderr, flush=True)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


# ----------------------------------------------------------------------------- the command


def run(args: argparse.Namespace) -> int:
    start_distributed(args)  # first: jax-md (imported with dispgns.training) starts JAX's backend at import
    import jax

    from dispgns.data import DatasetError, load_dataset
    from dispgns.render import plot_training_curve
    from dispgns.training import BatchStream, compute_normalization, create_train_state
    from dispgns.training.checkpoint import (
        CONFIG_FILE,
        LOG_FILE,
        MODEL_DIR,
        Checkpointer,
        CheckpointError,
        JsonlLog,
        configs_from,
        export_model,
        read_json,
        run_config,
        write_json,
    )
    from dispgns.training.loggers import LoggerGroup
    from dispgns.training.loop import NonFiniteLossError, Validator, train

    run_dir = Path(args.out)
    if args.config:
        _config_values(args.config)  # a wrong name or file fails before the dataset is read
    try:
        metadata, splits = load_dataset(args.data, ["train"])
        valid = load_dataset(args.data, ["valid"])[1]["valid"] if "valid" in metadata.splits else []
    except DatasetError as error:
        raise CLIError(str(error)) from None
    train_trajectories = splits["train"]

    model_config, train_config, explicit = resolve_configs(args, metadata.connectivity_radius)
    initial = None
    if args.init_from and not args.resume:
        initial = _initial_model(args.init_from, explicit, model_config, train_config.seed)
        model_config = initial.model_config
    if args.resume:
        if not (run_dir / CONFIG_FILE).is_file():
            raise CLIError(f"{run_dir}: no run to resume ({CONFIG_FILE} not found); start one without --resume")
        try:
            stored = read_json(run_dir / CONFIG_FILE, "configuration of the run")
            stored_model, stored_train, normalization = configs_from(stored, str(run_dir / CONFIG_FILE))
        except CheckpointError as error:
            raise CLIError(str(error)) from None
        model_config, train_config = resumed_configs(stored_model, stored_train, explicit, run_dir)
        if args.init_from and stored.get("init_from", {}).get("model") != args.init_from:
            raise CLIError(
                f"{run_dir / CONFIG_FILE}: --init-from {args.init_from} on resume, but the run was started "
                f"{'from ' + repr(stored['init_from']['model']) if 'init_from' in stored else 'from random weights'}; "
                "a resumed run continues from its own checkpoint (drop --init-from)"
            )
    else:
        _check_fresh_run_dir(run_dir, overwrite=args.overwrite)
        if initial is not None:
            # The network was trained on inputs standardised with these statistics: keep them.
            normalization = initial.normalization
        else:
            normalization = compute_normalization(train_trajectories, noise_std=train_config.noise_std)
    if model_config.dim != metadata.dim:
        raise CLIError(
            f"{Path(args.data) / 'metadata.json'}: 'dim' is {metadata.dim}, but the model has dim = {model_config.dim}"
        )
    if tuple(map(tuple, metadata.bounds)) != model_config.bounds:
        # The box belongs to the data: the network is local and its parameters do not depend on it
        # (a model trained in one box rolls out in another with that box's bounds).
        model_config = dataclasses.replace(model_config, bounds=tuple(map(tuple, metadata.bounds)))
    # Saved and exported: model_config; computed with: its CPU kernels unless --no-tuning (same function).
    compute = compute_config(args, model_config)
    parallel = _data_parallel(args, train_config.batch_size)
    try:
        stream = BatchStream.for_training(
            train_trajectories, model_config, train_config, shards=1 if parallel is None else parallel.devices
        )
    except ValueError as error:
        raise CLIError(f"{Path(args.data) / 'train.h5'}: {error}") from None
    options = network_options(args, model_config)
    validator = Validator(valid, compute, train_config, compiler_options=options) if valid else None

    dataset_info = {
        "path": str(Path(args.data).absolute()),
        "preset": metadata.preset,
        "seed": metadata.seed,
        "trajectory_counts": dict(metadata.trajectory_counts),
        "frame_dt": metadata.frame_dt,
        "box_half_size": metadata.box_half_size,
        "length_scale": metadata.length_scale,
        "valid_fingerprint": validation_fingerprint(valid),
    }
    config = run_config(model_config, train_config, normalization, dataset_info)
    if initial is not None:
        config["init_from"] = initial.record
    elif args.resume and "init_from" in stored:
        config["init_from"] = stored["init_from"]
    init_key, key = jax.random.split(jax.random.key(train_config.seed))
    state = create_train_state(init_key, compute, train_config, normalization)
    if initial is not None:
        # Adam's moments start at zero whatever the weights: only the parameters (and their average) change.
        state = state.with_params(initial.params)
    primary = parallel is None or parallel.is_primary  # the one process that writes files other than checkpoints
    if parallel is not None:
        state = parallel.replicate(state)
    # Everything is validated: only now is the run directory created or changed.
    if not args.resume and primary:
        _create_run_dir(run_dir, overwrite=args.overwrite)
    if parallel is not None:
        parallel.barrier("run directory")
    if primary:
        clean_leftovers(*(run_dir / name for name in (MODEL_DIR, CONFIG_FILE, LOG_FILE, "training_curve.png")))
    checkpointer = Checkpointer(
        run_dir, keep=train_config.keep_checkpoints, config=config, remove_leftovers=primary and args.resume
    )
    for path in checkpointer.removed:
        print(f"{path}: removed (an unfinished checkpoint of an interrupted earlier run)", file=sys.stderr)
    log = JsonlLog(run_dir / LOG_FILE)
    if args.resume:
        if checkpointer.latest_step() is not None:
            try:
                state, key, extra = checkpointer.restore(state, key)
            except CheckpointError as error:
                checkpointer.close()
                raise CLIError(f"cannot resume: {error}") from None
            for reason in extra.get("skipped", []):
                print(f"skipped a damaged checkpoint: {reason}", file=sys.stderr)
            if extra.get("skipped"):
                print(f"resuming from the newest intact checkpoint, step {int(state.step)}", file=sys.stderr)
            if primary:  # without a checkpoint there was no validation to compare with
                validated = extra.get("config")
                _warn_if_validation_changed(
                    validated if isinstance(validated, Mapping) else stored,
                    dataset_info,
                    train_config,
                    Path(args.data),
                    int(state.step),
                )
        # Records past the checkpoint (or all, if the run died before its first one) are redone; a run
        # that had reached its last step redoes its final validation, so that record goes too.
        if primary:
            log.truncate_after(int(state.step))
            if int(state.step) >= train_config.num_steps and validator is not None:
                log.drop(kind="validation", step=int(state.step))
    if primary:
        write_json(run_dir / CONFIG_FILE, config)

    first, last = int(state.step), train_config.num_steps
    progress = _Progress(first, last, enabled=primary and not args.no_progress)
    if first >= last:
        progress.write(f"run is already at step {first} >= {last}; nothing to train (raise --steps to continue)")
    elif primary and not args.resume:
        if initial is not None:
            progress.write(
                f"fine-tuning {initial.record['source']} for {last - first:,} steps; the time per step measured "
                "here follows after the first steps. Ctrl-C checkpoints; --resume continues"
            )
        else:
            progress.write(_plan(args, explicit, state.params, last - first))
    timer = _StepTimer(first, last, progress.write if primary else None)

    extra_loggers = _make_loggers(args, run_dir, config) if primary else LoggerGroup([])

    def on_log(record):
        if not primary:
            return
        log.write(record)
        extra_loggers(record)
        if record["kind"] == "validation":
            shown = ", ".join(
                f"{k} {v:.4g}" for k, v in record.items() if k.startswith("valid_") and isinstance(v, float)
            )
            progress.write(f"step {record['step']}: {shown}")

    try:
        with sigterm_as_interrupt():
            result = train(
                state,
                stream,
                key,
                until_step=last,
                validator=validator,
                checkpointer=checkpointer,
                on_step=timer.wrap(progress.step),
                on_log=on_log,
                compiler_options=options,
                parallel=parallel,
            )
    except NonFiniteLossError as error:
        raise CLIError(f"{error} (dispgns train --data {args.data} --out {args.out} --resume)") from None
    except OSError as error:
        # A checkpoint or the log cannot be written (read-only or full file system): stop with the place named
        # and what is still on disk; the checkpoints written before are untouched.
        latest = checkpointer.last_saved
        kept = (
            f"the newest checkpoint, {run_dir / 'checkpoints' / str(latest)} (step {latest}), is intact"
            if latest is not None
            else "no checkpoint was saved"
        )
        raise CLIError(
            f"{file_error(error, run_dir)}; training stopped; {kept}; once {run_dir} can be written to again, "
            f"continue with dispgns train --data {args.data} --out {args.out} --resume"
        ) from None
    finally:
        progress.close()
        checkpointer.close()
        extra_loggers.close()
    state = result.state
    if not primary:
        return interrupted_status() if result.interrupted else 0
    records = log.read()
    record = {
        "steps": int(state.step),
        "train": train_config.to_dict(),
        "dataset": dataset_info,
        "last_validation": result.last_validation,
    }
    if "init_from" in config:
        record["init_from"] = config["init_from"]
    if result.interrupted:
        record["interrupted"] = True
    params = state.eval_params if parallel is None else parallel.local(state.eval_params)
    exported = False
    try:
        with sigterm_as_interrupt():
            export_model(run_dir / MODEL_DIR, params, model_config, record)  # atomic: all or nothing
            exported = True
            _plot_log(records, run_dir / "training_curve.png", plot_training_curve)
    except OSError as error:
        raise file_error(error, run_dir) from None
    except KeyboardInterrupt:
        # The checkpoint of this step is saved already; only the export (or the plot after it) was cut short.
        model = (
            f"{run_dir / MODEL_DIR} holds the model of step {int(state.step)}"
            if exported
            else f"{run_dir / MODEL_DIR} was not updated (it holds an earlier export, if any)"
        )
        print(
            f"interrupted while exporting the model of step {int(state.step)}; checkpoint saved in {run_dir}; "
            f"{model}; export it with dispgns train --data {args.data} --out {args.out} --resume",
            file=sys.stderr,
        )
        return interrupted_status()
    if result.interrupted:
        print(
            f"interrupted at step {int(state.step)} of {last}; checkpoint saved in {run_dir}; "
            f"{run_dir / MODEL_DIR} holds the model of step {int(state.step)} (interrupted, not the final one); "
            f"continue with dispgns train --data {args.data} --out {args.out} --resume",
            file=sys.stderr,
        )
        return interrupted_status()
    print(f"trained to step {int(state.step)}; model in {run_dir / MODEL_DIR}, log in {run_dir / LOG_FILE}")
    return 0


def _make_loggers(args, run_dir: Path, config):
    """The ``--logger`` choices beyond the JSONL log, as one ``on_log`` callable."""
    from dispgns.training.loggers import LoggerGroup, make_logger

    loggers = []
    try:
        for kind in dict.fromkeys(args.logger):  # in order, once each
            if kind == "tensorboard":
                loggers.append(make_logger(kind, run_dir, config))
            elif kind == "wandb":
                loggers.append(make_logger(kind, run_dir, config, project=args.wandb_project, mode=args.wandb_mode))
    except ModuleNotFoundError as error:
        LoggerGroup(loggers).close()
        raise CLIError(str(error)) from None
    return LoggerGroup(loggers)


def _duration(seconds: float) -> str:
    if seconds < 120:
        return f"{seconds:.0f} s"
    if seconds < 2 * 3600:
        return f"{seconds / 60:.0f} min"
    if seconds < 3 * 86400:
        return f"{seconds / 3600:.1f} h"
    return f"{seconds / 86400:.0f} days"


def _plan(args, explicit, params, steps: int) -> str:
    """What is about to be trained and, for a shipped configuration, how long it took on a 2-core CPU."""
    import jax

    from dispgns.pretrained import CONFIG_NAMES, named_config

    count = sum(x.size for x in jax.tree_util.tree_leaves(params["network"]))
    name = args.config or DEFAULT_CONFIG
    text = f"training {steps:,} steps of a {count / 1e6:.2g} M-parameter network"
    if name in CONFIG_NAMES and not Path(name).is_file():
        named = named_config(name)
        changed = any(named.values["model"].get(k) != v for k, v in explicit["model"].items())
        text += f" (--config {name}{' with another network (--set)' if changed else ''}: {named.summary})"
        if changed:
            pass  # the shipped run's time per step says nothing about another network
        elif named.seconds_per_step is not None:
            text += (
                f"; expected about {_duration(steps * named.seconds_per_step)} on a 2-core CPU "
                f"({named.seconds_per_step:.2f} s/step when the 'paper' model was trained)"
            )
        else:
            text += "; on a CPU this takes weeks"
    text += "; the time per step measured here follows after the first steps. Ctrl-C checkpoints; --resume continues"
    return text


class _StepTimer:
    """Prints, once, the time per step measured after compilation and the expected time to the last step.

    The median step time, not the mean: the first steps of a run recompile whenever a batch outgrows the graph
    budget (grown outside ``jit``, see :mod:`dispgns.capacity`), and a few of those would otherwise turn 0.2
    s/step into an estimate of days.
    """

    # Steps timed after the first (compiling) one; and at most this many seconds of timing.
    STEPS, SECONDS = 20, 120.0

    def __init__(self, first: int, last: int, write, clock=None):
        import time

        self.first, self.last, self.write = first, last, write
        self.clock = time.perf_counter if clock is None else clock
        self.start = self.previous = None
        self.durations: list[float] = []
        self.done = write is None

    def wrap(self, on_step):
        def step(step, metrics):
            on_step(step, metrics)
            if self.done:
                return
            now = self.clock()
            if self.start is None:
                self.start = self.previous = now  # after the first step: its compilation is behind us
                return
            self.durations.append(now - self.previous)
            self.previous = now
            if len(self.durations) >= self.STEPS or now - self.start >= self.SECONDS or step >= self.last:
                self.done = True
                per_step = statistics.median(self.durations)
                self.write(
                    f"measured {per_step:.3g} s/step: the remaining {self.last - step:,} steps take about "
                    f"{_duration(per_step * (self.last - step))} on this machine"
                )

        return step


def _data_parallel(args, batch_size: int):
    """A :class:`DataParallel` over every device of every process, or ``None`` for one device."""
    import jax

    if args.one_device or (jax.device_count() == 1 and not args.distributed):
        return None
    from dispgns.training.distributed import DataParallel

    parallel = DataParallel()
    try:
        parallel.check_batch_size(batch_size)
    except ValueError as error:
        raise CLIError(str(error)) from None
    return parallel


def _plot_log(records, path: Path, plot) -> None:
    train = [r for r in records if r.get("kind") == "train"]
    if not train:
        return
    validation = {}
    for key, label in (("valid_one_step_loss", "valid one-step loss"), ("valid_rollout_mse", "valid rollout MSE")):
        points = [(r["step"], r[key]) for r in records if r.get("kind") == "validation" and key in r]
        if points:
            validation[label] = ([p[0] for p in points], [p[1] for p in points])
    plot(
        [r["step"] for r in train],
        [r["loss"] for r in train],
        validation=validation or None,
        smooth=10 if len(train) > 30 else 0,
        path=path,
    )
