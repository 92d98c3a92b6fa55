"""Linear time-invariant descriptor systems."""

from __future__ import annotations

import math
from typing import ClassVar

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float

from .._dtype import as_matrix
from .._errors import InputError, ShapeError
from ._base import AbstractPlant


class DescriptorSystem(AbstractPlant):
    r"""A linear descriptor system, continuous or discrete in time,

    $$E\dot x(t) = A x(t) + B u(t), \qquad y(t) = C x(t) + D u(t),$$

    or, with a sampling period `dt` $= h$,

    $$E x[k+1] = A x[k] + B u[k], \qquad y[k] = C x[k] + D u[k], \qquad t_k = t_0 + kh,$$

    with $x \in \mathbb{R}^n$, $u \in \mathbb{R}^m$, $y \in \mathbb{R}^p$ and $E$ possibly
    singular. The matrices are the module's leaves (so a batch of systems is one
    `DescriptorSystem` whose leaves carry a leading batch axis under `jax.vmap`);
    the dimensions are derived from their shapes.

    **Arguments:**

    - `E`, `A`: ``(n, n)`` matrices.
    - `B`: ``(n, m)``; omit (or ``None``) for an autonomous system (``m = 0``).
    - `C`: ``(p, n)``; omit for full-state output ``C = I``.
    - `D`: ``(p, m)`` feedthrough; omit (or ``None``) for ``D = 0``, the thesis's
      ``y = Cx``. The ``design_*`` functions fold it into the observer's input matrix
      (the observer uses ``y - D u``: $W_u \leftarrow W_u - W_y D$,
      `fojax.observer._base.fold_feedthrough`), so the error dynamics and the design
      conditions do not depend on it.
    - `dt`: the sampling period $h > 0$ of a discrete-time model (keyword only); ``None``
      (default) for continuous time. A static field: analysis answers with the
      discrete-time notions (causality, $|\lambda| < 1$), observer design places the
      error eigenvalues inside the unit disk and `fojax.simulate` steps on the grid
      $t_0 + kh$. `fojax.discretize` turns a continuous model into a discrete one.

    Validation happens at construction: shapes must agree (each mismatch raises
    `fojax.errors.ShapeError` naming the matrix, the expected and the actual shape),
    entries must be finite (`fojax.errors.NonFiniteError`) and float64 must be available
    (`fojax.errors.Float64RequiredError`, see the README on enabling 64-bit JAX); a `dt` that
    is not a finite positive number raises `fojax.errors.InputError`.

    A model from python-control or SciPy converts with `fojax.interop.from_control` /
    `fojax.interop.from_scipy`. Sensor faults enter through the fault augmentation
    (`fojax.plant.augment_faults`).

    !!! example

        ```python
        sys = fojax.DescriptorSystem(E, A, B, C)
        sys.n, sys.m, sys.p
        fojax.analysis.finite_poles(sys)
        ```
    """

    E: Float[Array, "n n"]
    A: Float[Array, "n n"]
    B: Float[Array, "n m"]
    C: Float[Array, "p n"]
    D: Float[Array, "p m"]
    dt: float | None = eqx.field(static=True)

    linear_in_state: ClassVar[bool] = True
    #: design files written before `D` existed load with ``D = 0`` (`fojax._serialize`).
    _file_defaults: ClassVar[dict] = {"D": lambda s: jnp.zeros((s.C.shape[-2], s.B.shape[-1]))}

    def __init__(self, E, A=None, B=None, C=None, D=None, *, dt=None):
        _refuse_foreign("DescriptorSystem", E)
        if A is None:
            raise InputError("DescriptorSystem needs E and A (then B, C, D); got E only. For the standard "
                             "system x' = Ax + Bu use DescriptorSystem.from_state_space(A, B, C, D).")
        E = as_matrix("E", E)
        n = E.shape[0]
        if E.shape[1] != n:
            raise ShapeError("E", (n, n), tuple(E.shape), "E must be square (n, n).")
        A = as_matrix("A", A)
        if A.shape != (n, n):
            raise ShapeError(
                "A", (n, n), tuple(A.shape), f"A must be square and match E, which is ({n}, {n})."
            )
        if B is None:
            B = jnp.zeros((n, 0))
        B = as_matrix("B", B, rows=n, hint=f"B needs one row per state (n = {n}).")
        if C is None:
            C = jnp.eye(n)
        C = as_matrix("C", C, cols=n, hint=f"C needs one column per state (n = {n}).")
        p, m = C.shape[0], B.shape[1]
        if D is None:
            D = jnp.zeros((p, m))
        D = as_matrix("D", D, rows=p, cols=m, hint=f"D maps the {m} inputs to the {p} outputs (p, m).")
        self.E, self.A, self.B, self.C, self.D = E, A, B, C, D
        self.dt = check_dt(dt)

    @property
    def m(self) -> int:
        return self.B.shape[-1]

    @property
    def p(self) -> int:
        return self.C.shape[-2]

    def rhs(self, t, x, u):
        return self.A @ x + self.B @ u

    def output(self, t, x, u):
        return self.C @ x + self.D @ u

    @classmethod
    def from_state_space(cls, A, B=None, C=None, D=None, *, dt=None) -> DescriptorSystem:
        r"""The standard system $\dot x = Ax + Bu$ (or $x[k+1] = Ax[k] + Bu[k]$ with `dt`),
        $y = Cx + Du$ as a descriptor system with $E = I$. (A python-control or SciPy
        model: `fojax.interop.from_control`, `fojax.interop.from_scipy`.)"""
        _refuse_foreign("DescriptorSystem.from_state_space", A)
        A = as_matrix("A", A)
        return cls(jnp.eye(A.shape[0]), A, B, C, D, dt=dt)

    def replace(self, **matrices) -> DescriptorSystem:
        """A copy with some matrices (or `dt`) replaced (validated again). Replacing `B` or
        `C` with a different number of columns/rows without a new `D` resets ``D`` to zeros."""
        kw = dict(E=self.E, A=self.A, B=self.B, C=self.C, D=self.D, dt=self.dt)
        unknown = set(matrices) - set(kw)
        if unknown:
            raise TypeError(f"unknown matrices {sorted(unknown)}; expected some of E, A, B, C, D, dt")
        if "D" not in matrices and (("B" in matrices and jnp.shape(matrices["B"])[-1:] != (self.m,))
                                    or ("C" in matrices and jnp.shape(matrices["C"])[:1] != (self.p,))):
            matrices["D"] = None
        kw.update(matrices)
        return DescriptorSystem(**kw)

    def __repr__(self) -> str:  # short: the matrices are printed by `print(sys.A)`.
        dt = "" if self.dt is None else f", dt={self.dt:g}"
        return f"DescriptorSystem(n={self.n}, m={self.m}, p={self.p}, rank E={_rank_or_q(self.E)}{dt})"


