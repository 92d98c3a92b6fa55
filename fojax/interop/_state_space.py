r"""python-control and SciPy state-space models in and out.

**In.** `from_control` and `from_scipy` read $(A, B, C, D)$ of a state-space model (a
transfer function is converted to state space by its own library first) and build the
`fojax.DescriptorSystem`

$$E\dot x = Ax + Bu, \qquad y = Cx + Du,$$

with $E = I$ unless an ``(n, n)`` `E` is given.

**Out.** `to_control` and `to_scipy` export

- a plant with $E = I$ as $(A, B, C, D)$ itself;
- a regular, impulse-free descriptor system by its exact state-space equivalent: in the
  SVD coordinates of $E$ ($U^\top E V = \mathrm{diag}(\Sigma, 0)$, $x = V[x_1; x_2]$,
  $U^\top A V = [\tilde A_{ij}]$, $U^\top B = [\tilde B_1; \tilde B_2]$, $CV = [C_1\;C_2]$)
  impulse-freeness means $\tilde A_{22}$ is invertible, the algebraic equation gives
  $x_2 = -\tilde A_{22}^{-1}(\tilde A_{21}x_1 + \tilde B_2 u)$ and

  $$\dot x_1 = \Sigma^{-1}(\tilde A_{11} - \tilde A_{12}\tilde A_{22}^{-1}\tilde A_{21})x_1
    + \Sigma^{-1}(\tilde B_1 - \tilde A_{12}\tilde A_{22}^{-1}\tilde B_2)u,\quad
    y = (C_1 - C_2\tilde A_{22}^{-1}\tilde A_{21})x_1 + (D - C_2\tilde A_{22}^{-1}\tilde B_2)u,$$

  whose transfer function equals $C(sE - A)^{-1}B + D$ at every $s$ (the fast
  subsystem contributes the static feedthrough). It is `fojax.simulation.reduce_index1`
  (``As, Bs, Cs, Ds``); its state is $x_1 = V_1^\top x$. A singular pencil raises
  `fojax.errors.IrregularSystemError`, an impulsive one `fojax.errors.ImpulsiveSystemError`.
- every linear observer (generalized, proportional, PI, unknown-input, the
  finite-time observer's running estimate, a design's observer) as the system with
  inputs $[u; y]$ and output the estimate $\hat z$:
  $\dot\xi = A_o\xi + [B_u\;B_y][u; y]$, $\hat z = C_o\xi + [D_u\;D_y][u; y]$
  (`fojax.observer.AbstractObserver.linear_matrices`). A Takagi–Sugeno observer is not linear:
  export one rule (`observer.rule(i)`).
"""

from __future__ import annotations

import numpy as np

from .._errors import InputError
from ..plant import DescriptorSystem


def _np(x) -> np.ndarray:
    return np.asarray(x, dtype=float)


def _system(E, A, B, C, D, dt, source: str) -> DescriptorSystem:
    A = _np(A)
    n = A.shape[0]
    if E is None:
        E = np.eye(n)
    if dt in (None, 0, False):
        return DescriptorSystem(E, A, B, C, D)
    try:
        return DescriptorSystem(E, A, B, C, D, dt=float(dt))
    except TypeError:
        raise InputError(f"{source} is a discrete-time model (dt = {dt}); this fojax version builds "
                         "continuous-time descriptor systems only.") from None


def from_control(sys, E=None) -> DescriptorSystem:
    r"""A python-control model as a `fojax.DescriptorSystem` ($E\dot x = Ax + Bu$, $y = Cx + Du$).

    **Arguments:**

    - `sys`: a `control.StateSpace` (or a `control.TransferFunction`, converted by
      `control.ss` first).
    - `E`: ``(n, n)`` descriptor matrix (default: identity).

    **Returns:** the `fojax.DescriptorSystem` with the model's $A, B, C, D$ (its `dt`
    carried over when fojax supports discrete time).

    **Raises:** `fojax.errors.InputError` when `sys` is not a python-control LTI model;
    `fojax.errors.ShapeError` for an `E` of the wrong shape.

    !!! example

        ```python
        P = control.ss(A, B, C, D)
        plant = fojax.interop.from_control(P)
        design = fojax.design_functional_observer(plant, L)
        ```
    """
    import control

    if isinstance(sys, control.TransferFunction):
        sys = control.ss(sys)
    if not isinstance(sys, control.StateSpace):
        raise InputError(f"from_control needs a control.StateSpace or control.TransferFunction, got "
                         f"{type(sys).__name__}. For SciPy models use fojax.interop.from_scipy; for matrices "
                         "fojax.DescriptorSystem(E, A, B, C, D).")
    return _system(E, sys.A, sys.B, sys.C, sys.D, sys.dt, "the python-control model")


