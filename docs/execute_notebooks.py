"""Execute the notebooks and store them with their outputs (what the documentation shows).

The documentation site renders ``notebooks/*.ipynb`` as stored, with their outputs and
figures; it does not execute them (`mkdocs.yml`: ``execute: false``). CI executes every
notebook once, in ``tests/test_notebook_*.py``, and checks what it prints. After changing
a notebook, or fojax in a way that changes a notebook's output, refresh the stored
outputs with

    python docs/execute_notebooks.py                          # every notebook
    python docs/execute_notebooks.py notebooks/quickstart.ipynb

`tests/test_docs.py` fails while a notebook is stored without outputs.
"""

from __future__ import annotations

import pathlib
import sys

import nbclient
import nbformat
from nbconvert.preprocessors import CoalesceStreamsPreprocessor


ROOT = pathlib.Path(__file__).resolve().parents[1]


def tidy(nb: nbformat.NotebookNode) -> nbformat.NotebookNode:
    """Merge consecutive stream outputs (progress bars' carriage returns resolved) and drop
    the per-cell execution timestamps, so that a re-run changes only what changed."""
    nb, _ = CoalesceStreamsPreprocessor().preprocess(nb, {})
    for cell in nb.cells:
        cell.metadata.pop("execution", None)
    return nb


def execute(path: pathlib.Path, timeout: int = 1800) -> None:
    nb = nbformat.read(path, as_version=4)
    nbclient.NotebookClient(nb, timeout=timeout, kernel_name="python3",
                            resources={"metadata": {"path": str(path.parent)}}).execute()
    nbformat.write(tidy(nb), path)


def main(argv: list[str]) -> None:
    paths = [pathlib.Path(a) for a in argv] or sorted((ROOT / "notebooks").glob("*.ipynb"))
    for path in paths:
        print(f"executing {path} ...", flush=True)
        execute(path)


if __name__ == "__main__":
    main(sys.argv[1:])
