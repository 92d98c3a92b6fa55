r"""Tunable parameterizations: free parameters → valid observer → verified design.

One abstraction for every way fojax moves an observer's free parameters (gradient tuning,
derivative-free searches, user code). An `AbstractParameterization` is an equinox module
built from a verified design; its data (the structure, the certificate, the frozen ``Z``)
are leaves, its options (sizes, kind, which blocks are frozen) static. Its protocol:

- ``init(design) -> params``: the unconstrained parameters that reproduce `design`'s
  observer exactly (host);
- ``design_params(params)``: the free parameters ``Z, Y1, Y2, Y3, J, G`` of
  `fojax.design.observer_matrices` (traceable), so conditions a.–d. hold *by construction*
  for every value;
- ``observer(params)`` (traceable);
- ``margin(params)`` (traceable): ``> 0`` iff the parameters are admissible (eigenvalues
  certified in the region), and ``barrier(params)`` (traceable): a term that is finite
  inside and tends to $+\infty$ at the boundary;
- ``certify(params) -> design`` (host): the verified design of these parameters, checked in
  float64 by the one verification routine (`fojax.design.verify`: residuals of a.–d.,
  eigenvalues, the region LMI at the returned certificate); raises
  `fojax.errors.DesignVerificationError` with the numbers otherwise;
- ``live(params)``: how many free parameters can change the estimate $\hat z$ (below).

Final classes: `SteinDisk` (the parameters themselves, certified by the Stein solution of
the iterate; default for LTI designs), `FixedCertificateDisk` (the exact disk version of
the thesis's Lemma 10 $(\mathcal L, \gamma)$ map with the LMI certificate fixed,
`fojax.design.disk_gain`), `CommonCertificate` (Takagi–Sugeno: the design's common
certificate fixed, region LMI and Lyapunov inequality for every rule).

**Live parameters.** A direction of the free parameters is *live* iff it changes the
observer's input–output map $(u, y) \mapsto \hat z$ to first order, and *dead* otherwise.
*Why this map and not the error matrix* (derived): every fojax study starts the observer
at rest, so $\hat z = H * (u, y)$ with
$H(s) = C_o(sI - A_o)^{-1}[B_u\;B_y] + [D_u\;D_y]$
(`fojax.observer.GeneralizedFunctionalObserver.linear_matrices`, every rule of a T-S
observer) is all of $\hat z$, and the estimation error $\hat z - z = H * (u, y) - z$ is all
of what a loss can see. Conditions a.–d. make $H_u + H_yG_y = G_z$ ($G$ the plant's transfer
functions), so what $H$ adds to $z$ is exactly the error transient $P e^{\mathbb At}\varepsilon(0)$,
$\varepsilon(0) = -TEx_0$: the error dynamics *as seen from the output*. A change of the
error matrix $\mathbb A$ alone (a mode of $v$ that $\hat z$ never sees, or that $(u, y)$
never excites) is dead; a change of the residues or zeros with $\mathbb A$ fixed is live.
`live` measures it by the Jacobian of $H$ at $K = 2d + 2$ points
$s_k = i\rho\tan(\pi(k + \tfrac12)/2K)$ on the imaginary axis ($d$ the observer order,
$\rho$ the spectral radius of the error dynamics at the starting point): a rational matrix
of McMillan degree $\le d$ is fixed by that many values, so a direction with zero Jacobian
there leaves $H$ unchanged. *Units:* each entry $H_{ij}$ is weighted by $1/(r_ic_j)$ (the
norms of output $i$'s and input $j$'s responses at the point, `_channel_weights`), so the
decision does not change with the units of $u$, $y$, $\hat z$; the parameters are the
design's, which are unit-free for a ``balance=True`` design
(`fojax.design.design_functional_observer`), so the count is then the same for a model and
any diagonal rescaling of its states and equations (``tests/test_unit_invariance.py``:
on the LC filter and its 1e-3…1e3 twin, 1 of 20 for the proportional design at the default
order, 13 of 97 at $q_0 = 3$ and 7 of 97 for the centred $q_0 = 3$ design; with the raw
designs they were 1 vs 2 and 12 vs 11, the twin's order-1 one because its raw design was
not an observer of $z$). The
number of live directions is the rank of the weighted Jacobian, decided by fojax's one rank
rule (`fojax._linalg`, relative tolerance ``RANK_RTOL``). *Checked* against central
differences of the Markov parameters $D$, $C_oA_o^kB_o$ in NumPy (same rank, with a gap of
more than 1e4 in the singular values). One live direction can still change the estimate
a lot: in a proportional observer of order one it moves the observer's only pole $N$
together with $Q$, and with it the error's decay rate.
Example: when $[R;\Psi]$ has full row
rank, $N_3 = F_3 = 0$, so $Y_1, Y_2, Y_3$ enter no observer matrix and $S = M = 0$ leaves
$v$ unexcited, so $J, G$ do not reach $\hat z$ either: only ``Z`` can be live. The
analysis is local (at the starting point); the structural zeros of this example hold
everywhere. The same Jacobian, through its SVD $J = U\Sigma V^\top$, gives the *whitened*
coordinates $\theta = \theta_0 + V_r\Sigma_r^{-1}\xi$ used by `fojax.tuning.tune`: one
unit of every coordinate of $\xi$ moves the (weighted) response by one unit.

**Exactness at any size.** Conditions a.–d. hold by construction; their float64 residual
stays at rounding relative to the terms of each condition for every block $Z, Y_1, Y_2,
Y_3, J, G$ up to 1e12 and beyond, also along *dead* directions (components that cannot
change the observer): `fojax.design.observer_matrices` projects them out before they
enter a product (derivation in `fojax.design._parameterization`, *Exactness at any
size*; `fojax.design.project_parameters`). Certified designs store the parameters as
given (``design.params``); their observer is that of the projected parameters.
"""

