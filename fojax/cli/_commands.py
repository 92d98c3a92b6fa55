"""``fojax check``, ``fojax design`` and ``fojax study`` (config-file commands)."""

from __future__ import annotations

import hashlib
import json
import pathlib
import time

import numpy as np

from ._signals import check as check_interrupted, on_interrupt


class _Progress:
    """Step messages with elapsed times (nothing when quiet)."""

    def __init__(self, quiet: bool):
        self.quiet = quiet

    def say(self, *args):
        if not self.quiet:
            print(*args, flush=True)

    def step(self, message: str):
        progress = self

        class _Step:
            def __enter__(self):
                self.t0 = time.perf_counter()
                progress.say(f"{message} ...")
                return self

            def __exit__(self, *exc):
                if exc[0] is None:
                    progress.say(f"  done in {time.perf_counter() - self.t0:.1f} s")
                return False

        return _Step()


def resolve_config(path: str) -> str:
    """A config path, or the shipped example of that name (``fojax check example_3_3_7``)."""
    from ..config import example_names, example_path

    p = pathlib.Path(path)
    if not p.exists() and p.suffix in ("", ".toml") and p.parent == pathlib.Path(".") and (
        p.stem in example_names()
    ):
        return str(example_path(p.stem))
    return path


def _load(path):
    from ..config import load_config

    return load_config(path)


def examples(quiet: bool = False) -> int:
    """List the shipped example configs."""
    from ..config import example_names, example_path

    for n in example_names():
        print(f"{n:<16} {example_path(n)}")
    return 0


def check(config_path: str, quiet: bool = False) -> int:
    """Print the structural analysis report(s) of the model in `config_path`."""
    from ..analysis import structure_report

    out = _Progress(quiet)
    cfg = _load(config_path)
    out.say(f"fojax check: {cfg.name} ({config_path})")
    if cfg.description:
        out.say(f"  {cfg.description}")
    if cfg.feedback is not None:
        out.say("  model.feedback is given: the plant analysed is (E, A + B K, B, C).")
    out.say("")
    systems = cfg.rule_systems()
    for i, sys_ in enumerate(systems):
        if cfg.is_takagi_sugeno:
            out.say(f"Takagi-Sugeno rule {i + 1} of {len(systems)} (E, A_{i + 1}, B_{i + 1}, C):")
        out.say(structure_report(sys_, cfg.L))
        out.say("")
    if cfg.has_faults:
        aug = cfg.design_system()
        out.say(
            f"Fault-augmented system (eq. 3.196, {aug.n} states) with the functional of the "
            "observers (z and the faults):" if cfg.estimate_faults else
            f"Fault-augmented system (eq. 3.196, {aug.n} states) with the functional [L 0]:"
        )
        out.say(structure_report(aug, cfg.design_L()))
        out.say(
            "  (the augmented system always has poles at 0, the constant fault states: 'NOT "
            "admissible' is expected here; what matters for the observers is observability "
            "and Assumption 1)"
        )
        out.say("")
    if cfg.dA is not None:
        out.say(
            f"Uncertainty: {cfg.dA.shape[0]} direction(s) dA; the reports above are for the "
            "nominal model (delta = 0)."
        )
    return 0


