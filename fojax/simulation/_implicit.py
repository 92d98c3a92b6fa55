r"""The default implicit solver of `simulate`: Kvaerno5 whose Newton step avoids two library bugs.

`diffrax.Kvaerno5` solves its stage equations with `diffrax.VeryChord`, whose Newton
step is a `lineax.linear_solve` with `lineax.AutoLinearSolver` (an LU solve). Two
problems of that linear solve in fojax's batched studies (jax/jaxlib 0.10.2,
lineax 0.1.1):

1. **Inside `jax.shard_map`** (every `fojax.studies.run_study` chunk runs in one) it
   fails while tracing with ``ValueError: pytree does not match out_structure``.
   Inside the shard map the `jax.ShapeDtypeStruct`\ s of the Jacobian operator carry
   the mesh's sharding (``NamedSharding(AbstractMesh('batch', Manual), P(None))``);
   lineax stores them with the LU factors, but its primitive's abstract evaluation
   rebuilds the right-hand side's structure from a bare ``ShapedArray`` (shape and
   dtype only), and ``lineax.LU.compute`` compares the two including the sharding.
   Same shapes, same dtypes, "different" structures. It does not depend on the plant
   (any diffrax-path study fails; a `FaultyPlant` is simply never LTI, so its studies
   always take the diffrax path) and is reproduced by ``jax.shard_map(jax.vmap(f))``
   of a scalar Kvaerno5 solve. Known upstream: lineax bug report 185 ("Issue with
   shard_map", open).
2. **Under `jax.vmap`** the LU factorisation is a batched LAPACK ``getrf`` call, which
   can deadlock jaxlib 0.10.2's CPU thread pool (see `fojax._small_linalg`).

`SmallLU` replaces that linear solver: LU with partial pivoting written in plain XLA
operations (fixed-length `lax.fori_loop`\ s over the rows, so the traced program does
not grow with the matrix size), and it compares only the shapes and dtypes of the
right-hand side, never the sharding. The factorisation is done
once per Jacobian (`init`) and reused by every Newton iteration (`compute`).
`default_implicit_solver` is what `simulate` uses when no `solver` is given.
"""

from __future__ import annotations

import math
from typing import Any

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
from jax import lax

from .._errors import ShapeError


def lu_factor_small(A):
    r"""LU factorisation with partial pivoting, $PA = LU$, in plain XLA operations.

    **Arguments:** `A` ``(n, n)``.

    **Returns:** ``(LU, perm)``: ``LU`` holds the unit-lower factor below the diagonal
    and ``U`` on and above it; ``perm`` ``(n,)`` is the row permutation
    (``A[perm] = L U``).
    """
    n = A.shape[0]
    rows = jnp.arange(n)

    def step(i, carry):
        M, perm = carry
        p = jnp.argmax(jnp.where(rows >= i, jnp.abs(M[:, i]), -1.0))
        ri, rp = M[i], M[p]
        M = M.at[i].set(rp).at[p].set(ri)
        qi, qp = perm[i], perm[p]
        perm = perm.at[i].set(qp).at[p].set(qi)
        factors = jnp.where(rows > i, M[:, i] / M[i, i], 0.0)
        upper = jnp.where(rows > i, M[i], 0.0)  # update only the trailing block
        M = M - factors[:, None] * upper[None, :]
        M = M.at[:, i].set(jnp.where(rows > i, factors, M[:, i]))
        return M, perm

    # A fixed-length fori_loop (a scan): trace size independent of n, vmaps without a
    # batched predicate.
    return lax.fori_loop(0, n, step, (A, rows))


def lu_solve_small(LU, perm, b, transpose: bool = False):
    r"""Solve $Ax = b$ (or $A^\top x = b$) from `lu_factor_small`'s ``(LU, perm)``.

    Forward and back substitution in fixed-length loops (no LAPACK/BLAS custom call).
    """
    n = LU.shape[0]
    rows = jnp.arange(n)

    def lower(i, w):  # unit lower triangular L w = rhs, row i
        return w.at[i].add(-(LU[i] @ jnp.where(rows < i, w, 0.0)))

    def upper(k, w):  # U w = rhs, row i = n - 1 - k
        i = n - 1 - k
        return w.at[i].set((w[i] - LU[i] @ jnp.where(rows > i, w, 0.0)) / LU[i, i])

    def upper_t(i, v):  # Uᵀ v = rhs (lower triangular), row i
        return v.at[i].set((v[i] - LU[:, i] @ jnp.where(rows < i, v, 0.0)) / LU[i, i])

    def lower_t(k, v):  # Lᵀ v = rhs (unit upper triangular), row i = n - 1 - k
        i = n - 1 - k
        return v.at[i].add(-(LU[:, i] @ jnp.where(rows > i, v, 0.0)))

    if not transpose:  # L U x = b[perm]
        w = lax.fori_loop(0, n, lower, b[perm])
        return lax.fori_loop(0, n, upper, w)
    # Aᵀ = Uᵀ Lᵀ P: Uᵀ v = b, Lᵀ w = v, x = Pᵀ w.
    v = lax.fori_loop(0, n, upper_t, b)
    v = lax.fori_loop(0, n, lower_t, v)
    return jnp.zeros_like(v).at[perm].set(v)


