"""`study_loss` on the exact kernel in fixed-width sample blocks, accumulating only the loss's metric.

Oracles: (1) `run_study`'s exact engine (the forward path, itself checked against
`fojax.simulate` and an independent SciPy recurrence in ``test_study_exact.py``): the
loss equals the mean over samples of its per-sample IAE / ISE; (2) central finite
differences of the same loss (ISE: smooth, so a sharp oracle); (3) the same loss and
gradient computed in one block (no `jax.lax.map`). The exact kernel's adjoint has no
plant part: differentiating with respect to the study is refused, not answered with zeros.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import fojax
from fojax import studies as S

# private: the exact study kernel is tested itself
from fojax.studies import _exact
from tests.helpers import small_step_input_study


@pytest.fixture(scope="module")
def case():
    # 3 δ × 2 faults = 6 samples; blocks of 4 below: one full block and one padded with 2 copies
    study, d = small_step_input_study(5, 3, 2)
    res = S.run_study(study, (d.observer,), stepper=fojax.Exact(), quantiles=(), quiet=True, devices=jax.devices()[:1])
    assert res.attrs["engine"] == "exact-batch"
    return study, d.observer, res


def _value_and_grad(study, observer, loss):
    dyn, st = eqx.partition(observer, eqx.is_inexact_array)
    f = eqx.filter_jit(eqx.filter_value_and_grad(lambda p: S.study_loss(study, eqx.combine(p, st), loss=loss)))
    return f, dyn


def test_blocked_iae_equals_run_study_and_one_block(case, monkeypatch):
    study, observer, res = case
    want = float(np.mean(np.asarray(res.metrics["iae"])[0]))  # mean over δ, faults and signals
    monkeypatch.setattr(_exact, "DIFF_BLOCK", 4)  # 6 samples: two blocks, the second padded
    f, dyn = _value_and_grad(study, observer, "iae")
    v, g = f(dyn)
    assert abs(float(v) - want) <= 1e-10 * abs(want), (float(v), want)
    monkeypatch.setattr(_exact, "DIFF_BLOCK", 8)  # one block of 6 (padded to 8) ...
    f1, _ = _value_and_grad(study, observer, "iae")
    v1, g1 = f1(dyn)
    assert abs(float(v1) - want) <= 1e-10 * abs(want)
    # ... gives the same gradient: the padded copies carry no cotangent
    for a, b in zip(jax.tree.leaves(g), jax.tree.leaves(g1)):
        np.testing.assert_allclose(a, b, rtol=1e-10, atol=1e-13 * float(jnp.max(jnp.abs(b))))


def test_blocked_ise_equals_run_study_and_its_gradient_central_differences(case, monkeypatch):
    study, observer, res = case
    want = float(np.mean(np.asarray(res.metrics["ise"])[0]))
    monkeypatch.setattr(_exact, "DIFF_BLOCK", 4)
    f, dyn = _value_and_grad(study, observer, "ise")
    v, g = f(dyn)
    assert abs(float(v) - want) <= 1e-10 * abs(want), (float(v), want)
    leaves, tree = jax.tree.flatten(dyn)
    gl = jax.tree.leaves(g)
    k = int(np.argmax([float(jnp.max(jnp.abs(x))) for x in gl]))  # the leaf with the largest entry
    idx = np.unravel_index(int(jnp.argmax(jnp.abs(gl[k]))), gl[k].shape)
    eps = 1e-6

    def at(s):
        moved = [x.at[idx].add(s) if i == k else x for i, x in enumerate(leaves)]
        return float(f(jax.tree.unflatten(tree, moved))[0])

    fd = (at(eps) - at(-eps)) / (2 * eps)
    assert abs(float(gl[k][idx]) - fd) <= 1e-6 * abs(fd), (float(gl[k][idx]), fd)


def test_gradient_with_respect_to_the_study_is_refused(case):
    # the plant trajectory is a constant of the split adjoint; a derivative through it
    # (here: the grid, which sets the plant's Φ_pp = e^{A_p h}) must raise, not be dropped
    study, observer, _ = case

    def loss(c):
        return S.study_loss(eqx.tree_at(lambda s: s.ts, study, c * study.ts), observer)

    with pytest.raises(fojax.errors.InputError, match="differentiates the observers only"):
        jax.jit(jax.grad(loss))(1.0)  # raised while tracing the reverse pass: nothing compiles
