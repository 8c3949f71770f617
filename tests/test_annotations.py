"""The public API's type annotations: every one resolves, and arrays carry jaxtyping shapes.

The promise of ``py.typed`` and the docstrings: every public function, method and class field of the
packages below is annotated, the annotations resolve with :func:`typing.get_type_hints`, and no array is
annotated as a bare ``np.ndarray``/``jax.Array``/``ArrayLike`` or ``Any``: arrays say their shape with a
jaxtyping annotation (``Float[ArrayLike, "T N D"]``; the common ones are named in :mod:`dispgns.arrays`).
"""

import dataclasses
import importlib
import inspect
import types
import typing
from pathlib import Path

import jax
import jaxtyping
import numpy as np
import pytest

# The modules whose ``__all__`` is the public API held to the promise: every module of the package but the
# command line (which parses arguments, and whose functions are its subcommands) and the private ones.
MODULES = (
    "dispgns",
    "dispgns.arrays",
    "dispgns.capacity",
    "dispgns.files",
    "dispgns.tuning",
    "dispgns.validation",
    "dispgns.physics",
    "dispgns.physics.config",
    "dispgns.physics.forces",
    "dispgns.physics.initial",
    "dispgns.physics.integrate",
    "dispgns.physics.walls",
    "dispgns.metrics",
    "dispgns.data",
    "dispgns.data.format",
    "dispgns.data.formats",
    "dispgns.data.generate",
    "dispgns.data.importers",
    "dispgns.data.lagrangebench",
    "dispgns.graph",
    "dispgns.features",
    "dispgns.model",
    "dispgns.kernels",
    "dispgns.simulator",
    "dispgns.training",
    "dispgns.training.batches",
    "dispgns.training.checkpoint",
    "dispgns.training.distributed",
    "dispgns.training.loggers",
    "dispgns.training.loop",
    "dispgns.training.noise",
    "dispgns.training.normalization",
    "dispgns.training.step",
    "dispgns.evaluation",
    "dispgns.pretrained",
    "dispgns.render",
)
NOT_PUBLIC = ("dispgns.cli", "dispgns.__main__")

# ``Any`` where no array goes: (qualified name, parameter or field) -> why.
ANY_ALLOWED = {
    ("dispgns.training.loggers.json_safe", "value"): "any JSON-like value, converted for a JSON file",
    ("dispgns.training.loggers.json_safe", "return"): "the same value with non-finite numbers replaced",
}


def _public_objects():
    """``{"module.qualname": object}`` of the functions and classes the modules export (each once)."""
    found = {}
    for module_name in MODULES:
        module = importlib.import_module(module_name)
        for name in module.__all__:
            obj = getattr(module, name)
            if not inspect.isclass(obj) and inspect.isfunction(getattr(obj, "__wrapped__", None)):
                obj = inspect.unwrap(obj)  # jax.jit, functools.cache
            if inspect.isfunction(obj) or (inspect.isclass(obj) and not issubclass(obj, BaseException)):
                found.setdefault(f"{obj.__module__}.{obj.__qualname__}", obj)
    return found


def _own_functions(cls):
    """The public methods (and an explicit ``__init__``) defined in ``cls``'s own body."""
    for name, member in vars(cls).items():
        function = member.__func__ if isinstance(member, (staticmethod, classmethod)) else member
        if isinstance(function, property):
            function = function.fget
        if not inspect.isfunction(function) or function.__qualname__ != f"{cls.__qualname__}.{name}":
            continue  # generated (dataclass, NamedTuple) or inherited
        if not name.startswith("_") or name == "__init__":
            yield name, function


def _functions():
    """``[(label, function)]``: the public functions and the public methods of the public classes."""
    out = []
    for label, obj in _public_objects().items():
        if inspect.isfunction(obj):
            out.append((label, obj))
        else:
            out.extend((f"{label}.{name}", function) for name, function in _own_functions(obj))
    return out


def _classes():
    return [(label, obj) for label, obj in _public_objects().items() if inspect.isclass(obj)]


def _fields(cls) -> list[str]:
    """The annotated fields of a NamedTuple or dataclass (other classes: none)."""
    if dataclasses.is_dataclass(cls):
        return [f.name for f in dataclasses.fields(cls)]
    if issubclass(cls, tuple) and hasattr(cls, "_fields"):
        return list(cls._fields)
    return []


BARE = (np.ndarray, jax.Array)


def _is_jaxtyping(annotation) -> bool:
    return inspect.isclass(annotation) and (
        issubclass(annotation, jaxtyping.AbstractArray) or annotation.__module__ == "jaxtyping"
    )


