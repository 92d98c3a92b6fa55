"""notebooks/interop.ipynb executes top to bottom (nbclient) and shows what it claims.

Oracles inside the notebook: SciPy's `lsim` (the recorded log), python-control's
`forced_response` of the exported observer, `scipy.io.loadmat` of the written file."""

from helpers import execute_notebook


def test_interop_notebook_executes():
    run = execute_notebook("interop.ipynb", timeout=300)
    nb, text = run.nb, run.text
    assert len(nb.cells) < 30
    assert "verification PASSED" in text
    assert "poles in the disk: True" in text
    line = next(ln for ln in text.splitlines() if ln.startswith("relative difference to control.forced_response"))
    assert float(line.rsplit(" ", 1)[-1]) < 1e-4
    line = next(ln for ln in text.splitlines() if ln.startswith("|z_hat - L x|"))
    e0, e8 = (float(part.rsplit(" ", 1)[-1]) for part in line.split(","))
    assert e8 < 1e-3 * e0
    assert "same model: True same L: True" in text
    assert "batch of estimates: (16, 801, 1)" in text
