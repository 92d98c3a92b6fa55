r"""Riccati design route: functional-observer gains without an SDP.

**The problem.** With the free parameter $Z$ fixed, the error dynamics of the
generalized/proportional functional observer are (`fojax.design.observer_matrices`)

$$\mathbb A = \mathbb A_1(Z) - \mathbb Y\mathbb A_2,\qquad
  \mathbb A_1 = \operatorname{diag}(N_1' - ZN_2', 0),\quad
  \mathbb A_2 = \operatorname{diag}(N_3, -I_{q_1}),$$

with every entry of $\mathbb Y = [[Y_1, J], [Y_2, G]]$ free (generalized), $Y_2 = 0$ (PI), or
$q_1 = 0$, $\mathbb Y = Y_1$ (proportional). The LMI route (`fojax.design._functional`)
linearises the bilinear region condition with $\mathcal W = X\mathbb Y$.

**Möbius map of a disk.** $\lambda \mapsto (\lambda - \alpha)/\tau$ sends the disk
$\mathcal Q(\alpha, \tau)$ onto the unit disk. So the eigenvalues of $\mathbb A$ lie in
$\mathcal Q(\alpha, \tau)$ iff $A_d - \mathbb Y C_d$ is Schur stable, with
$A_d = (\mathbb A_1 - \alpha I)/\tau$ and $C_d = \mathbb A_2/\tau$: a *discrete-time
output-injection* problem for the pair $(A_d, C_d)$ (the dual of state feedback).
It is solved by the filter Riccati equation (DARE, `scipy.linalg.solve_discrete_are`
on the transposed pair)

$$P = A_dPA_d^\top - A_dPC_d^\top(I + C_dPC_d^\top)^{-1}C_dPA_d^\top + I,\qquad
  \mathbb Y = A_dPC_d^\top(I + C_dPC_d^\top)^{-1},$$

whose stabilizing solution exists iff $(A_d, C_d)$ is detectable, i.e. iff every mode
of $\mathbb A_1$ that no gain can move lies inside the disk (the unit-weight choice
$Q = R = I$ is fojax's; any positive definite weights give a valid gain). Only the
row space of $C_d$ matters ($R = I$): the DARE is solved with $\tilde C = S_kV_k^\top$
from the thin SVD $C_d = U_kS_kV_k^\top$, and $\mathbb Y = \tilde{\mathbb Y}U_k^\top$ — the
gain has no component outside the range of $\mathbb A_2$, like the LMI route's
projected gain.

**Certificate (Stein equation).** With $A_{cl} = (\mathbb A - \alpha I)/\tau'$
(the disk radius $\tau' < \tau$, see below) Schur, the Stein equation
$A_{cl}^\top XA_{cl} - X + I = 0$ (`scipy.linalg.solve_discrete_lyapunov`) has a
unique solution $X \succeq I$, and $(\mathbb A - \alpha I)^\top X(\mathbb A - \alpha I)
= \tau'^2(X - I) \prec \tau^2X$: by a Schur complement this is the Chilali–Gahinet disk
LMI $\begin{bmatrix}-\tau X & X(\mathbb A - \alpha I)\\ \cdot & -\tau X\end{bmatrix}\prec 0$
that `fojax.design.verify` re-checks in float64. The certificate is recomputed from the
closed loop, not taken from the Riccati solution ($P^{-1}$ would also certify); for a
generalized observer it is solved block by block (the closed loop is block diagonal, below).

**Z, and the decoupling of the generalized observer.** $Z$ only enters the
$\varepsilon$-block $N_1' - ZN_2' - Y_1N_3$, itself an output-injection problem for the
pair $(N_1', [N_2'; N_3])$ with gain $[Z\;Y_1]$ (what the LMI route linearises with
$W = X_1Z$): one DARE of size $q_0$ gives $Z$ and $Y_1$ — for a proportional observer,
the whole design. For a generalized observer the pair $(\mathbb A_1(Z), \mathbb A_2)$
is block diagonal ($\mathbb A_1 = \operatorname{diag}(\cdot, 0)$,
$\mathbb A_2 = \operatorname{diag}(N_3, -I)$), and so are the weights $Q = R = I$: the
block-diagonal assembly of the two blocks' stabilizing solutions is a stabilizing
solution of the full DARE, hence *the* solution, and its gain is block diagonal:
$J = 0$, $Y_2 = 0$ ($S = 0$) and $G = gI$ with $g$ from the $1\times1$ DARE of
$(-\alpha/\tau', -1/\tau')$. fojax computes these blocks directly (a test checks them
against SciPy's DARE of the full pair), so the design costs one DARE of size $q_0$, not
$q_0 + q_1$. This decoupled gain is the route's **PI** observer ($S = 0$ exactly). Fixing
$Z = 0$ instead of taking it from the DARE also gives valid observers when $(N_1', N_3)$ is
detectable, but with large gains and badly conditioned certificates when $N_3$ has few
independent rows (thesis example 3.1.3); with $Z$ from the DARE the largest gain entries
are of the LMI route's size on the thesis examples.

**Coupled generalized design (`_couple`).** A **generalized** observer is meant to use
the coupling freedom of eq. 3.5: the integral state drives $\varepsilon$ ($J \ne 0$) and is
driven by the measured residual ($S = -Y_2N_3 \ne 0$). Starting from the decoupled loop
$\bar A_0$ (disk coordinates) and its Stein certificate $X_0$, the route adds
$J = \kappa\Pi$ and $Y_2 = \kappa\Pi^\top Y_1/\|Y_1\|$ ($\Pi = I$ padded to $q_0\times q_1$,
the thesis's coupling of $\varepsilon$ and $v$), which changes the loop by $\kappa D$. Since
$\bar A_0^\top X_0\bar A_0 = X_0 - I$, the loop's norm induced by $X_0$ is
$\sqrt{1 - 1/\lambda_{\max}(X_0)} < 1$; choosing $\kappa$ as half the room left below 1
divided by $\|D\|_{X_0}$ keeps the coupled loop a contraction in that norm, so its
eigenvalues stay in the disk, and its own Stein certificate is computed and verified. The
cost is $O(q_0^3)$ (one Cholesky factor and one Stein equation of size $q_0 + q_1$).
Larger couplings, or couplings chosen for a performance objective, come from the LMI route
or from tuning (`fojax.tuning`), which moves $J, Y_2, G$ freely from this starting point.

**Half-planes and sectors (mapped into a disk; sound).** If $X$ certifies the disk
$\mathcal Q(\alpha, \tau)$, then $\|X^{1/2}(\mathbb A - \alpha I)X^{-1/2}\| < \tau$, so the
$X$-numerical range $\{v^*X\mathbb Av / v^*Xv\}$ lies in the open disk. For a
half-plane or a sector the Chilali–Gahinet LMI at $X$ says exactly that this numerical
range lies in the region (the sector's $2\times2$ LMI is the real form of one Hermitian
condition per boundary line). Hence a disk *inside* the region gives a certificate of
the region itself, which `verify` re-checks anyway. fojax uses, for
$\operatorname{Re}s < -\sigma$, the disk tangent to the boundary with centre
$-\sigma-\rho$, radius $\rho = \max(1, \sigma)$, enlarged until it contains every
fixed mode (modes no gain can move) with a margin; for the sector of damping
$\zeta = \cos\theta$, the disk centred at $-a$ with radius $a\sin\theta$ (tangent to
both lines), $a$ chosen to contain the fixed modes (else $a = 1$, the sector's
target). Intersections of regions (and common certificates over rules) are left to
the LMI route.

**Margin.** Like the LMI route (which targets `region.tightened(0.05)`), the Riccati
route targets the disk with radius $\tau' = 0.95\tau$, so the eigenvalues keep a margin
of $0.05\tau$ inside the disk (hence inside the region).

**What is not different from the LMI route.** The result goes through the same
`verify_structure_design` (conditions a.–d., eigenvalues in the user's region, the
region LMI at $X$ in float64). A failure of the Riccati route (no stabilizing solution)
raises `fojax.errors.LMIInfeasibleError`, the error the LMI route raises when its solver finds
no solution, with the closed-loop spectral radius in the message.
"""