def design(
    config_path: str,
    out_dir: str | None = None,
    *,
    name: str | None = None,
    overwrite: bool = False,
    quiet: bool = False,
) -> int:
    """Design, verify and save every ``[[observer]]`` of `config_path` in a new results folder.

    For a Takagi–Sugeno model (``[takagi_sugeno]``) every observer is a Takagi–Sugeno
    functional observer (`fojax.design.design_ts_observer`: one common $T$, per-rule
    gains, a common certificate for all rules); otherwise
    `fojax.design.design_functional_observer` on the (fault-augmented) system.
    """
    from .._errors import ConfigError
    from ..design import design_functional_observer, design_ts_observer
    from ..results import (
        atomic_write_json,
        new_results_folder,
        plot_poles,
        save_design,
        write_report,
    )
    from ..results._io import atomic_write_bytes

    out = _Progress(quiet)
    cfg = _load(config_path)
    if cfg.is_takagi_sugeno and cfg.has_faults:
        raise ConfigError(
            config_path,
            "faults",
            "fault estimation for Takagi-Sugeno models is not available; remove [faults] to "
            "design Takagi-Sugeno functional observers of z = L x.",
        )
    from ..config import ObserverSpec

    observers = cfg.observers or (ObserverSpec("generalized", "generalized", _default_region()),)
    sys_ = cfg.design_system()
    L = cfg.design_L()
    folder = new_results_folder(
        out_dir if out_dir is not None else "fojax-results",
        prefix=f"design-{cfg.name}",
        name=name,
        overwrite=overwrite,
    )
    out.say(f"fojax design: {cfg.name} -> results folder {folder}")
    atomic_write_bytes(folder / "config.toml", pathlib.Path(config_path).read_bytes(), overwrite=overwrite)
    if cfg.has_faults:
        out.say(f"  designing for the fault-augmented system ({sys_.n} states), functional {L.shape[0]} x {L.shape[1]}")
    if cfg.is_takagi_sugeno:
        out.say(f"  Takagi-Sugeno model with {sys_.num_rules} rules: one observer per [[observer]] with "
                "a common T and per-rule gains, error poles of every rule (and every convex "
                "combination) in the region")
    design_fn = design_ts_observer if cfg.is_takagi_sugeno else design_functional_observer
    rows, figures, files, summary = [], {}, {}, []
    all_passed = True
    for spec in observers:
        with out.step(
            f"designing observer '{spec.name}' ({spec.kind}, error poles in "
            f"{spec.region.describe()}): structure checks, LMI solve, float64 verification"
        ):
            d = design_fn(
                sys_, L, kind=spec.kind, region=spec.region, R=spec.R, q0=spec.q0, q1=spec.q1
            )
        out.say(f"  {d}")
        path = save_design(
            d,
            folder / f"{spec.name}.npz",
            overwrite=overwrite,
            metadata={"config": str(config_path), "config_name": cfg.name, "observer": spec.name},
        )
        png = plot_poles(
            folder / f"poles-{spec.name}.png",
            d.report.eigenvalues,
            d.region,
            title=f"{cfg.name}: error poles of '{spec.name}' ({spec.kind})",
            overwrite=overwrite,
        )
        all_passed &= bool(d.report.passed)
        eig = np.asarray(d.report.eigenvalues)
        rows.append(
            [spec.name, spec.kind, d.observer.q0, d.observer.q1, d.region.describe(),
             float(np.max(eig.real)) if eig.size else float("nan"),
             float(d.report.relative_residual), d.report.passed]
        )
        figures[f"Error poles of '{spec.name}'"] = png
        files[f"design of '{spec.name}' (fojax.results.load_design)"] = path
        summary.append({"name": spec.name, "file": path.name, **d.report.to_dict(),
                        "kind": spec.kind, "q0": d.observer.q0, "q1": d.observer.q1})
        out.say(f"  saved {path}")
    atomic_write_json(folder / "designs.json", {"config": str(config_path), "designs": summary}, overwrite=overwrite)
    files["verification summary"] = folder / "designs.json"
    files["the config file used"] = folder / "config.toml"
    headers = ["observer", "kind", "q0", "q1", "region", "max Re(eig)", "relative residual", "verified"]
    report = write_report(
        folder,
        title=f"fojax design: {cfg.name}",
        summary=(cfg.description or "") + f"\n\nConfig: `{config_path}`. Every design below was "
        "verified in float64 (design-condition residuals, eigenvalues in the region, LMI "
        "re-check at the certificate).",
        tables={"Designs": (headers, rows)},
        figures=figures,
        files=files,
        overwrite=overwrite,
    )
    width = max([len("observer")] + [len(r[0]) for r in rows])
    out.say("")
    out.say(f"{'observer':<{width}}  kind          q0  q1  max Re(eig)  verified")
    for r in rows:
        out.say(f"{r[0]:<{width}}  {r[1]:<12}  {r[2]:>2}  {r[3]:>2}  {r[5]:>11.4g}  {'yes' if r[7] else 'NO'}")
    out.say(f"\nresults: {folder} (report: {report.name})")
    return 0 if all_passed else 1


