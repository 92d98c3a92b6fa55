r"""Fault-tolerant control with functional observers (thesis §4.2–4.4).

Every scheme augments the faults into the state, $\bar x = [x; f]$ with $\dot f = 0$
(`fojax.plant.augment_faults`, eq. 4.22/4.26/4.29), designs a functional observer of
$\bar z = \bar L\bar x$ on the augmented system, and feeds the control-law rows of its
estimate back, $u = \Pi\hat z + u_r$:

| scheme | plant | $\bar L$ | control law |
|---|---|---|---|
| sensor (§4.2, eq. 4.21–4.23) | $y = Cx + F_sf$ | $[L\;\;0]$ | $u = Lx + u_r$ (fault-free) |
| actuator (§4.3, eq. 4.24–4.27) | $E\dot x = Ax + B(u + f)$ | $[L\;\;-I]$ | $u = Lx - f + u_r$ |
| simultaneous (§4.4, eq. 4.28–4.29) | both | $\begin{bmatrix}L & -K_a & 0\\ 0 & I & 0\\ 0 & 0 & I\end{bmatrix}$ | $u = Lx - K_af_a + u_r$, and $\hat f$ |

Actuator faults must be *matched*, $F_a = BK_a$ (the thesis's $F_a = B$, $K_a = I$:
"$-I_a$" in eq. 4.29); otherwise no $u$ cancels them and a `fojax.errors.ExistenceConditionError`
is raised. The state feedback $L$ is designed by `design_state_feedback` when not
given (the thesis's two-step procedure, §4.1.2).

**Simulation model.** The faults are *exogenous signals* (`fojax.plant.AbstractSignal`:
`Step`, `Ramp`, `Sine`, `intermittent`, sums ``+``, `Stack`), not states: the
simulated plant is $E\dot x = Ax + Bu + F_af(t)$, $y = Cx + F_sf(t)$, and the closed
loop (`fojax.control.assemble`) is one `DescriptorSystem` on $[x; \zeta; v]$ with input
$[u_r; f]$. Constant faults match the design model; ramps, sines and intermittent
faults show its limits. Because signals are equinox modules with array leaves,
`FaultTolerantControl.simulate` maps over a batch of fault scenarios with `jax.vmap`.

**Comparisons.** The actuator scheme carries the healthy reference model (4.27)
$E\dot x_d = Ax_d + B(Lx_d + u_r)$; the sensor scheme carries the loop that is *not*
fault tolerant: the §4.1 observer of $z = Lx$ designed on the fault-free plant and fed
the faulty measurements (our reading of "the control law $u(t) = Lx(t)$ that is not
fault-tolerant" of Figure 4.8: a law that uses $x$ itself is not affected by sensor
faults at all, so the comparison must go through the measurements). Both are simulated
in the same call, on the same grid, from the same $x(0)$.
"""

from __future__ import annotations

import dataclasses
from typing import Any, TypedDict, Unpack

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._dtype import as_matrix, require_x64
from .._errors import ExistenceConditionError
from ..design import design_functional_observer, FunctionalObserverDesign
from ..design._conditions import check_impulse_free
from ..observer import AbstractObserver
from ..plant import AbstractSignal, as_signal, augment_faults, DescriptorSystem, Stack, Zero
from ..simulation._discretize import simulate_lti
from ._feedback import design_state_feedback, StateFeedbackDesign
from ._loop import assemble, LoopMaps, refuse_feedthrough


SCHEMES = ("sensor", "actuator", "simultaneous")


class FTCTrajectory(eqx.Module):
    r"""A simulated fault-tolerant control loop (all arrays over the grid ``ts``).

    **Fields:** `ts` ``(T,)``; `x` ``(T, n)`` plant state; `xi` ``(T, s)`` observer
    state $[\zeta; v]$; `u` ``(T, m)`` applied control; `z_hat` ``(T, q)`` observer
    output; `y` ``(T, p)`` faulty measurement; `u_r` ``(T, m)`` reference; `f`
    ``(T, nf)`` true faults; `f_hat` ``(T, nf)`` fault estimates (simultaneous scheme;
    ``(T, 0)`` otherwise); `x_ref` ``(T, n)`` and `u_ref` ``(T, m)``: the comparison
    loop (healthy model $x_d$ for the actuator scheme, the non-fault-tolerant loop for
    the sensor scheme; ``(T, 0)`` if none); `stats`: `fojax.simulate`'s statistics (``backend="fojax"``; empty otherwise).
    """

    ts: Float[Array, " T"]
    x: Float[Array, "T n"]
    xi: Float[Array, "T s"]
    u: Float[Array, "T m"]
    z_hat: Float[Array, "T q"]
    y: Float[Array, "T p"]
    u_r: Float[Array, "T m"]
    f: Float[Array, "T nf"]
    f_hat: Float[Array, "T nf"]
    x_ref: Float[Array, "T n"]
    u_ref: Float[Array, "T m"]
    stats: dict


