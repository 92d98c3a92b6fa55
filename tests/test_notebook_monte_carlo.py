"""notebooks/monte_carlo_and_tuning.ipynb executes top to bottom (nbclient) and prints its
Monte Carlo table.

Oracle: the table the notebook prints (1024 samples, mean ± std of IAE and ISE for each observer,
the tuned one included); the numbers themselves are checked against SciPy by the study modules.
"""

import pytest
from helpers import execute_notebook


@pytest.mark.filterwarnings("ignore::DeprecationWarning")
def test_notebook_executes_and_prints_the_table():
    out = execute_notebook("monte_carlo_and_tuning.ipynb").text
    assert "1024 samples, mean ± std" in out
    for label in ("proportional", "PI", "generalized", "tuned generalized"):
        assert label in out
    assert "IAE" in out and "ISE" in out
