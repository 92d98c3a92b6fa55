r"""§2.1.1 / §3.3.5–3.3.6: the flexible single-link robot arm, nonlinear and Takagi–Sugeno."""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np

from .._dtype import as_float_array
from ..plant import (
    NonlinearDescriptorSystem,
    SectorMembership,
    SincPremise,
    TakagiSugenoSystem,
)
from ._base import _array, ThesisExample


# Table 3.1 (g is not listed there; standard gravity).
_TABLE_3_1 = dict(J_m=0.01, J_l=0.08, m=0.15, l_c=0.25, k=0.3, beta=0.05, K_tau=0.2, l=0.18, g=9.81)

_E = [[1, 0, 0, 0, 0], [0, 1, 0, 0, 0], [0, 0, 1, 0, 0], [0, 0, 0, 1, 0], [0, 0, 0, 0, 0]]
_C = [[1, 0, 0, 0, 0], [0, 0, 1, 0, 0]]

#: First positive critical point of sin(x)/x: x cos x = sin x, in (pi, 3pi/2).
_X_STAR = 4.493409457909064


def _parameters(fname: str, given: dict) -> dict:
    """Table 3.1 with the `given` physical parameters in place of its values (a `TypeError`
    naming an unknown one, as Python would for `fname`)."""
    for name in given:
        if name not in _TABLE_3_1:
            raise TypeError(f"{fname}() got an unexpected keyword argument {name!r}")
    return {**_TABLE_3_1, **given}


def _sinc(x: float) -> float:
    return 1.0 if x == 0 else math.sin(x) / x


def _rho_range(x3_bound: float | None) -> tuple[float, float]:
    r"""Range of $\rho = \sin x_3 / x_3$ over $|x_3| \le$ `x3_bound` (all of $\mathbb R$ if None)."""
    if x3_bound is None or x3_bound >= _X_STAR:
        # Global minimum of sinc, attained at x* (where sinc(x*) = cos(x*)).
        return math.cos(_X_STAR), 1.0
    if x3_bound <= 0:
        raise ValueError(f"x3_bound must be positive, got {x3_bound}.")
    return _sinc(x3_bound), 1.0


# --------------------------------------------------------------------------- nonlinear


def _arm_rhs(x, u, theta, k):
    Jm, Jl, beta = theta["J_m"], theta["J_l"], theta["beta"]
    s3 = jnp.sin(x[2])
    return jnp.stack(
        [
            x[1],
            (-k * x[0] - beta * x[1] + k * x[2] + theta["K_tau"] * u[0]) / Jm,
            x[3],
            (k * x[0] - k * x[2] - theta["l_c"] * theta["m"] * theta["g"] * s3) / Jl,
            theta["l"] * s3 - x[4],
        ]
    )


def _arm_f(x, u, theta):
    r"""Right-hand side of eq. 2.7 / 3.188 with the restoring gravity term (see `robot_arm`)."""
    return _arm_rhs(x, u, theta, theta["k"])


def _arm_f_uncertain(t, x, u, theta):
    r"""`_arm_f` with $k(t) = k + \Delta_k \sin(\omega_k t)$ (thesis: $\Delta k = 0.04\sin t$)."""
    k = theta["k"] + theta["delta_k"] * jnp.sin(theta["omega_k"] * t)
    return _arm_rhs(x, u, theta, k)


def _arm_g(x, theta):
    """Measured output ``y = [x1, x3]`` (motor and link angles)."""
    return jnp.stack([x[0], x[2]])