def check_dt(dt) -> float | None:
    """`dt` as a Python float (``None`` stays ``None``: continuous time); `fojax.errors.InputError`
    unless it is a finite number ``> 0``."""
    if dt is None:
        return None
    try:
        h = float(dt)
    except (TypeError, ValueError):
        raise InputError(f"dt must be a positive sampling period (a float) or None for continuous time; "
                         f"got {dt!r} of type {type(dt).__name__}.") from None
    if isinstance(dt, bool) or not (math.isfinite(h) and h > 0):
        raise InputError(f"dt must be a finite sampling period > 0 (or None for continuous time); got dt={dt!r}. "
                         "Pass e.g. dt=0.01.")
    return h


def _refuse_foreign(where: str, first) -> None:
    """A python-control / SciPy model passed where matrices are expected: a clear error."""
    mod = type(first).__module__ or ""
    if mod.split(".")[0] == "control" or mod.startswith("scipy.signal"):
        name, lib = type(first).__name__, mod.split(".")[0]
        fix = "fojax.interop.from_control(sys, E=None)" if lib == "control" else "fojax.interop.from_scipy(sys, E=None)"
        raise InputError(f"{where} takes matrices (E, A, B, C, D), got a {lib} {name}; convert the model with {fix}.")


def _rank_or_q(E) -> str:
    try:
        from .._linalg import rank

        return str(rank(E))
    except Exception:  # traced values
        return "?"



