r"""`run_study`: many uncertain plants × fault scenarios × observers in one compiled call.

**How a study runs.** A `Study` holds a *template* (plant, initial state, input, grid,
functional ``L``) and two tuples of `Family` objects: `uncertainty` (all of one size
``N_u``) and `scenarios` (all of one size ``N_f``). Sample ``(i, j)`` is the template
with the ``i``-th member of every uncertainty family and the ``j``-th of every scenario
family substituted. The flat batch of ``N_u N_f`` index pairs is simulated with
`jax.vmap` over `fojax.simulate` inside one `equinox.filter_jit` function: new
numbers (a new key, new observer gains) reuse the compiled code; only a new
*structure* (types, shapes, chunk size, options) compiles again (`TRACE_COUNTS`).

**Engines.** Which engine runs is the stepper's choice (`run_study`'s `stepper`, default
`fojax.Auto()`; `fojax.simulation._steppers`): its ``batch_candidates`` in order, each
through its study engine (`fojax.studies._engines`, keyed by stepper class), then every
sample through `fojax.simulate` (this section's path). LTI studies with known signals do not
take this path: they run on the batch-last exact kernel (`fojax.simulation._batch`,
`fojax.studies._exact`), which streams chunks, pads and shards with the one driver
(`fojax.simulation._driver.run_batched`).
Time-varying affine studies (δ(t), faults, known inputs) run on the exponential
integrator through the same `run_batched` (`fojax.studies._exponential`).

**Chunks and devices (one code path).** Every engine runs through the one driver,
`fojax.simulation._driver.run_batched`: the index batch is cut into chunks of a fixed
size (the last one padded with copies of the last sample, whose results are dropped, so
the shape never changes), and each chunk is spread over a 1-d `jax.sharding.Mesh` of
`devices` (default `jax.devices()`) with `jax.shard_map`, each device running its own
blocks (on this path, `SimulateProblem`: one block per device and chunk, its own
vmapped adaptive loop; with plain sharding propagation the batched while loop's "any
sample still running" test would become an all-reduce at every step, which on forced
host devices of a busy CPU stalled for minutes); the template, families and observers
are replicated. With one device this is the plain single-device run.

**Metrics** (per sample, observer and estimated signal, for the error
$e = \hat z - z$ on the grid, trapezoidal rule): IAE $\int|e|$, ISE $\int e^2$, ITAE
$\int (t - t_0)|e|$, peak $\max|e|$, settling time (the first grid time after which
$|e| \le$ `settle_tol` for good, $+\infty$ if $|e|$ exceeds it at the final time), and
time-wise quantiles of $e$ over all samples (confidence bands): every engine keeps the
errors only on the band grid ``ts[::k]`` (`band_stride`, at most `run_study`'s
`band_points` points), and the host computes exactly ``np.quantile`` of them
(`band_quantiles`).

**Signal studies.** Without observers (``run_study(study)``) the same metrics and bands
are those of $z = Lx$ itself (e.g. the state and the regulation error of a closed loop
under uncertainty): every engine builds its output rows from the empty observer tuple
(``[L, H_z]`` instead of the observers' ``ẑ − z`` rows), so the chunks, padding, devices
and compiled kernels are the ones above.
"""

from __future__ import annotations

import dataclasses
import json
import os
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._errors import InputError, removed_keywords, ShapeError
from ..observer import AbstractObserver
from ..plant import AbstractPlant, AbstractSignal, as_signal, FaultyPlant
from ..simulation import simulate
from ..simulation._batch import DEFAULT_BLOCK, TRACE_COUNTS as BATCH_TRACE_COUNTS
from ..simulation._discrete import discrete_stepper
from ..simulation._driver import DEFAULT_CHUNK, run_batched
from ..simulation._problem import AbstractBatchProblem
from ..simulation._save import (
    error_metrics,
    METRIC_NAMES,
    Metrics,
    resolve_save,
    UNSET,
)
from ..simulation._steppers import AbstractStepper, resolve_stepper
from ._engines import SIMULATE_LABEL, study_engine
from ._families import Family
from ._sharding import (
    check_same_on_every_process,
    distributed_errors,
    spans_processes,
)