def _printed_gains() -> dict:
    """The observer gains printed in §3.3.6 (GDO, eq. 3.193, and proportional observer, eq. 3.194)."""
    N = _array(
        [
            [-25.62, 7.08, 7.14, 7.71],
            [-24.27, -51.32, -0.54, -1.79],
            [-7.4, -1.27, -51.49, -2.41],
            [-9.27, 0.55, 1.0, -50.92],
        ]
    )
    J = _array([[6.8] * 3, [0.98] * 3, [1.63] * 3, [1.36] * 3])
    F1 = _array([[514.27, 545.36], [-2234.93, 149.92], [-67.01, -2604.85], [120.52, 177.65]])
    F2 = _array([[514.27, 547.04], [-2234.93, 149.53], [-67.01, -2599.83], [120.52, 166.58]])
    H = _array([[0], [20], [0], [0]])
    S = _array([[9.91, 0, 0, 0]] * 3)
    G = _array([[-28.77, 3.93, 3.93], [3.93, -28.77, 3.93], [3.93, 3.93, -28.77]])
    M = _array([[-70.15, -70.73]] * 3)
    P = _array([[0, 1.0, 0, 0], [0, 0, 1.0, 0], [0, 0, 0, 1.0]])
    Q = _array([[46.32, 0.54], [1.27, 51.49], [-0.55, -1.0]])
    Np = _array(-0.5 * np.eye(3))
    Fa1 = _array([[-27.75, 30.0], [3.75, -8.58], [0, 0.09]])
    Fa2 = _array([[-27.75, 30.0], [3.75, -3.02], [0, -0.02]])
    Hp = _array([[20], [0], [0]])
    Pp = _array(np.eye(3))
    Qa = _array([[-4.5, 0], [0, 0.5], [0, 0]])
    return dict(
        N1=N, N2=N, J1=J, J2=J, F1=F1, F2=F2, H1=H, H2=H, S1=S, S2=S, G1=G, G2=G,
        M1=M, M2=M, P1=P, P2=P, Q1=Q, Q2=Q,
        Np1=Np, Np2=Np, Fa1=Fa1, Fa2=Fa2, Hp1=Hp, Hp2=Hp, Pp1=Pp, Pp2=Pp, Qa1=Qa, Qa2=Qa,
    )  # fmt: skip


def _arm_example(name: str, system, notes: tuple[str, ...], params: dict, **quantities) -> ThesisExample:
    """A §3.3.5 example of the arm: `params`, `quantities`, then what both forms share (`L`, `R`,
    `x0`, the uncertainty of $k$ and the printed gains, with their notes)."""
    return ThesisExample(
        name=name,
        section="3.3.5",
        system=system,
        notes=notes + _GAIN_NOTES,
        quantities=dict(
            params=params,
            **quantities,
            L=_array([[0, 1, 0, 0, 0], [0, 0, 0, 1, 0], [0, 0, 0, 0, 1]]),
            R=_array([[0, 1, 0, 0, 0], [0, 1, 0, 1, 0], [1, 0, 0, 0, 1]]),
            x0=_array([math.pi / 12, 0, math.pi / 6, 0, 0.09]),
            delta_k=0.04,
            omega_k=1.0,
            **_printed_gains(),
        ),
    )


_GAIN_NOTES = (
    "Printed R (3x5) has q0 = 3 rows: it is the proportional observer's (N_p is 3x3); the "
    "GDO has q0 = 4 (N_1 is 4x4) and its R is not printed.",
    "R's third row contains x5, which is not in the row space of Gamma = [E; C] (rank 4): "
    "R violates rank[R; Gamma] = rank(Gamma) of §3.3.2 (it holds with [E; E_perp A_i; C]). "
    "R's second row [0 1 0 1 0] would also give (T B)[1] = 20 != printed H_p[1] = 0.",
    "The observers use y only (F_i is q0 x p), the §3.3 form; §3.3.4's F_i = [0 F_ai], "
    "Q_i = [0 Q_ai] means the E_perp column of w = [-E_perp B u; y] is zero.",
    "Printed-gain check (tests/test_models.py): z3 = x5 cannot satisfy condition d for any T "
    "(the x5 columns of T E and Q C vanish; residual exactly 1), for both observers. The PO's "
    "(zeta1, zeta2) -> (z1, z2) part satisfies a, b, d exactly (T = [[4.5, 1, 0, 0, 0], "
    "[0, 0, -0.5, 1, 0]]) when F_a1 is paired with the printed A1 (the rho_max model); with "
    "the pairing swapped it misses by 320 half-units of the printed digits. The GDO satisfies "
    "b, c, d exactly for z1, z2, but condition a has no solution in either pairing (26.7 "
    "half-units; max residual 5.45 in the x3 column): F1 - F2 is not T (A1 - A2) for any T.",
    "Parametric uncertainty Delta k = 0.04 sin(t) on k (metadata delta_k, omega_k; "
    "robot_arm(uncertain=True) builds the time-varying plant).",
)


