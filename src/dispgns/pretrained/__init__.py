"""The trained model that ships with dispgns (weights, configs and training record).

``load_pretrained()`` returns ``(params, model_config, info)`` like
:func:`dispgns.training.checkpoint.load_model`; ``info["record"]`` holds how
it was trained and what it scored (see ``experiments/paper/README.md``).
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path

__all__ = [
    "DEFAULT_MODEL",
    "load_pretrained",
    "pretrained_path",
]

DEFAULT_MODEL = "paper"


def pretrained_path(name: str = DEFAULT_MODEL) -> Path:
    """Directory of the shipped model ``name`` (``params.msgpack`` + ``model.json``)."""
    path = Path(str(resources.files(__name__))) / name
    if not (path / "model.json").is_file():
        available = sorted(p.name for p in path.parent.iterdir() if (p / "model.json").is_file())
        raise FileNotFoundError(f"no shipped model {name!r} in {path.parent}; available: {available}")
    return path


def load_pretrained(name: str = DEFAULT_MODEL):
    """The shipped model: ``(params, model_config, info)``.

    Args:
      name: which shipped model (``"paper"``: trained on the paper's protocol).
    """
    from dispgns.training.checkpoint import load_model

    params, model_config, info = load_model(pretrained_path(name))
    return params, model_config, {**info, "source": f"dispgns.pretrained:{name}"}