#: Compilations of `run_study`'s chunk programs: the one driver's counter
#: (`fojax.simulation._batch.TRACE_COUNTS`), keyed ``"run_study"`` for the per-sample path
#: (`SimulateProblem`) and by the problem's class for the batch kernels.
TRACE_COUNTS = BATCH_TRACE_COUNTS

METRICS = METRIC_NAMES  # the one vocabulary: fojax.simulation._save


def band_stride(T: int, band_points: int | None) -> int:
    """The stride ``k`` of the quantile bands' time grid ``ts[::k]`` (the one definition,
    used by every engine of `run_study`): the smallest ``k`` whose grid has at most
    `band_points` points, ``ceil(T / k) <= band_points``; ``1`` (the full grid) for
    ``None``. E.g. ``T = 1001``, ``band_points = 201``: ``k = 5`` (every 5th point, the
    last grid time included since ``5 | 1000``)."""
    if band_points is None:
        return 1
    if isinstance(band_points, bool) or not isinstance(band_points, int | np.integer) or band_points < 2:
        raise InputError(
            f"band_points must be an integer >= 2 (time points of the quantile bands) or None "
            f"(every grid point); got {band_points!r}."
        )
    return max(1, -(-int(T) // int(band_points)))


def band_quantiles(errors: np.ndarray, quantiles, overwrite: bool = False) -> np.ndarray:
    """``np.quantile(errors, quantiles, axis=-1)`` (its default ``"linear"`` method),
    bit for bit, from one ``np.sort`` of the last axis (the samples).

    With `overwrite` (a writeable NumPy array the caller no longer needs, e.g. the
    exact engine's own host buffer) `errors` is sorted in place: no second array of the
    size of the errors is allocated (160 MB for the default §3.3.7 study at B = 10,000,
    whose first touch would cost more than the sort).

    The same interpolation as NumPy's (``a + (b - a) γ``, or ``b - (b - a)(1 - γ)`` for
    ``γ ≥ 0.5``, at the virtual index ``(n - 1) q``; ``nan`` where a row holds a ``nan``),
    but NumPy's vectorised sort instead of its partition with several ``kth`` (several
    times faster for many quantiles). Tested equal to ``np.quantile``."""
    if overwrite and isinstance(errors, np.ndarray) and errors.flags.writeable:
        s = errors
        s.sort(axis=-1)
    else:
        s = np.sort(np.asarray(errors), axis=-1)
    n = s.shape[-1]
    virt = (n - 1) * np.asarray(quantiles, dtype=float)
    lo = np.floor(virt).astype(np.intp)
    hi = np.minimum(lo + 1, n - 1)
    a, b = np.moveaxis(s[..., lo], -1, 0), np.moveaxis(s[..., hi], -1, 0)
    g = (virt - lo).reshape((-1,) + (1,) * (a.ndim - 1))
    with np.errstate(invalid="ignore"):  # inf - inf: nan, as np.quantile gives
        d = b - a
        out = np.where(g >= 0.5, b - d * (1 - g), a + d * g)
    return np.where(np.isnan(s[..., -1])[None], np.nan, out)


class _Sample(eqx.Module):
    plant: AbstractPlant
    x0: Float[Array, " n"]


class Study(eqx.Module):
    r"""A batch of simulation scenarios (see module docstring).

    **Arguments:**

    - `plant`: template plant (any `fojax.plant.AbstractPlant`; wrap it in `FaultyPlant` /
      `NoisyPlant` for fault or noise families).
    - `x0`: ``(n,)`` template initial state.
    - `ts`: ``(T,)`` output grid.
    - `L`: ``(q, n)`` functional: the true signal is $z = Lx$ (what the observers
      estimate; without observers, ``run_study(study)``, the signal whose metrics are
      reported, e.g. `fojax.control.LoopMaps.signal_rows` of a closed loop); with
      `fault_targets=True` and a `FaultyPlant` template the fault $\phi(t)$ is appended
      (for observers that also estimate the faults).
    - `u`: input signal (shared by all samples), constant vector, or ``None``.
    - `uncertainty`: families of size ``N_u`` (axis ``"uncertainty"``).
    - `scenarios`: families of size ``N_f`` (axis ``"fault"``).
    - `signal_names`: names of the ``q`` (+ ``n_f``) estimated signals.
    """

    plant: AbstractPlant
    x0: Float[Array, " n"]
    ts: Float[Array, " T"]
    L: Float[Array, "q n"]
    u: AbstractSignal
    uncertainty: tuple[Family, ...]
    scenarios: tuple[Family, ...]
    signal_names: tuple[str, ...] = eqx.field(static=True)
    fault_targets: bool = eqx.field(static=True)

    def __init__(self, plant, x0, ts, L, u=None, uncertainty=(), scenarios=(), signal_names=None,
                 fault_targets=False):
        if not isinstance(plant, AbstractPlant):
            raise InputError(f"plant must be a fojax.plant.AbstractPlant, got {type(plant).__name__}.")
        self.plant = plant
        self.x0 = jnp.asarray(x0, dtype=jnp.float64)
        self.ts = jnp.asarray(ts, dtype=jnp.float64)
        self.L = jnp.atleast_2d(jnp.asarray(L, dtype=jnp.float64))
        if self.L.shape[1] != plant.n:
            raise ShapeError("L", ("q", plant.n), tuple(self.L.shape), "L needs one column per state.")
        self.u = as_signal(u, plant.m)
        self.uncertainty = tuple(uncertainty)
        self.scenarios = tuple(scenarios)
        for name, fams in (("uncertainty", self.uncertainty), ("scenarios", self.scenarios)):
            sizes = {f.size for f in fams}
            if len(sizes) > 1:
                raise InputError(f"all {name} families must have the same size; got {sorted(sizes)}.")
        if fault_targets and not isinstance(plant, FaultyPlant):
            raise InputError("fault_targets=True needs a FaultyPlant template (its fault is the target).")
        self.fault_targets = bool(fault_targets)
        q = self.L.shape[0] + (plant.fault.size if fault_targets else 0)
        if signal_names is None:
            signal_names = tuple(f"z{i + 1}" for i in range(self.L.shape[0]))
            if fault_targets:
                signal_names += tuple(f"f{i + 1}" for i in range(plant.fault.size))
        if len(signal_names) != q:
            raise ShapeError("signal_names", f"{q} names", f"{len(signal_names)}")
        self.signal_names = tuple(signal_names)

    @property
    def num_uncertainty(self) -> int:
        return self.uncertainty[0].size if self.uncertainty else 1

    @property
    def num_scenarios(self) -> int:
        return self.scenarios[0].size if self.scenarios else 1

    @property
    def num_samples(self) -> int:
        return self.num_uncertainty * self.num_scenarios

    @property
    def num_signals(self) -> int:
        return len(self.signal_names)

    def sample(self, i, j) -> tuple[AbstractPlant, Array]:
        """``(plant, x0)`` of sample ``(i, j)`` (indices may be traced)."""
        s = _Sample(self.plant, self.x0)
        for f in self.uncertainty:
            s = f.apply(s, i)
        for f in self.scenarios:
            s = f.apply(s, j)
        return s.plant, s.x0

    def target(self, plant, ts, xs) -> Array:
        """``(T, q)`` true signals of one sample."""
        z = xs @ self.L.T
        if self.fault_targets:
            z = jnp.concatenate([z, jax.vmap(plant.fault)(ts)], axis=1)
        return z

    def split(self, uncertainty: int) -> tuple[Study, Study]:
        """Split the uncertainty axis: samples ``[:k]`` and ``[k:]`` (train / held-out)."""
        a = tuple(f[:uncertainty] for f in self.uncertainty)
        b = tuple(f[uncertainty:] for f in self.uncertainty)
        return eqx.tree_at(lambda s: s.uncertainty, self, a), eqx.tree_at(lambda s: s.uncertainty, self, b)


@dataclasses.dataclass(frozen=True)
class SimConfig:
    """Static options of the simulation inside a study (hashable: part of the compile key).

    `stepper` (a `fojax.simulation` stepper, default `fojax.Auto()`) says how samples are
    stepped (the keywords it replaced, ``method``, ``rtol``, ``atol``, ``max_steps`` and
    ``solver``, raise a `TypeError` naming it); `attrs` are its options as
    ``StudyResult.attrs`` records them."""

    settle_tol: float = 0.05
    # `study_loss` / `tune`: devices the samples are spread over (e.g. jax.devices() of a
    # jax.distributed run; fojax.studies._sharding), None: one block on the default device
    devices: tuple | None = None
    stepper: AbstractStepper | None = None
    # `study_loss` on the exponential engine: the step schedule (n_start, sub_start, substeps)
    # decided on the host for one concrete study by `resolve_engine` (as `fojax.tune` does), so
    # that the study may then be traced; None: decided on each call (needs a concrete study)
    exponential_schedule: tuple | None = None

    def __post_init__(self):
        object.__setattr__(self, "stepper", resolve_stepper(self.stepper, who="SimConfig"))

    def attrs(self) -> dict:
        """``method``, ``rtol``, ``atol``, ``max_steps`` of the stepper (its diffrax options)
        and ``settle_tol``: the options a `StudyResult` records."""
        d = self.stepper.diffrax_options
        return dict(method=self.stepper.method, rtol=float(d.rtol), atol=float(d.atol), max_steps=int(d.max_steps),
                    settle_tol=self.settle_tol)


SimConfig.__init__ = removed_keywords(SimConfig.__init__, who="SimConfig")


def sample_errors(study: Study, observers, i, j, cfg: SimConfig):
    """Errors ``ẑ_k − z`` ``(T, q)`` of every observer for sample ``(i, j)``, and success;
    without observers (a signal study), the one-element tuple ``(z,)``."""
    plant, x0 = study.sample(i, j)
    sol = simulate(plant, x0, study.ts, study.u, observers=tuple(observers), stepper=cfg.stepper, throw=False)
    z = study.target(plant, study.ts, sol.xs)
    if not observers:  # a signal study (`run_study(study)`): the metrics of z itself
        return (z,), sol.stats["success"]
    return tuple(zh - z for zh in sol.estimates), sol.stats["success"]


class SimulateProblem(AbstractBatchProblem):
    """Every sample of a study through `fojax.simulate` with the stepper of `cfg` (the
    ``"vmap-simulate"`` engine; a final `fojax.simulation._problem.AbstractBatchProblem`
    run by the one driver, `fojax.simulation._driver.run_batched`, with one block per
    device and chunk). A sample is an index pair ``(i, j)``; its block kernel is
    `jax.vmap` of `sample_errors` and `error_metrics` over the block, so any plant and
    grid the stepper takes run here (no uniform grid needed). Failed samples keep their
    metrics and are flagged by ``success``."""

    study: Study
    observers: tuple
    cfg: SimConfig = eqx.field(static=True)
    # 0, or the stride k of the error trajectories kept (ts[::k], `band_stride`)
    keep: int = eqx.field(static=True, default=0)
    uniform_grid = False

    @property
    def trace_name(self) -> str:
        return "run_study"

    @property
    def computed(self) -> tuple[str, ...]:
        return METRIC_NAMES

    def joint_size(self, p) -> None:
        return None

    def block_kernel(self, p, h, ts, basis):
        """``((metrics (5, K, b), success (b,)), errors (T_c, K, b))`` (the errors with
        `keep` only) of the block's samples ``p = (i, j)``, ``K`` = observers × signals."""
        del h, ts, basis  # each sample runs `fojax.simulate` on the study's own grid
        study, observers, cfg, keep = self.study, self.observers, self.cfg, self.keep

        def one(i, j):
            errs, ok = sample_errors(study, observers, i, j, cfg)
            mets = tuple(error_metrics(study.ts, e, cfg.settle_tol) for e in errs)
            return mets, (tuple(e[::keep] for e in errs) if keep else None), ok

        mets, errs, ok = jax.vmap(one)(*p)  # per observer: {name: (b, q)}, (b, T_c, q)
        M = jnp.stack([jnp.concatenate([m[name] for m in mets], axis=1).T for name in METRIC_NAMES])
        if not keep:
            return M, ok
        return (M, ok), jnp.transpose(jnp.concatenate(errs, axis=2), (1, 2, 0))


def _indices(study: Study):
    k = np.arange(study.num_samples)
    return k // study.num_scenarios, k % study.num_scenarios


@dataclasses.dataclass
class StudyResult:
    """Per-sample metrics with named axes.

    Attributes:
        metrics: dict of numpy arrays: ``"iae", "ise", "itae", "peak", "settling_time"``
            ``(observer, uncertainty, fault, signal)``; ``"quantiles"``
            ``(observer, quantile, time, signal)``; ``"success"`` ``(uncertainty, fault)``.
        axes: dict metric name → tuple of axis names.
        coords: labels: ``observer`` and ``signal`` names (strings), ``quantile`` levels
            and ``time`` as float arrays; ``time`` is the time axis of ``"quantiles"``: the
            band grid ``ts[::attrs["band_stride"]]`` (at most `run_study`'s
            `band_points` points; the study grid itself when ``band_stride == 1``).
        attrs: options of the run (JSON-serialisable).
    """

    metrics: dict
    axes: dict
    coords: dict
    attrs: dict = dataclasses.field(default_factory=dict)

    def summary(self, metric: str = "iae") -> dict:
        """``{observer: {signal: (mean, std)}}`` over all samples."""
        v = self.metrics[metric]
        out = {}
        for o, oname in enumerate(self.coords["observer"]):
            flat = v[o].reshape(-1, v.shape[-1])
            out[oname] = {
                s: (float(np.mean(flat[:, k])), float(np.std(flat[:, k])))
                for k, s in enumerate(self.coords["signal"])
            }
        return out

    def save(self, path) -> None:
        """Write ``path + ".npz"`` (arrays) and ``path + ".json"`` (axes, names, attrs), each
        atomically (temporary file in the same directory, then `os.replace`)."""
        path = os.fspath(path)
        arrays = {f"metric:{k}": np.asarray(v) for k, v in self.metrics.items()}
        meta = {"axes": {k: list(v) for k, v in self.axes.items()}, "attrs": self.attrs, "coords": {}}
        for k, v in self.coords.items():
            if isinstance(v, np.ndarray) and v.dtype.kind == "f":
                arrays[f"coord:{k}"] = v
            else:
                meta["coords"][k] = list(v)
        _atomic_write(path + ".npz", lambda f: np.savez(f, **arrays))
        _atomic_write(path + ".json", lambda f: f.write(json.dumps(meta, indent=1).encode()))

    @classmethod
    def load(cls, path) -> StudyResult:
        path = os.fspath(path)
        with open(path + ".json") as f:
            meta = json.load(f)
        with np.load(path + ".npz") as data:
            arrays = {k: data[k] for k in data.files}
        metrics = {k.split(":", 1)[1]: v for k, v in arrays.items() if k.startswith("metric:")}
        coords = {k: tuple(v) for k, v in meta["coords"].items()}
        coords.update({k.split(":", 1)[1]: v for k, v in arrays.items() if k.startswith("coord:")})
        axes = {k: tuple(v) for k, v in meta["axes"].items()}
        return cls(metrics=metrics, axes=axes, coords=coords, attrs=meta["attrs"])


def _atomic_write(path: str, write) -> None:
    """Replace `path` atomically with what ``write(f)`` writes (the one writer,
    `fojax._io.atomic_write`: umask permissions, confined to and recorded in a results folder)."""
    from .._io import atomic_write

    atomic_write(path, write, overwrite=True)


@removed_keywords
def run_study(
    study: Study,
    observers: AbstractObserver | Sequence[AbstractObserver] | None = None,
    *,
    observer_names: Sequence[str] | None = None,
    chunk_size: int | None = None,
    devices=None,
    stepper: AbstractStepper | None = None,
    save: Metrics | None = None,
    quantiles: Sequence[float] = UNSET,
    band_points: int | None = UNSET,
    settle_tol: float = UNSET,
    quiet: bool = False,
    compile_only: bool = False,
) -> StudyResult | None:
    r"""Simulate every sample of `study` with `observers` and return per-sample metrics.

    **Arguments:**

    - `study`: a `Study`.
    - `observers`: one observer or a sequence; each must estimate ``study.num_signals``
      signals, and the metrics are those of its error $\hat z - z$. ``None`` (default): a
      *signal study*, the metrics of $z = Lx$ itself (with ``fault_targets``, and the
      fault), e.g. the regulation error or the state of a closed loop under uncertainty
      (`fojax.control.closed_loop`, `fojax.control.LoopMaps.signal_rows`); the result
      has one entry on the ``observer`` axis, labelled ``"z"`` (or ``observer_names``),
      and the signals are named by ``study.signal_names``. Same engines, chunks and
      devices as with observers; the bands are the quantiles of $z$.
    - `observer_names`: labels (default ``"observer0", ...``; ``("z",)`` for a signal study).
    - `chunk_size`: samples per compiled call; rounded up to a multiple of the number of
      devices. The last chunk is padded, so one compilation serves every chunk. Default:
      on the exact and exponential engines 4,096 samples (2,048 with quantile bands), so
      their working memory follows the chunk, not the batch (only the per-sample results,
      and the band errors, ``8 · T_c · K · B`` bytes, are batch-sized); on the
      ``"vmap-simulate"`` engine the whole batch.
    - `devices`: devices of the 1-d mesh the batch axis is sharded over (default
      `jax.devices()`: after `jax.distributed.initialize`, the devices of every process,
      each process computing its share; every process then receives the whole result,
      bit-identical to a one-device run, and the processes must pass the same study and
      observers (checked; `fojax.errors.DistributedError` otherwise, and when another process
      dies). See ``docs/distributed.md``.
    - `stepper`: how the samples are stepped (`fojax.simulation._steppers`; default
      `fojax.Auto()`). `run_study` tries the stepper's batch kernels in order
      (``stepper.batch_candidates``, `fojax.studies._engines`), then, unless the stepper
      is `Exponential`, every sample through `fojax.simulate` (``attrs["engine"]``
      records the one that ran):

      - ``"exact-batch"`` (`fojax.Exact()`, `fojax.Auto()`): when every sample is an LTI
        loop driven by known signals (plant `DescriptorSystem` or
        `UncertainDescriptorSystem` with a constant δ, possibly in a `FaultyPlant` with
        `FaultProfile` step/ramp faults at any onset; LTI observers; uniform grid; input
        zero, constant, step, ramp, sine, piecewise constant or sums of them), the exact
        batch-last matrix-exponential kernel of `fojax.simulation._batch`
        (`fojax.studies._exact`; the metrics accumulated inside the time loop, no
        trajectory stored unless quantile bands are asked for);
      - ``"exponential-batch"`` (`fojax.Auto()`, `fojax.Exponential(...)`): samples that
        vary in time only through signals entering the differential equations affinely
        (a time-varying δ(t) such as `sinusoidal_delta` or `piecewise_constant_delta`,
        `FaultyPlant` faults, any known input), with LTI observers and every signal
        breakpoint (fault onset, switching time) on the step grid: the exponential
        integrator (ETDRK4, fourth order, steps a fraction of the grid chosen from the
        loop's fastest rate, see `fojax.Exponential` and `fojax.studies._exponential`) on
        the same batch kernel; an explicit `Exponential` raises `fojax.errors.InputError` saying
        why a study does not qualify;
      - ``"vmap-simulate"`` (`fojax.Auto()`, `fojax.Exact()`, `fojax.Diffrax(...)`):
        every sample runs `fojax.simulate` with the stepper under `jax.vmap`
        (``throw=False``; failed samples are flagged in ``metrics["success"]``; `Exact`
        then needs an LTI plant as in `fojax.simulate`). For non-stiff studies an explicit
        solver, ``Diffrax(diffrax.Tsit5())``, compiles and runs much faster than the
        default implicit one.
    - `save`: `fojax.Metrics(kinds, settle_tol, reduce, bands)` (default ``Metrics()``:
      all five metrics per signal, settling tolerance 0.05, ``Bands()``: quantiles 0.05,
      0.25, 0.5, 0.75, 0.95 on at most 201 time points). With `fojax.Bands` the errors are
      kept only on every ``k``-th grid point, ``ts[::k]`` with the smallest ``k`` giving at
      most ``points`` points (`band_stride`; ``coords["time"]``), and the quantiles are
      exactly ``np.quantile`` of the full-resolution errors at those times
      (``points=None``: every grid point, memory ``8 T · observers · signals · B`` bytes
      on the host); ``bands=None``: no trajectories are kept. ``reduce="sum"`` sums
      ``"iae"``/``"ise"``/``"itae"`` over the signals (the metric table of
      `fojax.simulation._save`).
    - `quantiles`, `band_points`, `settle_tol`: the legacy spelling of `save`
      (``Metrics(settle_tol=settle_tol, bands=Bands(quantiles, band_points))``, no bands
      for ``quantiles=()``; `fojax.simulation._save.as_save`); not together with `save`.
    - `quiet`: no progress bar.
    - `compile_only`: only prepare and compile the program the batch engines (exact,
      exponential) would run, and return ``None``: the same call afterwards (the same
      study shapes and observer structures; new numbers are fine) runs it without
      compiling. ``fojax study`` does this on a thread while it tunes. Nothing
      is compiled ahead for the ``vmap-simulate`` engine.

    **Returns:** a `StudyResult` (``None`` with `compile_only`).
    """
    signal_study = observers is None  # the metrics of z = L x itself (no observer)
    if isinstance(observers, AbstractObserver):
        observers = (observers,)
    observers = () if signal_study else tuple(observers)
    if not observers and not signal_study:
        raise InputError("run_study got an empty sequence of observers; pass observers=None (the default) for the "
                         "metrics of the study's signal z = L x itself.")
    for k, o in enumerate(observers):
        if o.output_size != study.num_signals:
            raise ShapeError(
                f"observers[{k}].output_size", study.num_signals, o.output_size,
                "Each observer must estimate the study's signals (L, plus faults with fault_targets).",
            )
    default_names = ("z",) if signal_study else tuple(f"observer{k}" for k in range(len(observers)))
    names = tuple(observer_names) if observer_names is not None else default_names
    if len(names) != len(default_names):
        raise ShapeError("observer_names", len(default_names), len(names),
                         "A signal study (observers=None) has one name." if signal_study else "")
    stepper = resolve_stepper(stepper, who="run_study")
    stepper = discrete_stepper(study.plant, stepper)  # a discrete-time plant: every sample through simulate
    save = resolve_save(save, quantiles, band_points, settle_tol, who="run_study")
    settle_tol = save.settle_tol
    quantiles = save.bands.quantiles if save.bands is not None else ()
    cfg = SimConfig(stepper=stepper, settle_tol=settle_tol)
    stride = band_stride(study.ts.shape[0], save.bands.points if save.bands is not None else None)
    keep = stride if len(quantiles) > 0 else 0  # 0: no error trajectories; else their stride
    if spans_processes(devices):  # a global mesh (jax.distributed): same inputs everywhere
        check_same_on_every_process((study, observers), "run_study")
    with distributed_errors("run_study"):
        for candidate in stepper.batch_candidates:  # in the stepper's order (fojax.simulation._steppers)
            engine = study_engine(candidate)  # what the candidate does with a study (fojax.studies._engines)
            prepared, _reason = engine.problem(candidate, study, observers, settle_tol=settle_tol, keep=keep,
                                               kinds=save.kinds, strict=not stepper.simulates)
            if prepared is not None:
                res = _run_batch(study, prepared, names, quantiles, cfg, chunk_size, devices, engine=engine.label,
                                 stride=stride, compile_only=compile_only, **engine.attrs(prepared[0]))
                return None if compile_only else _apply_save(res, save)
        if not stepper.simulates:  # (its candidate refuses with the reason when strict)
            raise InputError(f"stepper {stepper!r} cannot run this study.")
        if compile_only:  # every sample through simulate: compiled by its first chunk's call (nothing ahead)
            return None
        solver = stepper.diffrax_options.solver
        res = _run_vmap(study, observers, names, quantiles, cfg, chunk_size, devices, keep, solver, quiet, stride)
        return _apply_save(res, save)


def _apply_save(res: StudyResult, save: Metrics) -> StudyResult:
    """Keep the metrics `save` names (``"success"`` and ``"quantiles"`` always), summed over
    the signals for ``reduce="sum"`` (the signal axis dropped: axes ``(observer,
    uncertainty, fault)``). The default `Metrics()` returns `res` unchanged."""
    if save.kinds == METRIC_NAMES and save.reduce == "none":
        return res
    for name in METRIC_NAMES:
        if name not in save.kinds:  # computed all the same by the vmap engine (the batch kernels: "peak"
            # with the settling time alone, `StudyProblem.computed`)
            res.metrics.pop(name, None)
            res.axes.pop(name, None)
        elif save.reduce == "sum":
            res.metrics[name] = np.sum(res.metrics[name], axis=-1)
            res.axes[name] = res.axes[name][:-1]
    res.attrs["metrics"] = list(save.kinds)
    res.attrs["reduce"] = save.reduce
    return res


def _run_vmap(study, observers, names, quantiles, cfg: SimConfig, chunk_size, devices, keep, solver,
              quiet, stride) -> StudyResult:
    """`run_study` on the ``"vmap-simulate"`` engine (`fojax.simulate` per sample,
    `SimulateProblem`) through the one driver; default chunk: the whole batch."""
    idx = tuple(jnp.asarray(a) for a in _indices(study))
    chunk = study.num_samples if chunk_size is None else int(chunk_size)
    return _run_batch(study, (SimulateProblem(study, tuple(observers), cfg, keep), None, idx), names, quantiles,
                      cfg, chunk, devices, method=cfg.stepper.method,
                      solver=type(solver).__name__ if solver is not None else "default", engine=SIMULATE_LABEL,
                      stride=stride, block=None, progress=not quiet)


def _result(study, names, quantiles, cfg: SimConfig, metrics, axes, stride: int, **attrs) -> StudyResult:
    """The `StudyResult` of either engine: coordinates from the study (``time``: the band
    grid ``ts[::stride]``), attributes from `cfg` (without the solver object) updated by
    the engine's own `attrs`."""
    coords = {
        "observer": names,
        "signal": study.signal_names,
        "quantile": np.asarray(quantiles, dtype=float),
        "time": np.asarray(study.ts)[::stride],
    }
    merged = cfg.attrs()
    merged["band_stride"] = int(stride)
    merged.update(attrs)
    return StudyResult(metrics=metrics, axes=axes, coords=coords, attrs=merged)


def _run_batch(study, prepared, names, quantiles, cfg: SimConfig, chunk_size, devices, *, method: str, solver: str,
               engine: str, stride=1, compile_only=False, block: int | None = DEFAULT_BLOCK,
               progress: bool = False) -> StudyResult | None:
    """`run_study` on a batch kernel (`run_batched`): the prepared problem of a study engine
    (`fojax.studies._engines`: the exact problem of `fojax.studies._exact` or the exponential
    one of `fojax.studies._exponential`); `method`, `solver`, `engine` are recorded in
    ``attrs``."""
    problem, basis, idx = prepared
    B = study.num_samples
    keep = problem.keep
    # trajectories for the quantile bands are (T, K) per sample: smaller chunks bound memory
    default = DEFAULT_CHUNK // 2 if keep else DEFAULT_CHUNK
    chunk = min(B, default) if chunk_size is None else int(chunk_size)
    devices = jax.devices() if devices is None else devices  # all processes' devices, as `_mesh`
    out, layout = run_batched(problem, idx, study.ts, chunk_size=chunk, block=block, devices=devices,
                              basis=basis, host=True, compile_only=compile_only, progress=progress)
    if compile_only:
        return None
    if keep:
        (mets, ok), traj = out
    else:
        mets, ok = out
    mets, ok = np.asarray(mets), np.asarray(ok)  # (len(computed), K, B), (B,)
    computed = problem.computed  # the metrics the kernel accumulated
    Nu, Nf, q, n_obs = study.num_uncertainty, study.num_scenarios, study.num_signals, len(names)
    metrics = {}
    for k, name in enumerate(computed):
        v = mets[k].reshape(n_obs, q, Nu, Nf)
        metrics[name] = np.ascontiguousarray(np.transpose(v, (0, 2, 3, 1)))
    metrics["success"] = ok.reshape(Nu, Nf)
    axes = {name: ("observer", "uncertainty", "fault", "signal") for name in computed}
    axes["success"] = ("uncertainty", "fault")
    if keep:
        E = np.asarray(traj).reshape(traj.shape[0], n_obs, q, B)  # (T_c, obs, q, B)
        qs = band_quantiles(E, quantiles, overwrite=True)  # (nq, T_c, obs, q); E (run_batched's host buffer) sorted
        metrics["quantiles"] = np.ascontiguousarray(np.transpose(qs, (2, 0, 1, 3)))
        axes["quantiles"] = ("observer", "quantile", "time", "signal")
    return _result(study, names, quantiles, cfg, metrics, axes, stride, method=method, solver=solver,
                   chunk_size=layout["chunk_size"], num_chunks=layout["num_chunks"],
                   num_devices=layout["num_devices"], engine=engine)
