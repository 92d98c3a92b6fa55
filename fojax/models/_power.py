r"""A model that is not from the thesis: two control areas of a power system joined by a tie
line (load-frequency control), with the network's power balance kept as algebraic rows and an
uncertain inertia in area 1."""

from __future__ import annotations

import numpy as np

from ._base import _array, linear_example, physical_parameters, ThesisExample


#: per-unit defaults of `two_area_power` (see its docstring)
POWER_PARAMS = dict(H_1=5.0, D_1=0.6, R_1=0.05, tau_g1=0.2, tau_t1=0.5,
                    H_2=4.0, D_2=0.9, R_2=0.0625, tau_g2=0.3, tau_t2=0.6, P_s=2.0)
#: names of the states, in order
POWER_STATES = ("omega_1", "delta_12", "omega_2", "P_m1", "P_v1", "P_m2", "P_v2", "P_12", "P_e1", "P_e2")


def two_area_power(inertia_uncertainty: float = 0.4, **params) -> ThesisExample:
    r"""Two-area load-frequency control with an uncertain area inertia (**not from the thesis**:
    chosen so that a parameter's uncertainty matters to the estimate).

    Two control areas (each a lumped generator with governor and non-reheat turbine plus a
    frequency-sensitive load) exchange power over one tie line. All quantities are per-unit
    *deviations* from the operating point (1000 MVA base, 60 Hz), time in seconds.

    **State** ($n = 10$):
    $x = (\Delta\omega_1, \Delta\delta_{12}, \Delta\omega_2, \Delta P_{m1}, \Delta P_{v1},
    \Delta P_{m2}, \Delta P_{v2}, \Delta P_{12}, \Delta P_{e1}, \Delta P_{e2})$ — the area
    frequencies [pu], the angle difference across the tie line [rad], the turbines' mechanical
    powers and the governors' valve positions [pu], the tie-line flow from area 1 to area 2 and
    the areas' electrical powers [pu]. Input: $u = \Delta P_{\text{ref},1}$, the AGC set point
    of area 1's governor [pu]. The angle difference instead of the two angles: the angles
    share a rigid rotation (a pole at 0) that no quantity of interest depends on.

    **Equations** (one row each):

    $$\begin{aligned}
    \dot{\Delta\omega}_1 &= \tfrac{1}{2H_1}(\Delta P_{m1} - \Delta P_{e1}) &&\text{(swing equation, area 1)}\\
    \dot{\Delta\delta}_{12} &= \Delta\omega_1 - \Delta\omega_2 &&\text{(the tie-line block } P_s/s\text{ of the LFC diagram)}\\
    2H_2\dot{\Delta\omega}_2 &= \Delta P_{m2} - \Delta P_{e2} &&\text{(swing equation, area 2)}\\
    \tau_{t1}\dot{\Delta P}_{m1} &= \Delta P_{v1} - \Delta P_{m1} &&\text{(non-reheat turbine)}\\
    \tau_{g1}\dot{\Delta P}_{v1} &= u - \Delta\omega_1/R_1 - \Delta P_{v1} &&\text{(governor with droop } R_1\text{)}\\
    \tau_{t2}\dot{\Delta P}_{m2} &= \Delta P_{v2} - \Delta P_{m2}\\
    \tau_{g2}\dot{\Delta P}_{v2} &= -\Delta\omega_2/R_2 - \Delta P_{v2}\\
    0 &= P_s\Delta\delta_{12} - \Delta P_{12} &&\text{(linearised tie-line flow, synchronizing coefficient } P_s\text{)}\\
    0 &= D_1\Delta\omega_1 + \Delta P_{12} - \Delta P_{e1} &&\text{(area 1's power balance: frequency-sensitive load + export)}\\
    0 &= D_2\Delta\omega_2 - \Delta P_{12} - \Delta P_{e2} &&\text{(area 2: load − import; equal bases, } a_{12} = -1\text{)}
    \end{aligned}$$

    (the load set points are constant: their deviations are 0). Area 1's swing equation is
    written divided by $2H_1$ (so its row of $E$ is 1) because the uncertainty below is a change
    of $A$. $E = \operatorname{diag}(1, 1, 2H_2, \tau_{t1}, \tau_{g1}, \tau_{t2}, \tau_{g2}, 0, 0, 0)$;
    the algebraic block $\partial(\text{rows 8–10})/\partial(\Delta P_{12}, \Delta P_{e1}, \Delta P_{e2})
    = [[-1, 0, 0], [1, -1, 0], [-1, 0, -1]]$ has determinant $-1$: **index 1**, 7 finite poles
    (those of the classical 7-state LFC model with $\Delta P_{12}, \Delta P_{e1}, \Delta P_{e2}$
    substituted).

    **Measured**: $y = (\Delta\omega_1, \Delta\omega_2, \Delta P_{12})$ (the frequencies and the
    tie-line flow: the signals AGC already telemeters). **Estimated**: $z = \Delta P_{m1}$,
    area 1's mechanical power (not telemetered on the time scale of seconds).

    **Uncertainty**: area 1's inertia. With converter-interfaced generation and load the
    inertia of an area is known only roughly (estimating it is a research topic of its own);
    we take the inverse inertia $1/(2H_1)$ uncertain by $\pm a$ = `inertia_uncertainty`
    (default 0.4: $1/(2H_1)\cdot(1 + 0.4\delta)$, $|\delta| \le 1$, i.e. $H_1$ between
    $H_1/1.4 = 3.6$ s and $H_1/0.6 = 8.3$ s). ``dA`` is the change of $A$ for $\delta = 1$:
    $a$ times row 1 of $A$ (columns $\Delta P_{m1}$, $\Delta P_{e1}$), a rank-one change.

    **Why the nominal design is sensitive to $\delta$, and why the observer's freedom can remove
    that (an a-priori argument).** For the plant with
    $A + \delta\,\Delta A$ and an observer that satisfies conditions a.–d. for the nominal $A$
    (`fojax.design` §3.1.2: $\varepsilon = \zeta - TEx$, $w = \Psi x$ nominally), the error obeys

    $$\dot\varepsilon = N\varepsilon + Jv - \delta\,T\Delta A\,x,\qquad
      \dot v = S\varepsilon + Gv,\qquad \hat z - z = P\varepsilon$$

    (row 1 is differential, so $E^\perp\Delta A = 0$ and $w$ carries no $\delta$ term). Here
    $\Delta A x = a\,e_1\,(\Delta P_{m1} - \Delta P_{e1})/(2H_1) = a\,e_1\,\dot{\Delta\omega}_1$:
    the uncertainty acts as an unknown input $d = \delta a\,\dot{\Delta\omega}_1$ entering
    through the first column of $T$, $t_1 = Te_1$. (i) A design that ignores $\delta$ (the
    region LMI, centred or not) has no reason to make $t_1$ small, so its estimate carries
    an error driven by $\delta\,\dot{\Delta\omega}_1$ for as long as the set point moves —
    the whole horizon, whereas the initial-state error decays with the error eigenvalues.
    (ii) $z = \Delta P_{m1}$ does not need row 1 at all: the turbine and governor rows 4–5
    give $\Delta P_{m1}$ from the measured $\Delta\omega_1$ and the known $u$ through a stable
    filter (poles $-1/\tau_{t1} = -2$, $-1/\tau_{g1} = -5$), so observers with $t_1 = 0$,
    exactly insensitive to $H_1$, exist for this $z$. In fojax's parameterization
    $T = T_1 - Z_{\text{eff}}T_2$ is affine in the free $Z$, and $t_1 = 0$ is one linear
    equation per row of $Z$, solvable whenever $WT_2e_1 \ne 0$ ($W$ the projector onto $Z$'s
    live directions). Whether such an observer of the design's order and $R$ also has its
    eigenvalues in the tuning region, and what the trade-off with the initial-state transient
    costs, is what the tuning benchmark measures (``benchmarks/tuning_circuit.py --model
    two_area_power``). Contrast: on the flexible drive $z = \tau_2 = k_2\varphi_2 + \dots$
    contains the uncertain stiffness itself and the load speed is not measured, so an estimate
    of $\tau_2$ has to lean on $k_2$ (an a-priori remark, not a proved bound).

    **Tuning benchmark** (``benchmarks/tuning_circuit.py --model two_area_power``; its numbers
    are in ``benchmarks/results/``): region ``Disk(-3.5, 2.5)`` (eigenvalues in $[-6, -1]$: it
    contains the turbine and governor poles $-2$, $-5$ of the insensitive observer of (ii),
    which the other models' ``Disk(-3, 2)`` has on its edge); ``q0 = 5``, the smallest order at
    which $[R;\Psi]$ is rank deficient so that $Y$, $J$, $G$ are live (at ``q0 = 3, 4`` only $Z$
    is); $u = 0.1\sin 2t$ pu (near the inter-area modes at 1.7–1.8 rad/s where the inertia
    acts); initial deviations uniform, $|\Delta\omega_i| \le 0.002$ pu,
    $|\Delta\delta_{12}| \le 0.02$ rad, $|\Delta P_{m,v}| \le 0.02$ pu; δ uniform in
    $[-1, 1]$; 10 s on a 0.02 s grid. The centred LMI design (all eigenvalues at $-3.5$) is far
    more sensitive to $H_1$ than the min-gain one, so the benchmark tunes from both.

    **Values**: `POWER_PARAMS`, the two-area example of H. Saadat, *Power System Analysis*
    (McGraw-Hill, 1999), ch. 12 (the two-area LFC example: $R_1 = 0.05$, $D_1 = 0.6$,
    $H_1 = 5$ s, $\tau_{g1} = 0.2$ s, $\tau_{t1} = 0.5$ s; $R_2 = 0.0625$, $D_2 = 0.9$,
    $H_2 = 4$ s, $\tau_{g2} = 0.3$ s, $\tau_{t2} = 0.6$ s; $P_s = 2$ pu; as commonly
    reproduced — we did not check them against the printed book). The model's poles are
    checked against the 7-state ODE derived by hand in ``tests/test_models.py``.

    **Arguments:** `inertia_uncertainty` ($a$ above, in $[0, 1)$) and any of `POWER_PARAMS`
    by name.

    **Returns:** a `ThesisExample` (``section`` is empty) with `system` the nominal
    `fojax.DescriptorSystem` and the quantities ``E, A, B, C`` (as above), ``L``
    (``(1, 10)``: $z = \Delta P_{m1}$), ``dA`` (``(10, 10)``), ``params`` and ``states``.
    """
    p = physical_parameters("two_area_power", POWER_PARAMS, params,
                            ("H_1", "H_2", "R_1", "R_2", "tau_g1", "tau_t1", "tau_g2", "tau_t2", "P_s"),
                            "an inertia, droop, time constant or synchronizing coefficient")
    a = float(inertia_uncertainty)
    if not 0.0 <= a < 1.0:
        raise ValueError(f"two_area_power: inertia_uncertainty must be in [0, 1) (1/(2 H_1) times 1 + a delta, "
                         f"|delta| <= 1, must stay positive); got {a}.")
    w1, d12, w2, pm1, pv1, pm2, pv2, p12, pe1, pe2 = range(10)
    E = np.diag([1.0, 1.0, 2 * p["H_2"], p["tau_t1"], p["tau_g1"], p["tau_t2"], p["tau_g2"], 0.0, 0.0, 0.0])
    A = np.zeros((10, 10))
    A[0, [pm1, pe1]] = [1.0 / (2 * p["H_1"]), -1.0 / (2 * p["H_1"])]
    A[1, [w1, w2]] = [1.0, -1.0]
    A[2, [pm2, pe2]] = [1.0, -1.0]
    A[3, [pv1, pm1]] = [1.0, -1.0]
    A[4, [w1, pv1]] = [-1.0 / p["R_1"], -1.0]
    A[5, [pv2, pm2]] = [1.0, -1.0]
    A[6, [w2, pv2]] = [-1.0 / p["R_2"], -1.0]
    A[7, [d12, p12]] = [p["P_s"], -1.0]
    A[8, [w1, p12, pe1]] = [p["D_1"], 1.0, -1.0]
    A[9, [w2, p12, pe2]] = [p["D_2"], -1.0, -1.0]
    B = np.zeros((10, 1))
    B[4, 0] = 1.0
    C = np.zeros((3, 10))
    C[0, w1] = C[1, w2] = C[2, p12] = 1.0
    L = np.zeros((1, 10))
    L[0, pm1] = 1.0
    dA = np.zeros((10, 10))
    dA[0] = a * A[0]
    E, A, B, C = _array(E), _array(A), _array(B), _array(C)
    notes = ("Not from the thesis: a two-area load-frequency-control system with an "
             "uncertain area inertia (values of Saadat's textbook example, as commonly reproduced).",)
    return linear_example("two_area_power", "", notes, E, A, B, C,
                          params=p, states=POWER_STATES, L=L, dA=_array(dA))
