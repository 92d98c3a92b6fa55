"""``fojax examples`` and ``fojax check``."""

from __future__ import annotations

from ._common import _load, _Progress


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


#: The properties ``fojax check --require`` accepts: the yes/no fields of
#: `fojax.analysis.StructureReport`.
PROPERTIES = (
    "regular", "impulse_free", "stable", "admissible", "c_observable", "r_observable",
    "i_observable", "s_observable", "detectable", "c_controllable", "r_controllable",
    "i_controllable", "s_controllable", "stabilizable", "functionally_observable", "proper",
)


def report_dict(report) -> dict:
    """A `fojax.analysis.StructureReport` as JSON-ready data (complex numbers as
    ``{"real": [...], "imag": [...]}``, a non-finite float as a string)."""
    import dataclasses

    from .._serialize import json_safe

    return json_safe(dataclasses.asdict(report))


def check(config_path: str, quiet: bool = False, *, require=(), result: dict | None = None) -> int:
    """Print the structural analysis report(s) of the model in `config_path`.

    The model (every Takagi–Sugeno rule; with ``model.feedback`` the closed loop) must be
    admissible (regular, impulse-free, stable), and have every property of `require`
    (names of `PROPERTIES`); a property the analysis cannot decide (``None``, e.g. for a
    singular pencil) counts as failed. The fault-augmented system, which always has poles
    at 0, is reported but not required to be admissible.

    **Returns:** 0 if every requirement holds, 1 otherwise (each failure named on stderr).
    `result` (for ``--json``), if given, is filled with the reports and verdicts.
    """
    import sys

    from ..analysis import structure_report

    out = _Progress(quiet)
    cfg = _load(config_path)
    out.say(f"fojax check: {cfg.name} ({config_path})")
    if cfg.description:
        out.say(f"  {cfg.description}")
    if cfg.feedback is not None:
        out.say("  model.feedback is given: the plant analysed is (E, A + B K, B, C).")
    out.say("")
    required = ["admissible"] + [r for r in require if r != "admissible"]
    systems = cfg.rule_systems()
    reports, failed = [], []
    for i, sys_ in enumerate(systems):
        if cfg.is_takagi_sugeno:
            out.say(f"Takagi-Sugeno rule {i + 1} of {len(systems)} (E, A_{i + 1}, B_{i + 1}, C):")
        report = structure_report(sys_, cfg.L)
        reports.append(report)
        where = f"rule {i + 1}: " if cfg.is_takagi_sugeno else ""
        failed += [f"{where}{prop}" for prop in required if getattr(report, prop) is not True]
        out.say(report)
        out.say("")
    augmented = None
    if cfg.augments_faults:
        aug = cfg.design_system()
        out.say(
            f"Fault-augmented system (eq. 3.196, {aug.n} states) with the functional of the "
            "observers (z and the faults):" if cfg.estimate_faults else
            f"Fault-augmented system (eq. 3.196, {aug.n} states) with the functional [L 0]:"
        )
        augmented = structure_report(aug, cfg.design_L())
        out.say(augmented)
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
    if failed:
        print(f"fojax: {config_path}: required but not established: {', '.join(failed)} (exit code 1)",
              file=sys.stderr, flush=True)
    if result is not None:
        result.update({
            "config": str(config_path), "name": cfg.name, "ok": not failed, "required": required,
            "failed": failed, "verdicts": [r.verdict for r in reports],
            "systems": [report_dict(r) for r in reports],
            "fault_augmented": None if augmented is None else report_dict(augmented),
            "uncertainty_directions": 0 if cfg.dA is None else int(cfg.dA.shape[0]),
        })
    return 1 if failed else 0
