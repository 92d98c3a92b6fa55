"""``fojax study``: Monte Carlo study, tuning and comparison of the observers of a config."""

from __future__ import annotations

import concurrent.futures
import hashlib
import json
import pathlib

import numpy as np

from .._background import in_background
from ._common import _default_region, _Progress, _region_words, _Unavailable, figures_available
from ._signals import check as check_interrupted, on_interrupt


def _studies_available() -> bool:
    try:
        import fojax.studies  # noqa: F401
    except ImportError:
        return False
    return True


def _tuning_module():
    try:
        import fojax.tuning as tuning
    except ImportError:
        return None
    return tuning


STUDY_OPTIONS = "study-options.json"


def study(
    config_path: str | None = None,
    out_dir: str | None = None,
    *,
    samples: int | None = None,
    horizon: float | None = None,
    steps: int | None = None,
    resume: str | None = None,
    quiet: bool = False,
    distributed: bool = False,
    result: dict | None = None,
) -> int:
    """``fojax study``: structure check, LMI designs, Monte Carlo study, figures and report.

    Default config: the §3.3.7 benchmark (`fojax/examples/example_3_3_7.toml`). Each
    sample is one joint draw of every random element of the model (a constant δ for
    ``[uncertainty] profile = uniform``, a fault scenario for ``[faults]``: one random
    fault stepping in at a random onset), so exactly ``--samples`` samples are run; a
    model without random elements is one deterministic run (said before running, and
    recorded). See `fojax.cli._study_samples`.

    The results folder holds the config (``config.toml``), the effective options
    (``study-options.json``: samples requested and run with their breakdown, horizon,
    steps, seed, dt, learning rate, the tuning's loss), the samples themselves (``study-samples.npz`` /
    ``.json``: per sample fault, onset, magnitude, δ, initial states; the input), the
    per-sample metrics (``metrics.npz`` / ``.json``: IAE, ISE, ITAE, peak |e|, settling
    time) and the report. With
    `resume` (a folder of an interrupted study) that folder is reused: its config and
    options are read back (a different CONFIG or option is refused), the designs saved in
    it are loaded (bit-identical, so the tuning checkpoint ``tuning-<name>`` refers to
    exactly them), the tuning continues from its checkpoint, and the files the run
    regenerates (tuned designs, study results, metrics, figures, report) are replaced.

    SIGINT/SIGTERM stop the study with exit code 130/143 and leave the folder consistent
    (every file is written atomically; a signal arriving while a tuning checkpoint is
    being written takes effect once that write is complete).

    With `distributed` (``--distributed``, after `fojax.cli._distributed.initialize`) the
    samples are spread over every process's devices; only process 0 writes the folder.

    **Returns:** 0 if every design (and tuned design) passed its verification, else 1.
    `result` (for ``--json``), if given, is filled with the folder, the report, the
    sample plan, the verifications and the mean metrics per observer.
    """
    if distributed:
        from ._distributed import process_folders

        with process_folders(out_dir, resume) as (out_dir, resume, worker):
            return study(config_path, out_dir, samples=samples, horizon=horizon, steps=steps, resume=resume,
                         quiet=quiet or bool(worker), result=None if worker else result)
    if not _studies_available():
        raise _Unavailable(
            "fojax study is not available yet: the Monte Carlo study runner (fojax.studies) is "
            "not part of this fojax version. Use `fojax check` and `fojax design` meanwhile."
        )
    from .._errors import ConfigError, InputError
    from ..config import example_path, load_config, StudySpec, TuningSpec
    from ..results import atomic_write_json, new_results_folder
    from ..results._io import atomic_write_bytes, fojax_version

    out = _Progress(quiet)
    if resume is not None:
        folder, path, cfg = _resume_folder(
            resume, config_path, out_dir, {"samples": samples, "horizon": horizon, "steps": steps}
        )
        opts = json.loads((folder / STUDY_OPTIONS).read_text())
        n_samples, T, n_steps = opts["samples"], opts["horizon"], opts["steps"]
    else:
        path = config_path if config_path is not None else str(example_path("example_3_3_7"))
        cfg = load_config(path)
    from ..config._spec import SPECIAL_KINDS

    special = [(i, o.kind) for i, o in enumerate(cfg.observers) if o.kind in SPECIAL_KINDS]
    if special:
        i, kind = special[0]
        raise ConfigError(path, f"observer[{i}].kind", f"'{kind}' observers have no Monte Carlo study yet "
                          "(the study compares z estimates of generalized/PI/proportional observers); "
                          f"use `fojax design {path}` to design and verify it.")
    if getattr(cfg, "dt", None) is not None:
        raise ConfigError(path, "model.dt", f"is {cfg.dt:g}: fojax study runs continuous-time models only; "
                          f"a discrete-time model is checked and designed with `fojax check {path}` and "
                          f"`fojax design {path}`, and simulated in Python (fojax.simulate).")
    spec = cfg.study or StudySpec()
    tspec = cfg.tuning or TuningSpec()
    if resume is None:
        n_samples = samples if samples is not None else spec.samples
        T = horizon if horizon is not None else spec.horizon
        n_steps = steps if steps is not None else tspec.steps
        if n_samples < 1 or T <= spec.dt or n_steps < 0:
            raise InputError(
                f"--samples must be >= 1, --horizon > dt = {spec.dt} and --steps >= 0; got "
                f"{n_samples}, {T}, {n_steps}."
            )
    options = {"samples": n_samples, "horizon": T, "steps": n_steps, "seed": spec.seed,
               "dt": spec.dt, "learning_rate": tspec.learning_rate, "loss": tspec.loss}
    from ._study_samples import plan_samples

    plan = plan_samples(cfg, n_samples, T, spec.seed)
    if resume is not None:
        changed = [k for k, v in options.items() if opts.get(k) != v]
        if changed:
            raise InputError(
                f"--resume {folder}: its config.toml now gives {', '.join(f'{k} = {options[k]}' for k in changed)} "
                f"but the study was run with {', '.join(f'{k} = {opts[k]}' if k in opts else f'no {k} recorded' for k in changed)} "
                "(defaults of another fojax version?); start a new study instead."
            )
        out.say(f"fojax study: resuming {cfg.name} in {folder} (config.toml and options of the first run: "
                f"{n_samples} samples, horizon {T} s, {n_steps} tuning steps)")
    else:
        folder = new_results_folder(out_dir if out_dir is not None else "fojax-results", prefix=f"study-{cfg.name}")
        on_interrupt(f"{folder} was interrupted while it was being set up (it cannot be resumed); "
                     "delete it and start the study again")
        out.say(f"fojax study: {cfg.name} ({path}) -> results folder {folder}")
        config_bytes = pathlib.Path(path).read_bytes()
        atomic_write_bytes(folder / "config.toml", config_bytes)
        atomic_write_json(folder / STUDY_OPTIONS, {
            "command": "fojax study", "config": str(path), "name": cfg.name,
            "config_sha256": hashlib.sha256(config_bytes).hexdigest(), **options,
            # `samples` is the requested number; what is run, and why:
            "samples_run": plan.run, "sample_plan": plan.to_dict(),
            "fojax_version": fojax_version(), "jax_devices": _devices_line(),
        })
    out.say(f"samples: {plan.message}")
    out.say(f"devices: {_devices_line()}")
    on_interrupt(f"every file in {folder} is complete (tuning checkpoints included). Continue "
                 f"with: fojax study --resume {folder}")
    return _study(out, cfg, path, folder, spec, tspec, plan, T, n_steps, resumed=resume is not None,
                  result=result)


