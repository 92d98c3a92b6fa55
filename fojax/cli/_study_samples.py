"""The samples of `fojax study`: what is drawn, how many, from which keys; their record.

`plan_samples` decides, before anything runs, how many samples are simulated and why
(the study says it and records it); `make_study` / `make_training_study` build the
`fojax.studies.Study` objects; `describe_samples` reads back, per sample, what was
actually simulated (fault, onset, magnitude, δ, initial states, input) for
``study-samples.npz`` / ``.json`` and the report; `metric_tables` summarises IAE, peak
and settling time per observer and signal.

**Sample structure.** Every random element of a sample is drawn *jointly*: sample ``k``
is the ``k``-th draw of (δ, fault scenario), each family of size ``N`` in the study's
uncertainty axis. So any ``--samples N`` is run exactly (it used to be ``N_u`` δ draws
times 4 fault scenarios, rounding ``N`` down to a multiple of 4 and up to at least 4).
A model without any random element (no uniform δ, no faults; the initial state and the
input are fixed) is a single deterministic simulation: one sample is run, whatever
``--samples`` says, and the report says so.

**Keys.** The evaluated ("held-out") samples use ``PRNGKey(seed)``, the tuning's
training samples ``PRNGKey(seed + 1)`` and its held-out curve ``PRNGKey(seed + 2)``, each
split into a δ key and a fault key: distinct keys, so the evaluation never reuses a
training draw — except for a deterministic model, where all three are the same run.
"""

from __future__ import annotations

import collections
import dataclasses

import numpy as np


#: Range of fault magnitudes |a| of the study's fault scenarios (random sign).
FAULT_MAGNITUDE = (0.5, 1.5)
#: Fault onsets, as fractions of the horizon (uniform).
FAULT_ONSET = (0.1, 0.4)
#: Constant fault directions of the fault-augmented training study.
TRAIN_FAULTS = 32
#: |e| must stay below this for good for an error to count as settled
#: (`fojax.studies.run_study`'s `settle_tol`).
SETTLE_TOL = 0.05


@dataclasses.dataclass(frozen=True)
class SamplePlan:
    """What `fojax study` runs (JSON-able via `to_dict`)."""

    requested: int
    run: int
    random: tuple[str, ...]  # descriptions of the random elements (empty: deterministic)
    fixed: tuple[str, ...]  # descriptions of what every sample shares
    breakdown: str
    message: str
    training: int
    training_breakdown: str
    seed: int

    @property
    def deterministic(self) -> bool:
        return not self.random

    def to_dict(self) -> dict:
        return {
            "requested": self.requested, "run": self.run, "breakdown": self.breakdown,
            "deterministic": self.deterministic, "random_elements": list(self.random),
            "fixed_elements": list(self.fixed),
            "training_samples": self.training, "training_breakdown": self.training_breakdown,
            "seeds": {"evaluation": self.seed, "training": self.seed + 1, "training_heldout_curve": self.seed + 2},
        }


def _uniform_delta(cfg) -> bool:
    return cfg.dA is not None and (cfg.profile or {}).get("kind") == "uniform"


def _augmented_training(cfg) -> bool:
    return cfg.augments_faults and not cfg.ramp and (cfg.profile or {}).get("kind") in (None, "uniform")


def ts_fault_key(k_f):
    """The fault-scenario key of a Takagi–Sugeno study: ``fold_in(fault key, 1)``, since the
    fault key itself draws the initial states (`make_study`)."""
    import jax

    return jax.random.fold_in(k_f, 1)


def _nf(cfg) -> int:
    return (cfg.Fa if cfg.Fa is not None else cfg.Fs).shape[1]


def _x0(cfg) -> np.ndarray:
    return np.asarray(cfg.x0, dtype=float) if cfg.x0 is not None else np.full((cfg.n,), 0.5)


