"""The step rule of `fojax.tuning.tune` (`fojax.tuning._loop.backtracked_update`, on the host) at the region's boundary.

Oracle: closed forms. The admissible set is the unit disk of the parameters,
``margin(θ) = 1 − ‖θ‖²`` (gradient ``−2θ``), so which halving of an update stays inside, and
what the update without its outward component is, follow by hand.

Regression (issue 14): at an iterate on the boundary whose update points outside, every halving
of the update is outside, the step was rejected and the next update pointed the same way — the
iterate stopped moving (the LC filter tuned with ``barrier=0``: 79 of 100 steps rejected). Now
the halvings of the tangential update are tried when no halving of the update is admissible.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from fojax.tuning._loop import backtracked_update  # private: the step rule is tested itself


MIN_MARGIN = 1e-6
N_BACK = 8


def margin(theta):
    return 1.0 - jnp.sum(theta["a"] ** 2) - jnp.sum(theta["b"] ** 2)


margin_host = jax.jit(margin)
CALLS = {"margin": 0, "grad": 0}


def counted_margin(theta):
    CALLS["margin"] += 1
    return float(margin_host(theta))


def counted_grad(theta):
    CALLS["grad"] += 1
    return jax.grad(margin)(theta)


def step(p, u):
    CALLS.update(margin=0, grad=0)
    return backtracked_update(p, u, counted_margin, MIN_MARGIN, N_BACK, counted_grad)


def at_boundary(m0=1e-5):
    """θ on the a-axis with margin m0 (a = √(1 − m0)); parameters as a pytree of two leaves."""
    return {"a": jnp.array([np.sqrt(1.0 - m0), 0.0]), "b": jnp.array([0.0])}


def test_regression_outward_update_at_the_boundary_slides_along_it():
    p = at_boundary()
    u = {"a": jnp.array([0.1, 0.1]), "b": jnp.array([0.05])}  # outward (first entry) and tangential
    # every halving of u is outside: 1e-5 − 0.2·s·a − 0.0125·s² < 0 for s ≥ 2^-8 (closed form)
    s = 0.5 ** np.arange(N_BACK + 1)
    a0 = float(p["a"][0])
    assert np.all(1e-5 - 2 * 0.1 * s * a0 - (0.01 + 0.01 + 0.0025) * s**2 <= MIN_MARGIN)
    new, m, accepted, backtracks = step(p, u)
    assert bool(accepted)  # failed before the fix (rejected, parameters unchanged)
    # the tangential update removes u's component along g = −2θ = (−2a, 0; 0): u_t = (0, 0.1; 0.05);
    # its halvings: margin 1e-5 − 0.0125 s² > 1e-6 first at s = 2^-6 (closed form)
    expected_s = next(sc for sc in s if 1e-5 - 0.0125 * sc**2 > MIN_MARGIN)
    assert expected_s == 0.5**6
    np.testing.assert_allclose(np.asarray(new["a"]), [a0, 0.1 * expected_s], rtol=0, atol=1e-15)
    np.testing.assert_allclose(np.asarray(new["b"]), [0.05 * expected_s], rtol=0, atol=1e-15)
    np.testing.assert_allclose(float(m), 1e-5 - 0.0125 * expected_s**2, rtol=1e-9)
    assert int(backtracks) == N_BACK + 1 + 6
    assert float(margin(new)) > MIN_MARGIN
    # every halving of u, then those of u_t up to the first admissible; one gradient
    assert CALLS == {"margin": N_BACK + 1 + 7, "grad": 1}


@pytest.mark.parametrize("outward", [False, True])
def test_an_admissible_halving_of_the_update_is_taken_unchanged(outward):
    """Away from the boundary the rule is the old one: the first admissible halving of u itself."""
    p = {"a": jnp.array([0.5, 0.0]), "b": jnp.array([0.0])}
    # an inward update (scale 1 admissible), and an outward one whose first admissible halving is
    # 2^-4: margin(0.5 + 4s) = 0.75 − 4s − 16 s² is 0 at s = 1/8 and 0.4375 at s = 1/16 (closed form)
    u = ({"a": jnp.array([4.0, 0.0]), "b": jnp.array([0.0])} if outward
         else {"a": jnp.array([-0.2, 0.1]), "b": jnp.array([0.1])})
    s = 0.5 ** np.arange(N_BACK + 1)
    ms = [float(margin(jax.tree.map(lambda x, d: x + sc * d, p, u))) for sc in s]
    first = next(i for i, v in enumerate(ms) if v > MIN_MARGIN)
    assert first == (4 if outward else 0)
    new, m, accepted, backtracks = step(p, u)
    assert bool(accepted) and int(backtracks) == first
    for k in ("a", "b"):
        np.testing.assert_allclose(np.asarray(new[k]), np.asarray(p[k] + s[first] * u[k]), rtol=0, atol=1e-15)
    np.testing.assert_allclose(float(m), ms[first], rtol=1e-12)
    # evaluated in turn up to the first admissible candidate; no gradient needed
    assert CALLS == {"margin": first + 1, "grad": 0}


def test_no_admissible_candidate_keeps_the_parameters():
    """An update straight outward has no tangential part: the step is rejected, θ unchanged."""
    p = at_boundary()
    u = {"a": jnp.array([0.1, 0.0]), "b": jnp.array([0.0])}
    new, m, accepted, _ = step(p, u)
    assert not bool(accepted)
    for k in ("a", "b"):
        np.testing.assert_array_equal(np.asarray(new[k]), np.asarray(p[k]))
    assert float(m) < 0  # the full step's margin
