r"""Structural analysis of descriptor systems $E\dot x = Ax + Bu$, $y = Cx$ (thesis §2.1.2): regularity,
index, stability, observability, Kronecker structure, zeros, balancing and the index-1 split.

**Host-only functions** (NumPy/SciPy: SVD rank decisions, QZ; cvxpy/SCS for the LMI
certificate) must be called outside `jax.jit`/`jax.vmap`: `e_perp`, `is_regular`,
`finite_poles`, `nilpotency_index`, `is_impulse_free`, `is_stable`, `is_admissible`,
`weierstrass_form`, `admissibility_certificate`, the observability/controllability
predicates, `is_functionally_observable`, `balance_system`, `kronecker_structure`,
`system_zeros`, `properness`, `mode_counts` and `structure_report`.

**JAX-traceable screens** (raw matrices, continuous margins, for vmapping over many
uncertain samples): `impulse_free_margin`, `slow_matrix_index1`,
`stability_margin_index1`, `functional_observability_gap`, `regularity_margin_at`,
`regular_at`.

**Units do not matter: balancing first.** Every host function first balances the
system by an exact power-of-two diagonal scaling of equations and states,
``(D_l E D_r, D_l A D_r, D_l B, C D_r)`` (Ward's least-squares balancing, or SLICOT
``TB01ID`` when ``E = I``, with powers of two so that no rounding is added; see
`balance_system`). It changes no rank, eigenvalue, index or zero; ``balance=False``
turns it off, and `structure_report` shows the scaling applied. `unit_scaling` gives
the same balancing with unrounded factors (exactly unit-free, but not exact in floating
point): for *choices* that must not depend on units (the default ``R`` and
``design_functional_observer(balance=True)``), never for rank decisions.

**The rank-decision rule (one rule, everywhere).** After balancing, the blocks ``E``,
``A``, ``B``, ``C`` (and ``L``) are each divided by their spectral norm; a singular
value ``s`` of a matrix built from these normalised blocks counts as non-zero when
``s > max(RANK_RTOL * s_max, RANK_ATOL)`` with ``RANK_RTOL = 1e-10``,
``RANK_ATOL = 1e-12`` (`fojax._linalg`), where ``s_max`` is that matrix's largest
singular value; the deflation of `is_regular` compares with ``max(RANK_RTOL,
RANK_ATOL)`` since its blocks have norm 1. SLICOT ``AG08BD`` (`kronecker_structure`,
`system_zeros`, `mode_counts`) gets the same data and ``tol = RANK_RTOL`` (its rank is
the largest leading triangular factor with estimated condition below ``1/RANK_RTOL``).
Each host function accepts ``tol=`` (an absolute threshold on the normalised matrices)
to override it. The design layer calls these same functions (`is_regular`'s deflation,
`functional_rank_pair`), so analysis and design give the same verdict on the same data.
Stability uses a separate imaginary-axis tolerance ``AXIS_TOL = 1e-9`` (see
`is_stable`).

**The index-1 split of (E, A) lives here.** `index1_split` (host: the SVD coordinates of
``E`` split at analysis's rank, with `is_regular`/`nilpotency_index`'s verdict) is what
control (`reduce_host`, state feedback) and simulation (`check_index1_host`) call;
`fojax.analysis._traced.svd_split` is its traceable twin for code under ``jit``.

**Kronecker structure and zeros** (reference-software analysis, SLICOT ``AG08BD``):
`kronecker_structure` (square or non-square pencils: normal rank, minimal indices,
infinite elementary divisors, finite eigenvalues), `system_zeros` (invariant zeros of
``(E, A, B, C, D)``), `properness`, `mode_counts`.

**Singular pencils.** `is_regular`, `is_admissible` (answers ``False``),
`is_functionally_observable`, `e_perp` and `structure_report` accept them; every
other host function raises `fojax.errors.IrregularSystemError` with an explanation.
"""

from ._balance import (
    balance_system as balance_system,
    Balancing as Balancing,
    Scaling as Scaling,
    unit_scaling as unit_scaling,
)
from ._certificate import (
    admissibility_certificate as admissibility_certificate,
    AdmissibilityCertificate as AdmissibilityCertificate,
)
from ._discrete import is_causal as is_causal
from ._kronecker import (
    kronecker_structure as kronecker_structure,
    KroneckerStructure as KroneckerStructure,
    mode_counts as mode_counts,
    ModeCounts as ModeCounts,
    Properness as Properness,
    properness as properness,
    system_zeros as system_zeros,
    SystemZeros as SystemZeros,
)
from ._observability import (
    is_c_controllable as is_c_controllable,
    is_c_observable as is_c_observable,
    is_detectable as is_detectable,
    is_functionally_observable as is_functionally_observable,
    is_i_controllable as is_i_controllable,
    is_i_observable as is_i_observable,
    is_r_controllable as is_r_controllable,
    is_r_observable as is_r_observable,
    is_s_controllable as is_s_controllable,
    is_s_observable as is_s_observable,
    is_stabilizable as is_stabilizable,
)
from ._pencil import (
    algebraic_channel as algebraic_channel,
    AXIS_TOL as AXIS_TOL,
    e_perp as e_perp,
    finite_poles as finite_poles,
    is_admissible as is_admissible,
    is_impulse_free as is_impulse_free,
    is_regular as is_regular,
    is_stable as is_stable,
    nilpotency_index as nilpotency_index,
)
from ._report import structure_report as structure_report, StructureReport as StructureReport
from ._split import index1_split as index1_split, Index1Split as Index1Split
from ._traced import (
    functional_observability_gap as functional_observability_gap,
    impulse_free_margin as impulse_free_margin,
    regular_at as regular_at,
    regularity_margin_at as regularity_margin_at,
    slow_matrix_index1 as slow_matrix_index1,
    stability_margin_index1 as stability_margin_index1,
)
from ._weierstrass import weierstrass_form as weierstrass_form, WeierstrassForm as WeierstrassForm
