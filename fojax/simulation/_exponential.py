r"""`simulate_batch_exponential`: many time-varying linear loops, exponential integrator, metrics only.

Exact discretisation (`simulate_lti_batch`) needs a time-invariant loop. When the loop
varies in time — an uncertainty profile $\delta(t)$, a fault, an input signal — each
sample's reduced slow ODE is still linear in the state and close to a *common* linear
part,

$$\dot w = A_0 w + g_k(t, w),\qquad
  g_k(t, w) = (\bar A_k - A_0)\,w + \sum_{i=1}^{n_s} s_{k,i}(t)\,\big(D_{k,i} w + b_{k,i}(t)\big)
  + \bar b_k(t),$$

where $s_{k,i}(t)$ are the components of the signals inside the plant (the $\delta(t)$ of
a `fojax.UncertainDescriptorSystem`, the fault of a fault wrapper, output noise) and the
$b$'s collect the input $u_k(t)$. The stiff, common part $A_0$ is integrated exactly by an
*exponential Runge–Kutta method*; only the (non-stiff, small) remainder $g$ is
approximated. Because $A_0$ is the same for every sample, its $\varphi$-functions are
computed once and applied to the whole batch as matrix products.

**How the decomposition is found.** For every sample, ``model(params_k)`` builds the
plant (and LTI observers, and optionally an input signal). Every `fojax.plant.AbstractSignal`
inside the plant is replaced by a constant *probe* value $s$; the probed plant is
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
on the host from the set-up of each chunk when the inputs are concrete (under an outer
`jax.jit` every term is treated as per-sample, which is correct but slower); different
plans compile different kernels, so compilation happens once per structure *and*
sparsity pattern. All samples of a block are stepped together with the batch as the
last axis; metrics are accumulated inside the time loop (trapezoid rule on ``ts``), so no
trajectory is stored and memory grows linearly with ``B``.

**One batch kernel.** `ExponentialProblem` is a *problem* of
`fojax.simulation._driver.run_batched` (the chunking, padding, blocking and device
sharding of `simulate_lti_batch` and of `fojax.run_study`'s exact engine) that brings
its own block stepping; what is reduced along the grid is another problem's
``init``/``update``/``final`` (the integrated metrics of `simulate_batch_exponential`,
or `fojax.run_study`'s IAE/ISE/ITAE/peak/settling time, `fojax.studies._exponential`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from .._errors import InputError, ShapeError
from ._batch import DEFAULT_BLOCK
from ._driver import _step_size, DEFAULT_CHUNK, run_batched
from ._expm import expm_stack, matvec_last
from ._exponential_setup import (
    _check_structure,
    _full_plan,
    _ModelSetup,
    _parse_model_output,
    _Plan,
    _plant_signals,
    _signal_values,
    batch_params,
    check_affine,
    CstackOutputs,
    kernel_inputs,
    prepare,
    setup_all,
    TRACE_COUNTS,
)
from ._lti_batch import _check_metrics, _ModelProblem, METRIC_KINDS
from ._problem import AbstractBatchProblem
from ._reduction import (
    host_initial_checks,
    is_concrete,
)


#: One-sided signal values at a step boundary ``t + h``: the last ETDRK4 stage of the step
#: ``[t, t + h]`` reads the signals at ``t + (1 − SIDE_OFFSET) h`` (their left limits) and the
#: next step starts from their values at ``t + (1 + SIDE_OFFSET) h`` (right limits), so a jump
#: on the boundary belongs to the next step even when the boundary and the jump time differ
#: by rounding. For a smooth signal this moves a stage by 1e-9 of a step.
SIDE_OFFSET = 1e-9

__all__ = ["METRIC_KINDS", "simulate_batch_exponential"]


# --------------------------------------------------------------------------- model output


# --------------------------------------------------------------------------- signal probes


# --------------------------------------------------------------------------- decomposition


# --------------------------------------------------------------------------- host check


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
    round-off (compared in ``tests/test_exponential.py``).
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
    $o = \sum_i c_i(t)\,(G_i w + H_i v)$ along the grid (the integrated metrics of
    `simulate_batch_exponential`, or `run_study`'s metrics). ``shared`` (the terms equal
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
        TRACE_COUNTS["simulate_batch_exponential"] += 1
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


# --------------------------------------------------------------------------- public entry


def _positive_int(name, value, what, zero=False):
    ok = isinstance(value, int | np.integer) and not isinstance(value, bool) and value >= (0 if zero else 1)
    if not ok:
        kind = "non-negative" if zero else "positive"
        raise InputError(f"{name} must be a {kind} integer ({what}), got {value!r}.")
    return int(value)


def simulate_batch_exponential(
    model: Callable,
    params,
    x0,
    ts,
    *,
    metrics: Mapping[str, tuple],
    reference=None,
    substeps: int = 1,
    startup: tuple[int, int] | None = None,
    chunk_size: int = DEFAULT_CHUNK,
    block: int = DEFAULT_BLOCK,
    devices=None,
) -> dict:
    r"""Integrated metrics of a batch of time-varying linear descriptor loops (exponential RK4).

    For every sample $k$, ``model(params_k)`` returns an index-1 plant that is linear in
    the state and depends on time only through the `fojax.plant.AbstractSignal`\ s it contains
    (e.g. a `fojax.UncertainDescriptorSystem` with a `fojax.Sine` uncertainty
    $\delta_k(t)$; faults and output noise added by wrappers), optionally LTI observers
    driven by its input and output, and optionally the input signal $u_k(t)$. The joint
    plant+observer system is reduced to its slow ODE $\dot w = A_0 w + g_k(t, w)$ (see the
    module docstring) and integrated with Krogstad's fourth-order exponential Runge–Kutta
    method on the uniform grid ``ts``, `substeps` steps per grid interval. For each
    metric ``name: (kind, C)`` with $o = C\,[x; \xi_1; \dots]$ the trapezoid rule on ``ts``
    is accumulated during the time loop (kinds as in `simulate_lti_batch`: ``"iae"``,
    ``"ise"`` per row → ``(B, k)``, ``("iae", C, "sum")``, ``("ise", C, "sum")`` (legacy
    ``"iae_l1"``, ``"ise_l2"``) → ``(B,)``; the metric table of `fojax.simulation._save`).

    This is the exponential stepper's batch kernel (`fojax.Exponential`): `fojax.run_study`
    with ``stepper=Exponential()`` or ``Auto()`` runs the same ETDRK4 kernel on a `Study`
    (choosing the substeps itself); this function is its entry for a user's own
    ``model(params)`` with explicit `substeps`.

    **The common linear part.** $A_0$ is the joint slow matrix of ``model(reference)``
    with every signal inside its plant set to zero (for an uncertain plant: the nominal
    $\delta = 0$ loop; inputs and faults are never part of $A_0$). Choose `reference` so
    that this is representative of the batch — for an uncertainty with zero mean the
    nominal is the natural choice, and it is what the default (the first sample's
    ``params``, whose signals are zeroed) gives. $A_0$ is integrated exactly, whatever its
    stiffness; the step size only has to resolve $g$.

    **Accuracy.** Fixed step, no error control: the step $h = (t_1 - t_0)/((T-1)\,
    \text{substeps})$ is yours to choose. The method has classical order 4 (for very stiff
    problems with non-smooth data the analysis of Hochbruck & Ostermann 2010 guarantees
    less in the worst case; here $g$ is smooth and the fourth order is observed, see the
    tests), so the global error behaves like
    $C h^4$ where $C$ grows with the time derivatives of $g$ along the solution — the
    signal frequencies and amplitudes, and the fast modes of $A_0$ the perturbation
    couples into. Check by halving the step (the error should drop ~16×). On
    the time-varying §4.1.3 loop of ``benchmarks/time_varying.py`` ($|\delta| \le 0.3$,
    $\omega \le 5$ rad/s, fastest pole −39.8; worst of 100 samples) the metrics are
    accurate to ~2e-9 relative with one step per 0.01 s, ~2e-10 with 2 and ~4e-11 with 3
    substeps. Signals should be smooth between
    steps: a jump (a `fojax.Step`, `fojax.PiecewiseConstant`) costs $O(h)$ locally unless it
    falls on a step boundary.

    **Initial layer (`startup`).** An initial state off the slow manifold of $A_0$ excites
    its fast modes; $A_0$ carries them exactly, but the perturbation couples them into
    $g$, whose derivatives are then of the size of the fast eigenvalues until those modes
    have decayed — in the loop above almost the whole error is made in the first
    ~0.05 s. ``startup=(k, s)`` integrates the first ``k`` grid intervals with ``s`` steps
    each and the rest with `substeps`; take $k\,\Delta t \approx 5/|\lambda_{\max}(A_0)|$.
    On that loop (worst of 100 samples) ``substeps=2, startup=(13, 4)`` gives
    ~2e-11 with 2,026 steps, better than uniform ``substeps=3`` (3,000 steps); with
    ``substeps=1`` after the same start-up the bulk step limits (~3e-10: signals up to
    5 rad/s).

    **Arguments:**

    - `model`: ``params_k -> plant``, ``(plant, observers)`` or ``(plant, observers, u)``;
      the plant linear in the state, regular and index 1 along the trajectory, with its
      time dependence entering its differential equations affinely through signals;
      observers LTI (`linear_matrices()`); ``u`` a `fojax.plant.AbstractSignal` of size
      ``plant.m`` or ``None``. Use a stable function object (not a new lambda per call) so
      the compiled kernels are reused.
    - `params`: pytree of arrays with a leading batch axis ``B``.
    - `x0`: ``(B, n)`` initial plant states (made consistent by keeping their slow part, as
      `fojax.simulate` does).
    - `ts`: ``(T,)`` uniform increasing output grid.
    - `metrics`: mapping ``name -> (kind, C)``, ``C`` of shape ``(k, n + Σ observer sizes)``.
    - `reference`: params of one sample (no batch axis) defining $A_0$; ``None``: the
      first sample's.
    - `substeps`: integration steps per grid interval (``≥ 1``).
    - `startup`: ``(k, s)``: the first ``k`` grid intervals with ``s`` steps each (see
      above); ``None``: uniform.
    - `chunk_size`: samples per compiled call (default 4096), rounded up to a multiple of
      ``block × devices``; the last chunk is padded. Chunks, padding, blocks and devices
      are those of the batch kernel (`fojax.simulation._driver.run_batched`, shared with
      `simulate_lti_batch` and `fojax.run_study`): this function only brings the stepping
      (`ExponentialProblem`).
    - `block`: samples stepped together in one time loop (default 256).
    - `devices`: the devices the blocks of a chunk are spread over, round-robin, with
      `jax.shard_map` (default `jax.local_devices()`; on a CPU e.g.
      ``XLA_FLAGS=--xla_force_host_platform_device_count=2`` for two cores). The result
      does not depend on the number of devices.

    **Returns:** a dict ``name -> (B,)`` or ``(B, k)`` array (float64).

    **Raises:** `fojax.errors.InputError` (plant not linear in the state, non-LTI observers, the
    affine decomposition fails the host check, unknown metric kind, non-uniform grid,
    bad `substeps`/`startup`/`reference`), `fojax.errors.ShapeError` (shapes of ``x0``, ``ts``, ``params``,
    metric maps); index-1 checks run on the host for the first sample when the inputs
    are concrete.

    !!! example

        ```python
        def model(p):
            nominal = fojax.DescriptorSystem(E, A, B)
            plant = fojax.UncertainDescriptorSystem(
                nominal, dA=dA, delta=fojax.Sine(p["a"], p["omega"], p["phase"]))
            return plant, (), fojax.Constant(p["fault"])

        out = simulate_batch_exponential(model, params, x0, jnp.linspace(0, 10, 1001),
                                         metrics={"iae": ("iae_l1", Cx)}, substeps=3)
        ```
    """
    x0, Bn = batch_params(params, x0)
    substeps = _positive_int("substeps", substeps, "steps per grid interval")
    if startup is None:
        startup = (0, substeps)
    if not (isinstance(startup, tuple | list) and len(startup) == 2):
        raise InputError(
            "startup must be a pair (n_intervals, substeps): the first n_intervals grid intervals "
            f"are integrated with that many steps each; got {startup!r}."
        )
    n_start = _positive_int("startup[0]", startup[0], "grid intervals", zero=True)
    sub_start = _positive_int("startup[1]", startup[1], "steps per start-up interval")
    chunk_size = _positive_int("chunk_size", chunk_size, "samples per compiled call")
    block = _positive_int("block", block, "samples stepped together")
    T, h, ts = _step_size(ts, who="simulate_batch_exponential")
    n_start = min(n_start, T - 1)
    schedule = (n_start, sub_start, substeps)
    params = jax.tree.map(jnp.asarray, params)
    first = jax.tree.map(lambda a: a[0], params)
    if reference is None:
        reference = first
    else:
        ref_leaves, ref_def = jax.tree.flatten(reference)
        if ref_def != jax.tree.structure(params) or any(
            jnp.shape(r) != jnp.shape(p)[1:] for r, p in zip(ref_leaves, jax.tree.leaves(params))
        ):
            raise InputError(
                "reference must be the params of one sample: the same pytree structure as "
                "params, each leaf without the batch axis "
                f"(expected shapes {[tuple(jnp.shape(p)[1:]) for p in jax.tree.leaves(params)]}, got "
                f"{[tuple(jnp.shape(r)) for r in jax.tree.leaves(reference)]})."
            )
        reference = jax.tree.map(jnp.asarray, reference)
    plant0, observers0, u0 = _parse_model_output(model(first))
    _check_structure(plant0, observers0)
    n = x0.shape[1]
    if plant0.n != n:
        raise ShapeError("x0", f"(B, {plant0.n})", tuple(x0.shape))
    size = n + sum(o.state_size for o in observers0)
    names, kinds, Cstack = _check_metrics(metrics, size)
    ns = sum(sg.size for sg in _plant_signals(plant0))
    concrete = is_concrete(params, x0, ts, reference, Cstack)
    if concrete:
        host_initial_checks(plant0, x0[0], ts[0], u0, strict=False, tol=0.0)
    n_terms = 1 + ns
    setup = _ModelSetup(model, Cstack)
    p = (params, x0)
    if concrete:
        # A0, the plan of the whole batch (read in chunks) and the affine check on sample 0
        A0, plan, per, shared, data0 = prepare(setup, p, (reference, x0[0]), chunk_size)
        check_affine(model, first, data0, A0, CstackOutputs(Cstack), float(ts[0]), float(ts[-1]), ns, plant0.m)
    else:  # under an outer jax.jit: every term per sample
        data, A0 = setup_all(setup, p, (reference, x0[0]))
        plan = _full_plan(size, n_terms)
        per, shared = kernel_inputs(data, plan, jnp)
    keep = np.asarray(plan.keep, dtype=int)
    A0k = A0[keep][:, keep]
    phis = (phi_functions(A0k, h / substeps), phi_functions(A0k, h / sub_start))
    problem = ExponentialProblem(setup, _ModelProblem(model, Cstack, None, None, kinds), shared, phis, plan, schedule)
    out, _ = run_batched(problem, (p, per), ts, chunk_size=chunk_size, block=block, devices=devices)
    out = out.T
    result, off = {}, 0
    for name, (kind, k) in zip(names, kinds):
        if kind in ("iae_l1", "ise_l2"):
            result[name] = out[:, off]
            off += 1
        else:
            result[name] = out[:, off : off + k]
            off += k
    return result
