r"""The reference workload of issue 7, built independently of fojax with NumPy/SciPy.

Plant and gains: thesis §4.1.3 (printed, two-decimal values), used exactly as printed.

**Closed loop.** Plant $E\dot x = A_k x + B u$, $y = Cx$ with $E = \mathrm{diag}(1,1,1,0)$;
observer (thesis eq. 4.3)

$$\dot\zeta = N\zeta + Jv + Fw + Hu,\qquad \dot v = S\zeta + Gv + Mw,\qquad
  \hat z = P\zeta + Qw,\qquad w = \begin{bmatrix}-E^\perp B u\\ y\end{bmatrix},$$

with $E^\perp = [0\;0\;0\;1]$ and the controller $u = \hat z$ ($u_r = 0$).
Because $w$ contains $-E^\perp B u$ and $u = \hat z$ contains $Qw$, this is an algebraic
loop in $u$: $u = P\zeta + Q_1(-E^\perp B u) + Q_{2:4} y$, i.e.
$(I + Q_1 E^\perp B) u = P\zeta + Q_{2:4} C x$. For this example $E^\perp B = [0, 0]$
(the last row of $B$ is zero; checked below), so the loop vanishes and
$w = W x$ with $W = [0_{1\times 4}; C]$, $u = P\zeta + QWx$. The 8-state closed loop
$\bar x = [x; \zeta; v]$ is the descriptor system $\mathcal E\dot{\bar x} = \mathcal A_k\bar x$,

$$\mathcal E = \mathrm{diag}(E, I_2, I_2),\qquad
  \mathcal A_k = \begin{bmatrix} A_k + BQW & BP & 0\\ FW + HQW & N + HP & J\\ MW & S & G\end{bmatrix}.$$

(The thesis's eq. 4.13 writes the loop in the error coordinates $\varepsilon$; with the
rounded printed gains the constraints a.–d. hold only approximately, so we close the loop
with the observer *as implemented*, eq. 4.3, which is what a simulation of the printed
gains does.)

**Index-1 reduction (by hand).** $\mathcal E$ is diagonal with a single zero at the plant's
4th state (0-based index 3). Let $d$ be the 7 differential indices and $a = \{3\}$ the
algebraic one. The algebraic row reads $0 = \mathcal A_{ad}\bar x_d + \mathcal A_{aa} x_a$ with
$\mathcal A_{aa} = A_{44} = 1 \neq 0$ (index 1), so

$$x_a = -\mathcal A_{aa}^{-1}\mathcal A_{ad}\,\bar x_d,\qquad
  \dot{\bar x}_d = (\mathcal A_{dd} - \mathcal A_{da}\mathcal A_{aa}^{-1}\mathcal A_{ad})\,\bar x_d
  =: A^{\rm red}_k\,\bar x_d,$$

a 7-state ODE ($\mathcal E_{dd} = I$). The full state is $\bar x = T\bar x_d$ with $T$ the
$8\times 7$ matrix stacking $I_7$ and $-\mathcal A_{aa}^{-1}\mathcal A_{ad}$ in the original
order. The perturbation $\delta_k\Delta A$ only touches plant rows 1 and 2, so $T$ (and the
output map below) is the same for every sample; this is asserted.

**Outputs and metrics.** $x = [I_4\; 0]\,T\bar x_d$ and
$\hat z - Lx = [QW - L,\; P,\; 0]\,T\bar x_d$, stacked into $C^{\rm out}$ (6×7). Per sample:
IAE of $\|x(t)\|_1$ and IAE of $\|\hat z(t) - Lx(t)\|_1$, by the trapezoid rule on the
0.01 s grid of $[0, 10]$.

**Samples.** $A_k = A + \delta_k\Delta A$ with $\Delta A$ ones at (1,3) and (2,2) (1-based),
$\delta_k\sim U[-0.3, 0.3]$; $x(0)_k = [16,-1,3,7]\odot(1 + 0.1\xi_k)$, $\xi_k$ standard normal,
then the algebraic component $x_4(0)$ is replaced by its consistent value
$-\mathcal A_{aa}^{-1}\mathcal A_{ad}\bar x_d(0)$ ($= x_1 + 2x_2$ here); observer states start at
0. $\delta$ and $\xi$ come from two independent streams spawned from one
`numpy.random.SeedSequence`, so sample $k$ is the same for every batch size $B > k$.

**Study 2** (``time_varying.py``): the same loop with a time-varying uncertainty and a fault.

Sample $k$: $A_k(t) = A + \delta_k(t)\,\Delta A$ with
$\delta_k(t) = a_k\sin(\omega_k t + \varphi_k)$, $a_k\sim U[0, 0.3]$,
$\omega_k\sim U[0.5, 5]$ rad/s, $\varphi_k\sim U[0, 2\pi)$, and a constant actuator fault
$f_k\in\mathbb R^2$, $f_{k,i}\sim U[-1, 1]$: the plant receives $u + f_k$ while the observer
is fed the commanded $u = \hat z$ (its $Hu$ term and $w$), i.e. the closed loop is
$\mathcal E\dot{\bar x} = \mathcal A(\delta_k(t))\bar x + B_f f_k$ with $B_f = [B; 0_{4\times 2}]$.
$x(0)_k$ is drawn exactly as in study 1 (the same stream, so sample $k$ starts from the same
state in both studies). Horizon, grid and metrics are those of study 1.

Reduction: $\Delta A$ and $B_f$ only touch plant rows 1–3 (differential), so the algebraic row
and hence $T$ are the same for every sample and time, the reduced matrix is affine in
$\delta$, $A^{\rm red}(\delta) = A^{\rm red}_0 + \delta\,\Delta A^{\rm red}$, and the fault enters
as $b^{\rm red} f_k$ (all asserted).

Stability for *every* profile with $|\delta(t)|\le 0.3$ (whatever its rate): a common quadratic
Lyapunov function $P \succ 0$ with $A^{\rm red}(\pm 0.3)^\top P + P A^{\rm red}(\pm 0.3) + 2\alpha P
\prec 0$ exists for $\alpha = 0.5$ (found by `quadratic_stability_certificate`, an LMI solved with
cvxpy and then verified with NumPy eigenvalues); by convexity it holds on the whole interval, so
every sample's homogeneous part decays at least like $e^{-0.5 t}$ and the fault response stays bounded.
"""