from __future__ import annotations

import abc
import math
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import scipy.linalg

from .._errors import DesignVerificationError, InputError
from .._linalg import RANK_RTOL
from ._functional import build_observer, FunctionalObserverDesign, verify_structure_design
from ._parameterization import (
    error_dynamics,
    FunctionalObserverStructure,
    observer_matrices,
)
from ._regions import AbstractRegion, Disk
from ._stein import stein_certificate


class LiveParameters(NamedTuple):
    """How many free parameters can change the estimate (see `AbstractParameterization.live`).

    Attributes:
        live: the number of live directions (rank of the response Jacobian).
        total: the number of free (tuned) parameters.
        singular_values: the singular values of the response Jacobian (descending).
        basis: ``(total, live)`` orthonormal live directions $V_r$ in the flattened parameters.
        names: the parameter names in flattening order (sorted), with their shapes.
        response_norm: the norm of the response features at the point (their unit).
        kind: the observer kind (``"generalized"``, ...), for `void_generalized`.
    """

    live: int
    total: int
    singular_values: np.ndarray
    basis: np.ndarray
    names: tuple
    response_norm: float = 1.0
    kind: str = ""

    def live_mask(self) -> np.ndarray:
        """Per flattened parameter: ``True`` unless the parameter is dead by itself (its own
        direction has no component in the live basis, beyond rounding)."""
        if self.live == 0:
            return np.zeros(self.total, dtype=bool)
        return np.linalg.norm(self.basis, axis=1) > 1e3 * np.finfo(float).eps

    def live_blocks(self) -> tuple[str, ...]:
        """The parameter blocks (``Z``, ``Y1``, ...) with at least one coordinate that is not dead
        by itself (`live_mask`), in `names` order."""
        mask, out, i = self.live_mask(), [], 0
        for k, shape in self.names:
            size = math.prod(shape)
            if size and mask[i:i + size].any():
                out.append(k)
            i += size
        return tuple(out)

    @property
    def void_generalized(self) -> bool:
        r"""A ``"generalized"`` observer whose extra freedom cannot reach $\hat z$: no block but
        ``Z`` is live (e.g. $[R;\Psi]$ of full row rank: $N_3 = F_3 = 0$, module docstring), so it
        acts as a proportional observer of the same order."""
        return self.kind == "generalized" and set(self.live_blocks()) <= {"Z"}

    def __str__(self) -> str:
        live = self.live_blocks()
        dead = [k for k, shape in self.names if math.prod(shape) and k not in live]
        out = f"{self.live} of {self.total} free parameters are live (reach the estimate ẑ)"
        if self.names:
            out += f"; blocks that reach it: {', '.join(live) or 'none'}"
            out += f"; blocks that cannot: {', '.join(dead)}" if dead else ""
        if self.void_generalized:
            out += (". The generalized structure is void here: only Z reaches ẑ, so this observer acts as a "
                    "proportional one of the same order (choose another R or a larger q0 for a generalized "
                    "observer with its own freedom)")
        return out


