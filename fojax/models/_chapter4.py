r"""Chapter 4 numerical examples: observer-based and fault-tolerant control.

The observers of chapter 4 have the form (4.3): with $w = [-E^\perp B u;\, y]$
($r_1 + p$ entries, $r_1 = n - \operatorname{rank}E$),

$$\dot\zeta = N\zeta + Jv + Fw + Hu,\quad \dot v = S\zeta + Gv + Mw,\quad
  \hat z = P\zeta + Qw,$$

so $N$ is $q_0\times q_0$, $J$ $q_0\times q_1$, $F$ $q_0\times(r_1+p)$, $H$
$q_0\times m$, $S$ $q_1\times q_0$, $G$ $q_1\times q_1$, $M$ $q_1\times(r_1+p)$, $P$
$q\times q_0$ and $Q$ $q\times(r_1+p)$. For §4.2–4.4 these dimensions refer to the
fault-augmented system (`augmented`). `E_perp` records the $E^\perp$ under which
the printed gains were checked (a selection of identity rows, sign +1).
"""

from __future__ import annotations

import numpy as np

from ._base import _array, linear_example, ThesisExample


# The plant shared by §4.1.3 and §4.3.2.
def _plant_4a():
    E = _array(np.diag([1.0, 1, 1, 0]))
    A = _array(
        [[-3.0, 2.0, 1.0, 1.0], [1.0, -2.0, 1.0, -2.0], [3.0, 0, 1.0, -0.5], [-1.0, -2.0, 0, 1.0]]
    )
    B = _array([[1.0, 0], [0.5, -1.0], [0, 1.0], [0, 0]])
    C = _array([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 0, 1]])
    L = _array([[-8.95, -26.07, 12.1, -4.85], [1.71, 1.31, -3.51, -0.16]])
    return dict(E=E, A=A, B=B, C=C, L=L)


# The plant shared by §4.2.2 and §4.4.2.
def _plant_4b():
    E = _array(np.diag([1.0, 1, 0]))
    A = _array([[-3.0, 2.0, 1.0], [-2.0, 1.0, -2.0], [-1.0, -2.0, 1.0]])
    B = _array([[1, 0], [0.5, -1], [0, 0]])
    C = _array([[1, 0, 0], [0, 0, 1]])
    Fs = _array(np.eye(2))
    L = _array([[2.61, 1.09, -1.38], [-0.43, 0.04, 0.02]])
    return dict(E=E, A=A, B=B, C=C, Fs=Fs, L=L)


def _sensor_fault_example(name, section, notes, **quantities) -> ThesisExample:
    r"""An example on the plant of §4.2.2 and §4.4.2 with its sensor faults as states: `augmented`
    (its $\bar E^\perp = e_3^T$) and the consistent ``x0 = [1, -1, -1]``, besides `quantities`."""
    plant = _plant_4b()
    return linear_example(
        name, section, notes, **plant,
        faults=dict(Fs=plant["Fs"]),
        **quantities,
        E_perp=_array([[0, 0, 1, 0, 0]]),
        x0=_array([1, -1, -1]),
    )