def robot_arm(*, uncertain: bool = False, **params: float) -> ThesisExample:
    r"""Flexible single-link robot arm, nonlinear descriptor model (eqs. 2.7 / 3.188).

    States $x = [\theta_m, \dot\theta_m, \theta_l, \dot\theta_l, P_y]$ (motor angle and
    speed, link angle and speed, vertical tip position), input $u$ (motor voltage),
    output $y = [x_1, x_3]$:

    $$\begin{aligned}
    \dot x_1 &= x_2, &
    \dot x_2 &= \tfrac{1}{J_m}\big(-k x_1 - \beta x_2 + k x_3 + K_\tau u\big),\\
    \dot x_3 &= x_4, &
    \dot x_4 &= \tfrac{1}{J_l}\big(k x_1 - k x_3 - l_c m g \sin x_3\big),\\
    0 &= l\sin x_3 - x_5 .
    \end{aligned}$$

    **Deviation (gravity sign).** Eqs. 2.6, 2.7, 3.187 and 3.188 print
    $+\,l_c m g \sin x_3 / J_l$. The thesis's own T-S matrices (2.12 / 3.192) have
    $A_{4,3} = -8.33$ at $\rho = 1$ and $-2.77$ at $\rho = \rho_{\min}$, i.e.
    $-(k + l_c m g \rho)/J_l$ = $-8.348$ / $-2.751$ with Table 3.1; the printed sign
    would give $+0.849$ / $-4.749$. We therefore use the restoring term
    $-l_c m g \sin x_3$ (link angle measured from the hanging position), which is also
    what the printed observer gains were designed for.

    **Parameters** are Table 3.1's (the mass is printed "0.15 m": kg); $g = 9.81$
    m/s² is not in the table. The system's `theta` is a dict of these parameters as
    float64 JAX scalars (differentiable leaves).

    **Arguments:** any of the physical parameters by name (default: Table 3.1, `PARAMETERS`);
    `uncertain=True` makes the plant
    time-varying with $k(t) = k + 0.04\sin t$ (§3.3.6; `theta` then also holds
    ``delta_k`` and ``omega_k``).

    **Returns:** a `ThesisExample` with

    - `system`: `fojax.NonlinearDescriptorSystem` (``m = 1``, ``p = 2``);
    - `params`: Table 3.1 values (dict of floats);
    - `L` (3x5, $z = [x_2, x_4, x_5]$), `R` (3x5, the proportional observer's);
    - `x0` $= [\pi/12, 0, \pi/6, 0, 0.09]$ (consistent: $x_5 = l\sin x_3 = 0.09$);
    - `delta_k` = 0.04, `omega_k` = 1.0 (the uncertainty $\Delta k = 0.04\sin t$);
    - GDO gains (eq. 3.193) `N1, N2, J1, J2, F1, F2, H1, H2, S1, S2, G1, G2, M1, M2,
      P1, P2, Q1, Q2`; proportional observer gains (eq. 3.194) `Np1, Np2, Fa1, Fa2,
      Hp1, Hp2, Pp1, Pp2, Qa1, Qa2`. The printed rule 1 is the $\rho = \bar\rho$ model
      (see `robot_arm_ts`).
    """
    params = _parameters("robot_arm", params)
    theta = {name: as_float_array(name, value) for name, value in params.items()}
    if uncertain:
        theta["delta_k"] = as_float_array("delta_k", 0.04)
        theta["omega_k"] = as_float_array("omega_k", 1.0)
        system = NonlinearDescriptorSystem(
            _array(_E), _arm_f_uncertain, _arm_g, theta, m=1, p=2, time_varying=True
        )
    else:
        system = NonlinearDescriptorSystem(_array(_E), _arm_f, _arm_g, theta, m=1, p=2)
    notes = (
        "Gravity sign: eqs. 2.6/2.7/3.187/3.188 print +l_c m g sin(x3)/J_l; the printed T-S "
        "matrices (A_1[3,2] = -8.33, A_2[3,2] = -2.77) correspond to -(k + l_c m g rho)/J_l "
        "(-8.348 / -2.751 with Table 3.1), the '+' sign would give +0.849 / -4.749. The "
        "restoring term -l_c m g sin(x3) is used.",
        "Table 3.1 prints the mass unit as 'm' (it is kg) and has no g; g = 9.81 m/s^2.",
        "x5 is called d_y in eq. 2.7 and P_y in eq. 3.188: the tip height l sin(x3); "
        "x0[4] = 0.09 = 0.18 sin(pi/6) is consistent.",
    )
    return _arm_example("robot_arm", system, notes, params)