def _check_kind(design, who: str):
    if design.kind not in ("generalized", "proportional"):
        raise InputError(
            f"{who} supports generalized and proportional designs; got kind={design.kind!r} (the PI "
            "constraint S = -Y2 N3 = 0 is not preserved when Y2 moves)."
        )


def _rule_matrices(obs) -> tuple:
    """``(A, [B_u B_y], C, [D_u D_y])`` of every rule of `obs` (one for an LTI observer)."""
    rules = [obs.rule(i) for i in range(obs.num_rules)] if hasattr(obs, "num_rules") else [obs]
    out = []
    for o in rules:
        lm = o.linear_matrices()
        out.append((lm[0], jnp.concatenate([lm[1], lm[2]], axis=1), lm[3], jnp.concatenate([lm[4], lm[5]], axis=1)))
    return tuple(out)


def _response_and_jacobian(mats, jac, rho: float, K: int):
    r"""Real and imaginary parts of the frequency response of every rule at ``K`` points, and
    their Jacobian (host, complex128).

    `mats`: `_rule_matrices` at the point; `jac`: their Jacobians (last axis the parameters).
    At $s = i\omega$ with $X = (sI - A)^{-1}B$, $H = CX + D$ and, by $d(sI - A)^{-1} =
    (sI - A)^{-1}\,dA\,(sI - A)^{-1}$,

    $$dH = dC\,X + C\,(sI - A)^{-1}(dA\,X + dB) + dD,$$

    one factorisation per point for the response and every parameter direction (host, no
    compilation per observer structure). Returns ``f`` ``(rules·K·2, q, m + p)`` and ``J`` ``(…, parameters)``.
    """
    omegas = rho * np.tan(np.pi * (np.arange(K) + 0.5) / (2 * K))
    fs, js = [], []
    for (A, B, C, D), (dA, dB, dC, dD) in zip(mats, jac):
        A, B, C, D = (np.asarray(x) for x in (A, B, C, D))
        dA, dB, dC, dD = (np.moveaxis(np.asarray(x), -1, 0) for x in (dA, dB, dC, dD))  # parameters first
        eye = np.eye(A.shape[0])
        for w in omegas:
            M = 1j * w * eye - A
            X = np.linalg.solve(M, B)
            dX = np.linalg.solve(M[None], dA @ X[None] + dB)
            H, dH = C @ X + D, dC @ X[None] + C[None] @ dX + dD
            fs.append(np.stack([H.real, H.imag]))
            js.append(np.moveaxis(np.stack([dH.real, dH.imag]), 1, -1))
    return np.concatenate(fs), np.concatenate(js)


