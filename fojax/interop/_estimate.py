r"""Run a designed observer on recorded samples of ``u`` and ``y``.

Between two samples $t_k < t_{k+1}$ (step $h_k$) the signal $v = [u; y]$ is taken as

- ``interpolation="linear"`` (default, first-order hold): the straight line through
  $v_k$ and $v_{k+1}$;
- ``interpolation="zoh"`` (zero-order hold): the constant $v_k$.

For that signal the observer $\dot\xi = A_o\xi + B_o v$, $\hat z = C_o\xi + D_o v$
(`fojax.observer.AbstractObserver.linear_matrices`, $B_o = [B_u\;B_y]$, $D_o = [D_u\;D_y]$) is
stepped exactly:

$$\xi_{k+1} = e^{A_o h_k}\xi_k + \int_0^{h_k} e^{A_o(h_k - s)} B_o\, v(t_k + s)\,\mathrm ds,$$

the integral from one matrix exponential of the Van Loan matrix (the simulation
layer's `discretize`, exact for polynomial inputs: degree 1 here, so with linear
interpolation the step is the exact first-order-hold discretisation, the rule
python-control's `forced_response` and `scipy.signal.lsim` use). The estimate is
$\hat z_k = C_o\xi_k + D_o v_k$ at every sample time.

A discrete-time observer (``dt`` $= h$ set, e.g. from `fojax.discretize` or a design on
a discrete-time plant) is its own recursion $\xi_{k+1} = A_o\xi_k + B_o v_k$ on samples
$h$ apart; there is nothing to interpolate, and ``ts`` must have that spacing.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._dtype import as_float_array
from .._errors import InputError, ShapeError


INTERPOLATIONS = ("linear", "zoh")


def _observer(obj):
    from ..observer import AbstractObserver

    obs = obj if isinstance(obj, AbstractObserver) else getattr(obj, "observer", None)
    if not isinstance(obs, AbstractObserver):
        raise InputError(f"estimate needs a fojax observer or a design result; got {type(obj).__name__}.")
    lm = obs.linear_matrices()
    if lm is None:
        hint = " Run one rule (observer.rule(i)) or fojax.simulate with the plant." if hasattr(obs, "rule") else ""
        raise InputError(f"estimate runs linear time-invariant observers; {type(obs).__name__} has no "
                         f"linear_matrices().{hint}")
    return obs, lm


def _samples(name: str, x, T: int, width: int):
    x = as_float_array(name, x)
    if x.ndim == 1 and width == 1:
        x = x[:, None]
    if x.ndim != 2 or x.shape[0] != T or x.shape[1] != width:
        raise ShapeError(name, (T, width), tuple(x.shape),
                         f"{name} needs one row per sample time (len(ts) = {T}) and {width} column(s).")
    return x


def _is_concrete(*xs) -> bool:
    return not any(isinstance(x, jax.core.Tracer) for x in xs)


def estimate(observer, ts, u, y, *, xi0=None, interpolation: str = "linear"):
    r"""Run a linear observer on recorded samples $(t_k, u_k, y_k)$; returns $\hat z(t_k)$.

    See the module docstring for the interpolation between samples and the exact
    stepping. Traceable: ``jax.jit``, ``jax.vmap`` over a batch of records (same
    length) and ``jax.grad`` with respect to the data, the times and the observer's
    matrices.

    **Arguments:**

    - `observer`: a linear observer (generalized, proportional, PI, unknown-input; the
      running estimate of a finite-time observer) or a design result (its observer).
      Designed for a plant with feedthrough, it already takes the measured ``y = Cx + Du``.
    - `ts`: ``(T,)`` strictly increasing sample times, ``T ≥ 2`` (any spacing).
    - `u`: ``(T, m)`` input samples (``(T,)`` when ``m = 1``; ``None`` when ``m = 0``).
    - `y`: ``(T, p)`` measured output samples (``(T,)`` when ``p = 1``).
    - `xi0`: the observer's state at ``ts[0]`` (default `observer.initial_state()`, zero).
    - `interpolation`: ``"linear"`` (first-order hold, default) or ``"zoh"``; unused for
      a discrete-time observer (its samples must be ``dt`` apart).

    **Returns:** ``(T, q)`` estimates $\hat z(t_k)$.

    **Raises:** `fojax.errors.ShapeError` (lengths or widths that do not match ``ts`` and the
    observer), `fojax.errors.NonFiniteError` (NaN or infinite samples), `fojax.errors.InputError`
    (times not strictly increasing, fewer than two samples, a nonlinear observer, an
    unknown interpolation). With traced data (under ``jit``/``vmap``) the value checks
    run inside XLA as `equinox` runtime errors with the same messages.

    !!! example

        ```python
        design = fojax.design_functional_observer(plant, L)
        z_hat = fojax.estimate(design, ts, u_log, y_log)           # (T, q)
        batch = jax.vmap(fojax.estimate, in_axes=(None, None, 0, 0))(design.observer, ts, U, Y)
        ```
    """
    obs, lm = _observer(observer)
    if interpolation not in INTERPOLATIONS:
        raise InputError(f"interpolation must be one of {INTERPOLATIONS}; got {interpolation!r}.")
    ts = as_float_array("ts", ts, ndim=1)
    T = ts.shape[0]
    if T < 2:
        raise InputError(f"estimate needs at least two samples; ts has {T}.")
    m, p = lm.Bu.shape[1], lm.By.shape[1]
    u = jnp.zeros((T, 0)) if u is None and m == 0 else _samples("u", u, T, m)
    y = _samples("y", y, T, p)
    xi = obs.initial_state() if xi0 is None else as_float_array("xi0", xi0, ndim=1)
    if xi.shape != (obs.state_size,):
        raise ShapeError("xi0", (obs.state_size,), tuple(xi.shape), "One entry per observer state.")
    h = jnp.diff(ts)
    dt = getattr(obs, "dt", None)
    if dt is not None:
        return _run_discrete(lm, ts, h, u, y, xi, dt)
    if _is_concrete(ts, u, y):  # (NaNs in concrete data were refused by as_float_array)
        hs = np.asarray(h)
        if (hs <= 0).any():
            k = int(np.argwhere(hs <= 0)[0][0])
            raise InputError(f"ts must be strictly increasing; ts[{k + 1}] = {float(ts[k + 1])!r} follows "
                             f"ts[{k}] = {float(ts[k])!r}. Sort the record and drop repeated times.")
    else:
        ok = jnp.all(jnp.isfinite(ts)) & jnp.all(jnp.isfinite(u)) & jnp.all(jnp.isfinite(y))
        ts = eqx.error_if(ts, ~ok, "estimate: ts, u or y has a NaN or infinite entry")
        ts = eqx.error_if(ts, jnp.any(h <= 0), "estimate: ts must be strictly increasing")
        h = jnp.diff(ts)
    return _run(lm, ts, h, u, y, xi, interpolation)


def _run_discrete(lm, ts, h, u, y, xi0, dt: float):
    """The recursion of a discrete-time observer on samples ``dt`` apart."""
    tol = 1e-9 * max(1.0, dt)
    if _is_concrete(ts):
        off = np.abs(np.asarray(h) - dt)
        if (off > tol).any():
            k = int(np.argmax(off > tol))
            raise InputError(f"the observer is discrete-time with dt = {dt:g}, so the samples must be dt apart; "
                             f"ts[{k + 1}] - ts[{k}] = {float(h[k])!r}. Resample the record or discretize the "
                             "continuous design with that period (fojax.discretize).")
    else:
        ts = eqx.error_if(ts, jnp.any(jnp.abs(h - dt) > tol), "estimate: the samples must be dt apart")
    v = jnp.concatenate([u, y], axis=1)
    Bo = jnp.concatenate([lm.Bu, lm.By], axis=1)
    Do = jnp.concatenate([lm.Du, lm.Dy], axis=1)

    def step(xi, vk):
        return lm.A @ xi + Bo @ vk, xi

    _, xis = jax.lax.scan(step, xi0, v)
    return xis @ lm.C.T + v @ Do.T


def _run(lm, ts, h, u, y, xi0, interpolation):
    from ..simulation._discretize import discretize, gauss_nodes

    v = jnp.concatenate([u, y], axis=1)  # (T, m + p)
    Bo = jnp.concatenate([lm.Bu, lm.By], axis=1)
    Do = jnp.concatenate([lm.Du, lm.Dy], axis=1)
    nu = 2 if interpolation == "linear" else 1
    Phi, W = jax.vmap(lambda hk: discretize(lm.A, Bo, hk, nu)[:2])(h)  # (T-1, s, s), (T-1, nu, s, m+p)
    c = jnp.asarray(gauss_nodes(nu)[0])  # the quadrature nodes in [0, 1] (static)
    if interpolation == "linear":
        nodes = v[:-1, None, :] + c[None, :, None] * (v[1:] - v[:-1])[:, None, :]  # (T-1, nu, m+p)
    else:
        nodes = jnp.broadcast_to(v[:-1, None, :], (v.shape[0] - 1, nu, v.shape[1]))
    drive = jnp.einsum("kjsi,kji->ks", W, nodes)  # (T-1, s)

    def step(xi, inputs):
        P, d = inputs
        nxt = P @ xi + d
        return nxt, nxt

    _, xis = jax.lax.scan(step, xi0, (Phi, drive))
    xis = jnp.concatenate([xi0[None], xis], axis=0)
    return xis @ lm.C.T + v @ Do.T
