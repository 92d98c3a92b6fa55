"""``fojax check``, ``fojax design`` and ``fojax study`` (config-file commands)."""

from __future__ import annotations

import concurrent.futures
import hashlib
import json
import pathlib
import time

import numpy as np

from .._background import in_background
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
    """List the shipped example configs: name and one-line description (the file's own
    ``description``), then the folder that holds them."""
    import tomllib

    from ..config import example_names, example_path

    names = example_names()
    width = max((len(n) for n in names), default=0)
    for n in names:
        path = example_path(n)
        try:
            with open(path, "rb") as f:
                text = str(tomllib.load(f).get("description", "")).strip()
        except (OSError, tomllib.TOMLDecodeError) as err:  # a broken shipped file is a bug: say so
            text = f"(cannot read the file: {type(err).__name__})"
        print(f"{n:<{width}}  {text.splitlines()[0] if text else '(no description)'}")
    if names:
        print(f"\nfiles: {example_path(names[0]).parent}/<name>.toml")
    if not quiet:
        print("use one by name (`fojax check example_3_3_7`, `fojax design example_4_1_3`) or copy "
              "its file to start your own model (format: docs/config.md).")
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
    if cfg.augments_faults:
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
    elif cfg.has_faults:  # Takagi-Sugeno: faults of the simulated plant only
        out.say("Faults ([faults]): they act on the simulated plant in `fojax study`; the "
                "Takagi-Sugeno observers estimate z = L x only (no fault-augmented T-S design).")
        out.say("")
    if cfg.dA is not None:
        out.say(
            f"Uncertainty: {cfg.dA.shape[0]} direction(s) dA; the reports above are for the "
            "nominal model (delta = 0)."
        )
    return 0