class _Layout(eqx.Module):
    """Shapes and dtypes of a pytree of arrays (no sharding): static, hashable."""

    treedef: Any = eqx.field(static=True)
    shapes: tuple = eqx.field(static=True)
    dtypes: tuple = eqx.field(static=True)

    @classmethod
    def of(cls, structure) -> _Layout:
        leaves, treedef = jax.tree.flatten(structure)
        return cls(treedef, tuple(tuple(x.shape) for x in leaves), tuple(jnp.dtype(x.dtype) for x in leaves))

    def ravel(self, tree):
        leaves, treedef = jax.tree.flatten(tree)
        shapes = tuple(tuple(x.shape) for x in leaves)
        if treedef != self.treedef or shapes != self.shapes:
            raise ShapeError(
                "right-hand side of the Newton step",
                f"a pytree {self.treedef} with leaf shapes {self.shapes}",
                f"{treedef} with leaf shapes {shapes}",
            )
        dtype = jnp.result_type(*leaves)
        return jnp.concatenate([x.astype(dtype).reshape(-1) for x in leaves])

    def unravel(self, flat):
        out, k = [], 0
        for shape, dtype in zip(self.shapes, self.dtypes):
            size = math.prod(shape)
            out.append(flat[k : k + size].reshape(shape).astype(dtype))
            k += size
        return jax.tree.unflatten(self.treedef, out)


class _SmallLUState(eqx.Module):
    lu: jax.Array
    perm: jax.Array
    inp: _Layout  # layout of the solution (operator input)
    out: _Layout  # layout of the right-hand side (operator output)
    transpose: bool = eqx.field(static=True)


class SmallLU(lx.AbstractLinearSolver):
    r"""`lineax` LU solver for small square operators, free of LAPACK and of sharding checks.

    Use it as the Newton linear solver of diffrax's implicit solvers when they run
    inside `jax.shard_map` (every `fojax.studies.run_study`) or under `jax.vmap` on a
    busy CPU (see the module docstring for the two bugs it avoids). Meant for the small
    systems fojax simulates: the factorisation is ``N`` sequential row steps of
    ``O(N²)`` work (no blocking).

    **Arguments:** none.
    """

    def init(self, operator: lx.AbstractLinearOperator, options: dict[str, Any]):
        del options
        n_in, n_out = operator.in_size(), operator.out_size()
        if n_in != n_out:
            raise ShapeError("Newton Jacobian", "a square operator", f"({n_out}, {n_in})",
                             "SmallLU solves square systems only.")
        lu, perm = lu_factor_small(operator.as_matrix())
        return _SmallLUState(lu, perm, _Layout.of(operator.in_structure()),
                             _Layout.of(operator.out_structure()), False)

    def compute(self, state: _SmallLUState, vector, options: dict[str, Any]):
        del options
        b = state.out.ravel(vector)
        x = lu_solve_small(state.lu, state.perm, b, transpose=state.transpose)
        return state.inp.unravel(x), lx.RESULTS.successful, {}

    def transpose(self, state: _SmallLUState, options: dict[str, Any]):
        del options
        return _SmallLUState(state.lu, state.perm, state.out, state.inp, not state.transpose), {}

    def conj(self, state: _SmallLUState, options: dict[str, Any]):
        del options
        return _SmallLUState(state.lu.conj(), state.perm, state.inp, state.out, state.transpose), {}

    def assume_full_rank(self):
        return True


def default_implicit_solver() -> diffrax.AbstractSolver:
    r"""`diffrax.Kvaerno5` with diffrax's default Newton method (`diffrax.VeryChord`, tolerances
    taken from the step-size controller) and `SmallLU` as its linear solver.

    Identical numerics to ``diffrax.Kvaerno5()`` up to the round-off of the LU solve;
    works inside `jax.shard_map` and `jax.vmap` (see the module docstring).
    """
    root_finder = diffrax.with_stepsize_controller_tols(diffrax.VeryChord)(linear_solver=SmallLU())
    return diffrax.Kvaerno5(root_finder=root_finder)