from __future__ import annotations

import dataclasses

import numpy as np


# ---------------------------------------------------------------- printed §4.1.3 data
E = np.diag([1.0, 1.0, 1.0, 0.0])
A = np.array(
    [
        [-3.0, 2.0, 1.0, 1.0],
        [1.0, -2.0, 1.0, -2.0],
        [3.0, 0.0, 1.0, -0.5],
        [-1.0, -2.0, 0.0, 1.0],
    ]
)
B = np.array([[1.0, 0.0], [0.5, -1.0], [0.0, 1.0], [0.0, 0.0]])
C = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]])
L = np.array([[-8.95, -26.07, 12.1, -4.85], [1.71, 1.31, -3.51, -0.16]])
N = np.array([[-3.24, -4.26], [-0.1, -2.33]])
J = np.array([[2.94, 2.94], [0.3, 0.3]])
F = np.array([[8.12, 39.76, -15.39, 17.1], [-2.01, -11.6, 5.58, -2.45]])
H = np.array([[-25.04, 34.63], [7.74, -9.09]])
S = np.array([[0.2, 0.7], [0.11, 0.37]])
G = np.array([[-2.73, -0.73], [-0.38, -2.38]])
M = np.array([[0.05, -0.62, 0.76, -0.05], [0.09, -0.26, 0.54, -0.09]])
P = np.array([[1.0, -0.01], [-0.01, 0.96]])
Q = np.array([[-0.37, 4.48, -4.29, -4.48], [1.67, -1.53, -0.98, -1.83]])
E_PERP = np.array([[0.0, 0.0, 0.0, 1.0]])

DELTA_A = np.zeros((4, 4))
DELTA_A[0, 2] = 1.0  # (1,3) 1-based
DELTA_A[1, 1] = 1.0  # (2,2) 1-based
DELTA_MAX = 0.3
X0_NOMINAL = np.array([16.0, -1.0, 3.0, 7.0])
X0_SPREAD = 0.1

