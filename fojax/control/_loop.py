r"""Closed loops of a descriptor plant and a linear observer used as a controller (eq. 4.13).

**The implementable loop.** The plant

$$E\dot x = Ax + Bu + F_a f,\qquad y = Cx + F_s f$$

is driven by $u = \Pi\hat z + B_r u_r$, where $\hat z$ is the output of a linear
observer $\dot\xi = A_o\xi + B_{o,u}u + B_{o,y}y$, $\hat z = C_o\xi + D_uu + D_yy$
(`AbstractObserver.linear_matrices`; for the generalized functional observer
$\xi = [\zeta; v]$, $C_o = [P\;0]$, $D_u = QW_u$, $D_y = QW_y$) and $\Pi$ selects the
rows of $\hat z$ that are the control law ($\Pi = I$ in §4.1–4.3; the first $m$ rows
in §4.4, where the remaining rows are fault estimates). When $\Pi D_u \ne 0$ — a
descriptor plant with $E^\perp B \ne 0$, whose observer uses $w = [-E^\perp Bu; y]$ —
$u$ appears on both sides: it is an algebraic loop, solved exactly,

$$u = K\big(\Pi C_o\xi + \Pi D_y(Cx + F_sf) + B_ru_r\big),\qquad K = (I - \Pi D_u)^{-1},$$

and refused (`fojax.errors.AlgebraicLoopError`) when $I - \Pi D_u$ is singular. Substituting
gives one descriptor system on $[x; \xi]$ with input $[u_r; f]$. No design condition is
assumed: this is the loop that a simulation of plant + observer runs.

**The thesis's coordinates** (eq. 4.13) $\bar x = [x; \varepsilon; v]$ with
$\varepsilon = \zeta - TEx$:

$$\mathcal E = \operatorname{blkdiag}(E, I, I),\quad
\mathcal A = \begin{bmatrix}A + BL & BP & 0\\ 0 & N & J\\ 0 & S & G\end{bmatrix},\quad
\mathcal B = \begin{bmatrix}B\\0\\0\end{bmatrix}.$$

This matrix *assumes* the design conditions a.–d. (it is the implementable loop after
the change of coordinates only when they hold), so its finite poles are by
construction those of $(E, A + BL)$ together with the eigenvalues of
$[N\;J;\,S\;G]$. The *separation property* is the statement that the implementable
loop has the same finite poles; `closed_loop` builds both so that it can be checked
(tests/test_control.py does, to 1e-8, for fojax's designs).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._dtype import as_matrix, require_x64
from .._errors import AlgebraicLoopError, InputError, ShapeError
from ..design import FunctionalObserverDesign
from ..observer import AbstractObserver, GeneralizedFunctionalObserver
from ..plant import DescriptorSystem


COORDINATES = ("plant-observer", "error")
#: ``I − Π D_u`` counts as singular when its reciprocal condition number is below this.
LOOP_RCOND = 1e-12


@dataclasses.dataclass(frozen=True)
class LoopMaps:
    r"""Output maps of an implementable loop on the state $X = [x; \xi]$ with input $r = [u_r; f]$.

    $u = K_X X + K_r r$ (the applied control), $\hat z = Z_X X + Z_r r$ (the full
    observer output) and $y = Y_X X + Y_r r$ (the measurement). NumPy/JAX arrays.
    """

    K_X: Any
    K_r: Any
    Z_X: Any
    Z_r: Any
    Y_X: Any
    Y_r: Any
    n: int
    s: int

    def signal_rows(self, L):
        r"""``(n + q, n + s)`` rows of $[x;\ \hat z - Lx]$ on the loop state $X = [x; \xi]$:
        $[I_n\ 0]$ stacked on $Z_X - [L\ 0]$.

        The functional of a `fojax.Study` of the loop (zero reference: with $r \ne 0$ the
        estimate also has the feed-through $Z_r r$, which a study's $z = LX$ cannot hold),
        so that ``fojax.run_study(study)`` reports per sample the metrics of the state and
        of the estimation error of the control law; e.g. the IAE of $\lVert x\rVert_1$ is
        the sum of the first ``n`` signals' IAEs.

        !!! example

            ```python
            loop = fojax.control.closed_loop(sys, observer)
            maps = fojax.control.loop_maps(sys, observer)
            study = fojax.Study(loop, x0, ts, maps.signal_rows(L), uncertainty=...)
            result = fojax.run_study(study)  # observers=None: the metrics of [x; ẑ − Lx]
            ```
        """
        xp = _namespace(self.Z_X, L)
        L = xp.asarray(L)
        q = self.Z_X.shape[0]
        if L.shape != (q, self.n):
            raise ShapeError("L", (q, self.n), tuple(L.shape), "L is the control law ẑ estimates (u = Lx).")
        state = xp.eye(self.n, self.n + self.s)
        return xp.concatenate([state, xp.asarray(self.Z_X) - L @ state], axis=0)


@eqx.filter_jit
def _jit_linear_matrices(observer):
    return observer.linear_matrices()


def linear_matrices(observer):
    """`observer.linear_matrices()` in one compiled call (faster than eager dispatch of its
    block/concatenate operations for every new observer size); ``None`` if not LTI."""
    return _jit_linear_matrices(observer)


def _namespace(*arrays):
    """NumPy on the host (concrete inputs: no dispatch/compile cost), jax.numpy under tracing."""
    for a in arrays:
        if isinstance(a, jax.core.Tracer):
            return jnp
    return np


def refuse_feedthrough(sys) -> None:
    """The loops here are built for ``y = Cx``: a plant with a nonzero feedthrough ``D`` is refused."""
    if np.any(np.asarray(getattr(sys, "D", 0.0))):
        raise InputError("the observer-based loops are built for plants without feedthrough (y = C x); this "
                         "plant has D != 0. Simulate the plant and its observer with fojax.simulate instead.")


def _observer_of(observer):
    if isinstance(observer, FunctionalObserverDesign):
        return observer.observer
    if not isinstance(observer, AbstractObserver):
        raise TypeError(
            f"observer must be a fojax observer or a FunctionalObserverDesign, got "
            f"{type(observer).__name__}."
        )
    return observer


def assemble(E, A, B, C, observer, *, Fa=None, Fs=None, select=None, Br=None):
    r"""The implementable loop (module docstring) as matrices.

    **Arguments:** the plant matrices, a linear `observer`, fault directions `Fa`
    ``(n, nf)`` / `Fs` ``(p, nf)`` (``None``: no fault input), `select` ``Π``
    ``(m, q)`` (``None``: identity) and `Br` ``(m, k)`` (``None``: identity).

    **Returns:** ``(system, maps)``: a `DescriptorSystem` on ``[x; ξ]`` (full-state
    output) with input ``[u_r; f]`` and the `LoopMaps`.

    **Raises:** `fojax.errors.AlgebraicLoopError`, `fojax.errors.ShapeError`.
    """
    require_x64("closed-loop assembly")
    lm = linear_matrices(observer)
    if lm is None:
        raise TypeError(
            f"{type(observer).__name__} has no linear realisation (linear_matrices() is None); "
            "closed_loop needs an LTI observer."
        )
    xp = _namespace(E, A, B, C, Fa, Fs, select, Br, *lm)
    Ao, Bou, Boy, Co, Du, Dy = (xp.asarray(x) for x in lm)
    E, A, B, C = (xp.asarray(x) for x in (E, A, B, C))
    n, m = B.shape
    p = C.shape[0]
    s, q = Ao.shape[0], Co.shape[0]
    if Bou.shape[1] != m or Boy.shape[1] != p:
        raise ShapeError(
            "observer inputs",
            f"(u: {m}, y: {p}) from the plant",
            f"(u: {Bou.shape[1]}, y: {Boy.shape[1]})",
            "The observer must be designed for this plant's input and output (for FTC: for the "
            "fault-augmented system, which has the same u and y).",
        )
    nf = 0
    if Fa is not None or Fs is not None:
        nf = (Fa if Fa is not None else Fs).shape[1]
    Fa = xp.zeros((n, nf)) if Fa is None else xp.asarray(Fa)
    Fs = xp.zeros((p, nf)) if Fs is None else xp.asarray(Fs)
    Pi = xp.eye(m, q) if select is None else xp.asarray(select)
    if Pi.shape != (m, q):
        raise ShapeError("select", (m, q), tuple(Pi.shape), "It picks the control law rows of ẑ.")
    Br = xp.eye(m) if Br is None else xp.asarray(Br)
    k = Br.shape[1]
    Mloop = xp.eye(m) - Pi @ Du
    Mnp = np.asarray(Mloop) if xp is np else None
    if Mnp is not None and m and np.linalg.cond(Mnp) * LOOP_RCOND > 1.0:
        raise AlgebraicLoopError(
            f"the feedback u = ẑ + u_r is an ill-posed algebraic loop: ẑ depends on u through "
            f"Q Wu (= Q [−E⊥B; 0]) and I − Π Q Wu is singular (condition number "
            f"{np.linalg.cond(Mnp):.3e}). Choose another E⊥ scaling or observer (Q), or a plant "
            "with E⊥B = 0 for the inputs fed back."
        )
    K = xp.linalg.solve(Mloop, xp.eye(m)) if m else xp.zeros((0, 0))
    # u = Kx x + Kxi ξ + Kr u_r + Kf f
    Kx = K @ Pi @ Dy @ C
    Kxi = K @ Pi @ Co
    Kr = K @ Br
    Kf = K @ Pi @ Dy @ Fs
    Acl = xp.block(
        [
            [A + B @ Kx, B @ Kxi],
            [Boy @ C + Bou @ Kx, Ao + Bou @ Kxi],
        ]
    )
    Bcl = xp.block(
        [
            [B @ Kr, B @ Kf + Fa],
            [Bou @ Kr, Boy @ Fs + Bou @ Kf],
        ]
    )
    Ecl = xp.block([[xp.asarray(E), xp.zeros((n, s))], [xp.zeros((s, n)), xp.eye(s)]])
    system = DescriptorSystem(Ecl, Acl, Bcl)
    K_X = xp.concatenate([Kx, Kxi], axis=1)
    K_r = xp.concatenate([Kr, Kf], axis=1)
    Y_X = xp.concatenate([xp.asarray(C), xp.zeros((p, s))], axis=1)
    Y_r = xp.concatenate([xp.zeros((p, k)), Fs], axis=1)
    Z_X = xp.concatenate([xp.zeros((q, n)), Co], axis=1) + Du @ K_X + Dy @ Y_X
    Z_r = Du @ K_r + Dy @ Y_r
    return system, LoopMaps(K_X, K_r, Z_X, Z_r, Y_X, Y_r, n, s)


def closed_loop(
    sys: DescriptorSystem,
    observer,
    *,
    L=None,
    u_r=None,
    coordinates: str = "plant-observer",
) -> DescriptorSystem:
    r"""The observer-based control loop $u = \hat z + u_r$ as a `fojax.DescriptorSystem` (eq. 4.13).

    **Arguments:**

    - `sys`: the plant $(E, A, B, C)$.
    - `observer`: a linear fojax observer whose estimate $\hat z$ has $m$ entries (the
      control law), e.g. a `GeneralizedFunctionalObserver` designed for $z = Lx$, or a
      `fojax.design.FunctionalObserverDesign` (its observer and $L$ are used).
    - `L`: the state feedback $u = Lx$ the observer estimates; needed for
      ``coordinates="error"`` unless `observer` is a design.
    - `u_r`: how the reference enters: ``None`` (default) — the loop's input is
      $u_r \in \mathbb R^m$, $u = \hat z + u_r$; or an ``(m, k)`` matrix $B_r$ —
      $u = \hat z + B_r r$ with input $r \in \mathbb R^k$ (``k = 0``: autonomous loop).
    - `coordinates`: ``"plant-observer"`` (default) — the implementable loop on
      $[x; \zeta; v]$, with the algebraic loop in $u$ solved (see module docstring); or
      ``"error"`` — the thesis's $\mathcal E, \mathcal A, \mathcal B$ on
      $[x; \varepsilon; v]$ (eq. 4.13), valid when conditions a.–d. hold.

    **Returns:** a `DescriptorSystem` with full-state output ($C = I$), ready for
    `fojax.analysis.finite_poles` and `fojax.simulate`. For the applied control and
    the estimate along a simulated trajectory use `loop_maps`.

    **Raises:** `fojax.errors.AlgebraicLoopError` when $I - QW_u$ is singular;
    `fojax.errors.ShapeError` for mismatched sizes; `ValueError` for unknown coordinates.

    !!! example

        ```python
        design = fojax.design.design_functional_observer(sys, L, region=fojax.Disk(-2, 1))
        loop = fojax.control.closed_loop(sys, design)
        fojax.analysis.finite_poles(loop)   # poles of (E, A + BL) ∪ eig([N J; S G])
        ```
    """
    if coordinates not in COORDINATES:
        raise ValueError(f"coordinates must be one of {COORDINATES}, got {coordinates!r}")
    if not isinstance(sys, DescriptorSystem):
        raise TypeError(f"sys must be a fojax.DescriptorSystem, got {type(sys).__name__}.")
    if L is None and isinstance(observer, FunctionalObserverDesign):
        L = observer.L
    refuse_feedthrough(sys)
    obs = _observer_of(observer)
    m = sys.m
    if obs.output_size != m:
        raise ShapeError(
            "observer output ẑ",
            f"{m} entries (one per plant input: u = ẑ + u_r)",
            f"{obs.output_size} entries",
            "Estimate the control law z = Lx with L of shape (m, n); for fault estimates "
            "as well use fojax.control.design_simultaneous_ftc.",
        )
    Br = None if u_r is None else as_matrix("u_r", u_r, rows=m)
    if coordinates == "plant-observer":
        system, _ = assemble(sys.E, sys.A, sys.B, sys.C, obs, Br=Br)
        return system
    if not isinstance(obs, GeneralizedFunctionalObserver):
        raise TypeError(
            "coordinates='error' needs a GeneralizedFunctionalObserver (N, J, S, G, P)."
        )
    if L is None:
        raise ValueError("coordinates='error' needs L (the control law the observer estimates).")
    L = as_matrix("L", L, rows=m, cols=sys.n)
    xp = _namespace(sys.E, sys.A, sys.B, L, Br, obs.N, obs.J, obs.S, obs.G, obs.P)
    Br = xp.eye(m) if Br is None else xp.asarray(Br)
    A, B, E, L = (xp.asarray(x) for x in (sys.A, sys.B, sys.E, L))
    N, J, S, G, P = (xp.asarray(x) for x in (obs.N, obs.J, obs.S, obs.G, obs.P))
    n, q0, q1 = sys.n, obs.q0, obs.q1
    Z = xp.zeros
    Acal = xp.block(
        [
            [A + B @ L, B @ P, Z((n, q1))],
            [Z((q0, n)), N, J],
            [Z((q1, n)), S, G],
        ]
    )
    Ecal = xp.block([[E, Z((n, q0 + q1))], [Z((q0 + q1, n)), xp.eye(q0 + q1)]])
    Bcal = xp.concatenate([B @ Br, Z((q0 + q1, Br.shape[1]))], axis=0)
    return DescriptorSystem(Ecal, Acal, Bcal)


def loop_maps(sys: DescriptorSystem, observer, *, u_r=None) -> LoopMaps:
    r"""Maps from the implementable loop's state $[x; \xi]$ and input $u_r$ to $u$, $\hat z$, $y$.

    Same arguments as `closed_loop` (``coordinates="plant-observer"``). With
    ``X = sol.xs`` and ``R = sol.us`` of a `fojax.simulate` run of the loop,
    ``u = X @ maps.K_X.T + R @ maps.K_r.T``.
    """
    refuse_feedthrough(sys)
    obs = _observer_of(observer)
    Br = None if u_r is None else as_matrix("u_r", u_r, rows=sys.m)
    _, maps = assemble(sys.E, sys.A, sys.B, sys.C, obs, Br=Br)
    return maps