def _one_line(err: BaseException) -> str:
    return " ".join(str(err).split("\n")[0].split())


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

    Every observer is designed even when another one fails: a design that raises a
    `fojax.FojaxError` (existence condition, LMI infeasible, verification failed) is
    reported by name on stderr (``fojax: observer 'po': LMIInfeasibleError: ...``), in
    ``report.md`` and in ``designs.json`` (``status``, ``error``, ``message``); the others
    are saved and plotted as usual. Any other exception (a bug) or an interrupt stops the
    run, after writing a report that says so. ``report.md`` and ``designs.json`` are
    always written.

    **Returns:** 0 if every observer was designed and verified, 1 otherwise.
    """
    import sys

    from .._errors import FojaxError, InputError
    from .._io import folder_manifest, name_problem, NAME_RULE, suggest_name
    from ..design import design_functional_observer, design_ts_observer
    from ..results import (
        atomic_write_json,
        new_results_folder,
        plot_poles,
        save_design,
        write_report,
    )
    from ..results._io import atomic_write_bytes

    if name is not None and name_problem(name) is not None:  # before any work
        raise InputError(
            f"--name {name!r} cannot be used: {name_problem(name)}. The {NAME_RULE}; e.g. "
            f"--name {suggest_name(name, 'run1')}. (--out may be any path: the results folder "
            "is created inside it.)"
        )
    out = _Progress(quiet)
    cfg = _load(config_path)
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
    replaced = (folder_manifest(folder) or {}).get("replaced_previous_run")
    if replaced:
        out.say(f"  --overwrite: removed the {len(replaced['removed'])} file(s) of the previous run"
                + (f"; kept {', '.join(replaced['kept_changed'])} (changed since that run wrote them)"
                   if replaced["kept_changed"] else ""))
    atomic_write_bytes(folder / "config.toml", pathlib.Path(config_path).read_bytes(), overwrite=overwrite)
    if cfg.augments_faults:
        out.say(f"  designing for the fault-augmented system ({sys_.n} states), functional {L.shape[0]} x {L.shape[1]}")
    if cfg.is_takagi_sugeno:
        out.say(f"  Takagi-Sugeno model with {sys_.num_rules} rules: one observer per [[observer]] with "
                "a common T and per-rule gains, error poles of every rule (and every convex "
                "combination) in the region")
    design_fn = design_ts_observer if cfg.is_takagi_sugeno else design_functional_observer
    rows, figures, files, summary, failed = [], {}, {}, [], {}

    def finish(aborted: BaseException | None = None) -> pathlib.Path:
        """designs.json and report.md of what was done (also when the run is aborted)."""
        n_ok = sum(1 for e in summary if e["status"] == "verified")
        verdict = (f"{n_ok} of {len(observers)} observer(s) designed and verified in float64 "
                   "(design-condition residuals, eigenvalues in the region, LMI re-check at the "
                   "certificate)")
        if failed:
            verdict += f"; {len(failed)} could not be designed: {', '.join(failed)} (see 'Failed designs')"
        if aborted is not None:
            verdict += (f". The run was ABORTED by {type(aborted).__name__}: {_one_line(aborted)}; "
                        f"observers not listed below were not designed")
        atomic_write_json(folder / "designs.json", {
            "config": str(config_path), "status": "aborted" if aborted is not None else "complete",
            **({"aborted": {"error": type(aborted).__name__, "message": str(aborted)}} if aborted is not None else {}),
            "designs": summary,
        }, overwrite=overwrite)
        files["verification summary"] = folder / "designs.json"
        files["the config file used"] = folder / "config.toml"
        headers = ["observer", "kind", "q0", "q1", "region", "route", "max Re(eig)", "relative residual", "verified"]
        sections = {"Failed designs": "\n\n".join(
            f"- **{nm}**: `{err_type}`: {msg}" for nm, (err_type, msg) in failed.items())} if failed else {}
        return write_report(
            folder,
            title=f"fojax design: {cfg.name}",
            summary=(cfg.description or "") + f"\n\nConfig: `{config_path}`. {verdict}.",
            tables={"Designs": (headers, rows), **_hinf_table(summary), **_h2_table(summary)},
            figures=figures,
            files=files,
            sections=sections,
            overwrite=overwrite,
        )

    try:
        for spec in observers:
            try:
                with out.step(
                    f"designing observer '{spec.name}' ({spec.kind}, error poles in "
                    f"{_region_words(spec)}): structure checks, design {spec.route_words()}, float64 verification"
                ):
                    d = _design_observer(design_fn, sys_, L, spec)
            except FojaxError as err:  # this observer failed; design the others
                kind = type(err).__name__
                print(f"fojax: observer '{spec.name}': {kind}: {_one_line(err)}", file=sys.stderr, flush=True)
                failed[spec.name] = (kind, " ".join(str(err).split()))
                rows.append([spec.name, spec.kind, "-", "-", _region_words(spec), "-", float("nan"),
                             float("nan"), f"FAILED ({kind})"])
                summary.append({"name": spec.name, "kind": spec.kind, "status": "failed",
                                "region": _region_words(spec), "error": kind, "message": str(err)})
                continue
            out.say(f"  {d}")
            live = _live_parameters(d)
            if live is not None:
                out.say(f"  {live}")
            path = save_design(
                d,
                folder / f"{spec.name}.npz",
                overwrite=overwrite,
                metadata={"config": str(config_path), "config_name": cfg.name, "observer": spec.name},
            )
            view = _DesignView.of(d)
            png = plot_poles(
                folder / f"poles-{spec.name}.png",
                view.eigenvalues,
                view.region,
                title=f"{cfg.name}: error poles of '{spec.name}' ({spec.kind})" + view.title_note,
                overwrite=overwrite,
            )
            eig = np.asarray(view.eigenvalues)
            rows.append(
                [spec.name, spec.kind, view.q0, view.q1, view.region_words, _route(d),
                 float(np.max(eig.real)) if eig.size else float("nan"),
                 view.relative_residual, view.passed]
            )
            figures[f"Error poles of '{spec.name}'"] = png
            files[f"design of '{spec.name}' (fojax.results.load_design)"] = path
            summary.append({"name": spec.name, "file": path.name,
                            "status": "verified" if view.passed else "not verified",
                            **view.report, "kind": spec.kind, "route": _route(d), "q0": view.q0, "q1": view.q1,
                            **{k: _certificate_dict(getattr(d, k)) for k in ("hinf", "h2")
                               if getattr(d, k, None) is not None},
                            **({"live_parameters": {"live": live.live, "free": live.total,
                                                    "live_blocks": list(live.live_blocks()),
                                                    "void_generalized": live.void_generalized}}
                               if live is not None else {})})
            out.say(f"  saved {path}")
    except BaseException as err:  # a bug or an interrupt: say so in the folder, then stop
        import contextlib

        with contextlib.suppress(Exception):
            finish(aborted=err)
        raise
    report = finish()
    width = max([len("observer")] + [len(r[0]) for r in rows])
    out.say("")
    out.say(f"{'observer':<{width}}  kind          q0  q1  route     max Re(eig)  verified")
    for r in rows:
        verified = r[8] if isinstance(r[8], str) else ("yes" if r[8] else "NO")
        out.say(f"{r[0]:<{width}}  {r[1]:<12}  {r[2]:>2}  {r[3]:>2}  {r[5]:<8}  {r[6]:>11.4g}  {verified}")
    for name, row in zip(*_hinf_rows(summary)):
        out.say(f"{name}: H∞ bound gamma = {row[1]:.6g} >= ||T||inf = {row[2]:.6g} (SLICOT AB13DD, peak at "
                f"{row[3]:.4g} rad/s, tightness {row[4]:.4f}; region-only design {row[5]:.6g})")
    for row in _h2_rows(summary):
        out.say(f"{row[0]}: H2 bound nu = {row[1]:.6g} >= ||T||2 = {row[2]:.6g} (SciPy Lyapunov, tightness "
                f"{row[3]:.4f}; region-only design {row[4]:.6g})")
    out.say(f"\nresults: {folder} (report: {report.name})")
    if failed:
        print(f"fojax: {len(failed)} of {len(observers)} observer(s) of {config_path} could not be designed "
              f"({', '.join(failed)}); the others are saved in {folder}, the reasons are in its report.md.",
              file=sys.stderr, flush=True)
    all_ok = not failed and all(e["status"] == "verified" for e in summary)
    return 0 if all_ok else 1


def _live_parameters(d):
    """`fojax.design.live_parameters` of a generalized/PI/proportional or T-S design, else ``None``."""
    from ..design import FunctionalObserverDesign, live_parameters, TakagiSugenoObserverDesign

    return live_parameters(d) if isinstance(d, FunctionalObserverDesign | TakagiSugenoObserverDesign) else None


def _certificate_dict(cert) -> dict:
    """An H∞/H2 certificate (a dataclass) as designs.json stores it: every field, arrays as lists
    of rows, a non-finite float as ``None`` (`fojax._serialize.json_safe` otherwise)."""
    import dataclasses

    from .._serialize import json_safe

    return {k: None if isinstance(v, float) and not np.isfinite(v) else json_safe(v)
            for k, v in dataclasses.asdict(cert).items()}


def _hinf_rows(summary) -> tuple[list, list]:
    """Names and rows of the ``objective = "hinf"`` designs of a `design` summary."""
    names, rows = [], []
    for e in summary:
        h = e.get("hinf")
        if h:
            names.append(e["name"])
            rows.append([e["name"], h["gamma"], h["norm"], h["peak_frequency"], h["tightness"],
                         h["region_only_norm"]])
    return names, rows


def _hinf_table(summary) -> dict:
    """The report's "H∞ bounds" table (empty dict if no design has one)."""
    _, rows = _hinf_rows(summary)
    if not rows:
        return {}
    headers = ["observer", "γ (certified bound)", "‖T‖∞ (SLICOT AB13DD)", "peak ω [rad/s]",
               "tightness γ/‖T‖∞", "‖T‖∞ of the region-only design"]
    return {"H∞ bounds (d = [w; ν] → ẑ − z)": (headers, rows)}


