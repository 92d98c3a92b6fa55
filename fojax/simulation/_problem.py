r"""`AbstractBatchProblem`: what the batch kernels integrate for one sample, what they save,
and the loss they accumulate.

A *batch problem* describes a family of samples indexed by a per-sample pytree ``p``
(e.g. a study's index pair ``(i, j)``); the driver (`fojax.simulation._driver.run_batched`)
streams the samples in chunks, groups them in blocks and hands each block to the
problem's `AbstractBatchProblem.block_kernel`, which returns the problem's reduction
with the batch as the last axis. The final classes:

| problem | one sample | stepped by |
|---|---|---|
| `fojax.studies._exact.StudyProblem` | the joint LTI loop of plant, observers and exosystem of a study sample | the exact batch-last kernel (`fojax.simulation._batch`) |
| `fojax.studies._exact.LossProblem` | the same samples, one loss metric (``"iae"`` or ``"ise"``) | the exact kernel, reverse-differentiable (`fojax.studies.study_loss`) |
| `fojax.simulation._exponential.ExponentialProblem` | a time-varying affine sample's decomposition | ETDRK4 (its own `block_kernel`) |
| `fojax.studies._runner.SimulateProblem` | any study sample, through `fojax.simulate` with the study's stepper | `jax.vmap` of `fojax.simulate` (its own `block_kernel`) |

Every problem returns the metrics `computed` of its outputs $o_k$ (``(K, b)`` per grid
point, e.g. the errors $\hat z - z$), the stepped ones reduced along the grid with
`init`, `update` (and `update_block`, several steps at once) and `final`, and keeps the
outputs on every `keep`-th grid point when ``keep ≥ 1`` (the quantile bands'
trajectories).
"""

# no `from __future__ import annotations`: equinox reads `eqx.AbstractVar` from the evaluated
# annotation (as a string it became a field, ordered before the subclasses' own fields)
import abc

import equinox as eqx
import jax

from ._batch import _block_kernel


#: `eval_shape_cached`'s results by structure (cleared when it holds `_SHAPE_CACHE_MAX`).
_SHAPE_CACHE: dict = {}


_SHAPE_CACHE_MAX = 256


def eval_shape_cached(fn, *args):
    """``eqx.filter_eval_shape(fn, *args)``, cached by ``fn`` and the structure of `args`
    (tree structure, shapes and dtypes of the array leaves, the other leaves by value).

    A shape evaluation traces ``fn`` in Python every time, and `run_study` asks for three
    or four of them per call (the study's plant and observers, the joint system), a visible
    part of its fixed cost for small systems. What they return depends only on that key, so a second call with new numbers reuses it. ``fn`` must be a stable object (a
    module-level function); arguments with unhashable non-array leaves are not cached."""
    leaves, treedef = jax.tree.flatten(args)
    key = (fn, treedef) + tuple((x.shape, x.dtype) if eqx.is_array(x) else x for x in leaves)
    try:
        hit = key in _SHAPE_CACHE
    except Exception:  # an unhashable or array-valued leaf: no cache
        return eqx.filter_eval_shape(fn, *args)
    if not hit:
        if len(_SHAPE_CACHE) >= _SHAPE_CACHE_MAX:
            _SHAPE_CACHE.clear()
        _SHAPE_CACHE[key] = eqx.filter_eval_shape(fn, *args)
    return _SHAPE_CACHE[key]


def _joint_of(problem, p):
    return problem.joint(p)


