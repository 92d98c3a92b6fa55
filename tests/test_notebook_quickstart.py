"""notebooks/quickstart.ipynb executes top to bottom (nbclient) and shows what it claims.

Oracles: the notebook's printed verification reports (design conditions in float64), the
estimation errors it prints (below 1 % of the initial error at t = 6), the bit-identical
reload of a saved design, and the held-out IAE before and after tuning.
"""

from helpers import execute_notebook


def test_quickstart_executes():
    run = execute_notebook("quickstart.ipynb", timeout=300)
    nb, text = run.nb, run.text
    assert len(nb.cells) < 30
    assert "Assumption 1 yes" in text
    assert text.count("verification PASSED") == 3  # PO, FGDO and the tuned FGDO
    assert "bit-identical N, X: True True" in text
    # both observers converge: the error at t = 6 is below 1 % of the error at t = 0
    for name in ("PO", "FGDO"):
        line = next(ln for ln in text.splitlines() if ln.startswith(f"{name}: max |error|"))
        e0 = float(line.split("t = 0: ")[1].split(",")[0])
        e6 = float(line.rsplit(" ", 1)[-1])
        assert e0 > 0.1 and e6 < 0.01 * e0
    # the Monte Carlo study ran for both observers, and tuning lowered the held-out IAE
    assert "PO    IAE mean ± std over 32 samples" in text and "FGDO  IAE mean ± std over 32 samples" in text
    line = text[text.index("held-out mean IAE"):].splitlines()[0]
    before, after = float(line.split("LMI ")[1].split()[0]), float(line.split("tuned ")[1].split()[0])
    assert after < before
    # the figure was produced
    assert run.figures >= 1
