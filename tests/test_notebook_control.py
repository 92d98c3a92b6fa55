"""notebooks/control_and_ftc.ipynb executes top to bottom and prints what Chapter 4 claims.

Oracles: the thesis's Chapter 4 figures and printed numbers, read from what the notebook prints.

The notebook is executed once per module, in a fixture (nbclient, kernel ``python3``); the
tests read the numbers it prints. (It used to run at import: pytest-xdist imports every
test module in every worker to collect it, so each CI run executed it twice, untimed.)
"""

import re

import pytest
from helpers import execute_notebook, ExecutedNotebook


@pytest.fixture(scope="module")
def executed() -> ExecutedNotebook:
    return execute_notebook("control_and_ftc.ipynb")


def number(output: str, pattern: str) -> float:
    m = re.search(pattern, output)
    assert m, f"{pattern!r} not in the notebook output"
    return float(m.group(1))


def test_runs_and_draws_the_figures(executed):
    nb, figures = executed.nb, executed.figures
    assert not executed.errors
    assert figures >= 6
    for fig in (
        "4.2",
        "4.3",
        "4.5",
        "4.6",
        "4.7",
        "4.8",
        "4.10",
        "4.11",
        "4.12",
        "4.13",
        "4.14",
        "4.15",
    ):
        assert f"Fig. {fig} " in "".join(c.source for c in nb.cells)


def test_separation_and_printed_poles(executed):
    output = executed.text
    gaps = [float(g) for g in re.findall(r"separation gap ([0-9.e+-]+)", output)]
    assert len(gaps) == 2 and max(gaps) < 1e-8
    assert "printed gains, loop poles:    [-39.781, -4.477, -2.211, -2.000, -2.000" in output


def test_fault_tolerance_numbers(executed):
    output = executed.text
    assert number(output, r"FTC: max\|x\| on \[13, 15\] s = ([0-9.e+-]+)") < 1e-4
    assert number(output, r"not FT = ([0-9.e+-]+)") > 0.05
    assert number(output, r"fojax  : max ‖x − x_d‖ on \[11, 15\] s = ([0-9.e+-]+)") <= 1e-3
    assert number(output, r"fojax  : f̂\(15\) − f = .*?\|x\(15\)\| = ([0-9.e+-]+)") < 1e-6
    assert number(output, r"max \|ẑ − Lx\| for t ≥ h: ([0-9.e+-]+)") < 1e-8
