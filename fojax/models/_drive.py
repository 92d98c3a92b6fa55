r"""A model that is not from the thesis: a DC motor driving two inertias through a gear and two
flexible shafts, with the armature equation and the shaft torques kept as algebraic rows."""

from __future__ import annotations

import numpy as np

from ._base import _array, linear_example, physical_parameters, ThesisExample


#: per-unit defaults of `flexible_drive` (see its docstring)
DRIVE_PARAMS = dict(J_m=1.0, b_m=0.1, K_t=1.0, K_b=1.0, R=1.0, N=2.0,
                    k_1=4.0, c_1=0.1, J_1=1.0, b_1=0.05, k_2=2.0, c_2=0.05, J_2=0.5, b_2=0.1)
#: names of the states, in order
DRIVE_STATES = ("omega_m", "phi_1", "omega_1", "phi_2", "omega_2", "i", "tau_1", "tau_2")


def flexible_drive(k_2_uncertainty: float = 0.5, **params) -> ThesisExample:
    r"""A three-inertia flexible drive train (**not from the thesis**: a second tuning model).

    A DC motor (inertia $J_m$, viscous friction $b_m$, torque constant $K_t$, back-EMF
    constant $K_b$, armature resistance $R$) drives, through a gear of ratio $N$ (motor speed
    $N$ times the gear's output speed), a flexible shaft (stiffness $k_1$, damping $c_1$) into a
    disk $J_1$ (friction $b_1$), which drives a second flexible shaft ($k_2$, $c_2$) into the
    load $J_2$ (friction $b_2$): the torsional test rig of many control labs, or a roll drive.

    **State** (SI units; $n = 8$):
    $x = (\omega_m, \varphi_1, \omega_1, \varphi_2, \omega_2, i, \tau_1, \tau_2)$ — motor speed
    [rad/s], twist of shaft 1 $\varphi_1 = \theta_m/N - \theta_1$ [rad], disk speed [rad/s],
    twist of shaft 2 $\varphi_2 = \theta_1 - \theta_2$ [rad], load speed [rad/s], armature
    current [A], shaft torques [N m]. Input: the armature voltage $u$ [V]. Twists instead of
    angles: the drive has a free rigid-body rotation, and the angles themselves (a pole at 0)
    are not needed for the speeds and torques.

    **Equations** (one row each):

    $$\begin{aligned}
    J_m\dot\omega_m &= K_t i - b_m\omega_m - \tau_1/N &&\text{(motor shaft: the gear passes } \tau_1/N\text{ back)}\\
    \dot\varphi_1 &= \omega_m/N - \omega_1 &&\text{(kinematics of the twist)}\\
    J_1\dot\omega_1 &= \tau_1 - \tau_2 - b_1\omega_1 &&\text{(disk)}\\
    \dot\varphi_2 &= \omega_1 - \omega_2\\
    J_2\dot\omega_2 &= \tau_2 - b_2\omega_2 &&\text{(load)}\\
    0 &= u - R\,i - K_b\omega_m &&\text{(armature KVL; its inductance neglected, } L_a/R \ll J_m/b_m\text{)}\\
    0 &= k_1\varphi_1 + c_1(\omega_m/N - \omega_1) - \tau_1 &&\text{(Kelvin–Voigt shaft 1)}\\
    0 &= k_2\varphi_2 + c_2(\omega_1 - \omega_2) - \tau_2 &&\text{(Kelvin–Voigt shaft 2)}
    \end{aligned}$$

    so $E = \operatorname{diag}(J_m, 1, J_1, 1, J_2, 0, 0, 0)$. The algebraic block
    $\partial(\text{rows 6–8})/\partial(i, \tau_1, \tau_2) = \operatorname{diag}(-R, -1, -1)$
    is nonsingular: **index 1**, 5 finite poles (those of the ODE obtained by substituting
    $i$, $\tau_1$, $\tau_2$). **Measured**: $y = (\omega_m, \omega_1)$ (encoders on the motor
    and on the disk); **estimated**: $z = \tau_2$, the torque in the output shaft (no torque
    sensor; it needs the load side: $\tau_2 = J_2\dot\omega_2 + b_2\omega_2$). **Uncertainty**:
    the stiffness of the output shaft, $k_2(1 + a\,\delta)$ with $|\delta| \le 1$ and
    $a$ = `k_2_uncertainty`: ``dA`` is the change of $A$ for $\delta = 1$ (row 8, column
    $\varphi_2$: $a k_2$).

    **Values** (per unit: the motor's rated torque, speed and voltage, time in units of
    $J_m\omega_{\text{rated}}/\tau_{\text{rated}}$): `DRIVE_PARAMS`, $J_m = 1$, $b_m = 0.1$,
    $K_t = K_b = 1$, $R = 1$, $N = 2$, $k_1 = 4$, $c_1 = 0.1$, $J_1 = 1$, $b_1 = 0.05$,
    $k_2 = 2$, $c_2 = 0.05$, $J_2 = 0.5$, $b_2 = 0.1$: a slow, lightly damped drive
    (finite poles $-0.876$, $-0.201 \pm 1.567i$, $-0.174 \pm 2.880i$). Chosen by us, not
    identified on a rig.

    **Arguments:** `k_2_uncertainty` ($a$ above) and any of `DRIVE_PARAMS` by name.

    **Returns:** a `ThesisExample` (the models' container; ``section`` is empty) with
    `system` the nominal `fojax.DescriptorSystem` and the quantities ``E, A, B, C`` (as
    above), ``L`` (``(1, 8)``: $z = \tau_2$), ``dA`` (``(8, 8)``), ``params`` and ``states``
    (the names, in order).
    """
    p = physical_parameters("flexible_drive", DRIVE_PARAMS, params, ("J_m", "J_1", "J_2", "R", "N", "k_1", "k_2"),
                            "a physical inertia, resistance, gear ratio or stiffness")
    iw, ip1, iw1, ip2, iw2, ii, it1, it2 = range(8)
    E = np.diag([p["J_m"], 1.0, p["J_1"], 1.0, p["J_2"], 0.0, 0.0, 0.0])
    A = np.zeros((8, 8))
    A[0, [iw, ii, it1]] = [-p["b_m"], p["K_t"], -1.0 / p["N"]]
    A[1, [iw, iw1]] = [1.0 / p["N"], -1.0]
    A[2, [iw1, it1, it2]] = [-p["b_1"], 1.0, -1.0]
    A[3, [iw1, iw2]] = [1.0, -1.0]
    A[4, [iw2, it2]] = [-p["b_2"], 1.0]
    A[5, [iw, ii]] = [-p["K_b"], -p["R"]]
    A[6, [iw, ip1, iw1, it1]] = [p["c_1"] / p["N"], p["k_1"], -p["c_1"], -1.0]
    A[7, [iw1, ip2, iw2, it2]] = [p["c_2"], p["k_2"], -p["c_2"], -1.0]
    B = np.zeros((8, 1))
    B[5, 0] = 1.0
    C = np.zeros((2, 8))
    C[0, iw] = C[1, iw1] = 1.0
    L = np.zeros((1, 8))
    L[0, it2] = 1.0
    dA = np.zeros((8, 8))
    dA[7, ip2] = k_2_uncertainty * p["k_2"]
    E, A, B, C = _array(E), _array(A), _array(B), _array(C)
    notes = ("Not from the thesis: a model of our choice for the tuning benchmarks (a second model "
             "besides the LC filter of benchmarks/lc_filter.py).",
             "Per-unit values chosen by us (a slow, lightly damped drive), not measured on a rig.")
    return linear_example("flexible_drive", "", notes, E, A, B, C,
                          params=p, states=DRIVE_STATES, L=L, dA=dA)