def _devices_line() -> str:
    """The devices the study's samples are spread over (`fojax.cli._devices`)."""
    import jax

    n, kind = jax.device_count(), jax.default_backend()
    return f"{n} JAX {kind} device{'s' if n > 1 else ''}" + (
        f" ({jax.process_count()} processes)" if jax.process_count() > 1 else "")


def _resume_folder(folder, config_path, out_dir, given: dict):
    """Validate ``--resume FOLDER``; returns ``(folder, config path, Config)``."""
    import dataclasses

    from .._errors import InputError
    from ..config import load_config

    folder = pathlib.Path(folder)
    if out_dir is not None:
        raise InputError(f"--resume reuses {folder}; --out cannot be given with it.")
    if not folder.is_dir():
        raise InputError(f"--resume {folder}: no such results folder.")
    saved_config = folder / "config.toml"
    options = folder / STUDY_OPTIONS
    if not saved_config.is_file():
        raise InputError(
            f"--resume {folder}: the folder has no config.toml, so it is not a `fojax study` "
            "results folder; give the folder printed by the interrupted study."
        )
    try:
        opts = json.loads(options.read_text())
        ok = isinstance(opts, dict) and opts.get("command") == "fojax study"
    except (OSError, ValueError):
        ok = False
    if not ok:
        raise InputError(
            f"--resume {folder}: the folder has no readable {STUDY_OPTIONS}, so it was not made by "
            "`fojax study` of this fojax version; start a new study instead."
        )
    if hashlib.sha256(saved_config.read_bytes()).hexdigest() != opts.get("config_sha256"):
        raise InputError(
            f"--resume {folder}: its config.toml was changed after the study in it was started "
            f"(SHA-256 differs from the one in {STUDY_OPTIONS}); start a new study instead."
        )
    if config_path is not None and not pathlib.Path(config_path).is_file():
        raise InputError(f"--resume {folder}: CONFIG {config_path} does not exist; omit it (the "
                         "folder's config.toml is used).")
    if config_path is not None and pathlib.Path(config_path).read_bytes() != saved_config.read_bytes():
        raise InputError(
            f"--resume {folder}: CONFIG {config_path} differs from the config.toml the study in "
            "it was made with; omit CONFIG (the folder's config.toml is used) or start a new study."
        )
    for k, v in given.items():
        if v is not None and v != opts.get(k):
            raise InputError(
                f"--resume {folder}: the study in it was made with --{k} {opts.get(k)}, not {v}; "
                f"omit --{k} (the first run's value is used) or start a new study."
            )
    cfg = load_config(saved_config)
    # the first run's config path and name (a config without `name` is named after its file)
    cfg = dataclasses.replace(cfg, path=opts["config"], name=opts["name"])
    from .._io import register_results_folder

    register_results_folder(folder, continue_run=True)  # writes confined to it, added to its manifest
    return folder, opts["config"], cfg