def _h2_rows(summary) -> list:
    """Rows of the ``objective = "h2"`` designs of a `design` summary (``inf``: the region-only
    design has a feedthrough, so an infinite H2 norm)."""
    inf = (lambda x: float("inf") if x is None else x)
    return [[e["name"], e["h2"]["nu"], e["h2"]["norm"], inf(e["h2"]["tightness"]), inf(e["h2"]["region_only_norm"])]
            for e in summary if e.get("h2")]


def _h2_table(summary) -> dict:
    """The report's "H2 bounds" table (empty dict if no design has one)."""
    rows = _h2_rows(summary)
    if not rows:
        return {}
    headers = ["observer", "ν (certified bound)", "‖T‖₂ (SciPy Lyapunov)", "tightness ν/‖T‖₂",
               "‖T‖₂ of the region-only design"]
    return {"H2 bounds (d = [w; ν] → ẑ − z)": (headers, rows)}


def _region_words(spec) -> str:
    if spec.kind == "finite-time":
        return " and ".join(r.describe() for r in spec.regions)
    return spec.region.describe()


def _design_observer(design_fn, sys_, L, spec):
    """Design one ``[[observer]]``: `design_fn` (LTI or T-S) for the generalized, PI and
    proportional kinds; the unknown-input (§3.2) and finite-time (§3.1.2) routines for theirs."""
    from ..design import design_finite_time_observer, design_unknown_input_observer

    if spec.kind == "unknown-input":
        return design_unknown_input_observer(sys_, spec.D, L, region=spec.region, R=spec.R, q0=spec.q0, q1=spec.q1,
                                             **({} if spec.balance is None else {"balance": spec.balance}))
    if spec.kind == "finite-time":
        return design_finite_time_observer(sys_, L, h=spec.delay, regions=spec.regions, R=spec.R, q0=spec.q0,
                                           q1=spec.q1, method=spec.method)
    return design_fn(sys_, L, kind=spec.kind, region=spec.region, R=spec.R, q0=spec.q0, q1=spec.q1,
                     **spec.design_kwargs())


