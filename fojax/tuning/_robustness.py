r"""Built-in robustness terms of `fojax.tuning.tune` (``robustness=``): the H2 norm and a smooth
H∞ surrogate of the error system of the *current iterate's* observer.

**The error system** is the one the H∞/H2 designs bound (`fojax.design._hinf`, derived there):
$\dot e = \mathbb A e + \mathbb B d$, $\hat z - z = \mathbb C e + \mathbb D d$ with
$d = [w;\,\nu]$ (disturbance $w$ through $B_w$, measurement noise $\nu$ through $D_v$; the
uncertainty δ enters as a column block of $B_w$, `fojax.design.hinf_uncertainty_channel`).
The four matrices come from `fojax.design.observer_matrices` of the iterate's parameters by
the *same* function the design's verification uses (`error_system` with ``xp=jax.numpy``), so
the terms are traceable and differentiable with respect to every tuned parameter.

**`H2Term`** (exact). With the observability Gramian $L_o$,
$\mathbb A^\top L_o + L_o\mathbb A + \mathbb C^\top\mathbb C = 0$ (solved by the Kronecker
system $(I\otimes\mathbb A^\top + \mathbb A^\top\otimes I)\operatorname{vec}L_o =
-\operatorname{vec}\mathbb C^\top\mathbb C$, size $d^2$, $d = q_0 + q_1$ the observer order),

$$\text{value} = \text{weight}\cdot\big(\operatorname{tr}(\mathbb B^\top L_o\mathbb B)
  + \text{feedthrough\_weight}\cdot\|\mathbb D\|_F^2\big),$$

the first term being $\|C(sI - \mathbb A)^{-1}\mathbb B\|_2^2$ exactly. A feedthrough
$\mathbb D \ne 0$ makes the H2 norm infinite (white noise passes straight into $\hat z - z$); a
gradient method needs a finite value, so it is charged separately: for noise held constant over
$h$ seconds (`fojax.studies.output_noise`), $1/h$ weighs it like the strictly proper part
(its mean-square contribution per unit time is $\sigma^2\|\mathbb D\|^2$ against intensity
$\sigma^2 h$). The tuned design's reported ``h2_norm`` is ``inf`` whenever $\mathbb D$ is not
round-off, whatever this weight.

**`HinfTerm`** (a surrogate, *not* a bound). $\|T\|_\infty = \sup_\omega\sigma_{\max}(T(j\omega))$
is nonsmooth (the peak frequency and the top singular value jump). The term is the log-sum-exp
smooth maximum over a *fixed* frequency grid $\omega_1..\omega_K$:

$$\text{value} = \text{weight}\cdot\tau\log\sum_k \exp(\sigma_{\max}(T(j\omega_k))/\tau),
  \qquad \tau = \text{temperature}\cdot g_0,$$

($g_0$ the starting design's grid maximum, so `temperature` is relative.) It lies in
$[\max_k\sigma_k,\ \max_k\sigma_k + \tau\log K]$; $\max_k\sigma_k \le \|T\|_\infty$ and the gap
depends on the grid, so the surrogate is neither a lower nor an upper bound of the H∞ norm.
$\sigma_{\max}$ is differentiated as the largest eigenvalue of the real symmetric
$[\Re T\; -\Im T;\ \Im T\; \Re T]^\top[\dots]$ (its eigenvalues are those of $T^HT$, each
twice; the derivative exists where the top one is simple up to that pairing). The default grid:
0 and 200 log-spaced frequencies from $10^{-2}\min_i|\lambda_i|$ to $10^{2}\max_i|\lambda_i|$
($\lambda_i$ the starting error eigenvalues), plus the starting design's certified peak
frequency when it has one. What `tune` reports about the result is computed on the host after
the run, independently of the surrogate: ‖T‖∞ by SLICOT AB13DD and ‖T‖₂ by SciPy
(`fojax.design._hinf.error_norms`, the computations that verify every H∞/H2 design).

**Channels.** ``Bw``/``Dv`` ``None`` (default): taken from the starting design's
`HinfCertificate`/`H2Certificate` (an ``objective="hinf"``/``"h2"`` design); for other designs
they must be given.
"""

from __future__ import annotations

import abc

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._errors import InputError
from ..design import check_channels, error_dynamics, error_system, observer_matrices


