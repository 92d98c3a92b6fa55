"""``fojax design``: design, verify and save the observers of a config."""

from __future__ import annotations

import pathlib

import numpy as np

from ._common import _default_region, _load, _one_line, _Progress, _region_words, figures_available


def design(
    config_path: str,
    out_dir: str | None = None,
    *,
    name: str | None = None,
    overwrite: bool = False,
    quiet: bool = False,
    result: dict | None = None,
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

    **Returns:** 0 if every observer was designed and verified, 1 otherwise. `result`
    (for ``--json``), if given, is filled with the folder, the report and what
    ``designs.json`` holds.
    """
    import sys

    from .._errors import FojaxError, InputError
    from .._io import folder_manifest, name_problem, NAME_RULE, suggest_name
    from ..design import design_functional_observer, design_ts_observer
    from ..results import (
        atomic_write_bytes,
        atomic_write_json,
        new_results_folder,
        plot_poles,
        save_design,
        write_report,
    )

    if name is not None and name_problem(name) is not None:  # before any work
        raise InputError(
            f"--name {name!r} cannot be used: {name_problem(name)}. The {NAME_RULE}; e.g. "
            f"--name {suggest_name(name, 'run1')}. (--out may be any path: the results folder "
            "is created inside it.)"
        )
    out = _Progress(quiet)
    cfg = _load(config_path)
    draw = figures_available(out)
    from ..config import ObserverSpec

    observers = cfg.observers or (ObserverSpec("generalized", "generalized", _default_region(cfg.dt)),)
    discrete = cfg.dt is not None
    eig_head = "max |eig|" if discrete else "max Re(eig)"  # the error decays iff |eig| < 1 / Re(eig) < 0
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
        headers = ["observer", "kind", "q0", "q1", "region", "route", eig_head, "relative residual", "verified"]
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
            if draw:
                png = folder / f"poles-{spec.name}.png"
                plot_poles(
                    view.eigenvalues,
                    view.region,
                    title=f"{cfg.name}: error poles of '{spec.name}' ({spec.kind})" + view.title_note,
                    path=png,
                    overwrite=overwrite,
                )
                figures[f"Error poles of '{spec.name}'"] = png
            eig = np.asarray(view.eigenvalues)
            rows.append(
                [spec.name, spec.kind, view.q0, view.q1, view.region_words, _route(d),
                 float(np.max(np.abs(eig) if discrete else eig.real)) if eig.size else float("nan"),
                 view.relative_residual, view.passed]
            )
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
    out.say(f"{'observer':<{width}}  kind          q0  q1  route     {eig_head:>11}  verified")
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
    if result is not None:
        from .._serialize import json_safe

        result.update({"config": str(config_path), "name": cfg.name, "ok": all_ok, "folder": str(folder),
                       "report": str(report), "designs": json_safe(summary)})
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
