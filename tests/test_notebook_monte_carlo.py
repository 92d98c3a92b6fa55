"""Execute notebooks/monte_carlo_and_tuning.ipynb and check that it prints the Monte Carlo table."""

import pytest
from helpers import execute_notebook


@pytest.mark.filterwarnings("ignore::DeprecationWarning")
def test_notebook_executes_and_prints_the_table():
    out = execute_notebook("monte_carlo_and_tuning.ipynb").text
    assert "1024 samples, mean ± std" in out
    for label in ("proportional", "PI", "generalized", "tuned generalized"):
        assert label in out
    assert "IAE" in out and "ISE" in out