def ts_matrices(params: dict | None = None, x3_bound: float | None = None) -> dict:
    r"""The sector T-S form of `robot_arm` in NumPy (host; no JAX, no float64 mode needed):
    ``E``, ``A`` ``(2, 5, 5)`` $= [A(\underline\rho), A(\bar\rho)]$, ``B``, ``C``, ``rho_min``,
    ``rho_max`` for the physical `params` (default Table 3.1). `robot_arm_ts` builds its
    system from these; `fojax.config` checks a model file's ``[takagi_sugeno] plant`` with them."""
    p = dict(_TABLE_3_1, **(params or {}))
    rho_min, rho_max = _rho_range(x3_bound)

    def A_of(rho):
        return [
            [0, 1, 0, 0, 0],
            [-p["k"] / p["J_m"], -p["beta"] / p["J_m"], p["k"] / p["J_m"], 0, 0],
            [0, 0, 0, 1, 0],
            [p["k"] / p["J_l"], 0, -(p["k"] + p["l_c"] * p["m"] * p["g"] * rho) / p["J_l"], 0, 0],
            [0, 0, p["l"] * rho, 0, -1],
        ]

    return dict(E=np.array(_E, dtype=float), A=np.array([A_of(rho_min), A_of(rho_max)], dtype=float),
                B=np.array([[0], [p["K_tau"] / p["J_m"]], [0], [0], [0]], dtype=float),
                C=np.array(_C, dtype=float), rho_min=rho_min, rho_max=rho_max)


#: Names of `robot_arm`'s physical parameters (the entries of its `theta`).
PARAMETERS = tuple(_TABLE_3_1)


