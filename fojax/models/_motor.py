"""§2.1.1: the electrical motor driving a rotary load through a gear (eqs. 2.3–2.4)."""

from __future__ import annotations

from ._base import _array, linear_example, ThesisExample


def electrical_motor(
    J: float = 0.01,
    beta: float = 0.1,
    L: float = 0.5,
    R: float = 1.0,
    K_T: float = 0.01,
    K_b: float = 0.01,
    r1: float = 0.01,
    r2: float = 0.02,
    C=None,
) -> ThesisExample:
    r"""DC motor coupled to a rotary load (thesis §2.1.1, eqs. 2.3–2.4).

    With state $x = [\omega_1, i, \omega_2]$ (motor speed, armature current, load
    speed) and input the armature voltage $V$:

    $$\begin{bmatrix}J&0&0\\0&L&0\\0&0&0\end{bmatrix}\dot x =
      \begin{bmatrix}-\beta&K_T&0\\-K_b&-R&0\\r_1&0&-r_2\end{bmatrix}x
      + \begin{bmatrix}0\\1\\0\end{bmatrix}V,$$

    the third row being the gear constraint $r_1\omega_1 = r_2\omega_2$.

    **Deviations from the thesis.**

    - The printed matrix (2.4) has $+R$ in row 2; the derivation (2.3),
      $L\,\dot i = -K_b\omega_1 - R\,i + V$, gives $-R$ (a resistor dissipates). We use
      $-R$. With $-R$ the finite poles are the roots of
      $JLs^2 + (JR + \beta L)s + (\beta R + K_T K_b)$, stable for positive parameters.
    - The thesis gives no numerical values. The defaults are the small DC motor of
      the University of Michigan "Control Tutorials for MATLAB and Simulink" speed
      example ($J = 0.01$ kg m², $\beta = 0.1$ N m s, $K_T = K_b = 0.01$, $R = 1\,\Omega$,
      $L = 0.5$ H) with a 2:1 gear ($r_1 = 0.01$ m, $r_2 = 0.02$ m): plausible
      values, not the thesis's.
    - The thesis gives no output matrix. The default measures the load speed,
      $y = \omega_2$ (``C = [[0, 0, 1]]``), which makes the triplet impulse observable
      and leaves the current to be estimated. Pass `C` to choose another output.

    **Arguments:** the physical parameters above (SI units) and an optional
    ``(p, 3)`` output matrix `C`.

    **Returns:** a `ThesisExample` with `system` the `fojax.DescriptorSystem` and
    `params` (a dict of the physical parameters). The symbol ``L`` is the inductance
    here, so the parameters live in `params`, not as attributes.
    """
    E = _array([[J, 0, 0], [0, L, 0], [0, 0, 0]])
    A = _array([[-beta, K_T, 0], [-K_b, -R, 0], [r1, 0, -r2]])
    B = _array([[0], [1], [0]])
    C = _array([[0, 0, 1]]) if C is None else _array(C)
    params = dict(J=J, beta=beta, L=L, R=R, K_T=K_T, K_b=K_b, r1=r1, r2=r2)
    notes = (
        "Eq. 2.4 prints +R at A[1, 1]; the derivation 2.3 (L di/dt = -K_b w1 - R i + V) "
        "gives -R, which is used.",
        "The thesis gives no numerical parameters; defaults are the U. Michigan CTMS "
        "DC-motor speed example with a 2:1 gear (plausible values, not the thesis's).",
        "The thesis gives no output matrix; default y = omega_2 (load speed).",
    )
    return linear_example("electrical_motor", "2.1.1", notes, E, A, B, C, params=params)
