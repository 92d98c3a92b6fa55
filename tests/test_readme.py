"""The README's Python example runs as printed and does what its comments say.

Oracles: the estimate's convergence inside the design's disk (the error decays like
exp(-t) or faster), and central finite differences of the example's own loss for the
gradient it prints.
"""

import pathlib
import re

import numpy as np


README = pathlib.Path(__file__).resolve().parents[1] / "README.md"


def test_readme_is_short_and_its_example_comes_early():
    text = README.read_text()
    lines = text.splitlines()
    assert len(lines) <= 150
    first = next(i for i, ln in enumerate(lines, 1) if ln.startswith("```python"))
    assert first + 1 <= 60  # the example's first line


def test_readme_python_example_runs_and_the_estimate_converges(capsys):
    import equinox as eqx
    import jax.numpy as jnp

    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.S)
    assert blocks, "no ```python block in README.md"
    code = blocks[0]
    assert len([ln for ln in code.splitlines() if ln.strip()]) <= 15  # "a 15-line example"
    ns: dict = {}
    exec(compile(code, str(README), "exec"), ns)
    out = capsys.readouterr().out
    assert "verification PASSED" in out and "regular" in out
    design, sol, ex = ns["design"], ns["sol"], ns["ex"]
    assert design.report.passed
    # the estimate of z = L x converges: error at t = 10 below 1e-6 of its initial size
    err = np.abs(np.asarray(sol.estimates[0]) - np.asarray(sol.xs) @ np.asarray(ex.L).T)
    assert err[0].max() > 1e-2 and err[-1].max() < 1e-6 * err[0].max()
    # the gradient it computes is the derivative of its loss: a directional derivative along
    # a random direction of N against central differences
    loss, grads, obs = ns["mean_square_error"], ns["grads"], design.observer
    V = np.random.default_rng(0).standard_normal(np.shape(obs.N))
    h = 1e-6

    def at(t):
        return float(loss(eqx.tree_at(lambda o: o.N, obs, jnp.asarray(obs.N) + t * V)))

    fd = (at(h) - at(-h)) / (2 * h)
    ad = float(np.sum(np.asarray(grads.N) * V))
    assert abs(ad - fd) <= 1e-5 * max(1.0, abs(fd)), (ad, fd)