def from_scipy(sys, E=None) -> DescriptorSystem:
    r"""A SciPy model as a `fojax.DescriptorSystem` ($E\dot x = Ax + Bu$, $y = Cx + Du$).

    **Arguments:**

    - `sys`: a `scipy.signal.StateSpace`, any `scipy.signal.lti` / `dlti` (transfer
      function, zeros-poles-gain: converted with ``to_ss()``), or a tuple ``(A, B, C, D)``
      (the form `scipy.signal.lsim` accepts).
    - `E`: ``(n, n)`` descriptor matrix (default: identity).

    **Returns:** the `fojax.DescriptorSystem`.

    **Raises:** `fojax.errors.InputError` for anything else.
    """
    from scipy import signal

    dt = None
    if isinstance(sys, signal.lti | signal.dlti):
        dt = getattr(sys, "dt", None)
        ss = sys if isinstance(sys, signal.StateSpace) else sys.to_ss()
        A, B, C, D = ss.A, ss.B, ss.C, ss.D
    elif isinstance(sys, tuple | list) and len(sys) == 4:
        A, B, C, D = sys
    else:
        raise InputError(f"from_scipy needs a scipy.signal StateSpace / lti / dlti or an (A, B, C, D) tuple, "
                         f"got {type(sys).__name__}. For python-control models use fojax.interop.from_control.")
    return _system(E, A, B, C, D, dt, "the SciPy model")


def state_space(obj) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    r"""``(A, B, C, D)`` (NumPy, float64) of a plant, an observer or a design (module docstring).

    **Arguments:**

    - `obj`: a `fojax.DescriptorSystem` (``E = I``, or regular and impulse-free: its exact
      state-space equivalent), a linear `fojax.observer.AbstractObserver` (inputs ``[u; y]``,
      output ``ẑ``) or a design result (its observer).

    **Raises:** `fojax.errors.IrregularSystemError`, `fojax.errors.ImpulsiveSystemError` (a descriptor
    system without a state-space equivalent); `fojax.errors.InputError` for a nonlinear or
    time-varying observer or another object.
    """
    from ..observer import AbstractObserver

    obj = getattr(obj, "observer", obj) if not isinstance(obj, DescriptorSystem | AbstractObserver) else obj
    if isinstance(obj, DescriptorSystem):
        E = _np(obj.E)
        if np.array_equal(E, np.eye(E.shape[0])):
            return _np(obj.A), _np(obj.B), _np(obj.C), _np(obj.D)
        from ..simulation import reduce_index1

        red = reduce_index1(obj)
        return _np(red.As), _np(red.Bs), _np(red.Cs), _np(red.Ds)
    if isinstance(obj, AbstractObserver):
        lm = obj.linear_matrices()
        if lm is None:
            hint = " Export one rule: observer.rule(i)." if hasattr(obj, "rule") else ""
            raise InputError(f"{type(obj).__name__} is not a linear time-invariant observer (linear_matrices() "
                             f"is None), so it has no state-space form.{hint}")
        B = np.concatenate([_np(lm.Bu), _np(lm.By)], axis=1)
        D = np.concatenate([_np(lm.Du), _np(lm.Dy)], axis=1)
        return _np(lm.A), B, _np(lm.C), D
    raise InputError(f"expected a fojax.DescriptorSystem, a fojax observer or a design; got {type(obj).__name__}. "
                     "A python-control / SciPy model converts the other way: fojax.interop.from_control / "
                     "from_scipy.")


def _names(obj):
    """``(inputs, outputs)`` signal names of an observer export, else ``(None, None)``."""
    from ..observer import AbstractObserver

    obs = getattr(obj, "observer", obj)
    if not isinstance(obs, AbstractObserver) or isinstance(obj, DescriptorSystem):
        return None, None
    lm = obs.linear_matrices()
    m, p, q = lm.Bu.shape[1], lm.By.shape[1], lm.C.shape[0]
    return [f"u[{i}]" for i in range(m)] + [f"y[{i}]" for i in range(p)], [f"zhat[{i}]" for i in range(q)]


def _dt(obj):
    dt = getattr(getattr(obj, "observer", obj), "dt", None)
    return None if dt is None else float(dt)


def to_control(obj):
    r"""A plant, observer or design as a python-control `control.StateSpace` (module docstring).

    **Arguments:**

    - `obj`: a `fojax.DescriptorSystem` (``E = I``, or regular and impulse-free), a linear
      observer, or a design result.

    **Returns:** `control.StateSpace` (continuous, ``dt = 0``, unless `obj` has a `dt`);
    an observer's inputs are named ``u[i]``, ``y[j]`` and its outputs ``zhat[k]``.

    **Raises:** as `fojax.interop.state_space`.

    !!! example

        ```python
        Obs = fojax.interop.to_control(design)          # inputs [u; y], output ẑ
        resp = control.forced_response(Obs, T=ts, U=np.vstack([u, y]))
        ```
    """
    import control

    A, B, C, D = state_space(obj)
    inputs, outputs = _names(obj)
    dt = _dt(obj)
    kw = {} if inputs is None else dict(inputs=inputs, outputs=outputs)
    return control.ss(A, B, C, D, 0 if dt is None else dt, **kw)


def to_scipy(obj):
    r"""A plant, observer or design as a `scipy.signal.StateSpace` (continuous, or `dlti`
    with ``dt`` when `obj` has one); see `to_control`. ``tuple(fojax.interop.state_space(obj))``
    is the ``(A, B, C, D)`` tuple `scipy.signal.lsim` also accepts."""
    from scipy import signal

    A, B, C, D = state_space(obj)
    dt = _dt(obj)
    return signal.StateSpace(A, B, C, D) if dt is None else signal.StateSpace(A, B, C, D, dt=dt)