def plan_samples(cfg, requested: int, horizon: float, seed: int) -> SamplePlan:
    """The samples `fojax study` runs for `requested` (``--samples``) on config `cfg`."""
    random, fixed = [], []
    if _uniform_delta(cfg):
        b = float(cfg.profile["bound"])
        k = cfg.dA.shape[0]
        random.append(f"the uncertainty δ ({k} direction{'s' if k > 1 else ''} of [uncertainty] dA), constant "
                      f"in time, each entry uniform in [{-b:g}, {b:g}]")
    elif cfg.dA is not None:
        prof = cfg.profile or {"kind": "constant", "value": 0.0}
        fixed.append(f"the uncertainty profile δ ([uncertainty] profile {prof}, not random)")
    if cfg.has_faults:
        nf = _nf(cfg)
        lo, hi = (f * horizon for f in FAULT_ONSET)
        random.append(f"the fault scenario: one of the {nf} faults (uniformly chosen) steps at an onset "
                      f"uniform in [{lo:g}, {hi:g}] s to a magnitude |a| uniform in "
                      f"[{FAULT_MAGNITUDE[0]:g}, {FAULT_MAGNITUDE[1]:g}] with a random sign; the others stay 0")
    if cfg.parameter_spread:
        nl = cfg.takagi_sugeno["plant"]
        random.append(f"the physical parameters of the nonlinear plant '{nl}' ([uncertainty] parameters), "
                      "constant in time, each nominal * (1 + s U(-1, 1)) with "
                      + ", ".join(f"{k}: s = {v:g}" for k, v in cfg.parameter_spread.items()))
    x0 = _x0(cfg)
    if cfg.x0_spread is not None and (cfg.x0_spread > 0).any():
        random.append("the plant's initial state: x0 = [" + ", ".join(f"{v:g}" for v in x0)
                      + "] + U(-spread, spread) per state, spread = ["
                      + ", ".join(f"{v:g}" for v in cfg.x0_spread) + "] ([initial_state]; projected onto the "
                      "algebraic constraints by the simulation)")
    if cfg.is_takagi_sugeno:
        fixed.append("the plant: " + (f"the nonlinear model '{cfg.takagi_sugeno['plant']}' "
                                      "([takagi_sugeno] plant)" if cfg.takagi_sugeno.get("plant")
                                      else "the Takagi-Sugeno model itself"))
    if not any(r.startswith("the plant's initial state") for r in random):
        fixed.append(f"the plant's initial state x0 = [{', '.join(f'{v:g}' for v in x0)}] "
                 f"({'[model] x0' if cfg.x0 is not None else 'fojax default 0.5 per state'}; projected onto "
                 "the algebraic constraints by the simulation)")
    fixed.append("every observer's zero initial state")
    fixed.append("the input u(t) = sin(t) on every input channel")
    if random:
        run = requested
        breakdown = (f"{run} independent draws of ({', '.join(_short(r) for r in random)})"
                     if len(random) > 1 else f"{run} independent draws of {_short(random[0])}")
        message = f"{run} samples, as requested: {breakdown}."
    else:
        run = 1
        breakdown = "1 deterministic run (the model has no random element)"
        message = ("the model has no random element (no [uncertainty] with a uniform profile, no [faults]; "
                   "x0 and the input are fixed), so every sample would be the same simulation: running 1"
                   + (f" instead of the {requested} requested." if requested != 1 else "."))
    # the tuning's training set (same counts as before the joint draws were introduced)
    n_u_old = max(1, requested // (4 if cfg.has_faults else 1))
    if not random:
        training, tb = 1, "the same single deterministic run as the evaluation"
    elif _augmented_training(cfg):
        nu = max(1, n_u_old // 4) if _uniform_delta(cfg) else 1
        training = nu * TRAIN_FAULTS
        tb = (f"{nu} δ draw{'s' if nu > 1 else ''} x {TRAIN_FAULTS} constant fault vectors (every fault "
              f"active, each with a magnitude uniform in [{FAULT_MAGNITUDE[0]:g}, {FAULT_MAGNITUDE[1]:g}] and a "
              "random sign, present from t = 0) on the fault-augmented model, horizon min(T, 4) s, step "
              "max(dt, 0.05) s")
    else:
        training = max(1, requested // 4)
        tb = f"{training} independent draws like the evaluation samples"
    return SamplePlan(requested, run, tuple(random), tuple(fixed), breakdown, message, training, tb, int(seed))


def _short(description: str) -> str:
    for start, word in (("the uncertainty", "δ"), ("the physical", "parameters"), ("the plant's initial", "x0")):
        if description.startswith(start):
            return word
    return "fault scenario"


# ------------------------------------------------------------------------ studies


def make_study(cfg, seed: int, count: int, horizon: float, dt: float):
    """The evaluated study: `count` joint draws of every random element (module docstring)."""
    import jax
    import jax.numpy as jnp

    from .. import studies
    from ..plant import FaultProfile, FaultyPlant, Sine

    k_u, k_f = jax.random.split(jax.random.PRNGKey(seed))
    plant = cfg.plant()
    families, prefix = [], ("plant",)
    if cfg.has_faults:
        nf = _nf(cfg)
        plant = FaultyPlant(plant, cfg.Fa, cfg.Fs, fault=FaultProfile(jnp.zeros(nf)))
        prefix = ("plant", "base")
    if cfg.is_takagi_sugeno:  # physical parameters (δ key) and x0 (fault key), drawn jointly
        if cfg.parameter_spread:
            theta = plant.base.theta if cfg.has_faults else plant.theta
            families.append(studies.parameter_uncertainty(k_u, count, theta, cfg.parameter_spread,
                                                          path=prefix + ("theta",)))
        if cfg.x0_spread is not None and (cfg.x0_spread > 0).any():
            sp = jnp.asarray(cfg.x0_spread)
            families.append(studies.initial_conditions(k_f, count, _x0(cfg), bounds=(-sp, sp)))
        # the fault key already draws x0: the fault scenarios take their own key
        k_f = ts_fault_key(k_f)
    if _uniform_delta(cfg):
        b = float(cfg.profile["bound"])
        families.append(studies.constant_delta(k_u, count, cfg.dA.shape[0], bounds=(-b, b),
                                               path=prefix + ("delta",)))
    if cfg.has_faults:
        families.append(studies.fault_scenarios(
            k_f, count, _nf(cfg), magnitude=FAULT_MAGNITUDE,
            onset=(FAULT_ONSET[0] * horizon, FAULT_ONSET[1] * horizon)))
    ts = jnp.arange(0.0, horizon + 0.5 * dt, dt)
    u = Sine(jnp.ones(cfg.B.shape[-1]), 1.0)
    return studies.Study(plant, jnp.asarray(_x0(cfg)), ts, cfg.L, u, uncertainty=tuple(families),
                         fault_targets=cfg.has_faults and cfg.estimate_faults)


def make_training_study(cfg, seed: int, plan: SamplePlan, horizon: float, dt: float):
    """The study the gradient tuning runs on (`plan.training` samples). For a
    fault-augmented LTI model with a uniform (constant) δ it is the *augmented* system
    (faults as constant states with random values from t = 0) on a [0, min(T, 4)] s grid
    of max(dt, 0.05) s: linear and time-invariant, so simulated by exact stepping, whose
    gradient is cheap; otherwise draws like the evaluation (diffrax; slower to
    differentiate)."""
    import jax
    import jax.numpy as jnp

    from .. import studies
    from ..plant import Constant, Sine, UncertainDescriptorSystem

    if plan.deterministic or not _augmented_training(cfg):
        return make_study(cfg, seed, plan.training, horizon, dt)
    k_u, k_f = jax.random.split(jax.random.PRNGKey(seed))
    aug = cfg.design_system()
    nf = aug.n - cfg.n
    x0 = jnp.concatenate([jnp.asarray(_x0(cfg)), jnp.zeros(nf)])
    uncertainty, plant = (), aug
    if cfg.dA is not None:
        k = cfg.dA.shape[0]
        dA = np.zeros((k, aug.n, aug.n))
        dA[:, : cfg.n, : cfg.n] = cfg.dA
        plant = UncertainDescriptorSystem(aug, dA=dA, delta=Constant(jnp.zeros(k)))
        if _uniform_delta(cfg):
            b = float(cfg.profile["bound"])
            uncertainty = (studies.constant_delta(k_u, plan.training // TRAIN_FAULTS, k, bounds=(-b, b)),)
    # the error is linear in the fault: many fault directions, few δ values
    scenarios = (studies.constant_faults(k_f, TRAIN_FAULTS, x0, nf, magnitude=FAULT_MAGNITUDE),)
    h = max(dt, 0.05)
    ts_train = jnp.arange(0.0, min(horizon, 4.0) + 0.5 * h, h)
    u = Sine(jnp.ones(cfg.B.shape[-1]), 1.0)
    return studies.Study(plant, x0, ts_train, cfg.design_L(), u, uncertainty=uncertainty, scenarios=scenarios)


# ------------------------------------------------------------------------ the record


def describe_samples(study, cfg, observers: dict) -> dict:
    """Per-sample arrays of what `study` simulates (read back from the study itself).

    **Returns:** a dict of NumPy arrays: ``ts``, ``u`` ``(T, m)`` (shared input),
    ``x0`` ``(N, n)`` (given plant initial state per sample), ``x0_consistent``
    (the state the simulation starts from: `x0` projected onto the algebraic constraints
    by `fojax.simulation.consistent_initial_condition`), ``delta`` ``(N, k)``
    (constant δ), ``fault_amplitude`` ``(N, nf)``, ``fault_onset``, ``fault_rise``
    ``(N,)``, ``fault_index`` ``(N,)`` (the active fault, ``-1`` none; for the augmented
    training study the faults are the last ``nf`` entries of ``x0``, present from
    ``t0``), and ``observer_x0/<name>`` (the observers' initial states, shared).
    Missing entries mean the study has no such element.
    """
    import jax.numpy as jnp

    from ..plant import Constant, FaultyPlant, UncertainDescriptorSystem

    N = study.num_samples
    k = np.arange(N)
    iu, jf = jnp.asarray(k // study.num_scenarios), jnp.asarray(k % study.num_scenarios)
    # one compiled call (eager vmap dispatches, and compiles, every primitive separately)
    (plants, x0s, x0c), u = _read_back(study, iu, jf)
    out = {"ts": np.asarray(study.ts), "u": np.asarray(u), "x0": np.asarray(x0s), "x0_consistent": np.asarray(x0c)}
    base = plants
    # a nonlinear plant's physical parameters (under the fault wrapper, if any)
    theta = getattr(plants.base if isinstance(plants, FaultyPlant) else plants, "theta", None)
    if isinstance(theta, dict):
        for name, val in theta.items():
            out[f"theta/{name}"] = np.broadcast_to(np.asarray(val), (N,)).copy()
    if isinstance(plants, FaultyPlant):
        f = plants.fault
        amp = np.broadcast_to(np.asarray(f.amplitude), (N, f.amplitude.shape[-1]))
        out["fault_amplitude"] = amp
        out["fault_onset"] = np.broadcast_to(np.asarray(f.onset), (N,)).copy()
        out["fault_rise"] = np.broadcast_to(np.asarray(f.rise), (N,)).copy()
        base = plants.base
    elif cfg.has_faults and out["x0"].shape[1] > cfg.n:  # augmented training: constant faults in x0
        nf = _nf(cfg)
        amp = out["x0"][:, cfg.n: cfg.n + nf]
        out["fault_amplitude"] = amp
        out["fault_onset"] = np.full((N,), float(study.ts[0]))
        out["fault_rise"] = np.zeros((N,))
    if "fault_amplitude" in out:
        amp = out["fault_amplitude"]
        active = np.abs(amp) > 0
        out["fault_index"] = np.where(active.sum(axis=1) == 1, np.argmax(active, axis=1), -1)
    if isinstance(base, UncertainDescriptorSystem) and isinstance(base.delta, Constant):
        out["delta"] = np.broadcast_to(np.asarray(base.delta.value), (N, base.delta.value.shape[-1])).copy()
    for name, obs in observers.items():
        out[f"observer_x0/{name}"] = np.asarray(obs.initial_state())
    return out


#: Traces of the read-back of `describe_samples` (one per study structure and sample count).
READ_TRACES: collections.Counter = collections.Counter()
_READ = None


def _read_back(study, iu, jf):
    """The sampled plants, initial states and input of `study`, in one compiled call. The
    jitted function is built once per process, so the training and held-out sets, of one
    structure, share one compilation."""
    global _READ
    if _READ is None:
        import equinox as eqx
        import jax

        from ..simulation import consistent_initial_condition

        @eqx.filter_jit
        def read(study, iu, jf):
            READ_TRACES["read_back"] += 1

            def one(i, j):
                plant, x0 = study.sample(i, j)
                x0c, _ = consistent_initial_condition(plant, x0, t0=study.ts[0], u=study.u)
                return plant, x0, x0c

            return jax.vmap(one)(iu, jf), jax.vmap(study.u)(study.ts)

        _READ = read
    return _READ(study, iu, jf)


def summarize_samples(arrays: dict) -> dict:
    """Ranges of the drawn values (JSON-able): counts, min/max of δ, fault magnitudes and onsets,
    how many samples have each fault."""
    s: dict = {"samples": int(arrays["x0"].shape[0])}
    for key in sorted(k for k in arrays if k.startswith("theta/")):
        d = arrays[key]
        if np.ptp(d) > 0:
            s.setdefault("parameters", {})[key[len("theta/"):]] = [float(d.min()), float(d.max())]
    if "delta" in arrays:
        d = arrays["delta"]
        s["delta_min"], s["delta_max"] = d.min(axis=0).tolist(), d.max(axis=0).tolist()
    if "fault_amplitude" in arrays:
        a = np.abs(arrays["fault_amplitude"])
        nz = a[a > 0]
        s["fault_magnitude_min"] = float(nz.min()) if nz.size else 0.0
        s["fault_magnitude_max"] = float(nz.max()) if nz.size else 0.0
        s["fault_onset_min"] = float(arrays["fault_onset"].min())
        s["fault_onset_max"] = float(arrays["fault_onset"].max())
        idx = arrays["fault_index"]
        s["samples_per_fault"] = {f"f{i + 1}": int((idx == i).sum()) for i in range(arrays["fault_amplitude"].shape[1])}
        if (idx < 0).any():
            s["samples_with_several_faults"] = int((idx < 0).sum())
    return s


def describe_in_words(summary: dict, what: str) -> str:
    """One markdown bullet about a drawn set (from `summarize_samples`)."""
    parts = [f"**{what}**: {summary['samples']} sample{'s' if summary['samples'] != 1 else ''}"]
    if "delta_min" in summary:
        parts.append("δ drawn in [" + ", ".join(f"{lo:.3g}..{hi:.3g}" for lo, hi in
                                                zip(summary["delta_min"], summary["delta_max"])) + "]")
    if "parameters" in summary:
        parts.append("parameters drawn in " + ", ".join(f"{k} {lo:.4g}..{hi:.4g}" for k, (lo, hi)
                                                        in summary["parameters"].items()))
    if "fault_magnitude_min" in summary:
        per = ", ".join(f"{k}: {v}" for k, v in summary["samples_per_fault"].items())
        parts.append(f"fault magnitudes |a| {summary['fault_magnitude_min']:.3g}..{summary['fault_magnitude_max']:.3g}, "
                     f"onsets {summary['fault_onset_min']:.3g}..{summary['fault_onset_max']:.3g} s, "
                     f"samples per fault ({per})"
                     + (f", {summary['samples_with_several_faults']} with several faults at once"
                        if "samples_with_several_faults" in summary else ""))
    return "- " + "; ".join(parts) + "."


# ------------------------------------------------------------------------ metric tables


def flat_metrics(res) -> dict:
    """``{metric: (observer, sample, signal)}`` from a `StudyResult` (samples flattened in
    the study's order)."""
    out = {}
    for name in ("iae", "ise", "itae", "peak", "settling_time"):
        v = np.asarray(res.metrics[name])
        out[name] = v.reshape(v.shape[0], -1, v.shape[-1])
    out["success"] = np.asarray(res.metrics["success"]).reshape(-1)
    return out


def mean_settling(st: np.ndarray, horizon: float) -> tuple[np.ndarray, np.ndarray]:
    """Mean over samples (axis 0) with never-settled samples (``inf``) counted as the
    horizon (so the mean is then a lower bound), and the number of never-settled samples."""
    st = np.asarray(st, dtype=float)
    unsettled = ~np.isfinite(st)
    return np.where(unsettled, horizon, st).mean(axis=0), unsettled.sum(axis=0)


def metric_tables(flat: dict, names: list, signals: list, horizon: float, tuned_pairs: dict) -> dict:
    """Markdown-ready tables ``{caption: (headers, rows)}`` of mean IAE, mean peak |e| and
    mean settling time per observer and signal, each tuned observer followed by its
    change (%) against the design it was tuned from (`tuned_pairs`: tuned → base)."""
    n_samples = flat["iae"].shape[1]
    tables = {}
    specs = (
        ("iae", "Mean IAE ∫|e| dt over the samples", True),
        ("peak", "Mean peak |e| over the samples", False),
        ("settling_time", f"Mean settling time [s] (|e| ≤ {SETTLE_TOL:g} from then on)", False),
    )
    for metric, caption, total in specs:
        headers = ["observer"] + list(signals) + (["total"] if total else [])
        values, notes = {}, {}
        for k, nm in enumerate(names):
            if metric == "settling_time":
                m, never = mean_settling(flat[metric][k], horizon)
                notes[nm] = never
            else:
                m = flat[metric][k].mean(axis=0)
            values[nm] = np.concatenate([m, [m.sum()]]) if total else m
        rows = []
        for nm in names:
            cells = []
            for j, v in enumerate(values[nm]):
                never = notes.get(nm)
                if never is not None and j < len(signals) and never[j]:
                    cells.append(f"≥ {v:.4g} ({never[j]}/{n_samples} never)")
                else:
                    cells.append(float(v))
            rows.append([nm] + cells)
            base = tuned_pairs.get(nm)
            if base is not None:
                change = [_pct(a, b) for a, b in zip(values[nm], values[base])]
                if metric == "settling_time":  # a mean with never-settled samples is only a bound
                    change = [f"never: {notes[base][j]}→{notes[nm][j]}/{n_samples}" if notes[nm][j] or notes[base][j]
                              else c for j, c in enumerate(change)]
                rows.append([f"change of {nm} vs {base}"] + change)
        tables[caption] = (headers, rows)
    return tables


def _pct(after: float, before: float) -> str:
    if before == 0:
        return "n/a" if after == 0 else "+inf %"
    return f"{100.0 * (after - before) / abs(before):+.1f} %"
