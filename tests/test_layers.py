"""The package's import graph follows the layers written in CONTRIBUTING.md, and every module has ``__all__``."""

import ast
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SRC = ROOT / "src"


def layers() -> list[tuple[str, list[str]]]:
    """``(layer, [module prefixes])`` in order, from the table under "## Layers" in CONTRIBUTING.md."""
    text = (ROOT / "CONTRIBUTING.md").read_text()
    section = text.split("## Layers", 1)[1].split("\n## ", 1)[0]
    rows = []
    for line in section.splitlines():
        cells = [cell.strip() for cell in line.strip().strip("|").split("|")]
        if len(cells) >= 2 and cells[1].startswith("`dispgns"):
            rows.append((cells[0], re.findall(r"`(dispgns[\w.]*)`", cells[1])))
    return rows


def module_name(path: Path) -> str:
    parts = path.relative_to(SRC).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imports(path: Path) -> set[str]:
    """Every dispgns module ``path`` imports (``from dispgns import x`` counts as ``dispgns.x``)."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found |= {alias.name for alias in node.names if alias.name.startswith("dispgns")}
        elif isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("dispgns"):
            if node.module == "dispgns":
                found |= {f"dispgns.{alias.name}" for alias in node.names}
            else:
                found.add(node.module)
    return found


def layer_of(module: str, table) -> int | None:
    best = None
    for rank, (_, prefixes) in enumerate(table):
        for prefix in prefixes:
            if module == prefix or module.startswith(prefix + "."):
                if best is None or len(prefix) > best[1]:
                    best = (rank, len(prefix))
    return None if best is None else best[0]


def test_the_table_is_read():
    table = layers()
    names = [name for name, _ in table]
    assert names[:2] == ["base", "physics"] and names[-1] == "cli" and len(names) >= 10


def test_every_import_goes_to_the_same_or_an_earlier_layer():
    table = layers()
    wrong = []
    for path in sorted((SRC / "dispgns").rglob("*.py")):
        module = module_name(path)
        if module == "dispgns":
            continue  # the lazy re-exporting facade
        rank = layer_of(module, table)
        assert rank is not None, f"{module} is in no layer of CONTRIBUTING.md"
        for target in imports(path):
            if target in ("dispgns", "dispgns.__version__"):
                continue
            target_rank = layer_of(target, table)
            assert target_rank is not None, f"{module} imports {target}, which is in no layer"
            if target_rank > rank:
                wrong.append(f"{module} ({table[rank][0]}) imports {target} ({table[target_rank][0]})")
    assert not wrong, "\n".join(wrong)


def test_the_check_would_catch_an_upward_import(tmp_path):
    table = layers()
    assert layer_of("dispgns.physics.integrate", table) < layer_of("dispgns.graph", table)
    assert layer_of("dispgns.metrics", table) < layer_of("dispgns.simulator", table)
    assert layer_of("dispgns.kernels", table) == layer_of("dispgns.model", table)
    fake = tmp_path / "fake.py"
    fake.write_text("from dispgns import simulator\nimport dispgns.training.loop\n")
    assert imports(fake) == {"dispgns.simulator", "dispgns.training.loop"}


def test_every_module_declares_its_public_names():
    for path in sorted((SRC / "dispgns").rglob("*.py")):
        if path.name in ("__main__.py",) or "cli" in path.relative_to(SRC).parts:
            continue
        tree = ast.parse(path.read_text())
        names = {
            target.id
            for node in tree.body
            if isinstance(node, ast.Assign)
            for target in node.targets
            if isinstance(target, ast.Name)
        }
        assert "__all__" in names, f"{module_name(path)} has no __all__"