class _DesignView:
    """What `fojax design` prints, plots and records of a design: one verification report,
    or, for a finite-time observer, its two designs' together (both must pass)."""

    def __init__(self, eigenvalues, region, region_words, q0, q1, relative_residual, passed, report,
                 title_note=""):
        self.eigenvalues, self.region, self.region_words = eigenvalues, region, region_words
        self.q0, self.q1, self.relative_residual, self.passed = q0, q1, relative_residual, passed
        self.report, self.title_note = report, title_note

    @classmethod
    def of(cls, d):
        from ..design import FiniteTimeObserverDesign

        if isinstance(d, FiniteTimeObserverDesign):
            d1, d2 = d.designs
            eig = np.concatenate([np.asarray(d1.report.eigenvalues), np.asarray(d2.report.eigenvalues)])
            return cls(eig, None, f"{d1.region.describe()} and {d2.region.describe()}", d1.observer.q0,
                       d1.observer.q1, max(float(d1.report.relative_residual), float(d2.report.relative_residual)),
                       bool(d1.report.passed and d2.report.passed),
                       {"observer_1": d1.report.to_dict(), "observer_2": d2.report.to_dict(), "h": float(d.h),
                        "reconstruction_rcond": float(d.reconstruction_rcond),
                        "reconstruction_residual": float(d.reconstruction_residual)},
                       title_note=f"\nboth observers, in {d1.region.describe()} and {d2.region.describe()}; h = {d.h:g}")
        return cls(d.report.eigenvalues, d.region, d.region.describe(), d.observer.q0, d.observer.q1,
                   float(d.report.relative_residual), bool(d.report.passed), d.report.to_dict())