def example_4_1_3() -> ThesisExample:
    r"""§4.1.3: functional observer-based stabilisation of an unstable descriptor system.

    $n = 4$, $\operatorname{rank}E = 3$ ($r_1 = 1$), $m = 2$, $p = 3$, $q = 2$,
    $q_0 = q_1 = 2$; $w = [-E^\perp Bu; y]$ has 4 entries ($E^\perp = e_4^T$, and
    $E^\perp B = 0$ so its first entry is identically zero). The control law is
    $u = \hat z \approx Lx$; the closed loop (4.13) is
    $\mathcal E = \operatorname{blkdiag}(E, I, I)$,
    $\mathcal A = [[A + BL, BP, 0], [0, N, J], [0, S, G]]$.

    **Checks (tests/test_models.py).** The printed eigenvalues of $(E, A)$,
    $(E, A+BL)$ and of the closed loop are reproduced from the printed matrices
    (within 0.01: $-39.79$ and $-4.48$ are printed truncated as $-39.78$, $-4.47$).
    The printed gains satisfy the design conditions a–d with one $T$ up to the
    rounding of the printed digits (within 0.61 half-units of the last digit;
    least-squares residuals $\le 0.06$).

    **Findings.** `x0` $= [16, -1, 3, 7]$ violates the algebraic row
    $-x_1 - 2x_2 + x_4 = 0$ (residual $-7$; a consistent completion is $x_4 = 14$).
    The observer pole $-4.48$ lies outside the stated disk $\mathcal D(-2, 1)$.
    Eqs. 4.4/4.11/4.12 print "$J(t)$" for $Jv(t)$ and "$Sv(t)$" for $Gv(t)$, and
    $\varepsilon = \zeta - TEz$ for $\zeta - TEx$.

    **Returns:** a `ThesisExample` with `system`, `E`, `A`, `B`, `C`, `L` (state
    feedback and functional), `E_perp`, gains `N, J, F, H, S, G, M, P, Q`, disk
    `alpha` = -2, `tau` = 1, `x0`, and the printed eigenvalues `eig_EA`,
    `eig_EA_BL`, `eig_loop` (finite poles of $(\mathcal E, \mathcal A)$).
    """
    gains = dict(
        N=_array([[-3.24, -4.26], [-0.1, -2.33]]),
        J=_array([[2.94, 2.94], [0.3, 0.3]]),
        F=_array([[8.12, 39.76, -15.39, 17.1], [-2.01, -11.6, 5.58, -2.45]]),
        H=_array([[-25.04, 34.63], [7.74, -9.09]]),
        S=_array([[0.2, 0.7], [0.11, 0.37]]),
        G=_array([[-2.73, -0.73], [-0.38, -2.38]]),
        M=_array([[0.05, -0.62, 0.76, -0.05], [0.09, -0.26, 0.54, -0.09]]),
        P=_array([[1.0, -0.01], [-0.01, 0.96]]),
        Q=_array([[-0.37, 4.48, -4.29, -4.48], [1.67, -1.53, -0.98, -1.83]]),
    )
    notes = (
        "x0 = [16, -1, 3, 7] violates the algebraic row -x1 - 2x2 + x4 = 0 (residual -7); "
        "a consistent completion keeping x1..x3 is x4 = 14.",
        "Printed closed-loop eigenvalues -39.78 and -4.47 are truncations of -39.790 and "
        "-4.480; all printed eigenvalues are reproduced within 0.01.",
        "The observer eigenvalue -4.48 lies outside the stated disk D(alpha=-2, tau=1).",
        "Printed gains satisfy conditions a-d with one T up to rounding (E_perp = +e4^T; within "
        "0.61 half-units of the printed digits, least-squares residuals <= 0.06).",
        "Eqs. 4.4/4.11/4.12: 'J(t)' means J v(t), the second 'S v(t)' means G v(t); "
        "epsilon = zeta - T E x (printed T E z).",
    )
    return linear_example(
        "example_4_1_3", "4.1.3", notes, **_plant_4a(),
        E_perp=_array([[0, 0, 0, 1]]),
        **gains,
        alpha=-2.0,
        tau=1.0,
        x0=_array([16, -1, 3, 7]),
        eig_EA=np.array([1.79, -4.4 - 1.72j, -4.4 + 1.72j]),
        eig_EA_BL=np.array([-1.7 + 1.99j, -1.7 - 1.99j, -39.78]),
        eig_loop=np.array([-1.7 + 1.99j, -1.7 - 1.99j, -39.78, -2.0, -2.0, -2.2, -4.47]),
    )


