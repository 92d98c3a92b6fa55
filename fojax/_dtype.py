"""float64 policy and array validation shared by every layer.

fojax never flips JAX's global configuration. Everything numerical needs 64-bit
floats (stiff descriptor systems, LMI verification to 1e-8), so a model refuses
to be built while ``jax_enable_x64`` is off, with a message that says how to turn
it on. Explicit float32/float16 inputs are refused too: fojax would otherwise hand
back a silently degraded answer.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np


X64_HINT = (
    "fojax computes in float64. Enable 64-bit JAX before creating fojax objects: "
    "`import jax; jax.config.update('jax_enable_x64', True)` (or set the environment "
    "variable JAX_ENABLE_X64=1)."
)


def x64_enabled() -> bool:
    return bool(jax.config.jax_enable_x64)


def require_x64(what: str = "this operation") -> None:
    """Raise `Float64RequiredError` unless 64-bit JAX is enabled."""
    from ._errors import Float64RequiredError

    if not x64_enabled():
        raise Float64RequiredError(f"{what} needs 64-bit floats, but jax_enable_x64 is off. {X64_HINT}")


def _is_tracer(x) -> bool:
    return isinstance(x, jax.core.Tracer)


#: Largest number of entries a `scipy.sparse` input is densified to (2^27 float64 = 1 GiB).
MAX_DENSIFIED_ENTRIES = 2**27


def _densify(name: str, x):
    """A `scipy.sparse` matrix or array as a dense NumPy array; anything else unchanged.

    fojax's algorithms (QZ, SVD rank decisions, LMIs, matrix exponentials) work on dense
    matrices, so a sparse input is densified here, once, at the boundary: memory is then
    ``8·rows·cols`` bytes, which is what the dense algorithms need anyway. Without this,
    ``np.asarray`` wraps a sparse matrix in a 0-d object array ("E has shape ()").
    A matrix whose dense form would exceed `MAX_DENSIFIED_ENTRIES` entries is refused.
    """
    if not (hasattr(x, "toarray") and hasattr(x, "nnz") and hasattr(x, "shape")):
        return x
    from ._errors import InputError

    shape = tuple(int(d) for d in x.shape)
    size = int(np.prod(shape)) if shape else 1
    if size > MAX_DENSIFIED_ENTRIES:
        raise InputError(
            f"{name} is a sparse {shape[0]}x{shape[1]} matrix ({x.nnz} stored entries); fojax "
            f"computes with dense matrices and would need {8 * size / 2**30:.1f} GiB for it "
            f"(limit {MAX_DENSIFIED_ENTRIES} entries = {8 * MAX_DENSIFIED_ENTRIES / 2**30:.0f} GiB). "
            "Reduce the model first (e.g. remove states that no output or function z = L x "
            "depends on) or pass a smaller matrix."
        )
    return np.asarray(x.toarray())


def as_float_array(name: str, x, ndim: int | None = None, *, check_finite: bool = True):
    """Convert `x` to a float64 JAX array, validating dtype, rank and finiteness.

    Tracers (inside jit/vmap/grad) are passed through after a dtype and rank check;
    finiteness of traced values cannot be checked at trace time.
    """
    from ._errors import Float64RequiredError, InputError, NonFiniteError, ShapeError

    if _is_tracer(x) or isinstance(x, jax.Array):
        dt = x.dtype
    else:
        x = np.asarray(_densify(name, x))
        dt = x.dtype
    if dt.kind == "c":
        # before the x64 check: complex data is wrong whatever the precision
        raise InputError(_complex_message(name, x, dt))
    require_x64(f"building {name}")
    if dt.kind == "f" and dt.itemsize < 8:
        raise Float64RequiredError(
            f"{name} has dtype {dt}; fojax refuses lower-precision inputs because results "
            f"would be silently inaccurate. Pass float64 data (e.g. np.asarray(M, dtype=float)). "
            f"{X64_HINT}"
        )
    if dt.kind not in "fiub":
        raise Float64RequiredError(f"{name} has non-numeric dtype {dt}; expected real numbers.")
    if ndim is not None and len(x.shape) != ndim:
        raise ShapeError(name, f"a {ndim}-d array", tuple(x.shape))
    if _is_tracer(x):
        return jnp.asarray(x, dtype=jnp.float64)
    arr = jnp.asarray(x, dtype=jnp.float64)
    if check_finite and not isinstance(arr, jax.core.Tracer):
        a = np.asarray(arr)
        bad = ~np.isfinite(a)
        if bad.any():
            idx = tuple(int(i) for i in np.argwhere(bad)[0])
            raise NonFiniteError(name, int(bad.sum()), idx)
    return arr


def _complex_message(name: str, x, dt) -> str:
    """What to do with complex data (descriptor matrices, signals and states are real)."""
    imag = ""
    if not _is_tracer(x):
        a = np.asarray(x)
        if a.size:
            imag = f", largest |imaginary part| {float(np.max(np.abs(a.imag))):.3g}"
    return (
        f"{name} is complex ({dt}{imag}); the matrices, signals and states of a descriptor "
        "system E x' = A x + B u, y = C x are real. If the imaginary parts are round-off, pass "
        f"np.real({name}); a system with complex coefficients must be written in real form "
        "(x = xr + i xi gives real matrices [[Re M, -Im M], [Im M, Re M]])."
    )


def as_matrix(name: str, x, rows: int | None = None, cols: int | None = None, hint: str = ""):
    """`as_float_array` for a 2-d matrix with optional expected shape.

    `scipy.sparse` matrices and arrays are accepted and densified (see `_densify`)."""
    from ._errors import ShapeError

    x = _densify(name, x)
    if not (_is_tracer(x) or isinstance(x, jax.Array | np.ndarray)):
        x = np.asarray(x, dtype=float) if np.asarray(x).dtype.kind in "iub" else np.asarray(x)
    if len(np.shape(x)) != 2:
        exp = f"({rows if rows is not None else 'rows'}, {cols if cols is not None else 'cols'})"
        raise ShapeError(name, f"a 2-d matrix {exp}", tuple(np.shape(x)), hint)
    r, c = np.shape(x)
    if (rows is not None and r != rows) or (cols is not None and c != cols):
        exp = (rows if rows is not None else r, cols if cols is not None else c)
        raise ShapeError(name, exp, (r, c), hint)
    return as_float_array(name, x, 2)


def to_numpy(x) -> np.ndarray:
    """Host float64 copy of an array (for SciPy/cvxpy work outside jit)."""
    return np.asarray(x, dtype=np.float64)