from __future__ import annotations

import math

import numpy as np
import scipy.linalg

from .._errors import InputError, LMIInfeasibleError
from ._conditions import unobservable_modes
from ._parameterization import FunctionalObserverStructure, pieces
from ._regions import AbstractRegion, Disk, HalfPlane, Sector
from ._stein import host_stein_certificate


#: The Riccati route targets the disk shrunk by this fraction (as the LMI route targets
#: `region.tightened(TIGHTEN)`).
TIGHTEN = 0.05
#: The closed loop (in the Möbius coordinates of the shrunk disk) must have spectral
#: radius below this before the certificate is computed.
SCHUR_TOL = 1.0 - 1e-9
METHODS = ("auto", "riccati", "lmi")


def check_method(method) -> str:
    """`method` if it is one of `METHODS`, else `fojax.errors.InputError` listing them."""
    if method in METHODS:
        return method
    raise InputError(
        f"method must be one of {', '.join(map(repr, METHODS))}; got {method!r}. "
        "'riccati' solves a discrete Riccati equation (disk, half-plane or sector regions), "
        "'lmi' the region LMI, 'auto' the Riccati route where it applies."
    )


def riccati_applies(region: AbstractRegion, kind: str, num_rules: int = 1) -> str | None:
    """``None`` if the Riccati route applies, else the reason it does not."""
    if num_rules != 1:
        return "several rules need a common certificate (LMI route)"
    if kind not in ("generalized", "PI", "proportional"):
        return f"kind {kind!r} is not an observer kind of this route"
    if not isinstance(region, Disk | HalfPlane | Sector):
        return f"the region {region.describe()} is not a single disk, half-plane or sector (LMI route)"
    return None