def _default_region():
    from ..design import Disk

    return Disk(-2.0, 1.0)


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
) -> int:
    """``fojax study``: structure check, LMI designs, Monte Carlo study, figures and report.

    Default config: the §3.3.7 benchmark (`fojax/examples/example_3_3_7.toml`). The
    samples are ``N_u`` uncertainty draws (``[uncertainty] profile = uniform``) times
    ``N_f`` fault scenarios (4 when ``[faults]`` is given: one random fault with a random
    onset each), ``N_u N_f ≈ [study] samples``.

    The results folder holds the config (``config.toml``) and the effective options
    (``study-options.json``: samples, horizon, steps, seed, dt, learning rate). With
    `resume` (a folder of an interrupted study) that folder is reused: its config and
    options are read back (a different CONFIG or option is refused), the designs saved in
    it are loaded (bit-identical, so the tuning checkpoint ``tuning-<name>`` refers to
    exactly them), the tuning continues from its checkpoint, and the files the run
    regenerates (tuned designs, study results, metrics, figures, report) are replaced.

    SIGINT/SIGTERM stop the study with exit code 130/143 and leave the folder consistent
    (every file is written atomically; a signal arriving while a tuning checkpoint is
    being written takes effect once that write is complete).
    """
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
    if cfg.is_takagi_sugeno:
        raise ConfigError(path, "takagi_sugeno", "studies of Takagi-Sugeno models are not available from config files yet.")
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
               "dt": spec.dt, "learning_rate": tspec.learning_rate}
    if resume is not None:
        changed = [k for k, v in options.items() if opts.get(k) != v]
        if changed:
            raise InputError(
                f"--resume {folder}: its config.toml now gives {', '.join(f'{k} = {options[k]}' for k in changed)} "
                f"but the study was run with {', '.join(f'{k} = {opts.get(k)}' for k in changed)} "
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
            "fojax_version": fojax_version(),
        })
    on_interrupt(f"every file in {folder} is complete (tuning checkpoints included). Continue "
                 f"with: fojax study --resume {folder}")
    return _study(out, cfg, path, folder, spec, tspec, n_samples, T, n_steps, resumed=resume is not None)


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
    return folder, opts["config"], cfg


