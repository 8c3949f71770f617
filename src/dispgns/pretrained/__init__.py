"""The trained models that ship with dispgns (weights, configs and training record).

``load_pretrained(name)`` returns ``(params, model_config, info)`` like
:func:`dispgns.training.checkpoint.load_model`; ``info["record"]`` holds how
it was trained and what it scored. Each model is a directory of this package
(``params.msgpack`` + ``model.json``):

* ``sedimentation-2d`` (the default): 2-D disks, the ``paper`` model fine-tuned on 400 generated
  training trajectories (the paper's training radii); the more accurate of the two 2-D models by
  validation (``experiments/accuracy/RESUME.md``);
* ``paper``: 2-D disks trained on the paper's 16 training trajectories only, the like-for-like
  comparison with the paper (``experiments/paper/README.md``);
* ``sedimentation-3d``: spheres in the ``paper3d`` cube, predictions averaged over the floor's 8
  symmetries (``experiments/three_d/``).
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path
from typing import Any, NamedTuple

# dispgns.model and dispgns.arrays import JAX and Flax: named through the package, not imported here, so
# reading the shipped configs stays fast (the annotations below resolve when read).
import dispgns

__all__ = [
    "CONFIG_NAMES",
    "DEFAULT_CONFIG",
    "DEFAULT_MODEL",
    "MODEL_3D",
    "PAPER_DATA_MODEL",
    "NamedConfig",
    "default_model_name",
    "load_pretrained",
    "named_config",
    "pretrained_path",
    "shipped_models",
]

DEFAULT_MODEL = "sedimentation-2d"
PAPER_DATA_MODEL = "paper"
MODEL_3D = "sedimentation-3d"
DEFAULT_CONFIG = "cpu"


class NamedConfig(NamedTuple):
    """A training configuration shipped with dispgns (``dispgns train --config NAME``).

    Attributes:
      name: ``"cpu"``, ``"paper_gpu"`` or ``"paper"``.
      path: the YAML file inside the installed package.
      values: ``{"model": {...}, "train": {...}}`` as written in it.
      summary: one line: what it is and for what machine.
      seconds_per_step: a measured time per step on a 2-core CPU (``None``: not measured), for
        the expected duration printed before training.
    """

    name: str
    path: Path
    values: dict
    summary: str
    seconds_per_step: float | None


# The shipped run (experiments/paper/README.md): 65,046 steps in 2.1 h on a 2-core CPU.
_CONFIGS = {
    "cpu": (
        "the 'paper' model's configuration (latent 64, 5 message-passing steps, 120,000 steps), sized for a CPU",
        2.1 * 3600 / 65_046,
    ),
    "paper_gpu": (
        "the paper's network (latent 128, 10 message-passing steps) and 2,000,000-step schedule with "
        "dispgns's fixes: a GPU recipe",
        None,
    ),
    "paper": ("the authors' exact recipe (2,000,000 steps, no standardisation): a GPU recipe", None),
}
CONFIG_NAMES = tuple(_CONFIGS)


def named_config(name: str) -> NamedConfig:
    """The shipped training configuration ``name`` (one of :data:`CONFIG_NAMES`)."""
    import yaml

    if name not in _CONFIGS:
        raise ValueError(f"no shipped configuration {name!r}; expected one of {list(CONFIG_NAMES)}")
    path = Path(str(resources.files(__name__))) / "configs" / f"{name}.yaml"
    values = yaml.safe_load(path.read_text()) or {}
    summary, seconds = _CONFIGS[name]
    return NamedConfig(name, path, {k: dict(values.get(k) or {}) for k in ("model", "train")}, summary, seconds)


def shipped_models() -> list[str]:
    """Names of the models this installation ships (directories with a ``model.json``), sorted."""
    root = Path(str(resources.files(__name__)))
    return sorted(p.name for p in root.iterdir() if (p / "model.json").is_file())


def default_model_name(dim: int = 2) -> str:
    """The shipped model for ``dim``-D data: :data:`DEFAULT_MODEL` in 2-D, :data:`MODEL_3D` in 3-D."""
    if dim not in (2, 3):
        raise ValueError(f"dim must be 2 or 3, got {dim!r}")
    return DEFAULT_MODEL if dim == 2 else MODEL_3D


def pretrained_path(name: str = DEFAULT_MODEL) -> Path:
    """Directory of the shipped model ``name`` (``params.msgpack`` + ``model.json``).

    Raises:
      FileNotFoundError: no such model in this installation (the message lists the shipped ones).
    """
    root = Path(str(resources.files(__name__)))
    # A plain name only: never a path that leads out of the package.
    if not isinstance(name, str) or not name or name in (".", "..") or "/" in name or "\\" in name:
        raise FileNotFoundError(f"no shipped model {name!r}; available: {shipped_models()}")
    path = root / name
    if not (path / "model.json").is_file():
        raise FileNotFoundError(f"no shipped model {name!r} in {root}; available: {shipped_models()}")
    return path


def load_pretrained(
    name: str = DEFAULT_MODEL,
) -> tuple[dispgns.arrays.Params, dispgns.model.ModelConfig, dict[str, Any]]:
    """A shipped model: ``(params, model_config, info)``.

    Args:
      name: which shipped model: ``"sedimentation-2d"`` (the default: 2-D disks, trained on
        400 generated trajectories; its config has ``symmetrize=True``, every prediction averaged
        with the mirrored one, two network evaluations per step:
        ``dataclasses.replace(model_config, symmetrize=False)`` for one), ``"paper"`` (2-D disks,
        trained on the paper's 16) or
        ``"sedimentation-3d"`` (spheres in the ``paper3d`` cube);
        :func:`shipped_models` lists what this installation has.

    Raises:
      FileNotFoundError: ``name`` is not shipped (the message lists what is).
    """
    from dispgns.training.checkpoint import load_model

    params, model_config, info = load_model(pretrained_path(name))
    return params, model_config, {**info, "source": f"dispgns.pretrained:{name}"}