def _fixed_modes_eps(s: FunctionalObserverStructure) -> np.ndarray:
    pc = pieces(s, xp=np)
    N1, N2, N3 = (np.asarray(x)[0] if np.ndim(x) == 3 else np.asarray(x) for x in (pc.N1, pc.N2, pc.N3))
    return unobservable_modes(N1, np.vstack([N2, N3]))


def region_disk(region: AbstractRegion, fixed_modes=()) -> Disk:
    """A disk inside `region` (module docstring) containing the `fixed_modes` when possible."""
    fixed = np.atleast_1d(np.asarray(fixed_modes, complex))
    if isinstance(region, Disk):
        return region
    if isinstance(region, HalfPlane):
        sig = region.decay
        rho = max(1.0, sig)
        for lam in fixed:
            x, y = lam.real + sig, lam.imag  # x < 0 inside the half-plane
            if x < 0:
                # |lam - c| < rho with c = -sig - rho  <=>  rho > (x² + y²) / (-2x)
                rho = max(rho, 1.5 * (x * x + y * y) / (-2.0 * x))
        return Disk(-sig - rho, rho)
    if isinstance(region, Sector):
        th = math.acos(region.damping)
        s = math.sin(th)
        a = 1.0
        if fixed.size:
            cands = np.logspace(-3, 6, 400) * max(1.0, float(np.max(np.abs(fixed))))
            worst = [np.max(np.abs(fixed + c)) / (c * s) for c in cands]
            a = float(cands[int(np.argmin(worst))])
        return Disk(-a, a * s)
    raise InputError(f"the Riccati route needs a disk, half-plane or sector; got {region.describe()}.")


