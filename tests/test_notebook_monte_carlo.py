"""Execute notebooks/monte_carlo_and_tuning.ipynb and check that it prints the Monte Carlo table."""

import pathlib

import nbformat
import pytest
from nbclient import NotebookClient


NOTEBOOK = pathlib.Path(__file__).parent.parent / "notebooks" / "monte_carlo_and_tuning.ipynb"


@pytest.mark.filterwarnings("ignore::DeprecationWarning")
def test_notebook_executes_and_prints_the_table():
    nb = nbformat.read(NOTEBOOK, as_version=4)
    NotebookClient(nb, timeout=600, kernel_name="python3", resources={"metadata": {"path": str(NOTEBOOK.parent)}}).execute()
    out = "".join(
        o.get("text", "") for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", [])
    )
    assert "1024 samples, mean ± std" in out
    for label in ("proportional", "PI", "generalized", "tuned generalized"):
        assert label in out
    assert "IAE" in out and "ISE" in out
