r"""The exponential integrator's batch kernel: many time-varying linear loops, metrics only.

This is the stepping of `fojax.Exponential` (`fojax.run_study`, `fojax.studies.study_loss`;
`fojax.studies._exponential` builds its problems). Exact discretisation (`fojax.Exact`)
needs a time-invariant loop. When the loop varies in time — an uncertainty profile
$\delta(t)$, a fault, an input signal — each sample's reduced slow ODE is still linear in
the state and close to a *common* linear part,

$$\dot w = A_0 w + g_k(t, w),\qquad
  g_k(t, w) = (\bar A_k - A_0)\,w + \sum_{i=1}^{n_s} s_{k,i}(t)\,\big(D_{k,i} w + b_{k,i}(t)\big)
  + \bar b_k(t),$$

where $s_{k,i}(t)$ are the components of the signals inside the plant (the $\delta(t)$ of
a `fojax.UncertainDescriptorSystem`, the fault of a fault wrapper, output noise) and the
$b$'s collect the input $u_k(t)$. The stiff, common part $A_0$ is integrated exactly by an
*exponential Runge–Kutta method*; only the (non-stiff, small) remainder $g$ is
approximated. Because $A_0$ is the same for every sample, its $\varphi$-functions are
computed once and applied to the whole batch as matrix products.

**How the decomposition is found.** Every sample is a plant with LTI observers and an
input signal. Every `fojax.plant.AbstractSignal` inside the plant is replaced by a constant *probe* value $s$; the probed plant is
time-invariant, is reduced to its slow ODE in the masked SVD coordinates of
`fojax.simulation` (the reduction of `fojax.simulate`'s exact method, with the input
extended by a constant 1 to carry affine terms) and joined with the observers. Doing
this at $s = 0$ and at the unit vectors $s = e_i$ gives $\bar A_k$, $D_{k,i}$ and the input
maps. The decomposition is exact when the reduced field is affine in the signal values
— true when the signals enter the *differential* equations of an index-1 plant affinely
(an uncertainty in the algebraic equations would enter through $\tilde A_{22}^{-1}$) and
the plant depends on time only through its signals. This is **checked** on the first
sample whenever the inputs are concrete: the decomposition is compared with the plant's
own right-hand side (the vector field of `fojax.simulate`'s diffrax path) at random
signal values and at a random time, and a mismatch raises `fojax.errors.InputError`.

**The method** is Krogstad's fourth-order exponential Runge–Kutta method (ETDRK4-K;
S. Krogstad, *J. Comput. Phys.* 203 (2005) 72–88; the Butcher tableau as in
M. Hochbruck and A. Ostermann, *Exponential integrators*, *Acta Numerica* 19 (2010)
209–286). With
$\varphi_j = \varphi_j(hA_0)$, $\psi_j = \varphi_j(hA_0/2)$ and $N(\cdot)$ the values of $g$:

$$\begin{aligned}
 a &= \psi_0 w_n + \tfrac h2\psi_1 N_n, &
 b &= a + h\psi_2\,(N_a - N_n),\\
 c &= \varphi_0 w_n + h(\varphi_1 - 2\varphi_2)N_n + 2h\varphi_2 N_b, &
 w_{n+1} &= \varphi_0 w_n + h(\varphi_1 - 3\varphi_2 + 4\varphi_3)N_n
  + h(2\varphi_2 - 4\varphi_3)(N_a + N_b) + h(4\varphi_3 - \varphi_2)N_c,
\end{aligned}$$

with $N_n = g(t_n, w_n)$, $N_a = g(t_n + h/2, a)$, $N_b = g(t_n + h/2, b)$,
$N_c = g(t_n + h, c)$. The $\varphi$-functions come from one exponential of the
augmented matrix $\begin{bsmallmatrix} hA_0 & I & & \\ & 0 & I & \\ & & 0 & I\\ &&&0
\end{bsmallmatrix}$ (its first block row is $[\varphi_0, \varphi_1, \varphi_2,
\varphi_3]$), computed once per call by `fojax.simulation._expm.expm_stack` (scaling and squaring of a Taylor polynomial,
matrix products only: LAPACK-free, reverse-differentiable).

**Speed.** The stages only need what $g$ reads from a state and writes: the
perturbation's non-zero rows and columns. Terms identical for every sample of a chunk
(to round-off, $10^{-13}$ relative) are *shared*: their matrices are multiplied into the
stacked $\varphi$-matrices once per call, so each step is four matrix products (one per
stage, all samples of a block at once) plus elementwise work; per-sample terms are applied
as fused multiply–adds over the batch; terms that vanish are skipped. This *plan* is read
on the host from the set-up of each chunk when the inputs are concrete (under a trace,
`fojax.studies.study_loss` inside `fojax.tune`, every term is treated as per-sample, which
is correct but slower); different
plans compile different kernels, so compilation happens once per structure *and*
sparsity pattern. All samples of a block are stepped together with the batch as the
last axis; metrics are accumulated inside the time loop (trapezoid rule on ``ts``), so no
trajectory is stored and memory grows linearly with ``B``.

**One batch kernel.** `ExponentialProblem` is a *problem* of
`fojax.simulation._driver.run_batched` (the chunking, padding, blocking and device
sharding of `fojax.run_study`'s exact engine) that brings its own block stepping; what
is reduced along the grid is another problem's ``init``/``update``/``final``
(`fojax.run_study`'s IAE/ISE/ITAE/peak/settling time, `fojax.studies._exponential`).
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from ._expm import expm_stack, matvec_last
from ._exponential_setup import _Plan, _signal_values, TRACE_COUNTS
from ._problem import AbstractBatchProblem
from ._reduction import is_concrete


#: One-sided signal values at a step boundary ``t + h``: the last ETDRK4 stage of the step
#: ``[t, t + h]`` reads the signals at ``t + (1 − SIDE_OFFSET) h`` (their left limits) and the
#: next step starts from their values at ``t + (1 + SIDE_OFFSET) h`` (right limits), so a jump
#: on the boundary belongs to the next step even when the boundary and the jump time differ
#: by rounding. For a smooth signal this moves a stage by 1e-9 of a step.
SIDE_OFFSET = 1e-9

__all__ = ["ExponentialProblem", "phi_functions"]


# --------------------------------------------------------------------------- the kernel


def _phi_augmented(M, xp):
    r"""The augmented matrix $\begin{bmatrix}M & I & & \\ & 0 & I & \\ & & 0 & I\\ & & & 0\end{bmatrix}$
    ``(..., 4N, 4N)`` of a stack ``M`` ``(..., N, N)``, in `xp` (NumPy on the host,
    `jax.numpy` traced): the first block row of its exponential is
    ``[φ0(M), φ1(M), φ2(M), φ3(M)]`` (`_phi_blocks`)."""
    N = M.shape[-1]
    O = xp.zeros(M.shape, dtype=M.dtype)
    eye = xp.broadcast_to(xp.eye(N, dtype=M.dtype), M.shape)
    return xp.block([[M, eye, O, O], [O, O, eye, O], [O, O, O, eye], [O, O, O, O]])


def _phi_blocks(F, N: int, xp):
    """``[φ0, φ1, φ2, φ3]`` ``(..., 4, N, N)``: the first block row of the exponential ``F``
    of `_phi_augmented`."""
    return xp.stack([F[..., :N, j * N : (j + 1) * N] for j in range(4)], axis=-3)


def _phi(M):
    """``[φ0(M), φ1(M), φ2(M), φ3(M)]`` ``(..., 4, N, N)`` of a stack ``M`` ``(..., N, N)``
    from one exponential of the augmented matrix each (traceable)."""
    return _phi_blocks(expm_stack(_phi_augmented(M, jnp)), M.shape[-1], jnp)


def phi_functions(A0, h):
    r"""$[\varphi_j(hA_0)]_{j=0..3}$ and $[\varphi_j(hA_0/2)]_{j=0..3}$, each ``(4, N, N)``.

    $\varphi_0(z) = e^z$, $\varphi_{j+1}(z) = (\varphi_j(z) - 1/j!)/z$, from the exponential of
    the augmented matrix (first block row); both step sizes in one stacked exponential.
    Concrete inputs (`run_study`'s host pass): SciPy's `scipy.linalg.expm` of the two
    augmented matrices on the host (nothing to compile); under a trace
    (`fojax.studies.study_loss`, an outer `jax.jit`) `fojax.simulation._expm.expm_stack`
    is traced inline (matrix products only: reverse-differentiable). Both are accurate to
    round-off (compared in ``tests/test_study_exponential.py``).
    """
    if is_concrete(A0, h):
        return _phi_functions_host(np.asarray(A0, dtype=np.float64), float(h))
    F = _phi(jnp.stack([h * A0, 0.5 * h * A0]))
    return F[0], F[1]


def _phi_functions_host(A0: np.ndarray, h: float):
    """`phi_functions` of concrete data, in NumPy/SciPy (host): the same augmented matrices
    as `_phi`, exponentiated by `scipy.linalg.expm`."""
    import scipy.linalg

    N = A0.shape[0]
    return tuple(jnp.asarray(_phi_blocks(scipy.linalg.expm(_phi_augmented(scale * A0, np)), N, np))
                 for scale in (h, 0.5 * h))


def _etd_matrices(phis, h, rows, Pi):
    r"""The shared stage matrices of Krogstad's ETDRK4, restricted to what g reads and writes.

    ``rows``: the components $g$ writes ($S_r$ selects them); ``Pi`` ``(q, N)``: what $g$
    reads from a state — the shared perturbation matrices themselves (so their products
    come out of the same matrix product as the stages) and the components read by
    per-sample terms. Every stage then costs one product with a stacked matrix:
    ``L0 @ [w; N_n]`` gives $\Pi a$, $\Pi b_0$, $\Pi c_0$, $w'_0$, $\Pi w'_0$;
    ``L1 @ N_a``, ``L2 @ N_b``, ``L3 @ N_c`` their increments.
    """
    (E, p1, p2, p3), (E2, q1, q2, _) = phis
    Q1, P2 = 0.5 * h * q1, h * q2
    C1, C2 = h * (p1 - 2.0 * p2), 2.0 * h * p2
    F1, F2, F3 = h * (p1 - 3.0 * p2 + 4.0 * p3), h * (2.0 * p2 - 4.0 * p3), h * (4.0 * p3 - p2)
    r = np.asarray(rows, dtype=int)
    S = lambda M: M[:, r]  # noqa: E731
    L0 = jnp.block(
        [
            [Pi @ E2, Pi @ S(Q1)],
            [Pi @ E2, Pi @ S(Q1 - P2)],
            [Pi @ E, Pi @ S(C1)],
            [E, S(F1)],
            [Pi @ E, Pi @ S(F1)],
        ]
    )
    L1 = jnp.concatenate([Pi @ S(P2), S(F2), Pi @ S(F2)], axis=0)
    L2 = jnp.concatenate([Pi @ S(C2), S(F2), Pi @ S(F2)], axis=0)
    L3 = jnp.concatenate([S(F3), Pi @ S(F3)], axis=0)
    return E, L0, L1, L2, L3


class ExponentialProblem(AbstractBatchProblem):
    r"""A problem of the batch kernel (`fojax.simulation._driver.run_batched`) stepped by
    ETDRK4 instead of exact matrix exponentials (a final `AbstractBatchProblem`).

    A sample is ``p_k = (s_k, d_k)``: ``setup.signals(s_k)`` gives its signals ``(plant
    signals, input)``, ``d_k`` its part of `kernel_inputs` (``w0`` and the per-sample terms
    of the affine decomposition, computed once on the host by `prepare`, so the set-up of
    the decomposition is not part of the stepping kernel's graph). ``reducer`` is a
    batch-kernel problem whose ``init``/``update``/``final`` reduce the outputs
    $o = \sum_i c_i(t)\,(G_i w + H_i v)$ along the grid (`run_study`'s metrics, or
    `fojax.studies.study_loss`'s loss). ``shared`` (the terms equal
    for every sample) and the φ-functions of $A_0$ ``phis`` (kept block; bulk step and
    start-up step) are shared by every sample; ``plan`` (static, `_Plan`) says which terms
    are applied and how; ``schedule = (n_start, sub_start, substeps)``.

    `run_batched` owns chunks, padding, blocks and devices; `block_kernel` steps one block
    with the batch as the last axis: one `lax.scan` over every step of the schedule with
    one ETDRK4 step body (start-up and bulk steps differ only in data), the outputs and
    metrics taken under a `lax.cond` at the steps that end a grid interval. With
    ``checkpoint=True`` (reverse mode, `fojax.studies.study_loss`) the scan is cut into
    segments of about √S steps, each `jax.checkpoint`-ed, so the memory of the backward
    pass grows like √S.
    """

    setup: eqx.Module
    reducer: eqx.Module
    shared: dict
    phis: tuple
    plan: _Plan = eqx.field(static=True)
    schedule: tuple = eqx.field(static=True)

    @property
    def keep(self) -> int:
        return self.reducer.keep

    @property
    def computed(self) -> tuple[str, ...]:
        return self.reducer.computed

    def joint_size(self, p) -> None:
        return None  # its own stepping: the block width is the driver's

    # the reduction is the reducer's
    def init(self, o0):
        return self.reducer.init(o0)

    def update(self, acc, o, k, ts):
        return self.reducer.update(acc, o, k, ts)

    def final(self, acc, o0, o_end, ts, h, ok):
        return self.reducer.final(acc, o0, o_end, ts, h, ok)

    def block_kernel(self, p, h_grid, ts, basis=None, checkpoint: bool = False):
        """One block (leading axis ``b`` of every leaf of ``p``): the reducer's result
        (and the ``(T, K, b)`` outputs when ``reducer.keep``), batch last."""
        TRACE_COUNTS["ExponentialProblem"] += 1
        del basis  # the exponential kernel steps the slow state itself
        plan, (n_start, sub_start, substeps) = self.plan, self.schedule
        sig_p, inp = p
        sigpack = jax.vmap(self.setup.signals)(sig_p)
        T = ts.shape[0]
        t0 = ts[0]
        keep, rows, cols = (np.asarray(a, dtype=int) for a in plan[:3])
        nr = len(rows)
        R_out = inp["Gs"].shape[2]
        Nk = keep.size
        shared = [i for i, kind in plan.terms if kind == "shared"]
        sample = [i for i, kind in plan.terms if kind == "sample"]
        # Pi: what g reads from a state — the shared perturbation matrices (embedded in the
        # kept coordinates) and, for per-sample terms, the components they read
        Pi = [jnp.zeros((nr, Nk)).at[:, cols].set(self.shared["A"][j]) for j in range(len(shared))]
        if sample:
            Pi.append(jnp.eye(Nk)[cols])
        Pi = jnp.concatenate(Pi, axis=0) if Pi else jnp.zeros((0, Nk))
        q, n_sh = Pi.shape[0], len(shared) * nr
        # one step body for every step: the start-up and the bulk step differ only in data
        # (their h and stage matrices, stacked and picked by a per-step phase index), so the
        # compiled graph holds one ETDRK4 step whatever the schedule
        phase_sub = [sub_start] * bool(n_start) + [substeps] * bool(T - 1 - n_start)
        phase_phis = [self.phis[1]] * bool(n_start) + [self.phis[0]] * bool(T - 1 - n_start)
        hs = jnp.stack([h_grid / sub for sub in phase_sub])
        mats = jax.tree.map(
            lambda *m: jnp.stack(m),
            *[_etd_matrices(ph, h_grid / sub, rows, Pi) for ph, sub in zip(phase_phis, phase_sub)],
        )
        steps = _step_table(T, n_start, sub_start, substeps)  # (4, S): interval, substep, phase, last
        g_sh = [i for i, kind in plan.gterms if kind == "shared"]
        g_sa = [i for i, kind in plan.gterms if kind == "sample"]
        G_sh = self.shared["G"].reshape(-1, Nk) if g_sh else None
        last = lambda a: jnp.moveaxis(a, 0, -1)  # noqa: E731
        Ms = last(inp["Ms"]) if sample else None  # (k, nr, nc, b)
        Bs = last(inp["Bs"]) if plan.fterms else None
        Gs = last(inp["Gs"]) if g_sa else None
        Hs = last(inp["Hs"]) if plan.hterms else None
        w0 = last(inp["w0"])  # (Nk, b)
        sigs, usig = sigpack
        b = w0.shape[-1]

        def evaluate(t):
            def one(sg, us):
                return _signal_values(sg, t), jnp.concatenate([us(t), jnp.ones((1,))])

            if jax.tree.leaves((sigs, usig)):
                s, v = jax.vmap(one, out_axes=(1, 1))(sigs, usig)
            else:  # no per-sample signal data (e.g. no signals and a Zero input)
                s, v = one(sigs, usig)
                s = jnp.broadcast_to(s[:, None], (s.shape[0], b))
                v = jnp.broadcast_to(v[:, None], (v.shape[0], b))
            return jnp.concatenate([jnp.ones((1, b)), s], axis=0), v  # (1+ns, b), (m+1, b)

        def forcing(cf, v):
            f = jnp.zeros((nr, v.shape[1]))
            for j, i in enumerate(plan.fterms):
                f = f + cf[i][None, :] * _matvec_batch(Bs[j], v)
            return f

        def g(piy, cf, f):
            # piy = Pi y: the shared products D_i y, then the components per-sample terms read
            out = f
            for j, i in enumerate(shared):
                out = out + cf[i][None, :] * piy[j * nr : (j + 1) * nr]
            for j, i in enumerate(sample):
                out = out + cf[i][None, :] * _matvec_batch(Ms[j], piy[n_sh:])
            return out

        def outputs(w, cf, v):
            o = jnp.zeros((R_out, b))
            if g_sh:
                y = G_sh @ w
                R = y.shape[0] // len(g_sh)
                for j, i in enumerate(g_sh):
                    o = o + cf[i][None, :] * y[j * R : (j + 1) * R]
            for j, i in enumerate(g_sa):
                o = o + cf[i][None, :] * _matvec_batch(Gs[j], w)
            for j, i in enumerate(plan.hterms):
                o = o + cf[i][None, :] * _matvec_batch(Hs[j], v)
            return o

        def step(carry, t, h, mats):
            E, L0, L1, L2, L3 = mats
            w, piw, c0, v0 = carry
            # the last stage uses the signals' left limits at t + h, the next step their
            # right limits (a jump on the step boundary belongs to the next step)
            c1, v1 = evaluate(t + (1.0 + SIDE_OFFSET) * h)
            if nr == 0:
                return E @ w, piw, c1, v1
            ch, vh = evaluate(t + 0.5 * h)
            cl, vl = evaluate(t + (1.0 - SIDE_OFFSET) * h)
            fh, fl = forcing(ch, vh), forcing(cl, vl)
            Nn = g(piw, c0, forcing(c0, v0))
            Y0 = L0 @ jnp.concatenate([w, Nn], axis=0)
            pa, pb, pc = Y0[:q], Y0[q : 2 * q], Y0[2 * q : 3 * q]
            w_new, piw = Y0[3 * q : 3 * q + Nk], Y0[3 * q + Nk :]
            Na = g(pa, ch, fh)
            Y1 = L1 @ Na
            pb, w_new, piw = pb + Y1[:q], w_new + Y1[q : q + Nk], piw + Y1[q + Nk :]
            Nb = g(pb, ch, fh)
            Y2 = L2 @ Nb
            pc, w_new, piw = pc + Y2[:q], w_new + Y2[q : q + Nk], piw + Y2[q + Nk :]
            Nc = g(pc, cl, fl)
            Y3 = L3 @ Nc
            return w_new + Y3[:Nk], piw + Y3[Nk:], c1, v1

        reducer = self.reducer
        c_init, v_init = evaluate(t0)
        o_first = outputs(w0, c_init, v_init)
        o_zero = jnp.zeros_like(o_first)

        def body(carry, x):
            interval, sub, phase, last = x[0], x[1], x[2], x[3]
            state, acc = carry[:4], carry[4]
            h = hs[phase]
            state = step(state, t0 + interval * h_grid + sub * h, h, jax.tree.map(lambda m: m[phase], mats))

            def grid_point(acc):  # the step ends a grid interval: outputs and metrics there
                o = outputs(state[0], state[2], state[3])
                return reducer.update(acc, o, interval + 1, ts), o

            acc, o = lax.cond(last > 0, grid_point, lambda acc: (acc, o_zero), acc)
            return state + (acc,), (o if reducer.keep else None)

        carry = (w0, Pi @ w0, c_init, v_init, reducer.init(o_first))
        xs = jnp.asarray(steps.T)  # (S, 4)
        if checkpoint:
            # reverse mode: segments of ~√S steps, each recomputed in the backward pass
            # (jax.checkpoint), so memory grows like √S, not S; padded steps do nothing
            S = xs.shape[0]
            seg = max(1, math.isqrt(S - 1) + 1)
            n_seg = -(-S // seg)
            xs = jnp.concatenate([xs, jnp.full((n_seg * seg - S, 4), -1, dtype=xs.dtype)]).reshape(n_seg, seg, 4)

            def padded(carry, x):
                return lax.cond(x[0] >= 0, body, lambda c, x: (c, None if not reducer.keep else o_zero), carry, x)

            @jax.checkpoint
            def segment(carry, xseg):
                return lax.scan(padded, carry, xseg)

            carry, traj = lax.scan(segment, carry, xs)
            if reducer.keep:
                traj = traj.reshape((-1,) + traj.shape[2:])[:S]
        else:
            carry, traj = lax.scan(body, carry, xs)
        w_end, _, c_end, v_end, acc = carry
        ok = jnp.all(jnp.isfinite(w_end), axis=0)
        out = reducer.final(acc, o_first, outputs(w_end, c_end, v_end), ts, h_grid, ok)
        if reducer.keep:
            ends = np.flatnonzero(steps[3])
            # (T_c, K, b): the grid points (first, then every interval's end), every keep-th one
            out = (out, jnp.concatenate([o_first[None], traj[ends]], axis=0)[:: int(reducer.keep)])
        return out


@jax.custom_jvp
def _matvec_batch(M, v):
    r"""``Σ_j M[:, j, :] * v[j, :]`` (`matvec_last`, batch last) with a tangent rule whose
    transpose is cheap.

    The primal is `matvec_last` (unrolled over ``j``: the fastest forward step). Its
    automatic reverse mode transposes each slice ``M[:, j, :]`` into a zero-padded copy of
    the whole ``(N, N, b)`` array, ``N`` of them per product, and in a time loop they are
    accumulated at every step, so the gradient of `fojax.studies.study_loss` would cost
    many forward passes. The tangent is written as broadcast products instead,
    ``Σ_j dM[:, j] v[j] + M[:, j] dv[j]``, whose transposes are one outer product
    ``ct[:, None] v[None]`` and one reduction: the same numbers (to round-off), the same
    linear map."""
    return matvec_last(M, v)


def _matvec_batch_jvp(primals, tangents):
    M, v = primals
    dM, dv = tangents
    zero = jax.custom_derivatives.SymbolicZero
    out = matvec_last(M, v)
    parts = ([] if isinstance(dM, zero) else [jnp.sum(dM * v[None], axis=1)]) + (
        [] if isinstance(dv, zero) else [jnp.sum(M * dv[None], axis=1)])
    return out, sum(parts[1:], parts[0]) if parts else jnp.zeros_like(out)


_matvec_batch.defjvp(_matvec_batch_jvp, symbolic_zeros=True)


def _step_table(T: int, n_start: int, sub_start: int, substeps: int) -> np.ndarray:
    """The schedule as a table ``(4, S)`` of integers (host, static): for every step its grid
    interval, its index within the interval, its phase (0: start-up if any, else bulk)
    and whether it ends the interval."""
    parts = []
    for phase, (first, count, sub) in enumerate(
        [(0, n_start, sub_start)] * bool(n_start) + [(n_start, T - 1 - n_start, substeps)] * bool(T - 1 - n_start)
    ):
        interval = np.repeat(np.arange(first, first + count), sub)
        within = np.tile(np.arange(sub), count)
        parts.append(np.stack([interval, within, np.full_like(interval, phase), (within == sub - 1).astype(int)]))
    return np.concatenate(parts, axis=1).astype(np.int64)