def example_4_2_2() -> ThesisExample:
    r"""§4.2.2: sensor fault-tolerant control.

    $E\dot x = Ax + Bu$, $y = Cx + F_s f$ with constant $f\in\mathbb R^2$; $n = 3$,
    $\operatorname{rank}E = 2$, $m = 2$, $p = 2$. The observer is designed on the
    augmented system (4.22) $\bar x = [x; f]$ ($\bar n = 5$, $\bar r_1 = 1$,
    $\bar E^\perp = e_3^T$): `augmented` = ``augment_faults(system, Fs=Fs)``
    ($\bar A = \operatorname{blkdiag}(A, 0)$, $\bar C = [C\;F_s]$), with
    $\bar L = [L\;0]$. $q = q_0 = q_1 = 2$; $w$ has $\bar r_1 + p = 3$ entries.

    **Typos.** Eq. 4.21 gives $F \in \mathbb R^{n\times n_f}$; with $y = Cx + Ff$ it
    must be $p\times n_f$ (here $F_s$ is $2\times 2$, $C$ is $2\times 3$). "The
    functional observer of the form (4.2)" means (4.3). $H$ is not printed.

    **Finding.** The printed gains do not satisfy the design conditions for any $T$.
    Condition c, $ST\bar E + MW = 0$ ($W = [\bar E^\perp\bar A; \bar C]$), has no
    solution on its own (least-squares residual $\ge 0.3$ for every column order of
    $w$ and scale of $\bar E^\perp$). Conditions a and d together miss by 3.7 as
    printed; with the sign of $F$ flipped they nearly hold (within 3.3 half-units of
    the printed digits, residual 0.03). $Q$ and $\bar L$ agree on the $x_3$ column
    ($(\bar L - QW)_{:,3} \approx 0.003$ with $P = I$), confirming
    $\bar E^\perp = +e_3^T$.

    **Returns:** a `ThesisExample` with `system` (fault-free plant), `E`, `A`, `B`,
    `C`, `Fs`, `L`, `Lbar`, `augmented`, `E_perp` (of the augmented system), gains
    `N, J, F, S, G, M, P, Q` and `x0` $= [1, -1, -1]$ (consistent).
    """
    gains = dict(
        N=_array([[-4.92, 0.26], [0.08, -4.74]]),
        J=_array([[0.22, 0.22], [0.22, 0.22]]),
        F=_array([[3.43, -0.46, -5.0], [-1.37, -1.27, 1.09]]),
        S=_array([[-0.0511, -0.1585], [-0.0064, -0.0200]]),
        G=_array([[-5, 0], [0, -5]]),
        M=_array([[0.0166, -0.4619, -0.339], [0.0021, -0.0582, -0.0427]]),
        P=_array([[1, 0], [0, 1]]),
        Q=_array([[-0.366, -0.1064, -1.0110], [-0.1906, -0.2696, 0.2076]]),
    )
    notes = (
        "Eq. 4.21: F in R^{n x n_f} should be p x n_f (F_s is 2x2, C is 2x3).",
        "'observer of the form (4.2)' means (4.3); H is not printed.",
        "Printed gains are inconsistent with conditions a-d for every T: c alone has no solution "
        "(least-squares residual >= 0.3 for any column order of w); a and d miss by 3.7 as "
        "printed and nearly hold (3.3 half-units, residual 0.03) with the sign of F flipped.",
        "x0 = [1, -1, -1] satisfies the algebraic row -x1 - 2x2 + x3 = 0.",
    )
    return _sensor_fault_example(
        "example_4_2_2", "4.2.2", notes,
        Lbar=_array(np.hstack([_plant_4b()["L"], np.zeros((2, 2))])),
        **gains,
    )