def _study(out, cfg, path, folder, spec, tspec, n_samples, T, n_steps, *, resumed: bool) -> int:
    """The body of `study` (after the results folder is set up)."""
    import jax
    import jax.numpy as jnp

    from .. import studies
    from ..analysis import structure_report
    from ..design import design_functional_observer
    from ..plant import Sine
    from ..results import (
        plot_error_distributions,
        plot_estimates,
        plot_poles,
        save_design,
        write_metrics,
        write_report,
    )

    ow = resumed  # a resumed run replaces the files it regenerates
    report = structure_report(cfg.system(), cfg.L)
    out.say(f"structure: {report.verdict}")
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
            with out.step(f"designing '{o.name}' ({o.kind}, {o.region.describe()}) by LMI"):
                d = design_functional_observer(cfg.design_system(), cfg.design_L(), kind=o.kind,
                                               region=o.region, R=o.R, q0=o.q0, q1=o.q1)
            files[f"design of '{o.name}'"] = save_design(d, saved, overwrite=ow,
                                                         metadata={"config": path, "observer": o.name})
        check_interrupted()
        designs[o.name] = d
        figures[f"Error poles of '{o.name}'"] = plot_poles(folder / f"poles-{o.name}.png",
                                                           d.report.eigenvalues, d.region, overwrite=ow)
        out.say(f"  verification {'PASSED' if d.report.passed else 'FAILED'}")

    # the Monte Carlo study (and a separately drawn training study for the tuning)
    n_f = 4 if cfg.has_faults else 1
    n_u = max(1, n_samples // n_f)

    def make_study(seed, n_u, n_f):
        k_u, k_f = jax.random.split(jax.random.PRNGKey(seed))
        plant = cfg.plant()
        uncertainty, scenarios, prefix = (), (), ("plant",)
        if cfg.has_faults:
            nf = (cfg.Fa if cfg.Fa is not None else cfg.Fs).shape[1]
            plant = studies.FaultyPlant(plant, cfg.Fa, cfg.Fs, fault=studies.FaultProfile(jnp.zeros(nf)))
            scenarios = (studies.fault_scenarios(k_f, n_f, nf, magnitude=(0.5, 1.5),
                                                 onset=(0.1 * T, 0.4 * T)),)
            prefix = ("plant", "base")
        if cfg.dA is not None and (cfg.profile or {}).get("kind") == "uniform":
            b = float(cfg.profile["bound"])
            uncertainty = (studies.constant_delta(k_u, n_u, cfg.dA.shape[0], bounds=(-b, b),
                                                  path=prefix + ("delta",)),)
        x0 = jnp.asarray(cfg.x0) if cfg.x0 is not None else jnp.full((cfg.n,), 0.5)
        ts = jnp.arange(0.0, T + 0.5 * spec.dt, spec.dt)
        u = Sine(jnp.ones(cfg.B.shape[-1]), 1.0)
        return studies.Study(plant, x0, ts, cfg.L, u, uncertainty=uncertainty, scenarios=scenarios,
                             fault_targets=cfg.has_faults and cfg.estimate_faults)

    def make_training_study(seed, n_u, n_f):
        """The study the gradient tuning runs on. For a fault-augmented LTI model with a
        uniform (constant) δ it is the *augmented* system (faults as constant states with
        random values from t = 0) on a [0, min(T, 4)] s grid of 0.05 s: linear and
        time-invariant, so simulated by exact stepping, whose gradient is cheap; otherwise
        the study itself (diffrax; much slower to differentiate)."""
        profile = (cfg.profile or {}).get("kind")
        if not (cfg.has_faults and not cfg.ramp and profile in (None, "uniform")):
            return make_study(seed, n_u, n_f)
        from ..plant import Constant, UncertainDescriptorSystem

        k_u, k_f = jax.random.split(jax.random.PRNGKey(seed))
        aug = cfg.design_system()
        nf = aug.n - cfg.n
        x0 = jnp.asarray(cfg.x0) if cfg.x0 is not None else jnp.full((cfg.n,), 0.5)
        x0 = jnp.concatenate([x0, jnp.zeros(nf)])
        uncertainty, plant = (), aug
        if cfg.dA is not None:
            k = cfg.dA.shape[0]
            dA = np.zeros((k, aug.n, aug.n))
            dA[:, : cfg.n, : cfg.n] = cfg.dA
            plant = UncertainDescriptorSystem(aug, dA=dA, delta=Constant(jnp.zeros(k)))
            if profile == "uniform":
                b = float(cfg.profile["bound"])
                uncertainty = (studies.constant_delta(k_u, n_u, k, bounds=(-b, b)),)
        # the error is linear in the fault: many fault directions, few δ values
        scenarios = (studies.constant_faults(k_f, max(n_f, 32), x0, nf, magnitude=(0.5, 1.5)),)
        h = max(spec.dt, 0.05)
        ts_train = jnp.arange(0.0, min(T, 4.0) + 0.5 * h, h)
        u = Sine(jnp.ones(cfg.B.shape[-1]), 1.0)
        return studies.Study(plant, x0, ts_train, cfg.design_L(), u, uncertainty=uncertainty,
                             scenarios=scenarios)

    st = make_study(spec.seed, n_u, n_f)
    ts = st.ts
    tuning_rows, tuning_note = [], "Tuning: not available in this fojax version."
    tuning = _tuning_module()
    if tuning is not None and n_steps > 0:
        from ..design import Disk
        from ..results import plot_tuning_curve

        train = make_training_study(spec.seed + 1, max(1, n_u // 4), n_f)
        heldout_small = make_training_study(spec.seed + 2, max(1, n_u // 4), n_f)
        tunable = [nm for nm, d in designs.items() if d.kind == "generalized" and isinstance(d.region, Disk)]
        tuning_note = ("Tuning: no generalized observer with a disk region to tune."
                       if not tunable else
                       f"Tuning: {', '.join(tunable)} tuned for {n_steps} Adam steps (learning rate "
                       f"{tspec.learning_rate}) on {train.num_samples} training samples drawn with seed "
                       f"{spec.seed + 1} (held-out curve: {heldout_small.num_samples} samples, seed "
                       f"{spec.seed + 2}); the comparison table uses the {st.num_samples} samples of the "
                       "study, never seen in training.")
        for nm in tunable:
            checkpoint = folder / f"tuning-{nm}"
            done = _checkpoint_step(checkpoint) if resumed else None
            what = (f"{n_steps} gradient steps" if done is None else
                    f"steps {done + 1}..{n_steps} (resumed from the checkpoint at step {done})")
            with out.step(f"tuning '{nm}': {what} on {train.num_samples} training "
                          "samples (compiling the gradient first)"):
                tr = tuning.tune(designs[nm], train, heldout=heldout_small, steps=n_steps,
                                 optimizer=tuning.shared_optimizer("adam", learning_rate=tspec.learning_rate),
                                 eval_every=max(1, n_steps // 10), callback=_after_step,
                                 checkpoint=checkpoint, resume=resumed, quiet=out.quiet)
            tuned_name = f"{nm}-tuned"
            designs[tuned_name] = tr.design
            files[f"design of '{tuned_name}'"] = save_design(
                tr.design, folder / f"{tuned_name}.npz", overwrite=ow,
                metadata={"config": path, "observer": tuned_name})
            h = tr.history
            held = np.asarray(h["heldout_loss"], dtype=float)
            figures[f"Tuning curve of '{nm}'"] = plot_tuning_curve(
                folder / f"tuning-{nm}.png", h["step"], h["train_loss"],
                held if np.isfinite(held).any() else None, ylabel="IAE loss",
                title=f"Tuning '{nm}': training and held-out loss", overwrite=ow)
            tuning_rows.append([nm, n_steps, float(tr.initial_heldout), float(tr.final_heldout)])
            out.say(f"  held-out training-type loss {tr.initial_heldout:.4g} -> {tr.final_heldout:.4g}; "
                    f"verification {'PASSED' if tr.design.report.passed else 'FAILED'}")
    names = list(designs)
    with out.step(f"Monte Carlo study: {st.num_samples} samples x {len(names)} observers, "
                  f"{len(ts)} time steps (compiling first: this takes a while)"):
        # Explicit Tsit5: the benchmark loops are not stiff (error poles in the designed disks)
        # and the implicit default (Kvaerno5; works in studies since the issue-5 fix) is much
        # slower here. Measured with `fojax study --samples 16 --horizon 2 --steps 0` on the
        # 2 shared cores: first run_study call (compile + run) ~33 s vs ~12 s CPU time
        # (49-80 s vs 17-21 s wall), a second call 0.2-0.5 s vs 0.06-0.13 s; mean IAEs
        # agree to ~1e-6.
        import diffrax

        res = studies.run_study(st, [d.observer for d in designs.values()], observer_names=names,
                                quantiles=(0.05, 0.5, 0.95), quiet=out.quiet, solver=diffrax.Tsit5())
        check_interrupted()  # a signal during the run whose interruption was swallowed
    res.save(folder / "study")
    iae = np.asarray(res.metrics["iae"])  # (observer, uncertainty, fault, signal)
    signals = list(res.coords["signal"])
    per_sample = {nm: iae[k].reshape(-1, iae.shape[-1]).sum(axis=1) for k, nm in enumerate(names)}
    flat = {nm: iae[k].reshape(-1, iae.shape[-1]) for k, nm in enumerate(names)}
    write_metrics(folder, {
        "signals": ",".join(signals),
        "samples": st.num_samples,
        "iae": flat,
        "mean_iae": {nm: v.mean(axis=0) for nm, v in flat.items()},
    }, overwrite=ow)
    q = np.asarray(res.metrics["quantiles"])  # (observer, quantile, time, signal)
    figures["Estimation error, Monte Carlo 5-95 % band and median"] = plot_estimates(
        folder / "error-bands.png", np.asarray(ts), np.zeros((len(ts), len(signals))),
        {nm: (q[k, 0], q[k, 1], q[k, 2]) for k, nm in enumerate(names)},
        labels=[f"e({s})" for s in signals], truth_label="zero error", title="Estimation error over the Monte Carlo samples",
        overwrite=ow,
    )
    figures["IAE per sample (sum over signals)"] = plot_error_distributions(
        folder / "iae.png", per_sample, ylabel="IAE (sum over signals)", overwrite=ow)
    rows = [[nm] + [float(v) for v in flat[nm].mean(axis=0)] + [float(per_sample[nm].mean())]
            for nm in names]
    headers = ["observer"] + [f"IAE {s}" for s in signals] + ["IAE total"]
    for row in tuning_rows:  # the study's own samples (never seen in training): LMI vs tuned
        before, after = float(per_sample[row[0]].mean()), float(per_sample[f"{row[0]}-tuned"].mean())
        row += [before, after, 100.0 * (after - before) / before]
    rep = write_report(
        folder, title=f"fojax study: {cfg.name}",
        summary=f"{cfg.description}\n\nStructure: {report.verdict}\n\n{st.num_samples} samples "
        f"({st.num_uncertainty} uncertainty draws x {st.num_scenarios} fault scenarios), horizon {T} s, "
        f"seed {spec.seed}. " + tuning_note,
        tables={"Mean IAE over the samples": (headers, rows),
                **({"Tuning": (["observer", "steps", "held-out loss before", "after",
                                "study IAE total, LMI", "tuned", "change %"], tuning_rows)}
                   if tuning_rows else {})},
        figures=figures, files=files, overwrite=ow,
    )
    w = max(len("observer"), *(len(n) for n in names))
    out.say("")
    out.say(f"{'observer':<{w}}  " + "  ".join(f"{s:>9}" for s in signals) + "      total   (mean IAE)")
    for r in rows:
        out.say(f"{r[0]:<{w}}  " + "  ".join(f"{v:9.4g}" for v in r[1:-1]) + f"  {r[-1]:9.4g}")
    for row in tuning_rows:
        out.say(f"tuning '{row[0]}': study IAE total {row[4]:.4g} (LMI) -> {row[5]:.4g} (tuned), "
                f"{row[6]:+.1f} %")
    out.say(f"\nresults: {folder} (report: {rep.name})")
    return 0 if all(d.report.passed for d in designs.values()) else 1


def _after_step(step, record):
    """The tuning callback of `fojax study`: a signal received during the step ends the
    tuning here (the checkpoint of the previous step is complete), even if the
    interruption it raised was swallowed on the way."""
    check_interrupted()


def _saved_design(path, spec):
    """The design a first run saved for observer `spec` (checked to be that observer's)."""
    import dataclasses

    from .._errors import InputError
    from ..results import load_design, read_design_metadata

    meta = read_design_metadata(path)
    d = load_design(path)
    if (meta.get("user", {}).get("observer") != spec.name or getattr(d, "kind", None) != spec.kind
            or d.region != spec.region):
        raise InputError(
            f"{path} is not the design of observer '{spec.name}' ({spec.kind}, "
            f"{spec.region.describe()}) of the folder's config.toml; the folder was changed after "
            "the first run. Start a new study instead."
        )
    return dataclasses.replace(d, solver={k: v for k, v in d.solver.items() if k != "saved"})


def _checkpoint_step(checkpoint) -> int | None:
    """The step of a tuning checkpoint (``<checkpoint>.json``), or None if there is none."""
    try:
        return int(json.loads(pathlib.Path(f"{checkpoint}.json").read_text())["step"])
    except (OSError, ValueError, KeyError, TypeError):
        return None


class _Unavailable(Exception):
    """A command that is not available in this installation (exit code 3)."""
