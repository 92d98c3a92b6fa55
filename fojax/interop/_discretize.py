r"""`fojax.discretize`: zero-order-hold discretization of descriptor systems and observers.

**Descriptor systems (exact, derived).** Let $(E, A)$ be regular and impulse-free (index
$\le 1$) and take the SVD coordinates of analysis's split (`fojax.analysis.index1_split`):
$E = U_1\Sigma_1V_1^\top$, $x = V_1x_1 + V_2x_2$, $A_{ij} = U_i^\top AV_j$,
$B_i = U_i^\top B$. The equations are

$$\Sigma_1\dot x_1 = A_{11}x_1 + A_{12}x_2 + B_1u,\qquad 0 = A_{21}x_1 + A_{22}x_2 + B_2u,$$

with $A_{22}$ invertible (index 1), so $\dot x_1 = A_sx_1 + B_su$ with
$A_s = \Sigma_1^{-1}(A_{11} - A_{12}A_{22}^{-1}A_{21})$,
$B_s = \Sigma_1^{-1}(B_1 - A_{12}A_{22}^{-1}B_2)$ (the simulation layer's host reduction,
`fojax.simulation._reduction.reduce_host`). With the input held,
$u(t) = u[k]$ on $[t_k, t_k + h)$, the slow state is sampled exactly:
$x_1[k+1] = \Phi x_1[k] + \Gamma u[k]$, $\Phi = e^{A_sh}$,
$\Gamma = \int_0^h e^{A_ss}\,\mathrm ds\,B_s$ (one exponential of the Van Loan matrix
$\begin{bmatrix}A_s&B_s\\0&0\end{bmatrix}h$: the exact step of
`fojax.simulation._discretize.discretize_host` with one quadrature node, exact for a
constant input), and the algebraic equation holds at every
sample with $u(t_k) = u[k]$: $0 = U_2^\top(Ax[k] + Bu[k])$. Stacking the two (and
multiplying by the orthogonal $[V_1\;V_2]$ on the left) gives the discrete descriptor system

$$E_dx[k+1] = A_dx[k] + B_du[k],\quad E_d = V_1V_1^\top,\;
A_d = V_1\Phi V_1^\top + V_2U_2^\top A,\; B_d = V_1\Gamma + V_2U_2^\top B,\; C_d = C,$$

in the same state $x$: $x[k] = x(t_k)$ exactly. It is regular and causal (in the
coordinates $V^\top x$ its pencil is block triangular with $zI - \Phi$ and $-A_{22}$ on the
diagonal), its finite poles are $e^{\lambda h}$ for the finite poles $\lambda$ of $(E, A)$,
and for $E = I$ it is the state-space ZOH: $E_d = I$, $A_d = e^{Ah}$ (what
`scipy.signal.cont2discrete` returns). Impulsive systems have no ZOH equivalent of this
kind (the state depends on derivatives of the input): `fojax.errors.ImpulsiveSystemError`.

**Observers (their own dynamics).** A continuous LTI observer
$\dot\xi = \mathbb A\xi + B_uu + B_yy$, $\hat z = C_\xi\xi + D_uu + D_yy$ (for the
generalized functional observer: $\mathbb A = [N\;J;\;S\;G]$, driven by $w = W_uu + W_yy$
and $u$) is discretized with $u$ and $y$ held over each period:
$\xi[k+1] = e^{\mathbb Ah}\xi[k] + \Gamma_ww[k] + \Gamma_uu[k]$, so its error eigenvalues
are $e^{\lambda h}$ for the eigenvalues $\lambda$ of $\mathbb A$. The result is a
`fojax.GeneralizedFunctionalObserver` with ``dt = h`` whose state is the whole
$\xi = [\zeta; v]$ ($N_d = e^{\mathbb Ah}$, $q_1 = 0$; the held input reaches $v$ as
well, which the $[\zeta; v]$ block form cannot express). This is the sampled-data
implementation of the continuous design (what a controller running at period $h$ computes);
because $y$ varies between samples while the observer holds it, its estimate of a
continuous plant differs from $Lx$ by $O(h)$. For an observer that is exact on the samples,
design in discrete time: ``design_functional_observer(discretize(sys, h), L)``.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .._dtype import to_numpy
from .._errors import ImpulsiveSystemError, InputError, IrregularSystemError
from ..plant._descriptor import check_dt, DescriptorSystem


METHODS = ("zoh",)


def _zoh(As: np.ndarray, Bs: np.ndarray, h: float) -> tuple[np.ndarray, np.ndarray]:
    r"""``(Φ, Γ)`` = ``(e^{A h}, ∫_0^h e^{A s} ds B)``: the simulation layer's exact step
    (`discretize_host`) with one node, whose single weight is the Van Loan block Γ."""
    from ..simulation._discretize import discretize_host

    Phi, W = discretize_host(As, Bs, h, nu=1)
    return Phi, W[0]


def _discretize_system(sys: DescriptorSystem, h: float) -> DescriptorSystem:
    from ..analysis import index1_split

    E, A, B, C = (to_numpy(x) for x in (sys.E, sys.A, sys.B, sys.C))
    sp = index1_split(E, A, fname="discretize")
    if not sp.regular:
        raise IrregularSystemError(f"discretize: the pencil sE - A is singular ({sp.failed}); a singular "
                                   "model has no unique solution to sample.")
    if sp.index > 1:
        raise ImpulsiveSystemError(
            f"discretize: the system is impulsive (index {sp.index}); its state depends on derivatives of the "
            "input, which a zero-order hold does not define. Make it impulse-free (fojax.analysis.structure_report "
            "shows the structure), e.g. by a proportional-derivative feedback, before sampling."
        )
    from ..simulation._reduction import reduce_host

    r = sp.rank
    U2, V1, V2 = sp.U2, sp.V1, sp.V2
    As, Bs = reduce_host(E, A, B)[:2]  # the slow subsystem in the same split (x1 = V1ᵀx)
    Phi, Gam = _zoh(As, Bs, h)
    Ed = V1 @ V1.T
    Ad = V1 @ Phi @ V1.T + V2 @ (U2.T @ A)
    Bd = V1 @ Gam + V2 @ (U2.T @ B)
    if r == E.shape[0]:
        Ed = np.eye(r)  # V V^T = I exactly
    extra = {"D": sys.D} if getattr(sys, "D", None) is not None else {}
    return DescriptorSystem(Ed, Ad, Bd, C, dt=h, **extra)


def _discretize_observer(obs, h: float):
    from ..observer import GeneralizedFunctionalObserver

    if not isinstance(obs, GeneralizedFunctionalObserver):
        raise InputError(
            f"discretize: expected a fojax.DescriptorSystem, a functional observer (GeneralizedFunctionalObserver) "
            f"or a design holding one; got {type(obs).__name__}."
        )
    N, J, S, G = (to_numpy(x) for x in (obs.N, obs.J, obs.S, obs.G))
    F, M, H, P = (to_numpy(x) for x in (obs.F, obs.M, obs.H, obs.P))
    q0, q1 = N.shape[0], G.shape[0]
    Aa = np.block([[N, J], [S, G]])
    Bw = np.vstack([F, M])
    Bu = np.vstack([H, np.zeros((q1, H.shape[1]))])
    nw = Bw.shape[1]
    Phi, Gam = _zoh(Aa, np.hstack([Bw, Bu]), h)
    s = q0 + q1
    return GeneralizedFunctionalObserver(
        Phi, np.zeros((s, 0)), Gam[:, :nw], Gam[:, nw:], np.zeros((0, s)), np.zeros((0, 0)), np.zeros((0, nw)),
        np.hstack([P, np.zeros((P.shape[0], q1))]), obs.Q, obs.Wu, obs.Wy, kind=obs.kind, dt=h,
    )


def discretize(system_or_observer, dt, method: str = "zoh"):
    r"""The discrete-time equivalent of a continuous model or observer with sampling period `dt`.

    Zero-order hold: the input (and, for an observer, the measurement) is held constant
    over each period $[t_k, t_k + h)$. Derivations in `fojax.interop._discretize`.
    Host-only (NumPy/SciPy: analysis's rank decision and `scipy.linalg.expm`); call it
    outside `jax.jit`.

    **Arguments:**

    - `system_or_observer`: a continuous `fojax.DescriptorSystem` (regular, impulse-free),
      a continuous `fojax.GeneralizedFunctionalObserver`, or a design holding one
      (``design.observer`` is discretized).
    - `dt`: the sampling period $h > 0$.
    - `method`: ``"zoh"`` (the only one).

    **Returns:**

    - for a system, a `fojax.DescriptorSystem` with ``dt = h``,
      $E_dx[k+1] = A_dx[k] + B_du[k]$, $y[k] = Cx[k]$, exact at the samples
      ($x[k] = x(t_k)$ for held inputs), finite poles $e^{\lambda h}$; for $E = I$,
      $A_d = e^{Ah}$ and $B_d = \int_0^he^{As}\mathrm ds\,B$;
    - for an observer, a `fojax.GeneralizedFunctionalObserver` with ``dt = h`` and error
      eigenvalues $e^{\lambda h}$ ($\lambda$ those of the continuous error matrix).

    **Raises:** `fojax.errors.InputError` (bad `dt`, unknown `method`, an object that is already
    discrete or not discretizable), `fojax.errors.ImpulsiveSystemError` (an impulsive system),
    `fojax.errors.IrregularSystemError` (a singular pencil).

    !!! example

        ```python
        sys_d = fojax.discretize(sys, 0.05)            # E_d x[k+1] = A_d x[k] + B_d u[k]
        obs_d = fojax.discretize(design.observer, 0.05)  # eigenvalues exp(λ·0.05)
        fojax.simulate(sys_d, x0, t0 + 0.05 * jnp.arange(200), u, observers=obs_d)
        ```
    """
    h = check_dt(dt)
    if h is None:
        raise InputError("discretize needs a sampling period dt > 0; got None.")
    if method not in METHODS:
        raise InputError(f"discretize: method must be one of {METHODS}; got {method!r}.")
    obj = system_or_observer
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type) and hasattr(obj, "observer"):
        obj = obj.observer
    if getattr(obj, "dt", None) is not None:
        raise InputError(f"discretize: the {type(obj).__name__} is already discrete-time (dt = {obj.dt:g}); "
                         "discretize a continuous one.")
    if isinstance(obj, DescriptorSystem):
        return _discretize_system(obj, h)
    return _discretize_observer(obj, h)