@dataclasses.dataclass(frozen=True)
class FaultTolerantControl:
    r"""A designed fault-tolerant control loop (see the module docstring).

    **Fields:**

    - `scheme`: ``"sensor"``, ``"actuator"`` or ``"simultaneous"``.
    - `plant`: the fault-free plant $(E, A, B, C)$.
    - `Fa` ``(n, nf)``, `Fs` ``(p, nf)``: fault directions of the simulation model.
    - `L`: the state feedback ($u = Lx$); `Lbar`: the augmented functional $\bar L$.
    - `augmented`: the fault-augmented design model $(\bar E, \bar A, \bar B, \bar C)$.
    - `observer`: the functional observer of $\bar L\bar x$ used as controller.
    - `observer_design`: its `FunctionalObserverDesign` (``None`` if an observer was given).
    - `feedback`: the `StateFeedbackDesign` of $L$ (``None`` if `L` was given).
    - `select` ``(m, q)``: rows of $\hat z$ fed back; `fault_rows` ``(nf, q)``: rows of
      $\hat z$ that estimate $f$ (``(0, q)`` unless simultaneous).
    - `closed_loop`: the implementable loop, a `DescriptorSystem` on $[x; \zeta; v]$
      with input $[u_r; f]$; `maps`: its `LoopMaps`.
    - `comparison`: the comparison loop (see module docstring) on its own state with
      the same input, or ``None``; `comparison_maps`: ``(K_X, K_r)`` of its control.
    """

    scheme: str
    plant: DescriptorSystem
    Fa: np.ndarray
    Fs: np.ndarray
    L: np.ndarray
    Lbar: np.ndarray
    augmented: DescriptorSystem
    observer: AbstractObserver
    observer_design: FunctionalObserverDesign | None
    feedback: StateFeedbackDesign | None
    select: np.ndarray
    fault_rows: np.ndarray
    closed_loop: DescriptorSystem
    maps: LoopMaps
    comparison: DescriptorSystem | None
    comparison_maps: tuple | None

    @property
    def n_faults(self) -> int:
        return self.Fa.shape[1]

    def inputs(self, u_r=None, fault=None) -> AbstractSignal:
        """The loop input $[u_r; f]$ as one signal (`fojax.plant.Stack`), for `fojax.simulate`."""
        m = self.plant.m
        u_r = as_signal(u_r, m) if u_r is not None else Zero(m)
        fault = as_signal(fault, self.n_faults) if fault is not None else Zero(self.n_faults)
        return Stack((u_r, fault))

    def simulation_system(self) -> DescriptorSystem:
        """The loop and its comparison stacked block-diagonally (one input $[u_r; f]$)."""
        if self.comparison is None:
            return self.closed_loop
        from scipy.linalg import block_diag

        a, b = self.closed_loop, self.comparison
        E = block_diag(np.asarray(a.E), np.asarray(b.E))
        A = block_diag(np.asarray(a.A), np.asarray(b.A))
        return DescriptorSystem(E, A, np.vstack([np.asarray(a.B), np.asarray(b.B)]))

    def simulate(
        self, x0, ts, *, u_r=None, fault=None, observer_x0=None, backend: str = "stepper", **kwargs
    ) -> FTCTrajectory:
        r"""Simulate the loop (and its comparison) with `fojax.simulate`.

        **Arguments:**

        - `x0`: ``(n,)`` plant initial state (also $x_d(0)$ of the comparison).
        - `ts`: output grid (uniform for the exact method; put fault times on it).
        - `u_r`: reference signal (``None``: zero), size $m$.
        - `fault`: fault signal of size `n_faults` (``None``: fault-free).
        - `observer_x0`: initial observer state (default zero).
        - `backend`: ``"stepper"`` (default): exact host-discretized stepping
          (`fojax.simulation._discretize.simulate_lti`: only the time loop is compiled); ``"fojax"``: `fojax.simulate`
          with `kwargs` (e.g. ``stepper=fojax.Diffrax()`` for faults switching between grid points).

        Works under `jax.vmap` over `fault` / `u_r` / `x0` (write the single call inside).

        **Returns:** an `FTCTrajectory`.
        """
        n, m = self.plant.n, self.plant.m
        s = self.observer.state_size
        x0 = jnp.asarray(x0, dtype=jnp.float64)
        xi0 = (
            jnp.zeros((s,)) if observer_x0 is None else jnp.asarray(observer_x0, dtype=jnp.float64)
        )
        X0 = [x0, xi0]
        if self.comparison is not None:
            X0 += [x0, jnp.zeros((self.comparison.n - n,))]
        system, sig = self.simulation_system(), self.inputs(u_r, fault)
        if backend == "stepper":
            if kwargs:
                raise TypeError(f"unexpected arguments {sorted(kwargs)} for backend='stepper'")
            xs, R = simulate_lti(system, jnp.concatenate(X0), ts, sig)
            ts_out, stats = jnp.asarray(ts), {}
        elif backend == "fojax":
            from ..simulation import simulate as _simulate

            sol = _simulate(system, jnp.concatenate(X0), ts, sig, **kwargs)
            xs, R, ts_out, stats = sol.xs, sol.us, sol.ts, sol.stats
        else:
            raise ValueError(f"backend must be 'stepper' or 'fojax', got {backend!r}")
        N = n + s
        X = xs[:, :N]
        mp = self.maps
        u = X @ mp.K_X.T + R @ mp.K_r.T
        z_hat = X @ mp.Z_X.T + R @ mp.Z_r.T
        y = X @ mp.Y_X.T + R @ mp.Y_r.T
        f_hat = z_hat @ jnp.asarray(self.fault_rows).T
        if self.comparison is not None:
            Xc = xs[:, N:]
            Kc, Krc = self.comparison_maps
            x_ref, u_ref = Xc[:, :n], Xc @ Kc.T + R @ Krc.T
        else:
            x_ref, u_ref = jnp.zeros((len(ts), 0)), jnp.zeros((len(ts), 0))
        return FTCTrajectory(
            ts=ts_out,
            x=X[:, :n],
            xi=X[:, n:],
            u=u,
            z_hat=z_hat,
            y=y,
            u_r=R[:, :m],
            f=R[:, m:],
            f_hat=f_hat,
            x_ref=x_ref,
            u_ref=u_ref,
            stats=stats,
        )

    def __str__(self) -> str:
        o = self.observer
        return (
            f"{self.scheme} fault-tolerant control: n = {self.plant.n}, m = {self.plant.m}, "
            f"nf = {self.n_faults}; observer order q0 + q1 = {o.state_size}, estimates "
            f"{o.output_size} functions; closed loop n = {self.closed_loop.n}"
        )