T_END = 10.0
DT_GRID = 0.01
TS = np.linspace(0.0, T_END, int(round(T_END / DT_GRID)) + 1)  # 1001 points, t_i = i * 0.01

#: Nominal finite poles quoted in issue 7 (two decimals).
EXPECTED_POLES = np.array(
    [-39.78, -4.48, -2.21, -2.00, -2.00, -1.69 + 1.99j, -1.69 - 1.99j], dtype=complex
)

N_PLANT, N_OBS = 4, 4
N_FULL = N_PLANT + N_OBS  # 8
ALG = np.array([3])  # algebraic index of the closed loop (plant x4)
DIFF = np.array([i for i in range(N_FULL) if i not in ALG])  # 7 differential indices
DEFAULT_SEED = 20261121


def _check_algebraic_loop() -> np.ndarray:
    """Return ``W`` with ``w = W x``; asserts that the algebraic loop in ``u`` vanishes."""
    EpB = E_PERP @ B
    if np.any(EpB != 0.0):  # pragma: no cover - holds for the printed example
        raise AssertionError(f"E_perp B = {EpB} is not zero: the loop u = zhat would be algebraic")
    return np.vstack([np.zeros((1, 4)), C])


W = _check_algebraic_loop()
E_CL = np.zeros((N_FULL, N_FULL))
E_CL[:4, :4] = E
E_CL[4:, 4:] = np.eye(4)


def closed_loop_A(A_plant: np.ndarray) -> np.ndarray:
    """The 8×8 closed-loop matrix $\\mathcal A$ for plant matrices ``(..., 4, 4)``."""
    A_plant = np.asarray(A_plant, dtype=float)
    batch = A_plant.shape[:-2]
    Acl = np.zeros(batch + (N_FULL, N_FULL))
    Acl[..., :4, :4] = A_plant + B @ Q @ W
    Acl[..., :4, 4:6] = B @ P
    Acl[..., 4:6, :4] = F @ W + H @ Q @ W
    Acl[..., 4:6, 4:6] = N + H @ P
    Acl[..., 4:6, 6:8] = J
    Acl[..., 6:8, :4] = M @ W
    Acl[..., 6:8, 4:6] = S
    Acl[..., 6:8, 6:8] = G
    return Acl


def reduce_index1(Acl: np.ndarray):
    """Index-1 reduction of $\\mathcal E\\dot{\\bar x} = \\mathcal A\\bar x$ (see module docstring).

    **Returns:** ``(A_red, T)`` with ``A_red`` ``(..., 7, 7)`` and ``T`` ``(..., 8, 7)``
    mapping the differential states to the full state.
    """
    # The structure the hand reduction relies on: E_dd = I, E_da = E_ad = E_aa = 0.
    assert np.array_equal(E_CL[np.ix_(DIFF, DIFF)], np.eye(DIFF.size))
    assert not E_CL[np.ix_(DIFF, ALG)].any() and not E_CL[ALG].any()
    Add = Acl[..., DIFF[:, None], DIFF]
    Ada = Acl[..., DIFF[:, None], ALG]
    Aad = Acl[..., ALG[:, None], DIFF]
    Aaa = Acl[..., ALG[:, None], ALG]
    if np.min(np.abs(np.linalg.det(Aaa))) < 1e-12:  # pragma: no cover
        raise AssertionError("A_aa is singular: the loop is not index 1")
    K = -np.linalg.solve(Aaa, Aad)  # x_a = K x_d
    A_red = Add + Ada @ K
    T = np.zeros(Acl.shape[:-2] + (N_FULL, DIFF.size))
    T[..., DIFF, np.arange(DIFF.size)] = 1.0
    T[..., ALG, :] = K
    return A_red, T


def full_output_rows() -> np.ndarray:
    """``(6, 8)`` map from the closed-loop state $\\bar x$ to $[x; \\hat z - Lx]$ (``C_out = C_full T``)."""
    C_full = np.zeros((6, N_FULL))
    C_full[:4, :4] = np.eye(4)
    C_full[4:, :4] = Q @ W - L
    C_full[4:, 4:6] = P
    return C_full


def output_map(T: np.ndarray) -> np.ndarray:
    """``C_out`` (6×7): rows 0–3 give $x$, rows 4–5 give $\\hat z - Lx$, from $\\bar x_d$."""
    return full_output_rows() @ T