def _channels(term, design):
    Bw, Dv = term.Bw, term.Dv
    cert = getattr(design, "hinf", None) or getattr(design, "h2", None)
    if Bw is None and Dv is None:
        if cert is None:
            raise InputError(
                f"{type(term).__name__}: the design has no H∞/H2 certificate to take the channels from; "
                f"pass them, e.g. {type(term).__name__}(Bw=..., Dv=...) ((n, mw) disturbance, (p, mv) noise), "
                "or start from an objective='hinf'/'h2' design.")
        # the certificate's channels are in the frame of the design's structure (a balance=True
        # H∞/H2 design holds the unit-free D_l B_w: fojax.design._functional.balanced_design)
        return tuple(np.asarray(x, dtype=float) for x in (cert.Bw, cert.Dv))
    s = design.structure
    Bw, Dv = check_channels(s.n, s.p, Bw, Dv, objective=type(term).__name__)
    balance = (getattr(design, "solver", None) or {}).get("balance")
    if balance is not None:
        # a balance=True design holds the unit-free structure (E_b = D_l E D_r, ...): the
        # channel's rows are the model's equations, so B_w,b = D_l B_w; y and z keep their
        # units (C_b x_b = C x), so D_v is unchanged (fojax.design._functional.balanced_design)
        Bw = np.asarray(balance["row_factors"], dtype=float)[:, None] * Bw
    return Bw, Dv


class AbstractRobustnessTerm(eqx.Module):
    """A differentiable term added to `tune`'s training loss, a function of the current
    iterate's error system (module docstring). `bind` fixes the channels (and any grid) from
    the starting design on the host; `__call__` is traceable."""

    weight: eqx.AbstractVar[jax.Array]
    Bw: eqx.AbstractVar[jax.Array | None]
    Dv: eqx.AbstractVar[jax.Array | None]

    @abc.abstractmethod
    def bind(self, design) -> AbstractRobustnessTerm:
        """The term with everything fixed from the starting `design` (host)."""

    @abc.abstractmethod
    def unweighted(self, A, B, C, D):
        """The term's value without `weight` on the error system (traceable)."""

    def __call__(self, structure, design_params):
        mats = observer_matrices(structure, **design_params)
        return self.weight * self.unweighted(*error_system(structure, mats, self.Bw, self.Dv, xp=jnp))

    def describe(self) -> str:
        return f"{type(self).__name__}(weight={float(self.weight):.6g})"


def _weight(weight, name):
    w = float(weight)
    if not (np.isfinite(w) and w >= 0):
        raise InputError(f"{name}(weight=...) must be a finite number ≥ 0; got {weight!r}.")
    return jnp.asarray(w)


def h2_squared(A, B, C):
    r"""$\operatorname{tr}(B^\top L_o B)$, $A^\top L_o + L_oA + C^\top C = 0$ (Kronecker solve;
    traceable, differentiable; `A` Hurwitz): $\|C(sI - A)^{-1}B\|_2^2$."""
    d = A.shape[0]
    eye = jnp.eye(d)
    K = jnp.kron(eye, A.T) + jnp.kron(A.T, eye)  # vec(Aᵀ L + L A) for column-major vec
    rhs = -(C.T @ C).reshape(-1, order="F")
    Lo = jnp.linalg.solve(K, rhs).reshape(d, d, order="F")
    return jnp.trace(B.T @ (0.5 * (Lo + Lo.T)) @ B)


class H2Term(AbstractRobustnessTerm):
    r"""``weight · (‖C(sI − 𝔸)⁻¹𝔹‖₂² + feedthrough_weight · ‖𝔻‖_F²)`` of the iterate's error
    system, exact (module docstring).

    **Arguments:** `weight` (≥ 0), `Bw`, `Dv` (default: the starting design's channels),
    `feedthrough_weight` (default 1.0; e.g. ``1/h`` for noise held ``h`` seconds).
    """

    weight: jax.Array
    Bw: jax.Array | None
    Dv: jax.Array | None
    feedthrough_weight: jax.Array

    def __init__(self, weight=1.0, *, Bw=None, Dv=None, feedthrough_weight=1.0):
        self.weight = _weight(weight, "H2Term")
        self.Bw = None if Bw is None else jnp.asarray(np.asarray(Bw, dtype=float))
        self.Dv = None if Dv is None else jnp.asarray(np.asarray(Dv, dtype=float))
        self.feedthrough_weight = _weight(feedthrough_weight, "H2Term(feedthrough_weight)")

    def bind(self, design) -> H2Term:
        Bw, Dv = _channels(self, design)
        return H2Term(float(self.weight), Bw=Bw, Dv=Dv, feedthrough_weight=float(self.feedthrough_weight))

    def unweighted(self, A, B, C, D):
        return h2_squared(A, B, C) + self.feedthrough_weight * jnp.sum(D * D)


def sigma_max(A, B, C, D, w):
    r"""$\sigma_{\max}(C(j\omega I - A)^{-1}B + D)$ in real arithmetic (traceable)."""
    d = A.shape[0]
    eye = jnp.eye(d)
    # (jωI − A)(Xr + jXi) = B  ⇔  [−A, −ωI; ωI, −A][Xr; Xi] = [B; 0]
    Mbig = jnp.block([[-A, -w * eye], [w * eye, -A]])
    X = jnp.linalg.solve(Mbig, jnp.concatenate([B, jnp.zeros_like(B)], axis=0))
    Gr, Gi = C @ X[:d] + D, C @ X[d:]
    R = jnp.block([[Gr, -Gi], [Gi, Gr]])
    return jnp.sqrt(jnp.maximum(jnp.linalg.eigvalsh(R.T @ R)[-1], 0.0))


