"""Chapter 3 numerical examples: §3.1.2, §3.1.3 and §3.3.7."""

from __future__ import annotations

import numpy as np

from ..plant import DescriptorSystem
from ._base import _array, linear_example, ThesisExample


def example_3_1_2() -> ThesisExample:
    r"""§3.1.2: finite-time functional observer estimating a stabilising control law.

    $n = 4$, $\operatorname{rank}E = 3$ (row 3 algebraic), $m = 2$, $p = 3$
    ($y = [x_1, x_2, x_4]$). The functional is the state feedback $z = Lx$ fed back as
    $u = \hat z$.

    **Typo resolutions.**

    - $A_{4,1}$ is printed $2$; it must be $3$. With the printed $A$ the finite poles
      of $(E, A)$ are $2.869, -3.934 \pm 5.970i$ and those of $(E, A + BL)$
      $-6.375, -9.454, -274.661$, not the printed ones. Changing $A_{4,1}$ to $3$
      gives $3.064, -4.032 \pm 6.000i$ and $-5.017, -10.839, -274.635$, matching both
      printed lists (printed $3.06, -4.03 \pm 6.0i$; $-5.02, -10.84, -274.643$) to
      their precision ($L$ is rounded to 2 decimals). Among all single-entry changes
      of $A$, only this one reproduces both lists (best alternative misses by 0.2).
      The printed matrix is kept as `A_printed`.
    - The thesis writes $\lambda(E, A - BL)$; the printed poles are those of
      $(E, A + BL)$ (with $A - BL$: $-3.59, 12.49, 271.60$). This is fojax's
      convention ($u = Lx$, closed loop $A + BL$), so `L` is stored as printed.

    **Returns:** a `ThesisExample` with `system`, `E`, `A`, `A_printed`, `B`, `C`, `L`
    (2x4 state feedback = functional), `eig_EA` (printed finite poles of $(E, A)$),
    `eig_EA_BL` (printed finite poles of $(E, A + BL)$), the disks `alpha1` = -5,
    `tau1` = 0.5, `alpha2` = -2, `tau2` = 0.5, the delay / convergence time `h` = 0.5
    and `x0` $= [-0.5, 1, 2.5, -1]$ (consistent with the algebraic row).
    """
    E = _array(np.diag([1.0, 1, 0, 1]))
    A_printed = _array([[-1, 3, 0, 1], [1, -7, 2.5, 3], [3, -1, 1, 0], [2, -3.1, -2.2, 0.5]])
    A = np.array(A_printed)
    A[3, 0] = 3.0
    B = _array([[1, 0], [0, 1], [0, 0], [0, 0]])
    C = _array([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 0, 1]])
    L = _array([[-30.09, -8.39, 67.22, -1.96], [12.83, -6.5, -47.24, 24.11]])
    notes = (
        "A[3,0] (a_41) is printed 2 but must be 3: only then are the printed finite poles of "
        "(E, A) {3.06, -4.03 +- 6.0i} and of the closed loop {-5.02, -10.84, -274.643} "
        "reproduced (3.064, -4.032 +- 6.000i; -5.017, -10.839, -274.635). With the printed "
        "A: 2.869, -3.934 +- 5.970i and -6.375, -9.454, -274.661.",
        "The thesis writes lambda(E, A - BL) but the printed poles are those of (E, A + BL) "
        "(A - BL gives -3.59, 12.49, 271.60); fojax's convention u = Lx, closed loop A + BL, "
        "so L is stored as printed.",
        "x0 = [-0.5, 1, 2.5, -1] satisfies the algebraic row 3x1 - x2 + x3 = 0.",
    )
    return linear_example(
        "example_3_1_2", "3.1.2", notes, E, A, B, C,
        A_printed=A_printed, L=L,
        eig_EA=np.array([3.06, -4.03 - 6.0j, -4.03 + 6.0j]),
        eig_EA_BL=np.array([-5.02, -10.84, -274.643]),
        alpha1=-5.0, tau1=0.5, alpha2=-2.0, tau2=0.5, h=0.5,
        x0=_array([-0.5, 1, 2.5, -1]),
    )