def _study(out, cfg, path, folder, spec, tspec, plan, T, n_steps, *, resumed: bool, result=None) -> int:
    """The body of `study` (after the results folder is set up); `plan` is the
    `fojax.cli._study_samples.SamplePlan` announced and recorded by `study`."""
    import dataclasses

    from .. import studies
    from ..analysis import structure_report
    from ..design import design_functional_observer, design_ts_observer
    from ..results import (
        atomic_write_json,
        atomic_write_npz,
        plot_error_distributions,
        plot_estimates,
        plot_poles,
        plot_tuning_curve,
        save_design,
        write_metrics,
        write_report,
    )
    from . import _study_samples as ss

    ow = resumed  # a resumed run replaces the files it regenerates
    draw = figures_available(out)

    def figure(caption: str, filename: str, plot, *args, **kw):
        """Draw `plot` into ``<folder>/<filename>`` and list it in the report (with Matplotlib)."""
        if draw:
            plot(*args, path=folder / filename, overwrite=ow, **kw)
            figures[caption] = folder / filename

    reports = [structure_report(sys_, cfg.L) for sys_ in cfg.rule_systems()]
    report = reports[0]
    if cfg.is_takagi_sugeno:  # one verdict per rule
        report = dataclasses.replace(report, verdict="; ".join(
            f"rule {i + 1}: {r.verdict.rstrip('.')}" for i, r in enumerate(reports)) + ".")
    out.say(f"structure: {report.verdict}")
    design_fn = design_ts_observer if cfg.is_takagi_sugeno else design_functional_observer
    from ..config import ObserverSpec

    specs = cfg.observers or (ObserverSpec("generalized", "generalized", _default_region()),)
    designs, figures, files = {}, {}, {}
    for o in specs:
        saved = folder / f"{o.name}.npz"
        if resumed and saved.exists():
            # the design the first run saved (and tuned from): bit-identical to the LMI design
            d = _saved_design(saved, o)
            out.say(f"loaded '{o.name}' ({o.kind}, {o.region.describe()}) saved by the first run")
            files[f"design of '{o.name}'"] = saved
        else:
            with out.step(f"designing '{o.name}' ({o.kind}, {o.region.describe()}) {o.route_words()}"):
                d = design_fn(cfg.design_system(), cfg.design_L(), kind=o.kind,
                              region=o.region, R=o.R, q0=o.q0, q1=o.q1, **o.design_kwargs())
            files[f"design of '{o.name}'"] = save_design(d, saved, overwrite=ow,
                                                         metadata={"config": path, "observer": o.name})
        check_interrupted()
        designs[o.name] = d
        figure(f"Error poles of '{o.name}'", f"poles-{o.name}.png", plot_poles, d.report.eigenvalues, d.region)
        out.say(f"  verification {'PASSED' if d.report.passed else 'FAILED'}")

    # the Monte Carlo study (and separately drawn training studies for the tuning)
    st = ss.make_study(cfg, spec.seed, plan.run, T, spec.dt)
    assert st.num_samples == plan.run, (st.num_samples, plan.run)
    ts = st.ts
    # Explicit Tsit5: the benchmark loops are not stiff (error poles in the designed disks),
    # so an implicit solver (Kvaerno5) would only cost compile and run time for the same
    # metrics.
    import diffrax

    from ..simulation import Auto, Bands, Diffrax, Exact, Exponential, Metrics

    stepper = {"auto": Auto(diffrax=Diffrax(diffrax.Tsit5())), "exact": Exact(), "exponential": Exponential(),
               "diffrax": Diffrax(diffrax.Tsit5())}[spec.stepper]  # [study] stepper
    monte_carlo = dict(stepper=stepper, quiet=out.quiet,
                       save=Metrics(settle_tol=ss.SETTLE_TOL, bands=Bands((0.05, 0.5, 0.95))))
    compiling = None  # the Monte Carlo program, compiled on a thread while the tuning runs
    sample_sets = {"evaluation": st}
    tuning_rows, tuned_pairs, tuning_note = [], {}, "Tuning: not available in this fojax version."
    tuning = _tuning_module()
    if tuning is not None and n_steps > 0:
        from ..design import Disk

        train = ss.make_training_study(cfg, spec.seed + 1, plan, T, spec.dt)
        heldout_small = ss.make_training_study(cfg, spec.seed + 2, plan, T, spec.dt)
        tunable = [nm for nm, d in designs.items() if _tunable(cfg, d, Disk)]
        loss_words = _LOSS_WORDS[tspec.loss]
        if not tunable:
            tuning_note = ("Tuning: no generalized or proportional observer to tune." if cfg.is_takagi_sugeno
                           else "Tuning: no generalized observer with a disk region to tune.")
        elif plan.deterministic:
            tuning_note = (
                f"Tuning: {', '.join(tunable)} tuned for {n_steps} Adam steps (learning rate "
                f"{tspec.learning_rate}) to minimise {loss_words}. The model has no random element, so the training run, the "
                "tuning's held-out curve and the comparison below are the same single simulation: "
                "the comparison is on the training data, nothing is held out.")
        else:
            tuning_note = (
                f"Tuning: {', '.join(tunable)} tuned for {n_steps} Adam steps (learning rate "
                f"{tspec.learning_rate}) to minimise {loss_words} on {train.num_samples} training samples ({plan.training_breakdown}) "
                f"drawn with seed {spec.seed + 1} (held-out curve: {heldout_small.num_samples} samples, seed "
                f"{spec.seed + 2}); the comparison tables use the {st.num_samples} samples of the study, "
                f"drawn with seed {spec.seed}: other random keys than the training draws.")
        if tunable:
            sample_sets["training"] = train
            sample_sets["training_heldout_curve"] = heldout_small
            # the study runs the designs and then the tuned ones (same structures as the designs
            # they are tuned from): its program compiles on a thread while the tuning runs (XLA
            # compiles without the GIL). Not across processes (its collectives).
            import jax

            if jax.process_count() == 1:
                planned = [(nm, nm) for nm in designs] + [(f"{nm}-tuned", nm) for nm in tunable]
                compiling = in_background(lambda: studies.run_study(
                    st, [designs[base].observer for _, base in planned], observer_names=[nm for nm, _ in planned],
                    compile_only=True, **monte_carlo))
        for nm in tunable:
            checkpoint = folder / f"tuning-{nm}"
            done = _checkpoint_step(checkpoint) if resumed else None
            what = (f"{n_steps} gradient steps" if done is None else
                    f"steps {done + 1}..{n_steps} (resumed from the checkpoint at step {done})")
            with out.step(f"tuning '{nm}': {what} on {train.num_samples} training "
                          "samples (compiling the gradient first)"):
                tr = _tune(tuning, cfg, designs[nm], train, heldout=heldout_small, steps=n_steps, loss=tspec.loss,
                           optimizer=tuning.shared_optimizer("adam", learning_rate=tspec.learning_rate),
                           eval_every=max(1, n_steps // 10), callback=_after_step,
                           checkpoint=checkpoint, resume=resumed, quiet=out.quiet,
                           robustness=_robustness_terms(tuning, tspec, designs[nm]))
            tuned_name = f"{nm}-tuned"
            designs[tuned_name] = tr.design
            tuned_pairs[tuned_name] = nm
            files[f"design of '{tuned_name}'"] = save_design(
                tr.design, folder / f"{tuned_name}.npz", overwrite=ow,
                metadata={"config": path, "observer": tuned_name})
            h = tr.history
            held = np.asarray(h["heldout_loss"], dtype=float)
            figure(
                f"Tuning curve of '{nm}'", f"tuning-{nm}.png", plot_tuning_curve, h["step"], h["train_loss"],
                held if np.isfinite(held).any() else None, ylabel=f"{tspec.loss.upper()} loss",
                heldout_before=tr.initial_heldout, heldout_after=tr.final_heldout,
                title=f"Tuning '{nm}': training and held-out loss" if not plan.deterministic else
                f"Tuning '{nm}' (deterministic model: one run, nothing held out)")
            tuning_rows.append([nm, n_steps, float(tr.initial_heldout), float(tr.final_heldout)])
            out.say(f"  {'training-run' if plan.deterministic else 'held-out training-type'} {tspec.loss.upper()} loss "
                    f"{tr.initial_heldout:.4g} -> {tr.final_heldout:.4g}; "
                    f"verification {'PASSED' if tr.design.report.passed else 'FAILED'}; {tr.live_parameters}")
            if tr.robustness is not None:
                out.say("  " + _robustness_line(tr.robustness))

    # what every sample set simulates, per sample (before the long run: nothing is lost if
    # it is interrupted)
    sample_arrays, sample_words, sample_meta = {}, [], {}
    for set_name, study_ in sample_sets.items():
        arrays = ss.describe_samples(study_, cfg, {nm: d.observer for nm, d in designs.items()}
                                     if set_name == "evaluation" else {})
        summary = ss.summarize_samples(arrays)
        sample_arrays.update({f"{set_name}/{k}": v for k, v in arrays.items()})
        sample_meta[set_name] = {"summary": summary, "arrays": {k: list(v.shape) for k, v in arrays.items()}}
        sample_words.append(ss.describe_in_words(summary, set_name.replace("_", " ")))
    files["the samples (per sample: fault, onset, magnitude, δ, initial states; the input)"] = atomic_write_npz(
        folder / "study-samples.npz", sample_arrays, overwrite=ow)
    files["what study-samples.npz holds, with the distributions and seeds"] = atomic_write_json(
        folder / "study-samples.json", {
            "plan": plan.to_dict(), "sets": sample_meta,
            "keys": {"evaluation": f"jax.random.split(PRNGKey({spec.seed})) -> (delta key, fault key)",
                     "training": f"PRNGKey({spec.seed + 1}), split the same way",
                     "training_heldout_curve": f"PRNGKey({spec.seed + 2}), split the same way",
                     **({"takagi_sugeno": "the delta key draws the physical parameters, the fault key the "
                         "initial states, jax.random.fold_in(fault key, 1) the fault scenarios"}
                        if cfg.is_takagi_sugeno else {})},
            "arrays": {
                "ts": "time grid (T,)", "u": "input on the grid (T, m), the same for every sample",
                "x0": "plant initial state per sample as given (N, n); the simulation projects it onto "
                      "the algebraic constraints. For the fault-augmented training set the last nf "
                      "entries are the constant faults",
                "x0_consistent": "the plant state the simulation starts from: x0 projected onto the "
                                 "algebraic constraints (fojax.simulation.consistent_initial_condition) (N, n)",
                "delta": "constant uncertainty δ per sample (N, k)",
                "fault_amplitude": "fault vector after the onset (N, nf)",
                "fault_onset": "onset time [s] (N,)", "fault_rise": "rise time [s] (N,), 0: a step",
                "fault_index": "the active fault (0-based; -1: none or several) (N,)",
                "observer_x0/<name>": "the observer's initial state (the same for every sample)",
            },
        }, overwrite=ow)

    names = list(designs)
    with out.step(f"Monte Carlo study: {st.num_samples} samples x {len(names)} observers, "
                  f"{len(ts)} time steps (compiling first: this takes a while)"):
        if compiling is not None:  # its errors, if any, are the run's own: raised by it below
            concurrent.futures.wait([compiling])
        res = studies.run_study(st, [d.observer for d in designs.values()], observer_names=names, **monte_carlo)
        check_interrupted()  # a signal during the run whose interruption was swallowed
    flat = ss.flat_metrics(res)  # {metric: (observer, sample, signal)}
    # the samples are joint draws along one axis (the Study's fault axis has size 1): save
    # them as such, not as "uncertainty" x "fault"
    res.metrics.update(flat)
    res.axes.update({m: ("observer", "sample", "signal") for m in ("iae", "ise", "itae", "peak", "settling_time")})
    res.axes["success"] = ("sample",)
    res.attrs["samples"] = plan.breakdown
    res.save(folder / "study")
    signals = list(res.coords["signal"])
    failed = int((~flat["success"].astype(bool)).sum())
    failed_note = (f" WARNING: the simulation failed (solver did not reach the horizon) in {failed} of "
                   f"{st.num_samples} samples; their metrics are not meaningful (metrics.npz 'success')."
                   if failed else "")
    if failed:
        out.say(failed_note.strip())
    per_sample = {nm: flat["iae"][k].sum(axis=1) for k, nm in enumerate(names)}
    mean_settle = {nm: ss.mean_settling(flat["settling_time"][k], T) for k, nm in enumerate(names)}
    write_metrics(folder, {
        "signals": ",".join(signals),
        "samples": st.num_samples,
        "samples_requested": plan.requested,
        "settle_tol": ss.SETTLE_TOL,
        **{m: {nm: flat[m][k] for k, nm in enumerate(names)} for m in ("iae", "ise", "itae", "peak", "settling_time")},
        "mean_iae": {nm: flat["iae"][k].mean(axis=0) for k, nm in enumerate(names)},
        "mean_peak": {nm: flat["peak"][k].mean(axis=0) for k, nm in enumerate(names)},
        "mean_settling_time": {nm: v[0] for nm, v in mean_settle.items()},
        "never_settled": {nm: v[1] for nm, v in mean_settle.items()},
        "success": flat["success"],
    }, overwrite=ow)
    q = np.asarray(res.metrics["quantiles"])  # (observer, quantile, time, signal)
    figure(
        "Estimation error, Monte Carlo 5-95 % band and median", "error-bands.png", plot_estimates,
        np.asarray(res.coords["time"]), np.zeros((len(res.coords["time"]), len(signals))),
        {nm: (q[k, 0], q[k, 1], q[k, 2]) for k, nm in enumerate(names)},
        labels=[f"e({s})" for s in signals], truth_label="zero error", title="Estimation error over the Monte Carlo samples",
    )
    figure("IAE per sample (sum over signals)", "iae.png", plot_error_distributions, per_sample,
           ylabel="IAE (sum over signals)")
    tables = ss.metric_tables(flat, names, signals, T, tuned_pairs)
    for row in tuning_rows:  # LMI vs tuned on the study's samples
        base, tuned = names.index(row[0]), names.index(f"{row[0]}-tuned")
        before, after = float(per_sample[row[0]].mean()), float(per_sample[f"{row[0]}-tuned"].mean())
        pb, pa = (float(flat["peak"][i].mean(axis=0).sum()) for i in (base, tuned))
        row += [before, after, 100.0 * (after - before) / before, pb, pa, 100.0 * (pa - pb) / pb]
    where = ("the single deterministic run (also the training run)" if plan.deterministic and tuning_rows
             else "the single deterministic run" if plan.deterministic
             else f"the {st.num_samples} samples of the study")
    if tuning_rows:
        L = tspec.loss.upper()
        tables["Tuning"] = (["observer", "steps", f"held-out {L} loss before" if not plan.deterministic else
                             f"training {L} loss before", "after", "study IAE total, LMI", "tuned", "change %",
                             "sum of mean peaks, LMI", "tuned", "change %"], tuning_rows)
    settle_words = (
        f"IAE is ∫|e| dt (trapezoidal rule on the {spec.dt:g} s grid), peak is max_t |e(t)|, and the "
        f"settling time is the first grid time after which |e| ≤ {ss.SETTLE_TOL:g} (absolute, in the "
        "signal's units) for good, measured from t = 0 (0 if |e| never exceeds it). A sample whose error "
        "still exceeds it at the horizon never settles: it counts as the horizon and the cell says "
        "'≥ ... (k/N never)'. Each table is the mean over " + where + "; a 'change' row compares a "
        "tuned observer with the LMI design it was tuned from, metric by metric (a lower IAE can come "
        "with a larger peak); where samples never settle, the settling change gives their number before → "
        "after instead (the means are then only bounds).")
    rep = write_report(
        folder, title=f"fojax study: {cfg.name}",
        summary=f"{cfg.description}\n\nStructure: {report.verdict}\n\nSamples: {plan.message} "
        f"Horizon {T} s, seed {spec.seed}. " + tuning_note + failed_note,
        tables=tables, figures=figures, files=files, overwrite=ow,
        sections={
            "Metrics": settle_words,
            "Samples": "\n".join(
                ["Random in each sample (drawn jointly, one draw per sample):" if plan.random else
                 "Nothing is random in this model: one deterministic simulation."]
                + [f"- {r}" for r in plan.random]
                + ["", "The same in every sample:"] + [f"- {f}" for f in plan.fixed]
                + ["", "Drawn values (ranges over the samples; every value is in study-samples.npz):"]
                + sample_words
                + ["", f"Keys: evaluation samples from PRNGKey({spec.seed}), training from PRNGKey("
                   f"{spec.seed + 1}), the tuning's held-out curve from PRNGKey({spec.seed + 2}); each key is "
                   "split into a δ key and a fault key. " + (
                       "The model being deterministic, these are all the same run." if plan.deterministic
                       else "The evaluation samples are therefore other draws than the training samples.")]),
        },
    )
    def label(first: str) -> str:  # "change of X-tuned vs X" -> "  change vs X"
        return f"  change vs {first.rsplit(' vs ', 1)[1]}" if first.startswith("change of ") else first

    for caption, (headers, rows) in tables.items():
        if caption == "Tuning":
            continue
        w = max(len("observer"), *(len(label(r[0])) for r in rows))
        out.say("")
        out.say(f"{caption}:")
        out.say(f"{'observer':<{w}}  " + "  ".join(f"{h:>10}" for h in headers[1:]))
        for r in rows:
            out.say(f"{label(r[0]):<{w}}  " + "  ".join(f"{_cell(v):>10}" for v in r[1:]))
        cells = [v for r in rows for v in r[1:] if isinstance(v, str)]
        if any(v.startswith("≥") for v in cells):
            out.say("(≥t(k/N): k of the N samples never settle, counted as the horizon"
                    + ("; n:a→b/N: never-settled samples before -> after tuning)" if any(
                        v.startswith("never:") for v in cells) else ")"))
    for row in tuning_rows:
        out.say(f"tuning '{row[0]}': study IAE total {row[4]:.4g} (LMI) -> {row[5]:.4g} (tuned), "
                f"{row[6]:+.1f} %; sum of mean peaks {row[7]:.4g} -> {row[8]:.4g}, {row[9]:+.1f} %")
    out.say(f"\nresults: {folder} (report: {rep.name})")
    ok = all(d.report.passed for d in designs.values())
    if result is not None:
        from .._serialize import json_safe

        result.update(json_safe({
            "config": str(path), "name": cfg.name, "ok": ok, "folder": str(folder), "report": str(rep),
            "samples": plan.to_dict(), "horizon": T, "steps": n_steps, "signals": signals,
            "simulation_failures": failed,
            "observers": {nm: {"verified": bool(designs[nm].report.passed),
                               "tuned_from": tuned_pairs.get(nm),
                               "mean_iae": flat["iae"][k].mean(axis=0),
                               "mean_peak": flat["peak"][k].mean(axis=0),
                               "mean_settling_time": mean_settle[nm][0],
                               "never_settled": mean_settle[nm][1]}
                          for k, nm in enumerate(names)},
            "tuning": [dict(zip(["observer", "steps", "loss_before", "loss_after", "iae_lmi", "iae_tuned",
                                 "iae_change_percent", "peak_lmi", "peak_tuned", "peak_change_percent"], row))
                       for row in tuning_rows],
        }))
    return 0 if ok else 1


def _tunable(cfg, design, Disk) -> bool:
    """Which designs `fojax study` tunes: LTI generalized designs with a disk region
    (`fojax.tuning.tune`); every generalized or proportional Takagi–Sugeno design
    (`fojax.tune` with the common certificate of any region)."""
    if cfg.is_takagi_sugeno:
        return design.kind in ("generalized", "proportional")
    return design.kind == "generalized" and isinstance(design.region, Disk)


def _robustness_terms(tuning, tspec, design):
    """``[tuning] robustness`` as `fojax.tuning` terms for an ``objective = "hinf"``/``"h2"``
    design (their channels are its certificate's); ``None`` for any other design."""
    if not tspec.robustness or (getattr(design, "hinf", None) is None and getattr(design, "h2", None) is None):
        return None
    make = {"h2": tuning.H2Term, "hinf": tuning.HinfTerm}
    return [make[name](weight) for name, weight in tspec.robustness]


def _robustness_line(rob: dict) -> str:
    """The tuning line's norms of the LMI design and the tuned one (AB13DD ‖T‖∞, the tuned design's
    Riccati-certified γ, SciPy ‖T‖₂)."""
    a, b = rob["initial"], rob["final"]
    terms = ", ".join(rob["terms"]) or "no robustness term"
    gamma = "not certified" if b["gamma"] is None else f"{b['gamma']:.4g}"
    return (f"‖T‖∞ (AB13DD) {a['hinf_norm']:.4g} -> {b['hinf_norm']:.4g} (tuned: certified γ {gamma}), "
            f"‖T‖₂ (SciPy) {a['h2_norm']:.4g} -> {b['h2_norm']:.4g} (d = [w; ν] -> ẑ − z; {terms})")


#: Barrier weight of the T-S tuning of `fojax study` (tests/test_tuning_ts.py uses the same).
TS_BARRIER = 1e-3


#: What `fojax study` says its tuning minimises (`[tuning] loss`).
_LOSS_WORDS = {"ise": "the ISE ∫e² dt of the estimated signals' errors (mean over signals and samples)",
               "iae": "the IAE ∫|e| dt of the estimated signals' errors (mean over signals and samples)"}


def _tune(tuning, cfg, design, train, **kw):
    """The one tuning call of `fojax study`. A Takagi–Sugeno study simulates a nonlinear
    (or T-S) plant with diffrax's explicit Tsit5 (not stiff: error poles in the designed
    region), as the Monte Carlo run below does."""
    if cfg.is_takagi_sugeno:
        import diffrax

        from ..simulation import Auto, Diffrax

        kw.update(stepper=Auto(diffrax=Diffrax(diffrax.Tsit5())), barrier=TS_BARRIER)
    from .. import studies
    from . import _distributed

    exact = studies.exact_refusal(train, (design.observer,), kw.get("stepper")) is None
    return tuning.tune(design, train, devices=_distributed.tuning_devices(exact), **kw)  # LTI and T-S: one `tune`


def _after_step(step, record):
    """The tuning callback of `fojax study`: a signal received during the step ends the
    tuning here (the checkpoint of the previous step is complete), even if the
    interruption it raised was swallowed on the way."""
    check_interrupted()
def _cell(v) -> str:
    """A console table cell: numbers to 4 significant digits, strings shortened."""
    if isinstance(v, str):
        return v.replace(" never)", ")").replace("never: ", "n:").replace(" ", "")
    return f"{v:.4g}"


def _saved_design(path, spec):
    """The design a first run saved for observer `spec` (checked to be that observer's), for
    any `fojax.design.AbstractDesign`: the kind is the design's ``kind`` (generalized, PI,
    proportional) or its class (unknown-input, finite-time: no ``kind`` field), the region
    that of `_design_observer` (the two disks of a finite-time design), and the file's
    metadata is removed from every ``solver`` dict of the tree (a finite-time design has
    none of its own, its two designs have one each)."""
    from .._errors import InputError
    from ..design import FiniteTimeObserverDesign, UnknownInputObserverDesign
    from ..design._base import _mark_saved
    from ..results import load_design, read_design_metadata

    meta = read_design_metadata(path)
    d = load_design(path)
    special = {"unknown-input": UnknownInputObserverDesign, "finite-time": FiniteTimeObserverDesign}
    same_kind = (isinstance(d, special[spec.kind]) if spec.kind in special
                 else getattr(d, "kind", None) == spec.kind)
    region = tuple(spec.regions) if spec.kind == "finite-time" else spec.region
    if meta.get("user", {}).get("observer") != spec.name or not same_kind or d.region != region:
        raise InputError(
            f"{path} is not the design of observer '{spec.name}' ({spec.kind}, "
            f"{_region_words(spec)}) of the folder's config.toml; the folder was changed after "
            "the first run. Start a new study instead."
        )
    _mark_saved(d, None)  # the loaded design is ours: drop the file's metadata in place
    return d


def _checkpoint_step(checkpoint) -> int | None:
    """The step of a tuning checkpoint (``<checkpoint>.json``), or None if there is none."""
    try:
        return int(json.loads(pathlib.Path(f"{checkpoint}.json").read_text())["step"])
    except (OSError, ValueError, KeyError, TypeError):
        return None
