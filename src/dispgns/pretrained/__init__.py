"""The trained model that ships with dispgns (weights, configs and training record).

``load_pretrained()`` returns ``(params, model_config, info)`` like
:func:`dispgns.training.checkpoint.load_model`; ``info["record"]`` holds how
it was trained and what it scored (see ``experiments/paper/README.md``).
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
    "NamedConfig",
    "load_pretrained",
    "named_config",
    "pretrained_path",
]

DEFAULT_MODEL = "paper"
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
        "the shipped model's configuration (latent 64, 5 message-passing steps, 120,000 steps), sized for a CPU",
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


def pretrained_path(name: str = DEFAULT_MODEL) -> Path:
    """Directory of the shipped model ``name`` (``params.msgpack`` + ``model.json``)."""
    path = Path(str(resources.files(__name__))) / name
    if not (path / "model.json").is_file():
        available = sorted(p.name for p in path.parent.iterdir() if (p / "model.json").is_file())
        raise FileNotFoundError(f"no shipped model {name!r} in {path.parent}; available: {available}")
    return path


def load_pretrained(
    name: str = DEFAULT_MODEL,
) -> tuple[dispgns.arrays.Params, dispgns.model.ModelConfig, dict[str, Any]]:
    """The shipped model: ``(params, model_config, info)``.

    Args:
      name: which shipped model (``"paper"``: trained on the paper's protocol).
    """
    from dispgns.training.checkpoint import load_model

    params, model_config, info = load_model(pretrained_path(name))
    return params, model_config, {**info, "source": f"dispgns.pretrained:{name}"}
