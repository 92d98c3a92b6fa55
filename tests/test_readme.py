"""The README's Python example runs as printed and does what its comments say."""

import pathlib
import re

import numpy as np


README = pathlib.Path(__file__).resolve().parents[1] / "README.md"


def test_readme_python_example_runs_and_the_estimate_converges(capsys):
    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.S)
    assert blocks, "no ```python block in README.md"
    code = blocks[0]
    assert len([ln for ln in code.splitlines() if ln.strip()]) <= 10  # "a ten-line example"
    ns: dict = {}
    exec(compile(code, str(README), "exec"), ns)
    out = capsys.readouterr().out
    assert "verification PASSED" in out and "regular" in out
    design, sol, ex = ns["design"], ns["sol"], ns["ex"]
    assert design.report.passed
    # the estimate of z = L x converges: error at t = 10 below 1e-6 of its initial size
    err = np.abs(np.asarray(sol.estimates[0]) - np.asarray(sol.xs) @ np.asarray(ex.L).T)
    assert err[0].max() > 1e-2 and err[-1].max() < 1e-6 * err[0].max()