# --------------------------------------------------------------------------- helpers


class FTCOptions(TypedDict, total=False):
    """The keyword arguments every fault-tolerant control design takes (their meaning is in each
    design function's **Arguments**); absent ones are ``None``, except ``kind="generalized"``."""

    L: Any
    feedback: dict | None
    region: Any
    R: Any
    q0: int | None
    q1: int | None
    kind: str
    solver: str | None
    observer: Any


def _options(fname: str, sys, options: dict) -> dict:
    """`options` with their defaults, after the checks every scheme makes on `sys` (a
    `TypeError` naming an unknown keyword as Python would for `fname`)."""
    for key in options:
        if key not in FTCOptions.__optional_keys__:
            raise TypeError(f"{fname}() got an unexpected keyword argument {key!r}")
    if not isinstance(sys, DescriptorSystem):
        raise TypeError(f"sys must be a fojax.DescriptorSystem, got {type(sys).__name__}.")
    require_x64("fault-tolerant control design")
    refuse_feedthrough(sys)
    return {key: None for key in FTCOptions.__optional_keys__} | {"kind": "generalized"} | options


def _feedback(sys, o: dict, fname: str):
    """The state feedback ``(L, StateFeedbackDesign | None)``: the given `L`, checked, or designed."""
    L = o["L"]
    if L is not None:
        L = as_matrix("L", L, rows=sys.m, cols=sys.n)
        # the schemes need (E, A + BL) admissible (module docstring): a given L must at least
        # make it regular and impulse-free (fojax.analysis decides; design_state_feedback
        # guarantees both for the L it designs)
        E, A, B = (np.asarray(x, dtype=float) for x in (sys.E, sys.A, sys.B))
        check_impulse_free(E, A + B @ np.asarray(L, dtype=float), fname=fname,
                           what="the closed loop (E, A + BL) with the given L")
        return L, None
    fb = design_state_feedback(sys, **(o["feedback"] or {}))
    return fb.L, fb