def example_4_3_2() -> ThesisExample:
    r"""§4.3.2: actuator fault-tolerant control.

    $E\dot x = Ax + B(u + f)$, $y = Cx$, with the plant and $L$ of §4.1.3. The
    augmented system (4.26), $\bar x = [x; f]$ ($\bar n = 6$, $\bar r_1 = 1$,
    $\bar E^\perp = e_4^T$), is `augmented` = ``augment_faults(system, Fa=B)``
    ($\bar A = [[A, B], [0, 0]]$, $\bar C = [C\;0]$) and $\bar L = [L\; -I]$ (the FTC
    law $u = Lx - f$). $q = 2$, $q_0 = q_1 = 3$, $w$ has 4 entries.

    **Typo resolution.** $\bar L_{1,2}$ is printed $-267$; it is $L_{1,2} = -26.07$
    ($\bar L = [L\;-I]$ by eq. 4.26, and $L$ is printed just above). The printed
    gains confirm it: conditions a, b, d hold to rounding with $-26.07$ and miss by
    hundreds of half-units (residual ~45) with $-267$. The printed matrix is kept as `Lbar_printed`.

    **Checks.** The printed gains satisfy conditions a, b, d for one $T$ up to the
    rounding of their digits (within 0.67 half-units; least-squares residuals
    $\le 0.44$ with $|F|$ up to 1815), and $T\bar E + KW = R$ holds to 0.04 for some
    $K$ (so `R` is the $R$ used).

    **Finding.** Condition c fails: $MW = 0$ (to rounding) and $S$ is nonsingular,
    so $ST\bar E + MW = 0$ would need $T\bar E = 0$, contradicting d (85 half-units
    with d, 209 with a).

    **Finding.** `x0` $= [1, -1, 3, 1]$ violates the algebraic row
    $-x_1 - 2x_2 + x_4 = 0$ (residual 2; consistent completion $x_4 = -1$).

    **Returns:** a `ThesisExample` with `system` (fault-free plant), `E`, `A`, `B`,
    `C`, `Fa` (= `B`), `L`, `Lbar`, `Lbar_printed`, `R` (3x6), `augmented`,
    `E_perp`, gains `N, J, F, H, S, G, M, P, Q` and `x0`.
    """
    plant = _plant_4a()
    Lbar_printed = _array([[-8.95, -267, 12.1, -4.85, -1, 0], [1.71, 1.31, -3.51, -0.16, 0, -1]])
    Lbar = _array(np.hstack([plant["L"], -np.eye(2)]))
    gains = dict(
        N=_array([[1.04, 8.32, 11.95], [-21.76, -34.94, -43.03], [12.09, 16.63, 18.9]]),
        J=_array([[0.05, 0.05, 0.05], [-0.17, -0.17, -0.17], [0.1, 0.1, 0.1]]),
        F=_array(
            [
                [501.43, 1.66, -380.96, 190.53],
                [-1815.274, -48.76, 1363.92, -754.63],
                [1008.47, 18.97, -760.63, 405.41],
            ]
        ),
        H=_array([[13, 9.36], [-64.79, -56.7], [30.99, 28.72]]),
        S=_array(
            [[-0.0611, -0.0278, -0.0278], [-0.1110, -0.0222, -0.0111], [0.0722, 0.0361, 0.0444]]
        ),
        G=_array(-5 * np.eye(3)),
        M=_array([[0.03, 0.03, 0.06, -0.03], [0.03, 0.03, 0.06, -0.03], [0.06, 0.06, 0.11, -0.06]]),
        P=_array([[-12.1, 12.1, 11.1], [2.51, -3.51, -2.51]]),
        Q=_array([[-402.34, 432.42, -1323.51, 397.5], [122.75, -134.83, 400.78, -122.91]]),
    )
    notes = (
        "Lbar[0,1] is printed -267; it is L[0,1] = -26.07 (Lbar = [L -I], eq. 4.26). The printed "
        "gains satisfy a, b, d to rounding with -26.07 and miss by ~45 (1350 half-units) with -267.",
        "Printed gains satisfy conditions a, b, d for one T up to rounding (0.67 half-units; "
        "residuals <= 0.44 with |F| up to 1815) and T Ebar + K W = R to 0.04. Condition c fails: "
        "M W = 0 and S is nonsingular, so c would need T Ebar = 0, contradicting d.",
        "x0 = [1, -1, 3, 1] violates the algebraic row -x1 - 2x2 + x4 = 0 (residual 2); a "
        "consistent completion keeping x1..x3 is x4 = -1.",
    )
    return linear_example(
        "example_4_3_2", "4.3.2", notes, **plant,
        faults=dict(Fa=plant["B"]),
        Fa=plant["B"],
        Lbar=Lbar,
        Lbar_printed=Lbar_printed,
        R=_array([[1, 1, 0, 0, 1, 1], [1, 1, 1, 1, 0, 1], [0, 1, 0, 0, 1, 0]]),
        E_perp=_array([[0, 0, 0, 1, 0, 0]]),
        **gains,
        x0=_array([1, -1, 3, 1]),
    )