def _design_blocks(design, tune_Z: bool) -> dict:
    """The design's nonempty parameter blocks ``Z, Y1, Y2, Y3, J, G`` as arrays (``Z`` only
    with `tune_Z`): the parameters of `SteinDisk` and `CommonCertificate`."""
    p = {k: jnp.asarray(np.asarray(v)) for k, v in design.params.items()}
    return {k: v for k, v in p.items() if v.size and (tune_Z or k != "Z")}


class AbstractParameterization(eqx.Module):
    """The protocol of a tunable parameterization (module docstring)."""

    structure: eqx.AbstractVar[FunctionalObserverStructure]
    region: eqx.AbstractVar[AbstractRegion]
    kind: eqx.AbstractVar[str]

    @abc.abstractmethod
    def init(self, design) -> dict:
        """The parameters reproducing `design`'s observer (host)."""

    @abc.abstractmethod
    def design_params(self, params) -> dict:
        """The free parameters ``Z, Y1, Y2, Y3, J, G`` (traceable)."""

    @abc.abstractmethod
    def margin(self, params):
        """``> 0`` iff `params` are admissible (traceable)."""

    @abc.abstractmethod
    def certificate(self, params) -> np.ndarray:
        """The float64 certificate of `params` (host)."""

    def barrier(self, params):
        """Finite inside, $+\\infty$ at the boundary (traceable); 0 when the map needs none."""
        return jnp.zeros(())

    def matrices(self, params):
        """The observer matrices (`fojax.design.ObserverMatrices`) of `params` (traceable)."""
        return observer_matrices(self.structure, **self.design_params(params))

    def host_matrices(self, params):
        """`matrices` evaluated on the host by NumPy (float64; only `design_params` runs in JAX):
        no compilation, and no dispatch of the map's ~100 primitives one by one."""
        return observer_matrices(self.structure, **{k: np.asarray(v) for k, v in self.design_params(params).items()},
                                 xp=np)

    def observer(self, params):
        """The observer of `params` (traceable)."""
        return self._observer_of(self.matrices(params))

    def host_observer(self, params):
        """The observer of `params` from `host_matrices` (host): equal to `observer` to rounding."""
        return self._observer_of(self.host_matrices(params))

    def host_error_matrices(self, params) -> np.ndarray:
        r"""The error dynamics $\mathbb A_i$ of every rule, ``(rules, s, s)`` (host, NumPy)."""
        return np.asarray(error_dynamics(self.host_matrices(params), xp=np))

    def _observer_of(self, mats):
        return build_observer(self.structure, mats, kind=self.kind)

    def _design(self, p, mats, X, report):
        return FunctionalObserverDesign.from_matrices(
            self.structure, mats, p, observer=self._observer_of(mats), kind=self.kind, region=self.region, X=X,
            report=report, solver={"parameterization": type(self).__name__})

    def certify(self, params):
        """The verified design of `params` (host, float64): the checks of the design's own
        ``verify()``, including a.–d. in the unit-free frame (models with ``l + n ≤ 200``;
        `fojax.design._functional.unit_free_check`).

        **Raises:** `fojax.errors.DesignVerificationError` (with the report) when a residual of
        a.–d. exceeds 1e-8 relative (on the data as given or in the unit-free frame), an
        eigenvalue is outside the region, or the region LMI fails at the certificate.
        """
        p = {k: np.asarray(v, dtype=float) for k, v in self.design_params(params).items()}
        X = self.certificate(params)
        if not np.all(np.isfinite(X)):
            # no certificate: the one verification routine without one names the eigenvalue
            # outside the region and by how much (it raises here)
            report = verify_structure_design(self.structure, p, self.region, None)[1]
            raise DesignVerificationError(
                f"{type(self).__name__}.certify: no finite certificate for these parameters although their "
                f"error dynamics are inside {self.region.describe()} (margin {report.region_margin:.3e}); "
                "please report this.", report)
        mats, report = verify_structure_design(self.structure, p, self.region, X, unit_free=CERTIFY_UNIT_FREE_FIX)
        return self._design(p, mats, X, report)

    def host_margin(self, params) -> float:
        """``float(margin(params))``, computed by one compiled program per parameterization
        structure (host), rather than dispatching every primitive of the margin separately
        (and compiling each the first time) as an eager call would."""
        return float(_margin(self, params))

    def host_check(self, params, margin: float | None = None) -> tuple[bool, float, float]:
        """``(verified, margin, max real eigenvalue)``: `certify` succeeds and the traced margin is
        positive (host; used to accept every tuning iterate). `margin`: ``host_margin(params)``
        when the caller has it (the step rule computed it for the candidate)."""
        margin = self.host_margin(params) if margin is None else float(margin)
        maxre = float(max(np.max(np.linalg.eigvals(A).real) for A in self.host_error_matrices(params)))
        if not margin > 0:
            return False, margin, maxre
        try:
            self.certify(params)
        except (DesignVerificationError, np.linalg.LinAlgError, scipy.linalg.LinAlgError):
            return False, margin, maxre
        return True, margin, maxre

    def live(self, params) -> LiveParameters:
        """How many directions of `params` reach the estimate (module docstring; host)."""
        return _live(self.observer, params, self.kind, error_matrices=self.host_error_matrices(params))


