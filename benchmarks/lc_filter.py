r"""A model that is not from the thesis: a two-stage LC filter with a resistive divider load.

Written as a user would write it (issue 14): per-unit values, states and equations in the
order one reads them off the schematic. Benchmark-only (``benchmarks/tuning_circuit.py``).

**Circuit.** A voltage source $u$ feeds, in series, $R_1$ and the input inductor $L_1$
(current $i_1$) into node 1 (capacitor $C_1$ to ground, voltage $v_1$); the output inductor
$L_2$ with its resistance $R_2$ (current $i_2$) feeds node 2 (capacitor $C_2$, voltage
$v_2$); the load is a divider $R_a$ (node 2 → node 3) and $R_b$ (node 3 → ground), with
node voltage $v_3$ and load current $i_L$. State $x = (i_1, v_1, i_2, v_2, v_3, i_L)$,
$n = 6$. Kirchhoff's laws, one row each:

$$\begin{aligned}
L_1\dot i_1 &= u - R_1 i_1 - v_1, & C_1\dot v_1 &= i_1 - i_2,\\
L_2\dot i_2 &= v_1 - R_2 i_2 - v_2, & C_2\dot v_2 &= i_2 - i_L,\\
0 &= v_2 - v_3 - R_a i_L \quad(\text{KVL over } R_a), &
0 &= \tfrac{1}{2}v_2 - v_3 \quad(\text{the divider, } R_a = R_b).
\end{aligned}$$

The algebraic block $\partial(\text{rows 5, 6})/\partial(v_3, i_L) = [[-1, -R_a], [-1, 0]]$
has determinant $-R_a \ne 0$: index 1, 4 finite poles. Measured: $y = (i_1, v_2)$ (input
current and output voltage, where a converter has its sensors); estimated: $z = i_2$, the
output inductor current, which is not measured (it needs $\dot v_2$: $i_2 = C_2\dot v_2 + i_L$).
Uncertainty: the load resistance $R_a(1 + 0.5\delta)$, $|\delta| \le 1$ (row 5, column $i_L$).

Values (per unit, time in units of the base period): $R_1 = 0.2$, $L_1 = 1$, $C_1 = 1$,
$L_2 = 0.5$, $R_2 = 0.1$, $C_2 = 0.5$, $R_a = R_b = 2$.

**The badly scaled twin** is the same circuit in other units: $x = D_c x'$ and every row
multiplied by its own factor, $E' = D_rED_c$, $A' = D_rAD_c$, $B' = D_rB$, $C' = CD_c$,
$L' = LD_c$, $\Delta A' = D_r\Delta AD_c$, with $D_r, D_c$ diagonal between 1e-3 and 1e3
(`TWIN_ROWS`, `TWIN_STATES`). It has the same poles, the same outputs $y$ and the same
$z$ for the same physical initial state ($x_0' = D_c^{-1}x_0$).
"""

from __future__ import annotations

import numpy as np


PARAMS = dict(R1=0.2, L1=1.0, C1=1.0, L2=0.5, R2=0.1, C2=0.5, Ra=2.0)
#: row factors D_r and state factors D_c of the badly scaled twin (1e-3 .. 1e3)
TWIN_ROWS = np.array([1e-3, 1e2, 1.0, 1e3, 1e-2, 1e-3])
TWIN_STATES = np.array([1e3, 1e-3, 1e2, 1.0, 1e-3, 1e3])


def lc_filter(scaled: bool = False) -> dict:
    """``dict(E, A, B, C, L, dA, Dc)`` (NumPy float64) of the filter, or of its badly scaled
    twin; ``Dc`` maps the twin's states to the physical ones (``x = Dc x'``; identity for
    the plain model)."""
    p = PARAMS
    E = np.diag([p["L1"], p["C1"], p["L2"], p["C2"], 0.0, 0.0])
    A = np.array([
        [-p["R1"], -1.0, 0.0, 0.0, 0.0, 0.0],
        [1.0, 0.0, -1.0, 0.0, 0.0, 0.0],
        [0.0, 1.0, -p["R2"], -1.0, 0.0, 0.0],
        [0.0, 0.0, 1.0, 0.0, 0.0, -1.0],
        [0.0, 0.0, 0.0, 1.0, -1.0, -p["Ra"]],
        [0.0, 0.0, 0.0, 0.5, -1.0, 0.0],
    ])
    B = np.array([[1.0], [0.0], [0.0], [0.0], [0.0], [0.0]])
    C = np.array([[1.0, 0, 0, 0, 0, 0], [0, 0, 0, 1.0, 0, 0]])
    L = np.array([[0, 0, 1.0, 0, 0, 0]])
    dA = np.zeros((6, 6))
    dA[4, 5] = -0.5 * p["Ra"]
    m = dict(E=E, A=A, B=B, C=C, L=L, dA=dA)
    return rescaled(m, TWIN_ROWS, TWIN_STATES) if scaled else rescaled(m, np.ones(6), np.ones(6))


def rescaled(m: dict, rows, states) -> dict:
    """The same model in other units: ``x = Dc x'`` and row ``i`` multiplied by ``rows[i]``
    (``E' = Dr E Dc``, ``A' = Dr A Dc``, ``B' = Dr B``, ``C' = C Dc``, ``L' = L Dc``,
    ``dA' = Dr dA Dc``); the result also holds ``Dc``."""
    R, S = np.diag(np.asarray(rows, float)), np.diag(np.asarray(states, float))
    return dict(E=R @ m["E"] @ S, A=R @ m["A"] @ S, B=R @ m["B"], C=m["C"] @ S, L=m["L"] @ S, dA=R @ m["dA"] @ S,
                Dc=S)