def output_injection_gain(Ad: np.ndarray, Cd: np.ndarray) -> np.ndarray:
    """The DARE gain ``Y`` making ``Ad - Y Cd`` Schur (weights ``Q = R = I``; module docstring).

    Raises `LMIInfeasibleError` when SciPy finds no stabilizing solution."""
    d = Ad.shape[0]
    if Cd.size == 0:
        return np.zeros((d, Cd.shape[0]))
    U, sv, Vt = np.linalg.svd(Cd, full_matrices=False)
    # rank of Cd relative to the data (Ad and Cd): directions of Cd at round-off of Ad's
    # size are no output (the DARE of a pair with such a Cd has no numerical solution)
    scale = max(sv[0] if sv.size else 0.0, float(np.linalg.norm(Ad, 2)) if Ad.size else 0.0)
    k = int(np.sum(sv > max(Cd.shape) * np.finfo(float).eps * scale))
    if k == 0:
        return np.zeros((d, Cd.shape[0]))
    Ct = sv[:k, None] * Vt[:k]  # k × d, Cd = U_k Ct
    try:
        P = scipy.linalg.solve_discrete_are(Ad.T, Ct.T, np.eye(d), np.eye(k))
    except (np.linalg.LinAlgError, ValueError) as e:
        raise LMIInfeasibleError(
            "output-injection Riccati equation (disk mapped to the unit disk)", "no_stabilizing_solution",
            {"message": str(e)},
            "A mode that no observer gain can move lies outside the disk: enlarge the region, or "
            "choose another R / observer order.",
        ) from None
    P = 0.5 * (P + P.T)
    G = Ct @ P @ Ct.T + np.eye(k)
    Yt = np.linalg.solve(G, Ct @ P @ Ad.T).T  # Ad P Ctᵀ (I + Ct P Ctᵀ)^{-1}
    rho = _spectral_radius(Ad - Yt @ Ct)
    if not rho < SCHUR_TOL:
        raise LMIInfeasibleError(
            "output-injection Riccati equation (disk mapped to the unit disk)", "not_stabilizing",
            {"spectral_radius": rho},
            f"The Riccati gain leaves spectral radius {rho:.6g} ≥ 1 in the disk's coordinates: a "
            "mode that no observer gain can move lies outside the disk. Enlarge the region, choose "
            "another R / observer order, or use method='lmi'.",
        )
    return Yt @ U[:, :k].T


def _spectral_radius(M: np.ndarray) -> float:
    return float(np.max(np.abs(np.linalg.eigvals(M)))) if M.size else 0.0


#: The coupling of a generalized Riccati design uses this fraction of the room its decoupled
#: certificate leaves (`_couple`).
COUPLING_SHARE = 0.5


def _couple(Y, X0, Acl0, N3, q0, c, tau, steps):
    r"""Couple the decoupled generalized design in place: ``Y`` gets $J = \kappa\Pi$ and
    $Y_2 = \kappa\Pi^\top Y_1/\|Y_1\|$ (module docstring, *Coupled generalized design*);
    returns the certificate of the coupled loop and its spectral radius (disk coordinates).

    With the decoupled loop $\bar A_0$ (disk coordinates) and its Stein certificate $X_0$
    ($\bar A_0^\top X_0\bar A_0 = X_0 - I$), $\|\bar A_0\|_{X_0} = \sqrt{1 - 1/\lambda_{\max}(X_0)}$
    in the norm $\|M\|_{X_0} = \|X_0^{1/2}MX_0^{-1/2}\|_2$. The coupling changes the loop by
    $\kappa D$, $D = [[0, \Pi], [-\Pi^\top\hat Y_1N_3, 0]]/\tau$; with
    $\kappa = s\,(1 - \|\bar A_0\|_{X_0})/\|D\|_{X_0}$ (share $s$ = `COUPLING_SHARE`)
    the coupled loop has $X_0$-norm below 1, hence is Schur: its eigenvalues stay in the disk."""
    d, q1 = X0.shape[0], X0.shape[0] - q0
    Pi = np.eye(q0, q1)
    Y1 = Y[:q0, :c]
    nY1 = float(np.linalg.norm(Y1, 2)) if Y1.size else 0.0
    Y2 = Pi.T @ Y1 / nY1 if nY1 > 0 else np.zeros((q1, c))
    D = np.zeros((d, d))
    D[:q0, q0:] = Pi
    D[q0:, :q0] = -Y2 @ N3
    D /= tau
    try:
        Lc = np.linalg.cholesky(X0)  # X0 = Lc Lcᵀ: ‖M‖_X0 = ‖Lcᵀ M Lc⁻ᵀ‖
    except np.linalg.LinAlgError:  # no certificate of the decoupled loop: no room to couple
        Lc = None
    nD = 0.0 if Lc is None else float(np.linalg.norm(
        Lc.T @ scipy.linalg.solve_triangular(Lc, D.T, lower=True).T, 2))
    lam = float(np.linalg.eigvalsh(X0)[-1])
    room = 1.0 - math.sqrt(max(0.0, 1.0 - 1.0 / lam)) if lam > 1.0 else 0.0
    kappa = COUPLING_SHARE * room / nD if nD > 0 and np.isfinite(nD) else 0.0
    Y[:q0, c:] = kappa * Pi  # J
    Y[q0:, :c] = kappa * Y2
    Acl = Acl0 + kappa * D
    X = host_stein_certificate(Acl, notes=steps)
    rho = _spectral_radius(Acl)
    steps.append(f"coupled: J = {kappa:.3g}·Π, Y2 = {kappa:.3g}·Πᵀ Y1/‖Y1‖ (share {COUPLING_SHARE} of the "
                 f"certified room {room:.3g}); spectral radius {rho:.3g}")
    return X, rho