def _route(d) -> str:
    """``"Riccati"`` or ``"LMI"``: how the gain of design `d` was computed (its
    ``solver["lmi"]["method"]``); for a finite-time pair, its two routes."""
    designs = getattr(d, "designs", None) or (d,)
    names = []
    for di in designs:
        lmi = (getattr(di, "solver", None) or {}).get("lmi")
        if lmi is None:  # no solver record of the gain: the finite-time observers' pole placement
            names.append("pole placement")
        else:
            names.append("Riccati" if lmi.get("method") == "riccati" else "LMI")
    return " / ".join(dict.fromkeys(names))


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
    distributed: bool = False,
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
    """
    if distributed:
        from ._distributed import process_folders

        with process_folders(out_dir, resume) as (out_dir, resume, worker):
            return study(config_path, out_dir, samples=samples, horizon=horizon, steps=steps, resume=resume,
                         quiet=quiet or bool(worker))
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
    from ..config._load import SPECIAL_KINDS

    special = [(i, o.kind) for i, o in enumerate(cfg.observers) if o.kind in SPECIAL_KINDS]
    if special:
        i, kind = special[0]
        raise ConfigError(path, f"observer[{i}].kind", f"'{kind}' observers have no Monte Carlo study yet "
                          "(the study compares z estimates of generalized/PI/proportional observers); "
                          f"use `fojax design {path}` to design and verify it.")
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
    return _study(out, cfg, path, folder, spec, tspec, plan, T, n_steps, resumed=resume is not None)


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


def _study(out, cfg, path, folder, spec, tspec, plan, T, n_steps, *, resumed: bool) -> int:
    """The body of `study` (after the results folder is set up); `plan` is the
    `fojax.cli._study_samples.SamplePlan` announced and recorded by `study`."""
    import dataclasses

    from .. import studies
    from ..analysis import structure_report
    from ..design import design_functional_observer, design_ts_observer
    from ..results import (
        plot_error_distributions,
        plot_estimates,
        plot_poles,
        save_design,
        write_metrics,
        write_report,
    )
    from ..results._io import atomic_write_json, atomic_write_npz
    from . import _study_samples as ss

    ow = resumed  # a resumed run replaces the files it regenerates
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
        figures[f"Error poles of '{o.name}'"] = plot_poles(folder / f"poles-{o.name}.png",
                                                           d.report.eigenvalues, d.region, overwrite=ow)
        out.say(f"  verification {'PASSED' if d.report.passed else 'FAILED'}")

    # the Monte Carlo study (and separately drawn training studies for the tuning)
    st = ss.make_study(cfg, spec.seed, plan.run, T, spec.dt)
    assert st.num_samples == plan.run, (st.num_samples, plan.run)
    ts = st.ts
    # Explicit Tsit5: the benchmark loops are not stiff (error poles in the designed disks)
    # and the implicit default (Kvaerno5; works in studies since the issue-5 fix) is much
    # slower here. Measured with `fojax study --samples 16 --horizon 2 --steps 0` on the
    # 2 shared cores: first run_study call (compile + run) ~33 s vs ~12 s CPU time
    # (49-80 s vs 17-21 s wall), a second call 0.2-0.5 s vs 0.06-0.13 s; mean IAEs
    # agree to ~1e-6.
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
        from ..results import plot_tuning_curve

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
            # compiles without the GIL; issue 13). Not across processes (its collectives).
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
            figures[f"Tuning curve of '{nm}'"] = plot_tuning_curve(
                folder / f"tuning-{nm}.png", h["step"], h["train_loss"],
                held if np.isfinite(held).any() else None, ylabel=f"{tspec.loss.upper()} loss",
                heldout_before=tr.initial_heldout, heldout_after=tr.final_heldout,
                title=f"Tuning '{nm}': training and held-out loss" if not plan.deterministic else
                f"Tuning '{nm}' (deterministic model: one run, nothing held out)", overwrite=ow)
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
                                 "algebraic constraints (fojax.consistent_initial_condition) (N, n)",
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
    figures["Estimation error, Monte Carlo 5-95 % band and median"] = plot_estimates(
        folder / "error-bands.png", np.asarray(res.coords["time"]), np.zeros((len(res.coords["time"]), len(signals))),
        {nm: (q[k, 0], q[k, 1], q[k, 2]) for k, nm in enumerate(names)},
        labels=[f"e({s})" for s in signals], truth_label="zero error", title="Estimation error over the Monte Carlo samples",
        overwrite=ow,
    )
    figures["IAE per sample (sum over signals)"] = plot_error_distributions(
        folder / "iae.png", per_sample, ylabel="IAE (sum over signals)", overwrite=ow)
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
    return 0 if all(d.report.passed for d in designs.values()) else 1


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


class _Unavailable(Exception):
    """A command that is not available in this installation (exit code 3)."""