def _matched(sys: DescriptorSystem, Fa) -> np.ndarray:
    """``K_a`` with ``B K_a = F_a`` (matched actuator faults), or raise."""
    B = np.asarray(sys.B)
    Fa = np.asarray(Fa)
    Ka, *_ = np.linalg.lstsq(B, Fa, rcond=None)
    res = float(np.linalg.norm(B @ Ka - Fa)) / max(1.0, float(np.linalg.norm(Fa)))
    if res > 1e-9:
        raise ExistenceConditionError(
            "actuator-fault matching",
            f"F_a is not in the range of B (‖B K_a − F_a‖/‖F_a‖ = {res:.2e}): no control u "
            "cancels these faults (u = Lx − K_a f_a needs F_a = B K_a).",
            "Add actuators, or only estimate these faults (fojax.design.design_functional_observer "
            "on fojax.plant.augment_faults(sys, Fa=Fa)).",
            lhs=res,
            rhs=0.0,
        )
    return Ka


def _design_observer(sys, Lf, o: dict, structure: bool = True) -> FunctionalObserverDesign:
    """`design_functional_observer` of ``Lf x`` on `sys` with the options' `kind`, `region`,
    `solver` (and `R`, `q0`, `q1` when `structure`)."""
    kw = dict(kind=o["kind"], region=o["region"])
    if structure:
        kw.update(R=o["R"], q0=o["q0"], q1=o["q1"])
    if o["solver"] is not None:
        kw["solver"] = o["solver"]
    return design_functional_observer(sys, Lf, **kw)


def _observer(aug, Lbar, o: dict):
    """``(observer, FunctionalObserverDesign | None)``: the given `observer`, or one designed."""
    observer = o["observer"]
    if observer is None:
        d = _design_observer(aug, Lbar, o)
        return d.observer, d
    if isinstance(observer, FunctionalObserverDesign):
        return observer.observer, observer
    return observer, None


def _build(scheme, sys, Fa, Fs, L, fb, Lbar, aug, obs, odesign, select, fault_rows, comparison):
    loop, maps = assemble(sys.E, sys.A, sys.B, sys.C, obs, Fa=Fa, Fs=Fs, select=select)
    comp, comp_maps = (None, None) if comparison is None else comparison
    Fa, Fs, L, Lbar, select, fault_rows = map(np.asarray, (Fa, Fs, L, Lbar, select, fault_rows))
    return FaultTolerantControl(
        scheme=scheme, plant=sys, Fa=Fa, Fs=Fs, L=L, Lbar=Lbar, augmented=aug, observer=obs,
        observer_design=odesign, feedback=fb, select=select, fault_rows=fault_rows,
        closed_loop=loop, maps=maps, comparison=comp, comparison_maps=comp_maps,
    )


_COMMON_ARGS = r"""
    - `L`: ``(m, n)`` state feedback ($u = Lx$); a given `L` must make $(E, A + BL)$
      regular and impulse-free (`fojax.errors.IrregularSystemError` / `fojax.errors.ImpulsiveSystemError`
      otherwise, checked before any design); designed by `design_state_feedback`
      (with `feedback` as keyword arguments, e.g. ``{"decay": 1.0}``) when ``None``.
    - `region`, `R`, `q0`, `q1`, `kind`, `solver`: the observer design on the augmented
      system, passed to `fojax.design.design_functional_observer` (default region
      ``Disk(-2, 1)``).
    - `observer`: use this observer (e.g. the thesis's printed gains, or a
      `FunctionalObserverDesign`) instead of designing one.
"""