def nominal_finite_poles() -> np.ndarray:
    """Finite poles of the nominal loop: eigenvalues of the reduced 7×7 matrix, sorted by
    real part (rounded to 1e-9, so that a conjugate pair whose real parts differ in the
    last bits comes out as (-imag, +imag) on every BLAS), then imaginary part."""
    A_red, _ = reduce_index1(closed_loop_A(A))
    lam = np.linalg.eigvals(A_red)
    return lam[np.lexsort((lam.imag, np.round(lam.real, 9)))]


def poles_match(lam, expected, atol: float) -> bool:
    """Whether `lam` and `expected` pair one to one within `atol` (a matching, not a sort:
    the order of eigenvalues depends on the BLAS kernel)."""
    from scipy.optimize import linear_sum_assignment

    lam, expected = np.asarray(lam).ravel(), np.asarray(expected).ravel()
    if lam.size != expected.size:
        return False
    dist = np.abs(lam[:, None] - expected[None, :])
    # pairs beyond atol cost more than any matching within atol: found whenever one exists
    r, c = linear_sum_assignment(np.where(dist <= atol, dist, lam.size * atol + 1.0))
    return bool(np.all(dist[r, c] <= atol))


@dataclasses.dataclass(frozen=True)
class Workload:
    """A batch of the reference workload (all float64 NumPy arrays).

    - `delta` ``(B,)``, `A_plant` ``(B, 4, 4)``, `x0_plant` ``(B, 4)`` (consistent);
    - `A_cl` ``(B, 8, 8)``, `x0_cl` ``(B, 8)`` closed-loop descriptor data ($\\mathcal E$ is `E_CL`);
    - `A_red` ``(B, 7, 7)``, `xd0` ``(B, 7)`` reduced ODE; `T` ``(8, 7)`` and `C_out` ``(6, 7)``
      (sample-independent, asserted); `ts` ``(1001,)``.
    """

    delta: np.ndarray
    A_plant: np.ndarray
    x0_plant: np.ndarray
    A_cl: np.ndarray
    x0_cl: np.ndarray
    A_red: np.ndarray
    xd0: np.ndarray
    T: np.ndarray
    C_out: np.ndarray
    ts: np.ndarray

    @property
    def size(self) -> int:
        return self.delta.shape[0]


def _initial_states(xi: np.ndarray, T: np.ndarray):
    """``(x_raw, xd0, x0_cl)`` from the standard normals `xi` ``(B, 4)``: the drawn plant state,
    the reduced initial state (plant x1..x3; observer states zeta, v start at 0) and the
    consistent closed-loop one (x4 solved from the algebraic row)."""
    x_raw = X0_NOMINAL * (1.0 + X0_SPREAD * xi)
    xd0 = np.zeros((xi.shape[0], DIFF.size))
    xd0[:, :3] = x_raw[:, :3]
    return x_raw, xd0, xd0 @ T.T


def make_workload(batch: int, seed: int = DEFAULT_SEED, check_stability: bool = True) -> Workload:
    """Draw `batch` samples of the reference workload from a NumPy Generator seed."""
    ss_delta, ss_xi = np.random.SeedSequence(seed).spawn(2)
    delta = np.random.default_rng(ss_delta).uniform(-DELTA_MAX, DELTA_MAX, size=batch)
    xi = np.random.default_rng(ss_xi).standard_normal(size=(batch, 4))
    A_plant = A + delta[:, None, None] * DELTA_A
    A_cl = closed_loop_A(A_plant)
    A_red, T_b = reduce_index1(A_cl)
    T = T_b[0] if batch else reduce_index1(closed_loop_A(A))[1]
    if not np.allclose(T_b, T, rtol=0, atol=0):
        raise AssertionError("the algebraic map depends on the sample; C_out would be per-sample")
    x_raw, xd0, x0_cl = _initial_states(xi, T)
    assert np.allclose(x0_cl[:, :3], x_raw[:, :3]) and not x0_cl[:, 4:].any()
    resid = np.einsum("bij,bj->bi", A_cl[:, ALG, :], x0_cl)
    assert np.max(np.abs(resid), initial=0.0) < 1e-12, "x(0) is not consistent"
    if check_stability and batch:
        worst = np.max(np.linalg.eigvals(A_red).real)
        if not worst < 0:
            raise AssertionError(f"an unstable sample: max Re(pole) = {worst}")
    return Workload(
        delta=delta,
        A_plant=A_plant,
        x0_plant=x0_cl[:, :4].copy(),
        A_cl=A_cl,
        x0_cl=x0_cl,
        A_red=A_red,
        xd0=xd0,
        T=T,
        C_out=output_map(T),
        ts=TS.copy(),
    )