class HinfTerm(AbstractRobustnessTerm):
    r"""``weight · τ log Σ_k exp(σ_max(T(jω_k))/τ)``: a smooth maximum of the error system's gain
    over a fixed frequency grid (module docstring). A surrogate, **not** a bound on ‖T‖∞.

    **Arguments:** `weight` (≥ 0), `Bw`, `Dv` (default: the starting design's channels),
    `frequencies` (rad/s; default: the grid of the module docstring), `temperature` (relative
    to the starting design's grid maximum; default 0.01; smaller is closer to the grid
    maximum and less smooth).
    """

    weight: jax.Array
    Bw: jax.Array | None
    Dv: jax.Array | None
    frequencies: jax.Array | None
    tau: jax.Array | None
    temperature: float = eqx.field(static=True)

    def __init__(self, weight=1.0, *, Bw=None, Dv=None, frequencies=None, temperature=0.01, tau=None):
        self.weight = _weight(weight, "HinfTerm")
        self.Bw = None if Bw is None else jnp.asarray(np.asarray(Bw, dtype=float))
        self.Dv = None if Dv is None else jnp.asarray(np.asarray(Dv, dtype=float))
        if frequencies is not None:
            f = np.asarray(frequencies, dtype=float).ravel()
            if f.size == 0 or not np.all(np.isfinite(f)) or np.any(f < 0):
                raise InputError(f"HinfTerm(frequencies=...) must be finite frequencies ≥ 0 (rad/s); got {f}.")
            frequencies = jnp.asarray(f)
        self.frequencies = frequencies
        t = float(temperature)
        if not (np.isfinite(t) and t > 0):
            raise InputError(f"HinfTerm(temperature=...) must be > 0; got {temperature!r}.")
        self.temperature = t
        self.tau = None if tau is None else jnp.asarray(float(tau))

    def bind(self, design) -> HinfTerm:
        Bw, Dv = _channels(self, design)
        freqs = self.frequencies
        if freqs is None:
            s = design.structure
            p = {k: np.asarray(v) for k, v in design.params.items()}
            A = np.asarray(error_dynamics(observer_matrices(s, **p, xp=np), xp=np))[0]
            mag = np.abs(np.linalg.eigvals(A))
            lo, hi = max(float(mag.min()), 1e-6) * 1e-2, max(float(mag.max()), 1e-6) * 1e2
            grid = [0.0, *np.logspace(np.log10(lo), np.log10(hi), 200)]
            cert = getattr(design, "hinf", None)
            if cert is not None and np.isfinite(cert.peak_frequency):
                grid.append(float(cert.peak_frequency))
            freqs = np.sort(np.asarray(grid))
        out = HinfTerm(float(self.weight), Bw=Bw, Dv=Dv, frequencies=freqs, temperature=self.temperature,
                       tau=1.0)
        mats = observer_matrices(design.structure, **{k: jnp.asarray(v) for k, v in design.params.items()})
        g0 = float(jnp.max(out.gains(*error_system(design.structure, mats, out.Bw, out.Dv, xp=jnp))))
        return HinfTerm(float(self.weight), Bw=Bw, Dv=Dv, frequencies=freqs, temperature=self.temperature,
                        tau=self.temperature * max(g0, 1e-300))

    def gains(self, A, B, C, D):
        """σ_max of the error system at every grid frequency (traceable)."""
        return jax.vmap(lambda w: sigma_max(A, B, C, D, w))(self.frequencies)

    def unweighted(self, A, B, C, D):
        return self.tau * jax.nn.logsumexp(self.gains(A, B, C, D) / self.tau)


def robustness_terms(robustness, design) -> tuple[tuple, tuple | None]:
    """``(terms, channels)``: `robustness` (``None``, a term or a sequence of terms) bound to the
    starting `design` (host), and the ``(Bw, Dv)`` the tuned design's norms are reported for
    (the first term's, else the design's H∞/H2 certificate's, else ``None``)."""
    terms = () if robustness is None else (
        tuple(robustness) if isinstance(robustness, (list, tuple)) else (robustness,))
    for term in terms:
        if not isinstance(term, AbstractRobustnessTerm):
            raise InputError(f"robustness must be a fojax.tuning.H2Term or HinfTerm (or a list of them); got "
                             f"{type(term).__name__}.")
    s = getattr(design, "structure", None)
    if s is None or s.num_rules != 1:
        if terms:
            raise InputError("robustness terms are for linear functional-observer designs (one rule); this "
                             f"design is a {type(design).__name__}. Use extra_loss for a term of your own.")
        return (), None
    terms = tuple(term.bind(design) for term in terms)
    if terms:
        return terms, (np.asarray(terms[0].Bw), np.asarray(terms[0].Dv))
    cert = getattr(design, "hinf", None) or getattr(design, "h2", None)
    return (), (None if cert is None else (np.asarray(cert.Bw), np.asarray(cert.Dv)))