# --------------------------------------------------------------------------- public


def design_sensor_ftc(
    sys: DescriptorSystem, Fs=None, *, compare: bool = True, **options: Unpack[FTCOptions]
) -> FaultTolerantControl:
    r"""Sensor fault-tolerant control (thesis §4.2, eq. 4.21–4.23).

    Plant $E\dot x = Ax + Bu$, $y = Cx + F_sf$. The observer is designed on the
    augmented system $\bar E = \operatorname{blkdiag}(E, I)$,
    $\bar A = \operatorname{blkdiag}(A, 0)$, $\bar B = [B; 0]$, $\bar C = [C\;F_s]$ for
    $\bar L = [L\;0]$: it estimates the fault-free control law $Lx$ from the faulty
    measurements, so that $u = \hat z + u_r \to Lx + u_r$ for constant faults. (Eq. 4.21
    types $F \in \mathbb R^{n\times n_f}$; it is $p \times n_f$. Eq. 4.23's admissibility
    test of $(\bar E, \bar A + \bar B\bar L)$ cannot hold — the fault block of
    $\bar A + \bar B\bar L$ is zero, so $s = 0$ is a pole — what matters is that
    $(E, A + BL)$ is admissible and the observer's error dynamics are stable.)

    **Arguments:**

    - `sys`: the fault-free plant.
    - `Fs`: ``(p, nf)`` sensor fault directions (default $I_p$).
    {common}
    - `compare`: also build the non-fault-tolerant loop (module docstring).

    **Returns:** a `FaultTolerantControl`.
    """
    o = _options("design_sensor_ftc", sys, options)
    Fs = np.eye(sys.p) if Fs is None else np.asarray(as_matrix("Fs", Fs, rows=sys.p))
    nf = Fs.shape[1]
    L, fb = _feedback(sys, o, "design_sensor_ftc")
    aug = augment_faults(sys, Fs=Fs)
    Lbar = np.hstack([np.asarray(L), np.zeros((sys.m, nf))])
    obs, od = _observer(aug, Lbar, o)
    Fa = np.zeros((sys.n, nf))
    comparison = None
    if compare:
        plain = _design_observer(sys, L, o, structure=False).observer
        comp, cmaps = assemble(sys.E, sys.A, sys.B, sys.C, plain, Fa=Fa, Fs=Fs)
        comparison = (comp, (cmaps.K_X, cmaps.K_r))
    return _build("sensor", sys, Fa, Fs, L, fb, Lbar, aug, obs, od,
                  np.eye(sys.m), np.zeros((0, sys.m)), comparison)


def design_actuator_ftc(
    sys: DescriptorSystem, Fa=None, *, compare: bool = True, **options: Unpack[FTCOptions]
) -> FaultTolerantControl:
    r"""Actuator fault-tolerant control (thesis §4.3, eq. 4.24–4.27).

    Plant $E\dot x = Ax + B(u + f)$ (more generally $+F_af$ with $F_a = BK_a$), $y = Cx$.
    The observer is designed on $\bar A = [[A, F_a], [0, 0]]$, $\bar C = [C\;0]$ for
    $\bar L = [L\;\;-K_a]$, so that $u = \hat z + u_r \to Lx - K_af + u_r$ (eq. 4.25) and
    the faults are cancelled. The comparison is the healthy reference model (4.27)
    $E\dot x_d = Ax_d + B(Lx_d + u_r)$.

    **Arguments:**

    - `sys`: the fault-free plant.
    - `Fa`: ``(n, nf)`` actuator fault directions, matched ($F_a = BK_a$); default $B$
      (the thesis: faults add to the inputs).
    {common}
    - `compare`: also simulate the healthy reference model $x_d$.

    **Returns:** a `FaultTolerantControl`.

    **Raises:** `fojax.errors.ExistenceConditionError` when $F_a$ is not matched.
    """
    o = _options("design_actuator_ftc", sys, options)
    Fa = np.asarray(sys.B) if Fa is None else np.asarray(as_matrix("Fa", Fa, rows=sys.n))
    Ka = _matched(sys, Fa)
    nf = Fa.shape[1]
    L, fb = _feedback(sys, o, "design_actuator_ftc")
    aug = augment_faults(sys, Fa=Fa)
    Lbar = np.hstack([np.asarray(L), -Ka])
    obs, od = _observer(aug, Lbar, o)
    Fs = np.zeros((sys.p, nf))
    comparison = None
    if compare:
        m = sys.m
        E, A, B = (np.asarray(x) for x in (sys.E, sys.A, sys.B))
        L = np.asarray(L)
        healthy = DescriptorSystem(E, A + B @ L, np.hstack([B, np.zeros((sys.n, nf))]))
        K_X = L
        K_r = np.hstack([np.eye(m), np.zeros((m, nf))])
        comparison = (healthy, (K_X, K_r))
    return _build("actuator", sys, Fa, Fs, L, fb, Lbar, aug, obs, od,
                  np.eye(sys.m), np.zeros((0, sys.m)), comparison)