def max_real_pole_over_interval(num: int = 601) -> float:
    """Largest real part of the finite poles over a fine grid of $\\delta\\in[-0.3, 0.3]$."""
    d = np.linspace(-DELTA_MAX, DELTA_MAX, num)
    A_red, _ = reduce_index1(closed_loop_A(A + d[:, None, None] * DELTA_A))
    return float(np.max(np.linalg.eigvals(A_red).real))


def metrics_from_outputs(Y: np.ndarray, dt: float = DT_GRID) -> np.ndarray:
    """``(..., T, 6)`` outputs on the grid → ``(..., 2)`` metrics (trapezoid rule)."""
    f = np.stack([np.abs(Y[..., :4]).sum(-1), np.abs(Y[..., 4:]).sum(-1)], axis=-1)  # (..., T, 2)
    return dt * (f.sum(-2) - 0.5 * (f[..., 0, :] + f[..., -1, :]))


# ================================================================ study 2: time-varying δ(t) + fault

TV_AMPLITUDE_MAX = 0.3
TV_OMEGA_RANGE = (0.5, 5.0)
FAULT_MAX = 1.0
B_FAULT_CL = np.vstack([B, np.zeros((4, 2))])  # (8, 2): the fault enters the plant rows only
DELTA_A_CL = closed_loop_A(A + DELTA_A) - closed_loop_A(A)  # (8, 8), affine: A_cl(δ) = A_cl(0) + δ ΔA_cl


def _tv_reduction():
    """Hand reduction of the time-varying loop: ``(A_red0, dA_red, b_fault, T)``."""
    A_red0, T = reduce_index1(closed_loop_A(A))
    A_red1, T1 = reduce_index1(closed_loop_A(A + DELTA_A))
    assert np.array_equal(T, T1), "ΔA touches the algebraic row"
    assert not B_FAULT_CL[ALG].any(), "the fault enters the algebraic row"
    dA_red = A_red1 - A_red0
    b_fault = B_FAULT_CL[DIFF] - _da_over_aa(closed_loop_A(A)) @ B_FAULT_CL[ALG]
    return A_red0, dA_red, b_fault, T


def _da_over_aa(Acl: np.ndarray) -> np.ndarray:
    """$\\mathcal A_{da}\\mathcal A_{aa}^{-1}$ (7×1): how the algebraic equation feeds the ODE."""
    return Acl[np.ix_(DIFF, ALG)] @ np.linalg.inv(Acl[np.ix_(ALG, ALG)])


@dataclasses.dataclass(frozen=True)
class TimeVaryingWorkload:
    """A batch of study 2 (float64 NumPy arrays).

    - `amplitude`, `omega`, `phase` ``(B,)``: $\\delta_k(t) = a_k\\sin(\\omega_k t + \\varphi_k)$;
    - `fault` ``(B, 2)``: the constant actuator fault $f_k$;
    - `x0_cl` ``(B, 8)`` consistent closed-loop initial states, `xd0` ``(B, 7)`` reduced ones;
    - `A_red0`, `dA_red` ``(7, 7)``, `b_fault` ``(7, 2)``: $\\dot x_d = (A^{\\rm red}_0 +
      \\delta_k(t)\\Delta A^{\\rm red})x_d + b^{\\rm red} f_k$; `T` ``(8, 7)``, `C_out` ``(6, 7)``;
      `ts` ``(1001,)``.
    """

    amplitude: np.ndarray
    omega: np.ndarray
    phase: np.ndarray
    fault: np.ndarray
    x0_cl: np.ndarray
    xd0: np.ndarray
    A_red0: np.ndarray
    dA_red: np.ndarray
    b_fault: np.ndarray
    T: np.ndarray
    C_out: np.ndarray
    ts: np.ndarray

    @property
    def size(self) -> int:
        return self.amplitude.shape[0]

    def delta(self, t) -> np.ndarray:
        """$\\delta_k(t)$ for every sample, ``(B,)``."""
        return self.amplitude * np.sin(self.omega * t + self.phase)

    def forcing(self) -> np.ndarray:
        """``(B, 7)``: the constant fault term $b^{\\rm red} f_k$ of each sample's ODE."""
        return self.fault @ self.b_fault.T

    def rhs(self, k: int):
        """Sample ``k``'s reduced vector field ``f(t, x_d)`` (for `scipy.integrate.solve_ivp`)."""
        A0, dA = self.A_red0, self.dA_red
        a, om, ph = self.amplitude[k], self.omega[k], self.phase[k]
        c = self.b_fault @ self.fault[k]

        def f(t, x):
            return A0 @ x + (a * np.sin(om * t + ph)) * (dA @ x) + c

        return f