def epsilon_block_gain(N1, N2, N3, alpha: float, tau: float):
    """``(Z, Y1, closed loop)`` of the ε-block: the DARE gain ``[Z, Y1]`` of the output-injection
    pair ``(N1', [N2'; N3])`` in the coordinates of the disk ``Q(alpha, tau)`` (module
    docstring); the closed loop ``(N1' - Z N2' - Y1 N3 - αI)/τ`` is Schur."""
    q0, nZ = N1.shape[0], N2.shape[0]
    Ad = (N1 - alpha * np.eye(q0)) / tau
    Cd = np.vstack([N2, N3]) / tau
    K = output_injection_gain(Ad, Cd)
    return K[:, :nZ], K[:, nZ:], Ad - K @ Cd


def riccati_gains(s: FunctionalObserverStructure, region: AbstractRegion, *, kind: str):
    """Gains by the Riccati route for one rule (module docstring).

    **Returns:** ``(X, Z, [𝕐], info)`` like `fojax.design._functional.solve_gains`, where
    ``info["lmi"]`` holds ``method="riccati"``, the ``route`` line shown in the report,
    the ``disk`` used and the closed-loop ``spectral_radius`` in its coordinates.
    """
    pc = pieces(s, xp=np)
    N1 = np.asarray(pc.N1)[0]
    N2 = np.asarray(pc.N2)[0]
    N3 = np.asarray(pc.N3)
    q0, q1 = s.q0, (0 if kind == "proportional" else s.q1)
    c = N3.shape[0]
    d = q0 + q1
    fixed = _fixed_modes_eps(s) if not isinstance(region, Disk) else np.zeros(0)
    disk = region_disk(region, fixed)
    alpha, tau = disk.center, disk.radius * (1.0 - TIGHTEN)
    steps = []
    Z, Y1, Acl1 = epsilon_block_gain(N1, N2, N3, alpha, tau)
    rho = _spectral_radius(Acl1)
    steps.append(f"[Z, Y1] from the Riccati equation of (N1', [N2'; N3]): spectral radius {rho:.3g}")
    X1 = host_stein_certificate(Acl1, notes=steps)  # the one Stein certificate (disk coordinates)
    Y = np.zeros((d, c + q1))
    Y[:q0, :c] = Y1
    X = np.zeros((d, d))
    X[:q0, :q0] = X1
    if q1:
        # v-block: the 1×1 DARE of (a, b) = (-α/τ, -1/τ) (the data decouple, module docstring)
        a, b = -alpha / tau, -1.0 / tau
        g = output_injection_gain(np.array([[a]]), np.array([[b]]))[0, 0]
        acl = a - g * b
        Y[q0:, c:] = g * np.eye(q1)  # G = g I (the v-block of 𝔸 is G)
        X[q0:, q0:] = np.eye(q1) / (1.0 - acl * acl)  # 1×1 Stein: acl² x - x + 1 = 0
        rho = max(rho, abs(acl))
        steps.append(f"G = {g:.6g}·I from the 1×1 Riccati equation of the v-block")
        if kind == "generalized":
            Acl = np.zeros((d, d))
            Acl[:q0, :q0], Acl[q0:, q0:] = Acl1, acl * np.eye(q1)
            X, rho = _couple(Y, X, Acl, N3, q0, c, tau, steps)
        else:
            steps.append("J = 0, Y2 = 0 (S = 0)")
    route = (f"Riccati (DARE for the gain, Stein equation for the certificate) in "
             f"{disk.tightened(TIGHTEN).describe()}" + ("" if isinstance(region, Disk) else f" inside {region.describe()}"))
    info = {"lmi": {"route": route, "method": "riccati", "solver": "scipy.linalg.solve_discrete_are",
                    "disk": disk.to_dict(), "spectral_radius": rho, "steps": steps}}
    return X, Z, [Y], info