def design_simultaneous_ftc(
    sys: DescriptorSystem, *, Fa=None, Fs=None, **options: Unpack[FTCOptions]
) -> FaultTolerantControl:
    r"""Simultaneous fault estimation and fault-tolerant control (thesis §4.4, eq. 4.28–4.29).

    Plant $E\dot x = Ax + Bu + F_af_a$, $y = Cx + F_sf_s$, $f = [f_a; f_s]$, with matched
    actuator faults $F_a = BK_a$. One observer estimates

    $$\bar z = \bar L\bar x,\qquad
      \bar L = \begin{bmatrix}L & -K_a & 0\\ 0 & I_{n_a} & 0\\ 0 & 0 & I_{n_s}\end{bmatrix}$$

    (eq. 4.29's $[L,\ [-I_a\ 0];\ 0,\ I_{n_f}]$ with $K_a = I$): its first $m$ outputs
    are the control law $Lx - K_af_a$, fed back as $u = \hat z_{1:m} + u_r$, the others
    are the fault estimates $\hat f$ (`FTCTrajectory.f_hat`). With sensor faults only
    ($F_a$ absent, as in §4.4.2) the first block row is $[L\;0]$ — the thesis prints a
    $-1$ there (see `fojax.models.example_4_4_2`).

    **Arguments:**

    - `sys`: the fault-free plant.
    - `Fa`: ``(n, na)`` matched actuator fault directions (``None``: no actuator faults).
    - `Fs`: ``(p, ns)`` sensor fault directions (``None``: none). At least one is needed.
    {common}
    **Returns:** a `FaultTolerantControl` (no comparison loop).
    """
    o = _options("design_simultaneous_ftc", sys, options)
    if Fa is None and Fs is None:
        raise ValueError("design_simultaneous_ftc needs Fa=, Fs= or both.")
    n, m, p = sys.n, sys.m, sys.p
    Fa = np.zeros((n, 0)) if Fa is None else np.asarray(as_matrix("Fa", Fa, rows=n))
    Fs = np.zeros((p, 0)) if Fs is None else np.asarray(as_matrix("Fs", Fs, rows=p))
    na, ns = Fa.shape[1], Fs.shape[1]
    Ka = _matched(sys, Fa) if na else np.zeros((m, 0))
    nf = na + ns
    Fa_full = np.hstack([Fa, np.zeros((n, ns))])
    Fs_full = np.hstack([np.zeros((p, na)), Fs])
    L, fb = _feedback(sys, o, "design_simultaneous_ftc")
    aug = augment_faults(sys, Fa=Fa_full, Fs=Fs_full)
    top = np.hstack([np.asarray(L), -Ka, np.zeros((m, ns))])
    bottom = np.hstack([np.zeros((nf, n)), np.eye(nf)])
    Lbar = np.vstack([top, bottom])
    obs, od = _observer(aug, Lbar, o)
    q = m + nf
    select = np.eye(m, q)
    fault_rows = np.hstack([np.zeros((nf, m)), np.eye(nf)])
    return _build(
        "simultaneous", sys, Fa_full, Fs_full, L, fb, Lbar, aug, obs, od, select, fault_rows, None
    )


for _f in (design_sensor_ftc, design_actuator_ftc, design_simultaneous_ftc):
    _f.__doc__ = _f.__doc__.replace("    {common}\n", _COMMON_ARGS.lstrip("\n"))
del _f
