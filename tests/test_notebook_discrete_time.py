"""notebooks/discrete_time.ipynb executes top to bottom (nbclient) and shows what it claims.

Oracles: the notebook's own printed checks — eig(N_d) against exp(λh) computed by NumPy,
the float64 verification reports, and the estimation error against z = Lx on the samples.
"""

from helpers import execute_notebook


def test_discrete_time_notebook_executes():
    text = execute_notebook("discrete_time.ipynb", timeout=300).text
    assert "discrete-time (dt = 0.05)" in text and "causal            yes" in text
    assert text.count("verification PASSED") == 2  # the continuous and the discrete-time design
    gap = float(text.split("max |eig(N_d) - exp(λh)| = ")[1].split()[0])
    assert gap < 1e-8
    assert "RegionError: the region disk centred at -2" in text
    errs = {}
    for line in text.splitlines():
        if line.startswith(("discretized continuous design:", "discrete-time design:")):
            errs[line.split(":")[0]] = (float(line.split("t = 0: ")[1].split(",")[0]), float(line.rsplit(" ", 1)[-1]))
    e0, e1 = errs["discrete-time design"]
    assert e0 > 0.1 and e1 < 1e-9  # exact on the samples
    e0, e1 = errs["discretized continuous design"]
    assert e1 < 0.02 * e0  # converges up to an O(h) offset