class AbstractBatchProblem(eqx.Module):
    r"""Abstract base of the batch problems (module docstring); the subclasses are final.

    **What is integrated for one sample.** Problems stepped by the exact batch-last kernel
    give `joint`: for one sample ``p`` the joint slow system
    ``(Aj (N, N), w0 (N,), G (K, N), ok, jumps)`` of $\dot w = A_j w$, $o = G w$ (``ok``:
    whether the sample is valid; ``jumps``: ``None`` or ``(times (J,), Δw (J, N))``). A
    problem with its own stepping overrides `block_kernel` (and `joint_size`).

    **What is saved.** `keep`: ``0`` (the reduction only) or the stride ``k`` of the
    outputs kept on ``ts[::k]``; `computed`: the names of the reduction's rows (the
    metric kinds accumulated, in the order `final` stacks them).

    **The loss.** `init(o0)`, `update(acc, o, k, ts)` (`update_block` for ``m`` steps at
    once) and `final(acc, o0, o_end, ts, h, ok) -> (metrics, success)` reduce the
    outputs along the grid (trapezoid rule) for the kernels that step the grid (the exact
    kernel, ETDRK4; `SimulateProblem` takes the metrics of whole trajectories instead);
    `additive` says that `update` adds a function of the step's outputs to the
    accumulator (the adjoint of `fojax.studies._adjoint` then takes a whole segment's
    output cotangents at once).
    """

    keep: eqx.AbstractVar[int]

    #: `update` adds a function of ``(o, k, ts)`` to the accumulator (a class attribute)
    additive = False
    #: the kernel steps a uniform grid (`fojax.simulation._driver.run_batched` checks ``ts``)
    uniform_grid = True

    @property
    def trace_name(self) -> str:
        """The key of `fojax.simulation._batch.TRACE_COUNTS` counting this problem's
        compilations by the driver."""
        return type(self).__name__

    @property
    @abc.abstractmethod
    def computed(self) -> tuple[str, ...]:
        """The metric kinds `final` returns, in its order (its leading axis)."""

    def joint(self, p):
        """The joint slow system of sample ``p`` (class docstring); problems with their own
        `block_kernel` need not give it."""
        raise NotImplementedError(f"{type(self).__name__} steps its own blocks (block_kernel); it has no joint()")

    def joint_size(self, p) -> int | None:
        """``N`` of the joint system of the first sample of ``p`` (leaves with a leading
        batch axis; from a cached shape evaluation of `joint`), which sets the block width
        of the exact kernel (`fojax.simulation._batch.block_for`); ``None`` for a problem
        with its own stepping."""
        return eval_shape_cached(_joint_of, self, jax.tree.map(lambda a: jax.ShapeDtypeStruct(a.shape[1:], a.dtype), p))[0].shape[0]

    def block_kernel(self, p, h, ts, basis):
        """One block of samples (leading axis ``b`` of every leaf of ``p``) on the grid ``ts``
        of step ``h``: the reduction ``(metrics, success)`` with the batch last (and the
        kept outputs ``(T_c, K, b)`` when `keep`); by default the exact batch-last kernel
        `fojax.simulation._batch._block_kernel` with the output basis ``basis``."""
        return _block_kernel(self, p, h, ts, basis)

    def plant_first(self, N: int):
        """Static ``(perm, k)`` putting the ``k`` states that do not involve the observers
        first (the joint matrix is then block lower-triangular), or ``None``."""
        return None

    def init(self, o0):
        """The accumulator after the first grid point's outputs ``o0`` ``(K, b)``."""
        raise NotImplementedError(f"{type(self).__name__} does not reduce along the grid")

    def update(self, acc, o, k, ts):
        """The accumulator after the outputs ``o`` ``(K, b)`` of grid point ``k``."""
        raise NotImplementedError(f"{type(self).__name__} does not reduce along the grid")

    def update_block(self, acc, O, ks, ts):
        """`update` over ``m`` consecutive outputs ``O`` ``(b, K, m)`` at grid indices ``ks``."""
        for j in range(O.shape[2]):
            acc = self.update(acc, O[:, :, j].T, ks[j], ts)
        return acc

    def final(self, acc, o0, o_end, ts, h, ok):
        """``(metrics (len(computed), K, b), success (b,))`` from the accumulator, the first
        and last outputs and the samples' validity ``ok``."""
        raise NotImplementedError(f"{type(self).__name__} does not reduce along the grid")