#: What a failed unit-free check of `AbstractParameterization.certify` tells the user.
CERTIFY_UNIT_FREE_FIX = ("start from a design made with balance=True (its parameters are those of the unit-free "
                         "model, fojax.analysis.unit_scaling)")


#: Traces of the host margin programs (`AbstractParameterization.host_margin`).
MARGIN_TRACES: dict = {"margin": 0}


@eqx.filter_jit
def _margin(par, params):
    MARGIN_TRACES["margin"] += 1
    return par.margin(params)


@eqx.filter_jit
def _stein_margin_jit(structure, region, Z, params):
    MARGIN_TRACES["margin"] += 1
    return _stein_margin(structure, region, Z, params)


def _stein_P(structure, region, Z, params):
    """The traced Stein certificate of `SteinDisk` from its fields (so that `SteinDisk.__init__`
    can compile it before the module exists, sharing the program with `host_margin`)."""
    mats = observer_matrices(structure, **_full(structure, params, Z))
    return stein_certificate(error_dynamics(mats)[0], region.center, region.radius)


def _stein_margin(structure, region, Z, params):
    ev = jnp.linalg.eigvalsh(_stein_P(structure, region, Z, params))
    inside = jnp.all(jnp.isfinite(ev)) & (ev[0] > 0)
    return jnp.where(inside, 1.0 / jnp.where(inside, ev[-1], 1.0), -1.0)


@eqx.filter_jit
def _matrices_and_jacobian(observer_fn, names, flat):
    """`_rule_matrices` of ``observer_fn(params)`` at `flat` and their forward-mode Jacobian."""
    def mats(f):
        return _rule_matrices(observer_fn(unflatten(names, f)))

    return mats(flat), jax.jacfwd(mats)(flat)


def _channel_weights(f0: np.ndarray) -> np.ndarray:
    r"""Weights $1/(r_ic_j)$ of the response entries $H_{ij}$ (``f0``: ``(points, q, m + p)``):
    $r_i$ the norm of output $i$'s response over every point and input, then $c_j$ the norm
    of input $j$'s column after that row scaling. The weighted response is the same for
    $u$, $y$, $\hat z$ in any diagonal units ($H \to D_zHD_{uy}^{-1}$), so the rank decision
    (`fojax._linalg`'s relative rule) and the whitened coordinates are too. A channel whose
    response is zero at the point keeps weight 1 (scaled as the largest other one)."""
    def inv(norms):
        ok = norms > 0
        ref = float(np.max(norms)) if np.any(ok) else 1.0
        return np.where(ok, 1.0 / np.where(ok, norms, 1.0), 1.0 / ref)

    r = inv(np.linalg.norm(f0, axis=(0, 2)))
    c = inv(np.linalg.norm(f0 * r[None, :, None], axis=(0, 1)))
    return np.broadcast_to(r[None, :, None] * c[None, None, :], f0.shape)