def augment_faults(sys: DescriptorSystem, Fa=None, Fs=None, *, ramp: bool = False) -> DescriptorSystem:
    r"""Augment a descriptor system with its faults as extra states (thesis eq. 3.196).

    For

    $$E\dot x = Ax + Bu + F_a f, \qquad y = Cx + Du + F_s f,$$

    with constant faults ($\dot f = 0$) the augmented state is $\chi = [x; f]$ and

    $$\mathbf E = \begin{bmatrix}E&0\\0&I\end{bmatrix},\;
      \mathbf A = \begin{bmatrix}A&F_a\\0&0\end{bmatrix},\;
      \mathbf B = \begin{bmatrix}B\\0\end{bmatrix},\;
      \mathbf C = [C\;\;F_s],\; \mathbf D = D.$$

    With `ramp=True` (Remark 9: $\ddot f = 0$) the state is $[x; f; \dot f]$ and
    $\tfrac{d}{dt}f = \dot f$, $\tfrac{d}{dt}\dot f = 0$.

    For a discrete-time `sys` (``dt`` $= h$) the fault rows are the sampled versions:
    $f[k+1] = f[k]$ (the ``0`` block of $\mathbf A$ becomes $I$), and with `ramp=True`
    $f[k+1] = f[k] + h\,\dot f[k]$, $\dot f[k+1] = \dot f[k]$ (exact for a ramp).

    **Arguments:**

    - `sys`: the fault-free system.
    - `Fa`: ``(n, n_f)`` actuator/process fault directions (``None``: zeros).
    - `Fs`: ``(p, n_f)`` sensor fault directions (``None``: zeros).
      At least one of `Fa`, `Fs` must be given; both must have the same ``n_f``.

    **Returns:** the augmented `DescriptorSystem` with ``n + n_f`` (or ``n + 2 n_f``) states.
    """
    n, m, p = sys.n, sys.m, sys.p
    if Fa is None and Fs is None:
        raise ShapeError("Fa/Fs", "at least one fault matrix", "none", "Pass Fa=, Fs= or both.")
    if Fa is not None:
        Fa = as_matrix("Fa", Fa, rows=n, hint=f"Fa needs one row per state (n = {n}).")
    if Fs is not None:
        Fs = as_matrix("Fs", Fs, rows=p, hint=f"Fs needs one row per output (p = {p}).")
    nf = (Fa if Fa is not None else Fs).shape[1]
    if Fa is None:
        Fa = jnp.zeros((n, nf))
    if Fs is None:
        Fs = jnp.zeros((p, nf))
    if Fa.shape[1] != Fs.shape[1]:
        raise ShapeError(
            "Fs", (p, Fa.shape[1]), tuple(Fs.shape), "Fa and Fs must have the same number of faults."
        )
    Z = jnp.zeros
    hold = Z((nf, nf)) if sys.dt is None else jnp.eye(nf)  # ḟ = 0, or f[k+1] = f[k]
    if not ramp:
        E = jnp.block([[sys.E, Z((n, nf))], [Z((nf, n)), jnp.eye(nf)]])
        A = jnp.block([[sys.A, Fa], [Z((nf, n)), hold]])
        B = jnp.concatenate([sys.B, Z((nf, m))], axis=0)
        C = jnp.concatenate([sys.C, Fs], axis=1)
    else:
        E = jnp.block(
            [
                [sys.E, Z((n, 2 * nf))],
                [Z((2 * nf, n)), jnp.eye(2 * nf)],
            ]
        )
        A = jnp.block(
            [
                [sys.A, Fa, Z((n, nf))],
                [Z((nf, n)), hold, (1.0 if sys.dt is None else sys.dt) * jnp.eye(nf)],
                [Z((nf, n)), Z((nf, nf)), hold],
            ]
        )
        B = jnp.concatenate([sys.B, Z((2 * nf, m))], axis=0)
        C = jnp.concatenate([sys.C, Fs, Z((p, nf))], axis=1)
    return DescriptorSystem(E, A, B, C, sys.D, dt=sys.dt)


def check_functional(sys: AbstractPlant, L, name: str = "L"):
    """Validate a functional matrix ``L`` of shape ``(q, n)``; returns it as float64."""
    return as_matrix(name, L, cols=sys.n, hint=f"{name} needs one column per state (n = {sys.n}).")
