"""notebooks/interop.ipynb executes top to bottom (nbclient) and shows what it claims.

Oracles inside the notebook: SciPy's `lsim` (the recorded log), python-control's
`forced_response` of the exported observer, `scipy.io.loadmat` of the written file."""

import pathlib

import nbformat
from nbclient import NotebookClient


NOTEBOOK = pathlib.Path(__file__).resolve().parents[1] / "notebooks" / "interop.ipynb"


def _text(cell) -> str:
    out = []
    for o in cell.get("outputs", []):
        if o.get("output_type") == "stream":
            out.append(o["text"])
        elif "data" in o and "text/plain" in o["data"]:
            out.append(o["data"]["text/plain"])
    return "".join(out)


def test_interop_notebook_executes():
    nb = nbformat.read(NOTEBOOK, as_version=4)
    assert len(nb.cells) < 30
    client = NotebookClient(
        nb, timeout=300, kernel_name="python3", resources={"metadata": {"path": str(NOTEBOOK.parent)}}
    )
    client.execute()
    text = "\n".join(_text(c) for c in nb.cells if c.cell_type == "code")
    assert "verification PASSED" in text
    assert "poles in the disk: True" in text
    line = next(ln for ln in text.splitlines() if ln.startswith("relative difference to control.forced_response"))
    assert float(line.rsplit(" ", 1)[-1]) < 1e-4
    line = next(ln for ln in text.splitlines() if ln.startswith("|z_hat - L x|"))
    e0, e8 = (float(part.rsplit(" ", 1)[-1]) for part in line.split(","))
    assert e8 < 1e-3 * e0
    assert "same model: True same L: True" in text
    assert "batch of estimates: (16, 801, 1)" in text
