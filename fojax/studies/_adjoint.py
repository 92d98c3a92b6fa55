r"""Reverse mode of the exact kernel's time loop by an adjoint recurrence (custom VJP).

The differentiable study loss (`fojax.studies.study_loss` on the exact path) steps every
sample of a block, batch last, by the linear recurrence

$$w_k = \Phi w_{k-1} + \textstyle\sum_j [k = k_j]\, v_j \quad (k = 1, \dots, n = T-1),
\qquad o_k = G w_k ,$$

and reduces the outputs along the grid with the problem's accumulator
(``acc_0 = init(o_0)``, ``acc_k = update(acc_{k-1}, o_k, k, ts)``: the sums of $|o|$,
$o^2$, $(t_k - t_0)|o|$, the running peak $\max|o|$ and the last index above the settling
threshold for `run_study`'s metrics). `jax.grad` of the plain `jax.lax.scan` stores the
residuals of every step and differentiates the batched matrix–vector product generically
(at ``B = 1,000``, 1,000 steps: forward 0.25 s, value-and-gradient 2.0 s). This module
gives the loop a hand-written VJP, in the split form of `split_recurrence_reduce` (the
joint adjoint below is its derivation; its implementation, ``linear_recurrence_reduce``,
was no longer called by fojax and was removed: its forward, finite-difference and vmap
tests now run on the split loop).

**Derivation.** Let $\ell$ be a scalar function of the outputs ``(acc_n, w_n)`` and write
$\bar x = \partial\ell/\partial x$. Walking the loop backwards, the accumulator's
cotangent moves through each step by the VJP of ``update`` at the stored
$(acc_{k-1}, o_k)$:

$$(\overline{acc}_{k-1},\ \bar o_k,\ \bar t_{(k)}) = \mathrm{VJP}_{update}(acc_{k-1}, o_k, k, ts)\,[\overline{acc}_k],$$

(for the sums this is $\bar o_k = \bar s_1\,\mathrm{sign}(o_k) + 2\bar s_2\, o_k +
\bar s_3 (t_k - t_0)\,\mathrm{sign}(o_k)$, exactly what `jax.grad` of the scan gives,
including $\mathrm{sign}(0) = 0$ for the non-smooth $|o|$; the peak's ``maximum`` routes
its cotangent to the step that set it, as `jax.grad` does). With the adjoint state
$\lambda_k = \partial\ell/\partial w_k$ (total derivative through every later step),

$$\lambda_n = \bar w_n + G^\top \bar o_n,\qquad
\lambda_{k} = \Phi^\top \lambda_{k+1} + G^\top \bar o_k \quad (k = n-1, \dots, 0),$$

with $\bar o_0$ from the VJP of ``init``, and the parameter cotangents are sums over the
steps of outer products (per sample, batch last):

$$\bar\Phi = \sum_{k=1}^{n} \lambda_k w_{k-1}^\top,\qquad
\bar G = \sum_{k=0}^{n} \bar o_k w_k^\top,\qquad \bar v_j = \lambda_{k_j},\qquad
\bar w_0 = \lambda_0 .$$

The backward pass is one more scan of the forward's cost (per step: $\Phi^\top\lambda$,
one outer product, and the $K \times N$ output terms).

**Memory.** Running $w$ backwards with $\Phi^{-1}$ is unstable for stiff loops (the fast
modes grow), so the states are *checkpointed*: the forward keeps $(w, acc)$ only at the
start of each of $\lceil n/S\rceil$ segments of $S = \lceil\sqrt n\,\rceil$ steps; the
backward recomputes one segment at a time (storing its $S$ states) and then runs the
adjoint through it. Memory is $O(2\sqrt n\, N b)$ instead of $O(n N b)$; the cost is one
extra forward pass (the last segment is shorter when $S \nmid n$).

**The reverse pass.** Per segment the backward recomputes the states, runs the λ scan
and forms the outer-product sums (``q·N + K·N`` FMAs per sample and step, as many as a
forward step) and the outputs' cotangents; with the one extra forward pass, a gradient
costs a small multiple of a forward run (timings: ``benchmarks/study_profile.py``, its
results in ``benchmarks/results/study_profile_latest.json``). For problems whose
``update`` adds a function of ``(o, k, ts)`` (``problem.additive``:
`fojax.studies._exact.LossProblem`) the outputs' cotangents of a segment are taken at
once and the λ scan carries only $\Phi_{\xi\xi}^\top\lambda$; other problems take the
per-step VJP. The scans are not unrolled (unrolled scans are slower on XLA CPU).

**Passes** (`pass_recurrence_reduce`): the loss without jumps (what `tune` trains) runs
the same split loop on passes of ``S = 8`` grid steps, $\Phi^S$ and the stacked rows
$[G\Phi; \dots; G\Phi^S]$: the state's update, the λ scan and the λ outer products $S$
times fewer, at the price of a per-sample set-up (the joint exponential and its VJP, the
plant's exponential, the pass matrices). The observer block $e^{N h}$, the same for every
sample, is not shared across the block: the loss's gradient is formed per sample
(`fojax.studies._sharding`: the sum over samples in one order on any split), so the
cotangent of $e^{Nh}$ cannot be one sum over the block, and the per-sample
$\Phi_{\xi p}$ still needs the joint exponential.

Only the observers' arrays (and ``ts``) are differentiated; ``update`` and ``init`` must depend on
the problem's own arrays only through non-differentiable quantities (the settling
threshold enters only an integer index).
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
from jax import lax

from .._errors import InputError
from ..simulation._batch import repeat_groups
from ..simulation._expm import matvec_last


def _rmatvec_last(M, v):
    """``Σ_i M[i, :, :] * v[i, :]`` = ``Mᵀ v`` per sample (``M`` ``(K, N, b)``, ``v`` ``(K, b)``),
    as FMAs over the contiguous rows of ``M`` (through ``swapaxes`` and `matvec_last`, XLA
    CPU re-laid out the transposed matrix at every step: 5x slower backward)."""
    acc = M[0] * v[0][None, :]
    for i in range(1, v.shape[0]):
        acc = acc + M[i] * v[i][None, :]
    return acc


#: Output rows up to which the additive adjoint forms ``Gᵀō`` as unrolled FMAs (`_rmatvec_last`).
_RMATVEC_MAX = 8


def _jump(w, jv, kon, k):
    """``w + Σ_j [kon_j = k] jv_j`` (``jv`` ``(J, N, b)``, ``kon`` ``(J, b)``)."""
    if jv is None:
        return w
    for j in range(jv.shape[0]):
        w = w + jnp.where(kon[j] == k, 1.0, 0.0)[None, :] * jv[j]
    return w


def _float_part(tree):
    return eqx.partition(tree, eqx.is_inexact_array)


# --- the loop split into the plant (constant) and the observers (differentiated) ----------


def _split_outputs(plant, diff, kon, p, xi, k):
    """Step ``k`` (``1 ≤ k ≤ n``) of the split loop without the reduction: ``(p_k, ξ_k, o_k)``."""
    Ppp, _, jvp = plant
    Poo, Pop, Go, Gp, _, jvo, ts = diff
    pn = _jump(matvec_last(Ppp, p), jvp, kon, k)
    xn = _jump(matvec_last(Poo, xi) + matvec_last(Pop, p), jvo, kon, k)
    return pn, xn, matvec_last(Go, xn) + matvec_last(Gp, pn)


def _split_step(problem, plant, diff, kon, p, xi, acc, k):
    """Step ``k`` (``1 ≤ k ≤ n``) of the split loop: ``(p_k, ξ_k, acc_k)``."""
    pn, xn, o = _split_outputs(plant, diff, kon, p, xi, k)
    return pn, xn, problem.update(acc, o, k, diff[6])


def _split_layout(T: int, segment: int | None):
    """``(n, S, full, tail)``: ``n = T − 1`` steps in ``full`` segments of ``S`` steps and
    one of ``tail < S`` steps. (The segments have exact lengths: a padded last segment whose
    extra steps are skipped with selects slows every step on XLA CPU.)"""
    n = T - 1
    S = max(1, math.ceil(math.sqrt(n))) if segment is None else int(segment)
    return n, S, n // S, n % S


def _split_forward(problem, plant, diff, kon, segment, checkpoints: bool):
    Go, Gp, xi0, ts = diff[2], diff[3], diff[4], diff[6]
    p0 = plant[1]
    n, S, full, tail = _split_layout(ts.shape[0], segment)
    acc0 = problem.init(matvec_last(Go, xi0) + matvec_last(Gp, p0))

    def run(carry, ks):
        out, _ = lax.scan(lambda c, k: (_split_step(problem, plant, diff, kon, *c, k), None), carry, ks)
        return out

    def outer(carry, s):
        return run(carry, 1 + s * S + jnp.arange(S)), (carry if checkpoints else None)

    carry, saved = lax.scan(outer, (p0, xi0, acc0), jnp.arange(full))
    saved_tail = carry
    if tail:
        carry = run(carry, 1 + full * S + jnp.arange(tail))
    p_end, xi_end, acc = carry
    return (acc, p_end, xi_end), ((saved, saved_tail) if checkpoints else None)


#: Most grid steps one pass of `pass_recurrence_reduce` takes (a power of two; the pass is
#: the largest power of two up to this that divides the number of steps).
PASS_MAX = 8


#: Passes of `pass_recurrence_reduce` up to which its backward recomputes them in one
#: segment (its states: ``(2 dim p + dim ξ + 2 S K) · 8 · 32`` bytes per pass and block,
#: 3 MB for the 124 passes of a 1,000-step grid at ``S = 8``), instead of ``⌈√n⌉``-pass
#: checkpoint segments and a shorter last one: the same run time, and one segment body
#: less to compile.
PASS_SEGMENT_MAX = 256


def pass_length(n: int) -> int:
    """Static: the steps per pass of `pass_recurrence_reduce` for ``n`` grid steps, the
    largest power of two ``≤ PASS_MAX`` dividing ``n`` and leaving at least two passes
    (``1``: step by step, `split_recurrence_reduce`)."""
    S = 1
    while 2 * S <= PASS_MAX and n % (2 * S) == 0 and n // (2 * S) >= 2:
        S *= 2
    return S


def _pass_matrices(Ppp, Poo, Pop, Go, Gp, S: int):
    r"""Per sample (batch last): the blocks of $\Phi^S$ and the rows $G\Phi^i$,
    $i = 1, \dots, S$ (stacked step-major: row $(i-1)K + k$), of the block lower-triangular
    $\Phi = [[\Phi_{pp}, 0], [\Phi_{\xi p}, \Phi_{\xi\xi}]]$ and $G = [G_p, G_\xi]$, by
    doubling: $R_{w+1..2w} = R_{1..w}\Phi^w$, $\Phi^{2w} = \Phi^w\Phi^w$ ($S$ a power of
    two), as batched batch-first products (they compile faster than batch-last einsums or
    a `jax.lax.scan` of the steps).
    Returns ``(Φ^S_pp, Φ^S_ξp, Φ^S_ξξ, R_p, R_ξ)``."""

    Pp, Pxx, Pxp, Go, Gp = (jnp.moveaxis(X, -1, 0) for X in (Ppp, Poo, Pop, Go, Gp))  # batch first: batched GEMMs
    m = Pp.shape[1]
    X = jnp.concatenate([Pxp, Pxx], axis=2)  # the observers' rows of Φ^w, (b, q, N)
    zero = jnp.zeros(Pp.shape[:2] + (Pxx.shape[1],), Pp.dtype)

    def joint(Pp, X):
        return jnp.concatenate([jnp.concatenate([Pp, zero], axis=2), X], axis=1)  # Φ^w, (b, N, N)

    R = jnp.concatenate([Gp, Go], axis=2) @ joint(Pp, X)  # G Φ
    w = 1
    while w < S:
        F = joint(Pp, X)
        R, X, Pp = jnp.concatenate([R, R @ F], axis=1), X @ F, Pp @ Pp
        w *= 2
    Pp, Pxp, Pxx, Rp, Rx = (jnp.moveaxis(Y, 0, -1) for Y in (Pp, X[..., :m], X[..., m:], R[..., :m], R[..., m:]))
    return Pp, Pxp, Pxx, Rp, Rx


def pass_recurrence_reduce(diff, plant, problem, S: int, segment=None, reps: int = 1):
    r"""`split_recurrence_reduce` for an additive reduction (``problem.update(acc, o, k,
    ts) = acc + g(o)``, ``g`` elementwise, independent of ``k`` and ``ts``: `LossProblem`)
    without jumps, ``S`` grid steps per pass (`pass_length`).

    The step-by-step loop costs per sample and step $\dim\xi\,(\dim\xi + \dim p)$ +
    $\dim p^2 + K(\dim\xi + \dim p)$ FMAs forward, and its reverse pass (recompute, λ,
    the outer-product sums) about twice as many again. With $w'_j = w_{jS}$ the loop is
    the same recurrence on the passes,

    $$w'_j = \Phi^S w'_{j-1},\qquad
    O_j = \begin{bmatrix} G\Phi \\ \vdots \\ G\Phi^S\end{bmatrix} w'_j
    = (o_{jS+1}, \dots, o_{jS+S}),$$

    so `split_recurrence_reduce` runs on the ``n/S − 1`` passes ``j = 1 … n/S − 1`` with
    $\Phi^S$ and the stacked rows $R = [G\Phi; \dots; G\Phi^S]$ ($SK$ outputs; its adjoint
    is unchanged), the first pass's outputs $O_0 = R w_0$ (steps ``1 … S``) are added
    here, and $w_n = \Phi^S w'_{n/S-1}$. Per sample and step this is about
    $(\dim\xi + \dim p)(\dim\xi + \dim p + SK)/S$ FMAs forward: the outputs'
    rows are as many as before, the state's update $S$ times fewer. $\Phi^S$ and $R$
    (`_pass_matrices`: $\log_2 S$ squarings and doublings) are differentiated by `jax`.
    Equal to the step-by-step loop up to rounding (the products are associated
    differently; tested to 1e-12 relative).

    **Arguments:** as `split_recurrence_reduce` (``jvo``, ``jvp`` ``None``, no ``kon``);
    ``S`` (static) divides ``n = T − 1`` and leaves at least two passes. ``reps``
    (static): the matrices (``Poo``, ``Pop``, ``Go``, ``Gp``, ``Ppp``) are given once per
    group of ``reps`` consecutive samples (``xi0``, ``p0``: per sample); the pass matrices
    are formed per group and repeated to the samples.

    **Returns:** ``(acc, p_end, xi_end)``: ``acc`` ``(K, b)`` summed over the ``S`` rows of
    each output in order.
    """
    Poo, Pop, Go, Gp, xi0, jvo, ts = diff
    Ppp, p0, jvp = plant
    n = ts.shape[0] - 1
    if jvo is not None or jvp is not None or n % S or n // S < 2 or not getattr(problem, "additive", False):
        raise InputError(f"pass_recurrence_reduce: {S} steps per pass need an additive problem, no jumps and "
                         f"S | n with n / S >= 2 (n = {n}).")
    K = Go.shape[0]
    Pp, Pxp, Pxx, Rp, Rx = _pass_matrices(Ppp, Poo, Pop, Go, Gp, S)
    Pp, Pxp, Pxx, Rp, Rx = (repeat_groups(X, reps, -1) for X in (Pp, Pxp, Pxx, Rp, Rx))
    if segment is None and n // S - 1 <= PASS_SEGMENT_MAX:
        segment = n // S - 1  # one checkpoint segment (no shorter last one to compile)
    acc, p_end, xi_end = split_recurrence_reduce((Pxx, Pxp, Rx, Rp, xi0, None, ts[: n // S]),
                                                 (Pp, p0, None), problem, None, segment)
    # differentiated by jax: einsums (the transpose of the unrolled `matvec_last` pads a
    # cotangent per column: +2 s of compile)
    mv = lambda M, v: jnp.einsum("ijb,jb->ib", M, v)  # noqa: E731
    acc = problem.update(acc, mv(Rx, xi0) + mv(Rp, p0), 0, ts)  # steps 1 … S
    acc = acc.reshape((S, K) + acc.shape[1:]).sum(axis=0)
    return acc, mv(Pp, p_end), mv(Pxx, xi_end) + mv(Pxp, p_end)


def split_recurrence_reduce(diff, plant, problem, kon, segment=None):
    r"""The loop of the module docstring for a joint state $w = (p, \xi)$ whose first part
    $p$ (the plant and its exosystem) does not depend on the differentiated arguments,
    with an adjoint that runs at the size of $\xi$ (the observers).

    In a study the observers do not feed back into the plant, so $\Phi$ is block lower
    triangular, $\Phi = \begin{bmatrix}\Phi_{pp} & 0\\ \Phi_{\xi p} & \Phi_{\xi\xi}\end{bmatrix}$
    (the upper right block of $e^{\mathcal A h}$ is exactly zero because that of
    $\mathcal A$ is), and

    $$p_k = \Phi_{pp}p_{k-1} + v^p_{(k)},\qquad
    \xi_k = \Phi_{\xi\xi}\xi_{k-1} + \Phi_{\xi p}p_{k-1} + v^\xi_{(k)},\qquad
    o_k = G_\xi \xi_k + G_p p_k .$$

    With $\ell$ as in the module docstring and $p$ constant, only the observer part of the
    adjoint is needed: $\lambda_n = \bar\xi_n + G_\xi^\top\bar o_n$,
    $\lambda_k = \Phi_{\xi\xi}^\top\lambda_{k+1} + G_\xi^\top\bar o_k$, and

    $$\bar\Phi_{\xi\xi} = \sum_{k\ge1}\lambda_k\xi_{k-1}^\top,\quad
    \bar\Phi_{\xi p} = \sum_{k\ge1}\lambda_k p_{k-1}^\top,\quad
    \bar G_\xi = \sum_{k\ge0}\bar o_k\xi_k^\top,\quad
    \bar G_p = \sum_{k\ge0}\bar o_k p_k^\top,\quad \bar v^\xi_j = \lambda_{k_j},\quad
    \bar\xi_0 = \lambda_0 .$$

    (the same equations as the joint adjoint with the plant rows of $\lambda$ dropped: they
    would only feed the cotangents of $\Phi_{pp}$, $p_0$ and $v^p$). Per step the
    backward costs $\dim\xi^2$ instead of $(\dim p + \dim\xi)^2$ for $\Phi^\top\lambda$,
    and the outer-product sums skip the $\Phi_{pp}$ block.

    **Arguments:**

    - `diff`: ``(Poo, Pop, Go, Gp, xi0, jvo, ts)``: ``(q, q, b)``, ``(q, m, b)``,
      ``(K, q, b)``, ``(K, m, b)``, ``(q, b)``, ``(J, q, b)`` or ``None``, ``(T,)``.
    - `plant`: ``(Ppp, p0, jvp)``: ``(m, m, b)``, ``(m, b)``, ``(J, m, b)`` or ``None``;
      the caller must build them from data that the differentiated arguments do not
      reach. Differentiating with respect to them (e.g. `jax.grad` with respect to the
      study's own arrays) raises `fojax.errors.InputError` when the reverse pass is traced: the
      plant part of the adjoint is not computed, so such a gradient would be incomplete.
    - `problem`: gives ``init(o0)`` and ``update(acc, o, k, ts)`` (not differentiated).
    - `kon`: ``(J, b)`` grid index of each jump (``-1``: none) or ``None``.
    - `segment`: checkpoint segment length (default ``⌈√(T−1)⌉``).

    **Returns:** ``(acc, p_end, xi_end)``.
    """
    problem = jax.tree.map(lambda x: lax.stop_gradient(x) if eqx.is_array(x) else x, problem)
    return _split_reduce((diff, plant), problem, kon, segment)


@eqx.filter_custom_vjp
def _split_reduce(args, problem, kon, segment=None):
    diff, plant = args
    out, _ = _split_forward(problem, plant, diff, kon, segment, checkpoints=False)
    return out


@_split_reduce.def_fwd
def _split_fwd(perturbed, args, problem, kon, segment=None):
    diff, plant = args
    return _split_forward(problem, plant, diff, kon, segment, checkpoints=True)


@_split_reduce.def_bwd
def _split_bwd(saved, grad_obj, perturbed, args, problem, kon, segment=None):
    diff, plant = args
    if any(jax.tree.leaves(perturbed[1])):
        raise InputError(
            "study_loss's reverse mode differentiates the observers only: the plant's trajectory (Φ_pp, its "
            "initial state or jumps) is being differentiated, e.g. jax.grad with respect to the study's arrays. "
            "Differentiate with respect to the observer, or use cfg=SimConfig(stepper=fojax.Diffrax()) for derivatives "
            "with respect to the study.")
    Poo, Pop, Go, Gp, xi0, jvo, ts = diff
    p0 = plant[1]
    n, S, full, tail = _split_layout(ts.shape[0], segment)
    (ps_ck, xs_ck, accs_ck), tail_ck = saved
    acc_bar, _, xi_bar = grad_obj  # p_end does not depend on `diff`: its cotangent is not needed
    acc_f0, _ = _float_part(problem.init(matvec_last(Go, xi0) + matvec_last(Gp, p0)))
    given = (acc_f0 if acc_bar is None else _float_part(acc_bar)[0])
    acc_bar = jax.tree.map(
        lambda z, g: None if z is None else (jnp.zeros_like(z) if g is None or acc_bar is None else g),
        acc_f0, given, is_leaf=lambda x: x is None)
    mu = jnp.zeros_like(xi0) if xi_bar is None else xi_bar

    ts_bar = bool(perturbed[0][6])  # the grid's cotangent only when the grid is differentiated
    additive = bool(getattr(problem, "additive", False))
    q = xi0.shape[0]

    def update_vjp(acc_prev, o, k, cot):
        accf, acci = _float_part(acc_prev)

        def f(accf, o, ts):
            return _float_part(problem.update(eqx.combine(accf, acci), o, k, ts))[0]

        if ts_bar:
            _, vjp = jax.vjp(f, accf, o, ts)
            return vjp(cot)
        _, vjp = jax.vjp(lambda accf, o: f(accf, o, ts), accf, o)
        return vjp(cot) + (None,)

    def back_step(carry, x):
        mu, acc_bar, tb = carry
        o_k, acc_prev, k = x
        acc_bar, o_bar, t_bar = update_vjp(acc_prev, o_k, k, acc_bar)
        # Gᵀō as a dot: written as FMAs, XLA fused it (and ō) into every element of the
        # Φᵀλ product and recomputed it there (backward 6x slower)
        lam = mu + jnp.einsum("kib,kb->ib", Go, o_bar)
        return (_rmatvec_last(Poo, lam), acc_bar, tb if t_bar is None else tb + t_bar), (lam, o_bar)

    def lam_step(mu, r_k):
        lam = mu + r_k
        return _rmatvec_last(Poo, lam), lam

    def back(carry, start, ks):
        """The adjoint through the steps ``ks`` from the checkpoint ``start``."""
        mu, acc_bar, Po_b, G_b, jb, tb = carry

        def rec(c, k):
            p, xi, acc = c
            pn, xn, o = _split_outputs(plant, diff, kon, p, xi, k)
            return (pn, xn, problem.update(acc, o, k, ts)), (pn, xn, o, acc)

        _, (p_k, xi_k, o_k, acc_prev) = lax.scan(rec, start, ks)
        if additive:
            # acc_k = acc_{k-1} + g(o_k): its cotangent is the same at every step, so the
            # outputs' cotangents and Gᵀō of the whole segment are computed at once, and
            # the sequential scan carries only λ_k = Φᵀλ_{k+1} + Gᵀō_k (q² FMAs per step)
            _, o_bar, t_bar = jax.vmap(lambda a, o, k: update_vjp(a, o, k, acc_bar))(acc_prev, o_k, ks)
            if t_bar is not None:
                tb = tb + jnp.sum(t_bar, axis=0)
            # Gᵀō_k for every step k; for the many output rows of `pass_recurrence_reduce`
            # (S K) a dot: the unrolled FMAs compiled 1.8 s slower and ran slower
            r = (jnp.einsum("kib,skb->sib", Go, o_bar) if Go.shape[0] > _RMATVEC_MAX
                 else jax.vmap(_rmatvec_last, in_axes=(None, 0))(Go, o_bar))
            mu, lam = lax.scan(lam_step, mu, r, reverse=True)
        else:
            (mu, acc_bar, tb), (lam, o_bar) = lax.scan(back_step, (mu, acc_bar, tb), (o_k, acc_prev, ks),
                                                       reverse=True)
        # the outer-product sums, observer and plant columns in one product each:
        # Σ λ_k [ξ_{k-1}; p_{k-1}]ᵀ and Σ ō_k [ξ_k; p_k]ᵀ
        w_k = jnp.concatenate([xi_k, p_k], axis=1)
        w_prev = jnp.concatenate([jnp.concatenate([start[1], start[0]], axis=0)[None], w_k[:-1]], axis=0)
        Po_b = Po_b + jnp.einsum("kib,kjb->ijb", lam, w_prev)
        G_b = G_b + jnp.einsum("kib,kjb->ijb", o_bar, w_k)
        if jb is not None:
            hit = jnp.where(kon[None] == ks[:, None, None], 1.0, 0.0)  # (steps, J, b)
            jb = jb + jnp.einsum("kjb,kib->jib", hit, lam)
        return (mu, acc_bar, Po_b, G_b, jb, tb)

    zeros = jnp.zeros_like
    N = q + Pop.shape[1]
    carry = (mu, acc_bar, jnp.zeros((q, N) + Poo.shape[2:], Poo.dtype), jnp.zeros((Go.shape[0], N) + Go.shape[2:], Go.dtype),
             None if jvo is None else zeros(jvo), zeros(ts))
    if tail:
        carry = back(carry, tail_ck, 1 + full * S + jnp.arange(tail))

    def segment_back(carry, s):
        start = jax.tree.map(lambda a: a[s], (ps_ck, xs_ck, accs_ck))
        return back(carry, start, 1 + s * S + jnp.arange(S)), None

    if full:
        carry, _ = lax.scan(segment_back, carry, jnp.arange(full), reverse=True)
    mu, acc_bar, Po_b, G_b, jb, tb = carry
    Poo_b, Pop_b, Go_b, Gp_b = Po_b[:, :q], Po_b[:, q:], G_b[:, :q], G_b[:, q:]
    o0 = matvec_last(Go, xi0) + matvec_last(Gp, p0)
    _, vjp0 = jax.vjp(lambda o: _float_part(problem.init(o))[0], o0)
    (o0_bar,) = vjp0(acc_bar)
    lam0 = mu + (jnp.einsum("kib,kb->ib", Go, o0_bar) if Go.shape[0] > _RMATVEC_MAX else _rmatvec_last(Go, o0_bar))
    Go_b = Go_b + o0_bar[:, None, :] * xi0[None, :, :]
    Gp_b = Gp_b + o0_bar[:, None, :] * p0[None, :, :]
    return (Poo_b, Pop_b, Go_b, Gp_b, lam0, jb, tb), jax.tree.map(lambda _: None, plant)
