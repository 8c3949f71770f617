"""Execute the notebooks in place so that the committed copies show their outputs.

    python notebooks/execute.py                 # both notebooks, full settings
    python notebooks/execute.py quickstart.ipynb

CI runs the same notebooks with small settings (``tests/test_notebooks.py``) and keeps no output.
Each notebook is executed in a temporary directory (its files stay out of the repository) and written
back atomically.
"""

from __future__ import annotations

import os
import sys
import tempfile
from pathlib import Path

import nbformat
from nbclient import NotebookClient

HERE = Path(__file__).parent


def execute(path: Path) -> None:
    notebook = nbformat.read(path, as_version=4)
    with tempfile.TemporaryDirectory() as workdir:
        client = NotebookClient(
            notebook, timeout=1800, kernel_name="python3", resources={"metadata": {"path": workdir}}
        )
        client.execute()
    temporary = path.with_name(path.name + ".tmp")
    nbformat.write(notebook, temporary)
    os.replace(temporary, path)
    print(f"executed {path}")


def main(names: list[str]) -> int:
    for name in names or ["quickstart.ipynb", "jax_api.ipynb"]:
        execute(HERE / name)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