def example_4_4_2() -> ThesisExample:
    r"""§4.4.2: simultaneous fault estimation and fault-tolerant control (sensor faults).

    The plant, $F_s = I_2$ and $L$ of §4.2.2; `augmented` = ``augment_faults(system,
    Fs=Fs)`` (eq. 4.29 with $F_a = 0$), $\bar n = 5$, $\bar r_1 = 1$,
    $\bar E^\perp = e_3^T$. The functional $\bar L$ (4x5) stacks the control law and
    the two faults; $q = q_0 = q_1 = 4$, $w$ has 3 entries.

    **Typo resolution.** $\bar L$ is printed with $\bar L_{1,4} = -1$, the
    "$-I_a$" block of eq. 4.29, although this example has no actuator fault ($F_a = 0$;
    for sensor faults the control law is $u = Lx$, cf. §4.2.2). We set it to $0$:
    $\bar L = [[L, 0], [0, I_2]]$. Evidence: the printed gains satisfy conditions a,
    b, d for one $T$ up to the rounding of their digits with $\bar L_{1,4} = 0$
    (within 0.67 half-units), but not with $-1$ (42 half-units). The printed matrix
    is kept as `Lbar_printed`.

    **Finding.** Condition c, $ST\bar E + MW = 0$, has no solution $T$ on its own
    (least-squares residual 0.28; row 3 of $S$ is $\approx 0$ while row 3 of $M$ is
    $[-0.71, 0.24, 0.96]$).

    **Returns:** a `ThesisExample` with `system`, `E`, `A`, `B`, `C`, `Fs`, `L`,
    `Lbar` (4x5, resolved), `Lbar_printed`, `augmented`, `E_perp`, gains
    `N, J, F, H, S, G, M, P, Q` and `x0` $= [1, -1, -1]$ (consistent).
    """
    Lbar_printed = _array(
        [[2.61, 1.09, -1.38, -1, 0], [-0.43, 0.04, 0.02, 0, 0], [0, 0, 0, 1, 0], [0, 0, 0, 0, 1]]
    )
    Lbar = np.array(Lbar_printed)
    Lbar[0, 3] = 0.0
    gains = dict(
        N=_array(
            [
                [-4.63, 0.64, 0.47, -0.28],
                [0.53, -4.09, 0.68, -0.4],
                [0.49, 0.85, -4.37, -0.37],
                [0.21, 0.37, 0.28, -5.16],
            ]
        ),
        J=_array([[0.71] * 4, [1.01] * 4, [0.94] * 4, [0.41] * 4]),
        F=_array(
            [
                [3.43, -0.53, -5.05],
                [-1.37, -1.35, 1.04],
                [-3.41, -3.86, 2.27],
                [-4.32, -10.23, -0.45],
            ]
        ),
        H=_array([[-2.53, 0.36], [0.52, -0.34], [1.14, -0.91], [-0.23, -1.82]]),
        S=_array(
            [[0.08, 0.17, 0.09, -0.06], [-0.04, -0.37, 0.07, 0.02], [0, -0.01, 0, 0], [0, 0, 0, 0]]
        ),
        G=_array(-5 * np.eye(4)),
        M=_array(
            [
                [0.4282, -0.4969, -0.3055],
                [0.0781, -0.5188, -0.1316],
                [-0.7141, 0.2415, 0.9595],
                [0, 0, 0],
            ]
        ),
        P=_array(
            [
                [-0.88, 0.16, 0.17, -0.09],
                [0.16, -0.08, -0.09, -0.1],
                [0.17, -0.09, -0.61, -0.14],
                [-0.09, -0.1, -0.14, -0.93],
            ]
        ),
        Q=_array(
            [[-0.37, -0.11, -1.01], [-0.19, -0.27, 0.21], [-0.45, 0.23, 0.45], [-0.91, -2.05, 0.91]]
        ),
    )
    notes = (
        "Lbar[0,3] is printed -1 (the '-I_a' block of eq. 4.29) but the example has only sensor "
        "faults (F_a = 0); set to 0. The printed gains satisfy conditions a, b, d to rounding "
        "(0.67 half-units) with 0, not with -1 (42 half-units).",
        "'The system of the form (4.21)': sensor faults only, F_a = 0.",
        "Printed gains: condition c has no solution T on its own (least-squares residual 0.28; "
        "S row 3 ~ 0 but M row 3 = [-0.71, 0.24, 0.96]); a, b, d are consistent.",
        "x0 = [1, -1, -1] satisfies the algebraic row.",
    )
    return _sensor_fault_example(
        "example_4_4_2", "4.4.2", notes, Lbar=Lbar, Lbar_printed=Lbar_printed, **gains
    )