def example_3_1_3() -> ThesisExample:
    r"""§3.1.3: finite-time functional observer for a standard LTI system ($E = I$).

    $n = 5$, $m = 2$, $p = 2$, $z = Lx = [x_1, x_2]$, observer order $q_0 = 4$ (rows
    of `R`).

    **Typo resolution (B).** $B$ is printed with 4 rows for 5 states. We append a
    zero row, $B = [[1, 0], [-1, 0.5], [0, 1], [0, 0], [0, 0]]$: the printed rows
    read as the inputs acting on $x_1, x_2, x_3$ and the last printed row is already
    zero, so the only ambiguity left is which of the two trailing zero rows was
    dropped, and both give the same $B$. The data cannot decide further: inserting
    the zero row at any of the 5 positions leaves $(A, B)$ controllable (and $A$ is
    Hurwitz anyway), and nothing printed ($H = TB$ is not) depends on $B$. With this
    choice $(A, B)$ is controllable, $(C, A)$ observable, $\Sigma = [R; C]$ has full
    column rank and Assumption 1 holds trivially ($E = I$). The printed matrix is
    kept as `B_printed`.

    **Returns:** a `ThesisExample` with `system` (a `DescriptorSystem` with
    $E = I$), `A`, `B`, `B_printed`, `C`, `L`, `R`, disks `alpha1` = -7, `tau1` = 2,
    `alpha2` = -1, `tau2` = 0.5, convergence time `h` = 0.5 and
    `x0` $= [2, 1.5, -1, 0, 1]$.
    """
    A = _array(
        [
            [-1.0, 0, 0, 1.0, 3.0],
            [2.0, -5.0, 0, 1.0, 2.0],
            [0, 0, -4.0, 1.0, 3.0],
            [1.0, 0, 0, -2.0, 4.0],
            [0, 0, 0, -2.0, -4.0],
        ]
    )
    B_printed = _array([[1, 0], [-1, 0.5], [0, 1], [0, 0]])
    B = _array(np.vstack([B_printed, np.zeros((1, 2))]))
    C = _array([[1.0, 0, 0, 1.0, 0], [0, 1.0, 1.0, 0, 1.0]])
    L = _array([[1.0, 0, 0, 0, 0], [0, 1.0, 0, 0, 0]])
    R = _array([[1.0, 0, 0, 0, 0], [0, 1.0, 0, 0, 0], [1.0, 1.0, 0, 0, 1.0], [1.0, 0, 1.0, 0, 0]])
    notes = (
        "B is printed 4x2 for n = 5; a zero 5th row is appended (the last printed row is "
        "already zero, so dropping either trailing zero row gives the same B). Every insertion "
        "position keeps (A, B) controllable, so nothing printed decides further.",
        "Standard system (E = I, eq. 3.59): the observer uses F y, not [-E_perp B u; y].",
    )
    return linear_example(
        "example_3_1_3", "3.1.3", notes, _array(np.eye(5)), A, B, C,
        system=DescriptorSystem.from_state_space(A, B, C),
        B_printed=B_printed, L=L, R=R,
        alpha1=-7.0, tau1=2.0, alpha2=-1.0, tau2=0.5, h=0.5,
        x0=_array([2, 1.5, -1, 0, 1]),
    )


def example_3_3_7() -> ThesisExample:
    r"""§3.3.7: simultaneous state and fault estimation for an uncertain descriptor system.

    $$E\dot x = (A + \delta(t)\,\Delta A)x + Bu + F_a f, \qquad y = Cx + F_s f$$

    with $n = 6$, $\operatorname{rank}E = 4$, $m = 2$, $p = 3$, $n_f = 3$ (two
    actuator/process faults, one sensor fault on $y_3$). The augmented system
    (eq. 3.196, state $\chi = [x; f]$, $n = 9$) is `augmented`, built with
    `fojax.plant.augment_faults`, and the augmented functional is
    $\mathbf L = \operatorname{blkdiag}(L, I_3)$ (`L_aug`, 5x9).

    **Not available.** The uncertainty profile $\delta(t)$ is only shown in
    Figure 3.7, which is not part of the text: it is not recorded here (pass your own
    profile to `fojax.UncertainDescriptorSystem` with ``dA``). No observer gains,
    disks or delay are printed for this example. Tables 3.2/3.3 (IAE/ISE of the
    thesis's simulation) are kept as `IAE` and `ISE`.

    **Returns:** a `ThesisExample` with `system` (nominal $(E, A, B, C)$), `E`, `A`,
    `dA` ($\Delta A$: ones at (1,3) and (2,2), 1-based), `B`, `C`, `Fa`, `Fs`, `L`,
    `L_aug`, `augmented`, `IAE`, `ISE` (dicts ``{"FGDO": ..., "PO": ...}`` over
    $[z_1, z_2, f_1, f_2, f_3]$).
    """
    E = _array(np.diag([1.0, 1, 1, 1, 0, 0]))
    A = _array(
        [
            [0.66, 1.7, 7.9, 0.42, -3.05, -1.01],
            [0.95, -2.44, 2.19, 1.99, -1.77, 3.56],
            [-0.26, -0.19, -3.06, -0.03, 0.17, -0.18],
            [2.47, 1.84, 9.28, -1.54, -2.96, -0.39],
            [3.83, 1.91, 12.64, 2.18, -7.6, 1.32],
            [-1.51, -0.39, -2.8, -0.73, 1.35, -3.02],
        ]
    )
    dA = np.zeros((6, 6))
    dA[0, 2] = dA[1, 1] = 1.0
    B = _array([[1, 0], [0, 0], [0, 1], [0, 0], [0, 0], [0, 0]])
    C = _array([[1, 0, 0, 0, 0, 0], [0, 1, 0, 0, 0, 0], [0, 0, 0, 1, 0, 0]])
    Fa = _array([[1, 0, 0], [0, 1, 0], [0, 0, 0], [0, 0, 0], [0, 0, 0], [0, 0, 0]])
    Fs = _array([[0, 0, 0], [0, 0, 0], [0, 0, 1]])
    L = _array([[0, 0, 0, 0, 1, 0], [0, 1, 1, 0, 0, 0]])
    L_aug = np.zeros((5, 9))
    L_aug[:2, :6] = L
    L_aug[2:, 6:] = np.eye(3)
    notes = (
        "delta(t) is only shown in Figure 3.7, which is not available: not recorded.",
        "In the rank condition after eq. 3.196 the block 'C  F_a' should read 'C  F_s', and "
        "'C^+ A^+ = [E_perp A  E_perp F_a]' is garbled; neither affects the data.",
        "No observer gains, disks or delay are printed for this example.",
    )
    return linear_example(
        "example_3_3_7", "3.3.7", notes, E, A, B, C,
        faults=dict(Fa=Fa, Fs=Fs),
        dA=dA, Fa=Fa, Fs=Fs, L=L, L_aug=L_aug,
        IAE={
            "FGDO": _array([8.33, 4.88, 8.35, 24.21, 4.81]),
            "PO": _array([34.4, 21.99, 6.91, 160.68, 5.67]),
        },
        ISE={
            "FGDO": _array([19.35, 5.15, 30.39, 131.86, 15.92]),
            "PO": _array([163.58, 69.98, 271.0, 4097.1, 192.0]),
        },
    )