def robot_arm_ts(*, x3_bound: float | None = None, **params: float) -> ThesisExample:
    r"""Takagi–Sugeno form of `robot_arm` (eqs. 2.9–2.12 / 3.189–3.192).

    With the premise $\rho = \sin x_3 / x_3$ (known from the output: $x_3 = y_2$) the nonlinear
    model is exactly $E\dot x = A(\rho)x + Bu$, affine in $\rho$:

    $$A(\rho) = \begin{bmatrix}0&1&0&0&0\\ -k/J_m&-\beta/J_m&k/J_m&0&0\\ 0&0&0&1&0\\
      k/J_l&0&-(k + l_c m g\rho)/J_l&0&0\\ 0&0&l\rho&0&-1\end{bmatrix},
      \quad B = [0, K_\tau/J_m, 0, 0, 0]^T .$$

    The rule matrices are computed from the parameters as $A(\underline\rho)$ and
    $A(\bar\rho)$ (sector nonlinearity): since $A(\rho)$ is affine, the two-rule model
    with the weights of eq. 2.10 reproduces the nonlinear right-hand side exactly
    (to rounding) whenever $\underline\rho \le \rho \le \bar\rho$.

    **ρ range.** $\bar\rho = 1$ ($x_3 = 0$). By default $x_3$ is unrestricted and
    $\underline\rho = \min \operatorname{sinc} = \cos x^\star = -0.21723$ with
    $x^\star = 4.4934$ ($\tan x^\star = x^\star$), which is also what the printed
    $A_2[4,2] = -0.04 = l\underline\rho$ implies. With `x3_bound` $= b < x^\star$ the
    range is $[\sin b / b, 1]$ and exactness holds for $|x_3| \le b$ (the membership
    clips $\rho$ outside the range).

    **Typo resolutions.**

    - Row 4, column 3 is printed $\tfrac{1}{J_m}(k - l_c m g \rho)$; the printed
      numbers ($-8.33$, $-2.77$) and the nonlinear model give
      $-(k + l_c m g\rho)/J_l$ (restoring gravity, see `robot_arm`). Computed values
      are $-8.348$ and $-2.751$: the printed $-8.33$ / $-2.77$ differ by 0.018 / 0.019
      (more than their rounding; no choice of $g$ matches both). All other entries
      agree to the printed precision.
    - Rule/weight pairing: eq. 2.10 gives $w_1 = 1$ at $\rho = \underline\rho$, but
      the printed $A_1$ is the $\rho = \bar\rho$ model ($A_1[4,2] = 0.18 = l\cdot 1$).
      We keep eq. 2.10 (fojax's `SectorMembership`: rule 1 is the model at
      ``lower``) and order the rules accordingly: ``system.A[0]`` $= A(\underline\rho)
      \approx$ printed `A2`, ``system.A[1]`` $= A(\bar\rho) \approx$ printed `A1`.
      ``rule_of_printed = (1, 0)`` maps printed rule $i$ (0-based) to the system's rule
      index; printed gains with index 1 (`F1`, `Fa1`) belong to ``system.A[1]``
      (the proportional observer's gains satisfy the design conditions only in this
      pairing).

    **Arguments:** any of `robot_arm`'s physical parameters by name (default: Table 3.1) and
    `x3_bound`.

    **Returns:** a `ThesisExample` with `system` a `fojax.TakagiSugenoSystem`
    (membership ``SectorMembership(SincPremise(1), rho_min, rho_max)``), `rho_min`,
    `rho_max`, the printed `A1`, `A2`, `rule_of_printed`, `params`, and the same
    `L`, `R`, `x0`, `delta_k`, `omega_k` and printed observer gains as `robot_arm`.
    """
    params = _parameters("robot_arm_ts", params)
    mats = ts_matrices(params, x3_bound)
    rho_min, rho_max = mats["rho_min"], mats["rho_max"]
    A = _array(mats["A"])
    B = _array(mats["B"])
    membership = SectorMembership(SincPremise(1), rho_min, rho_max)
    system = TakagiSugenoSystem(_array(_E), A, B, _array(_C), membership)
    A1 = _array(
        [
            [0, 1, 0, 0, 0],
            [-30, -5, 30, 0, 0],
            [0, 0, 0, 1, 0],
            [3.75, 0, -8.33, 0, 0],
            [0, 0, 0.18, 0, -1],
        ]
    )
    A2 = _array(
        [
            [0, 1, 0, 0, 0],
            [-30, -5, 30, 0, 0],
            [0, 0, 0, 1, 0],
            [3.75, 0, -2.77, 0, 0],
            [0, 0, -0.04, 0, -1],
        ]
    )
    notes = (
        "Row 4, col 3 of A(rho) is printed (1/J_m)(k - l_c m g rho); the printed numbers and the "
        "nonlinear model give -(k + l_c m g rho)/J_l.",
        f"Computed A(rho_max)[3,2] = {A[1, 3, 2]:.4f} and A(rho_min)[3,2] = {A[0, 3, 2]:.4f} vs "
        "printed -8.33 / -2.77 (off by ~0.02, beyond rounding; no g reconciles both); every other "
        "entry agrees to the printed precision.",
        "Rule pairing: eq. 2.10 has w1 = 1 at rho_min, but printed A1 is the rho_max model. Eq. "
        "2.10 is kept (SectorMembership: rule 1 at `lower`); system.A[0] = A(rho_min) ~ printed "
        "A2, system.A[1] = A(rho_max) ~ printed A1; rule_of_printed = (1, 0).",
        f"rho range [{rho_min:.5f}, {rho_max}] "
        + (
            "(all x3: global minimum of sin(x)/x)."
            if x3_bound is None
            else f"(|x3| <= {x3_bound})."
        ),
    )
    return _arm_example("robot_arm_ts", system, notes, params, rho_min=rho_min, rho_max=rho_max,
                        A1=A1, A2=A2, rule_of_printed=(1, 0))