def make_tv_workload(batch: int, seed: int = DEFAULT_SEED) -> TimeVaryingWorkload:
    """Draw `batch` samples of study 2; streams 2–5 of the seed (1 is study 1's x(0) stream)."""
    children = np.random.SeedSequence(seed).spawn(6)
    xi = np.random.default_rng(children[1]).standard_normal(size=(batch, 4))
    amplitude = np.random.default_rng(children[2]).uniform(0.0, TV_AMPLITUDE_MAX, size=batch)
    omega = np.random.default_rng(children[3]).uniform(*TV_OMEGA_RANGE, size=batch)
    phase = np.random.default_rng(children[4]).uniform(0.0, 2 * np.pi, size=batch)
    fault = np.random.default_rng(children[5]).uniform(-FAULT_MAX, FAULT_MAX, size=(batch, 2))
    A_red0, dA_red, b_fault, T = _tv_reduction()
    _, xd0, x0_cl = _initial_states(xi, T)  # the fault does not enter the algebraic row
    return TimeVaryingWorkload(
        amplitude=amplitude,
        omega=omega,
        phase=phase,
        fault=fault,
        x0_cl=x0_cl,
        xd0=xd0,
        A_red0=A_red0,
        dA_red=dA_red,
        b_fault=b_fault,
        T=T,
        C_out=output_map(T),
        ts=TS.copy(),
    )


def quadratic_stability_certificate(alpha: float = 0.5):
    """A common Lyapunov matrix for $\\delta\\in[-0.3, 0.3]$ with decay rate `alpha`.

    Solves the LMI $P \\succeq I$, $A_\\pm^\\top P + PA_\\pm + 2\\alpha P \\preceq -10^{-2} I$ at the
    vertices $A_\\pm = A^{\\rm red}(\\pm 0.3)$ with cvxpy (Clarabel), then verifies it with
    NumPy. **Returns:** ``(P, worst)`` with ``worst`` the largest eigenvalue of the vertex
    matrices (negative: certified). Affine in δ, so the vertices certify the interval.
    """
    import cvxpy as cp

    A_red0, dA_red, _, _ = _tv_reduction()
    verts = [A_red0 + s * TV_AMPLITUDE_MAX * dA_red for s in (-1.0, 1.0)]
    P = cp.Variable((7, 7), symmetric=True)
    cons = [P >> np.eye(7)] + [V.T @ P + P @ V + 2 * alpha * P << -1e-2 * np.eye(7) for V in verts]
    cp.Problem(cp.Minimize(0), cons).solve(solver=cp.CLARABEL)
    Pv = 0.5 * (P.value + P.value.T)
    worst = max(float(np.linalg.eigvalsh(V.T @ Pv + Pv @ V + 2 * alpha * Pv).max()) for V in verts)
    assert np.linalg.eigvalsh(Pv).min() > 0
    return Pv, worst


if __name__ == "__main__":
    lam = nominal_finite_poles()
    print("nominal finite poles:", np.array2string(lam, precision=3))
    print(f"max Re(pole) over delta in [-0.3, 0.3]: {max_real_pole_over_interval():.4f}")
    wl = make_workload(5)
    print("delta:", wl.delta)
    print("x0 (consistent):\n", wl.x0_cl)