def _live(observer_fn, params, kind: str, error_matrices) -> LiveParameters:
    # the observer's matrices and their Jacobian are compiled (built op by op, the observer
    # compiles ~100 primitives, slow to compile); a parameterization's bound `observer` is a
    # pytree, so a second call with the same shapes reuses the program
    names = tuple(sorted((k, tuple(np.shape(v))) for k, v in params.items()))
    flat0 = jnp.concatenate([jnp.ravel(jnp.asarray(params[k])) for k, _ in names]) if names else jnp.zeros(0)
    As = np.asarray(error_matrices)  # the observer's error dynamics at `params` (they set the frequencies)
    rho = max(float(np.max(np.abs(np.linalg.eigvals(As)))), 1e-300) if As.size else 1.0
    K = 2 * As.shape[-1] + 2
    if flat0.size == 0:
        return LiveParameters(0, 0, np.zeros(0), np.zeros((0, 0)), names, 0.0, kind)
    mats, jac = _matrices_and_jacobian(observer_fn, names, flat0)  # compiled; the response on the host
    f0, Jm = _response_and_jacobian(mats, jac, rho, K)
    w = _channel_weights(f0)
    Jm = (w[..., None] * Jm).reshape(-1, Jm.shape[-1])  # (features, parameters), channels weighted
    fnorm = float(np.linalg.norm(w * f0))
    _, sv, Vt = np.linalg.svd(Jm, full_matrices=False)
    r = int(np.sum(sv > RANK_RTOL * sv[0])) if sv.size and sv[0] > 0 else 0
    return LiveParameters(r, int(flat0.size), sv, Vt[:r].T, names, fnorm, kind)


def live_parameters(design) -> LiveParameters:
    r"""How many free parameters ``Z, Y1, Y2, Y3, J, G`` of `design` can reach the estimate
    $\hat z$ (module docstring), for any `FunctionalObserverDesign` or
    `TakagiSugenoObserverDesign` (host). A "generalized" design whose extra freedom is
    structurally void shows it here: e.g. when $[R;\Psi]$ has full row rank only ``Z`` is live.
    """
    from ..observer import TakagiSugenoObserver
    from ._takagi_sugeno import TakagiSugenoObserverDesign

    s = design.structure
    ts = isinstance(design, TakagiSugenoObserverDesign)
    if not (ts or isinstance(design, FunctionalObserverDesign)):
        raise InputError(f"live_parameters needs a FunctionalObserverDesign or TakagiSugenoObserverDesign, got "
                         f"{type(design).__name__}.")
    Z = jnp.asarray(np.asarray(design.params["Z"]))
    params = {k: jnp.asarray(np.asarray(v)) for k, v in design.params.items() if np.size(v)}
    o = design.observer

    def observer(p):
        m = observer_matrices(s, **_full(s, p, Z, rules=s.num_rules if ts else None))
        if ts:
            return TakagiSugenoObserver(m.N, m.J, m.F, m.H, m.S, m.G, m.M, m.P, m.Q, o.Wu, o.Wy, m.T, o.membership,
                                        kind=design.kind)
        return build_observer(s, m, kind=design.kind)

    As = o.error_matrices if ts else o.error_matrix  # the design's own: nothing to compile
    return _live(observer, params, design.kind, As)


def unflatten(names: tuple, flat) -> dict:
    """The parameter dict of a flat vector (`LiveParameters.names` order; traceable)."""
    out, i = {}, 0
    for k, shape in names:
        size = math.prod(shape)
        out[k] = jnp.reshape(flat[i:i + size], shape)
        i += size
    return out