def _problems(annotation, top: bool = True) -> list[str]:
    """What is wrong with one resolved annotation: a bare array type anywhere inside it, or ``Any`` as the
    annotation itself (``x: Any``, ``x: Any | None``: it could hide an array; ``Mapping[str, Any]`` cannot)."""
    if _is_jaxtyping(annotation):
        return []  # a shape annotation (or a PyTree of them): nothing inside is bare
    if annotation is typing.Any:
        return ["Any"] if top else []
    if inspect.isclass(annotation) and issubclass(annotation, BARE):
        return ["bare np.ndarray" if issubclass(annotation, np.ndarray) else "bare jax.Array"]
    union = typing.get_origin(annotation) in (typing.Union, types.UnionType)
    problems = []
    for arg in typing.get_args(annotation):
        if arg is not Ellipsis and not isinstance(arg, (str, int, type(None), list)):
            problems.extend(_problems(arg, top=top and union))
    return problems


def _hints(obj):
    try:
        return typing.get_type_hints(obj)
    except Exception as error:  # the failure message is what the test reports
        raise AssertionError(f"{obj.__module__}.{obj.__qualname__}: annotations do not resolve: {error!r}") from None


FUNCTIONS = _functions()
CLASSES = _classes()


def _package_modules() -> set[str]:
    """Every module of the installed package, from its files (without importing any)."""
    root = Path(importlib.import_module("dispgns").__file__).parent
    names = set()
    for path in root.rglob("*.py"):
        parts = path.relative_to(root.parent).with_suffix("").parts
        names.add(".".join(parts[:-1] if parts[-1] == "__init__" else parts))
    return names


def test_every_public_module_is_held_to_the_promise():
    # A new public module must join MODULES (or be private): otherwise its annotations go unchecked.
    found = _package_modules()
    public = {
        name
        for name in found
        if not any(part.startswith("_") for part in name.split(".")[1:])
        and not any(name == m or name.startswith(m + ".") for m in NOT_PUBLIC)
    }
    assert "dispgns.render" in public and "dispgns.training.step" in public
    assert sorted(public - set(MODULES)) == []
    assert sorted(set(MODULES) - found) == []


def test_the_walk_finds_the_public_api():
    # A walk that found nothing would pass every test below.
    labels = {label for label, _ in FUNCTIONS}
    assert len(FUNCTIONS) > 100 and len(CLASSES) > 15
    for name in (
        "dispgns.simulator.rollout_scan",
        "dispgns.physics.integrate.simulate_scan",
        "dispgns.metrics.rollout_metrics",
        "dispgns.training.step.train_step",
        "dispgns.training.batches.BatchStream.make_batch",
    ):
        assert name in labels
    assert _problems(np.ndarray) == ["bare np.ndarray"]
    assert _problems(jaxtyping.ArrayLike) == ["bare jax.Array", "bare np.ndarray"]
    assert _problems(tuple[jax.Array, typing.Any] | None) == ["bare jax.Array"]
    assert _problems(typing.Any | None) == ["Any"] and _problems(dict[str, typing.Any]) == []
    assert _problems(jaxtyping.Float[jaxtyping.ArrayLike, "N D"] | None) == []
    assert _problems(jaxtyping.PyTree[jaxtyping.Float[jaxtyping.Array, "..."]]) == []


@pytest.mark.parametrize("label, function", FUNCTIONS, ids=[label for label, _ in FUNCTIONS])
def test_public_function_annotations_resolve_and_give_array_shapes(label, function):
    hints = _hints(function)
    signature = inspect.signature(function)
    problems = []
    for name, parameter in signature.parameters.items():
        if name in ("self", "cls") or parameter.kind in (parameter.VAR_POSITIONAL, parameter.VAR_KEYWORD):
            continue
        if name not in hints:
            problems.append(f"parameter {name!r} is not annotated")
            continue
        problems += [f"parameter {name!r}: {p}" for p in _problems(hints[name]) if (label, name) not in ANY_ALLOWED]
    if function.__name__ != "__init__":
        if "return" not in hints:
            problems.append("the return is not annotated")
        else:
            problems += [f"return: {p}" for p in _problems(hints["return"]) if (label, "return") not in ANY_ALLOWED]
    assert not problems, f"{label}: " + "; ".join(problems)


@pytest.mark.parametrize("label, cls", CLASSES, ids=[label for label, _ in CLASSES])
def test_public_class_fields_resolve_and_give_array_shapes(label, cls):
    hints = _hints(cls)
    problems = []
    for name in _fields(cls):
        if name not in hints:
            problems.append(f"field {name!r} is not annotated")
            continue
        problems += [f"field {name!r}: {p}" for p in _problems(hints[name]) if (label, name) not in ANY_ALLOWED]
    assert not problems, f"{label}: " + "; ".join(problems)


def test_the_checks_fail_on_a_bare_array():
    def bad(position: np.ndarray, radius) -> jax.Array:
        return position

    with pytest.raises(AssertionError, match=r"parameter 'position': bare np\.ndarray; parameter 'radius' is not"):
        test_public_function_annotations_resolve_and_give_array_shapes("bad", bad)

    def unresolved(position: "NoSuchType") -> None:  # noqa: F821
        return None

    with pytest.raises(AssertionError, match="annotations do not resolve"):
        test_public_function_annotations_resolve_and_give_array_shapes("unresolved", unresolved)