def _full(structure, params, Z, rules: int | None = None) -> dict:
    """All six free parameters: the tuned ones, the frozen ``Z`` and empty blocks."""
    out = {}
    for name, shape in structure.param_shapes().items():
        if name in params:
            out[name] = params[name]
        elif name == "Z":
            out[name] = Z
        else:
            out[name] = jnp.zeros(shape if rules is None else (rules,) + shape)
    return out


def _lti_design(design, who):
    if not isinstance(design, FunctionalObserverDesign):
        raise InputError(f"{who} needs a FunctionalObserverDesign (fojax.design.design_functional_observer), got "
                         f"{type(design).__name__}; for Takagi–Sugeno designs use CommonCertificate.")
    _check_kind(design, who)
    if design.structure.num_rules != 1:
        raise InputError(f"{who} supports single-rule (LTI) structures only.")


def _disk(design, region, who) -> Disk:
    region = design.region if region is None else region
    if not isinstance(region, Disk):
        raise InputError(
            f"{who} parameterizes disk regions only; got {region.describe()}. Design the observer "
            "with region=fojax.Disk(center, radius)."
        )
    return region


def certify(parameterization: AbstractParameterization, params):
    """The verified design of `params` under `parameterization` (host, float64): the one
    public call that turns tuned (or hand-set) parameters into a design.

    Equivalent to ``parameterization.certify(params)``: the residuals of a.–d. (≤ 1e-8
    relative to the terms of each condition; for LTI models with ``l + n ≤ 200`` also in the
    unit-free frame of `fojax.analysis.unit_scaling`, as the design's ``verify()`` does), the eigenvalues of the error dynamics in the
    region and the region LMI at the certificate (`SteinDisk`: the Stein solution of these
    parameters; `FixedCertificateDisk`, `CommonCertificate`: the design's fixed ``X``, plus
    the common Lyapunov inequality for T-S) are checked by `fojax.design.verify`. Parameters
    of any size are accepted: dead components are projected out
    (`fojax.design.project_parameters`); ``design.params`` keeps them as given.

    **Arguments:**

    - `parameterization`: an `AbstractParameterization` (`SteinDisk(design)`,
      `FixedCertificateDisk(design)`, `CommonCertificate(ts_design)`, or
      ``fojax.tuning.make_parameterization(design)``).
    - `params`: a dict of its parameters, e.g. ``parameterization.init(design)``, or those
      of a tuning run: ``certify(result.parameterization, result.params)`` for
      ``result = fojax.tuning.tune(...)`` rebuilds ``result.design``.

    **Returns:** a `FunctionalObserverDesign` (`TakagiSugenoObserverDesign` for
    `CommonCertificate`) whose ``report`` holds the numbers; ``design.verify()`` re-runs the
    check and ``design.save(path)`` stores it.

    **Raises:** `fojax.errors.DesignVerificationError` with the failed checks and their numbers
    (e.g. ``"eigenvalue 5 is outside the region (disk centred at -2 with radius 1) by
    6.000e+00"``, ``"region LMI re-checked in float64 has max eigenvalue ..."``) and the
    `VerificationReport` as ``err.report``; `fojax.errors.InputError` if `parameterization` is not
    an `AbstractParameterization`.

    !!! example

        ```python
        from fojax.design import certify, design_functional_observer, Disk, SteinDisk

        design = design_functional_observer(plant, L, kind="generalized", q1=1, region=Disk(-2.0, 1.0))
        par = SteinDisk(design)
        params = par.init(design)
        params["G"] = params["G"] - 0.5      # any change: conditions a.–d. hold by construction
        verified = certify(par, params)      # raises DesignVerificationError outside Disk(-2, 1)
        print(verified.report.relative_residual, verified.report.region_margin)
        ```
    """
    if not isinstance(parameterization, AbstractParameterization):
        raise InputError(f"certify needs an AbstractParameterization (e.g. fojax.design.SteinDisk(design)), got "
                         f"{type(parameterization).__name__}.")
    return parameterization.certify(params)
