"""``fojax`` command: ``demo``, ``check``, ``design``, ``study`` and ``examples``.

The CLI enables 64-bit JAX for its own process (it is an application, not a library
import), and says so in ``--help``.

Exit codes (the same in ``--help``):

| code | meaning |
|---|---|
| 0 | success |
| 1 | a result is negative: ``check``: the model is not admissible or a ``--require``d property does not hold; ``design``: an observer could not be designed or failed verification (the others are saved); ``study``/``demo``: a design failed verification |
| 2 | usage or input error: a bad option, a config that cannot be read, an invalid model (one line on stderr) |
| 3 | the command is not available in this installation |
| 130 / 143 | interrupted by SIGINT (Ctrl-C) / SIGTERM |
| 141 | stdout closed by its reader (e.g. piped into ``head``) |

``--json`` (``check``, ``design``, ``study``) prints exactly one JSON document on stdout,
``{"command", "exit_code", "results": [...]}`` (``"error"`` on exit code 2 or 3, and
with no ``results`` on a usage error); every message and progress bar goes to stderr.
``-q``/``--quiet`` prints nothing but errors; ``-v``/``--verbose`` adds the full Python
traceback to an error's one-line reason (the exit code stays 2).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
import time


DESCRIPTION = """\
fojax: functional observers for descriptor systems E x' = A x + B u, y = C x, z = L x.

Describe your model in a TOML file (format: docs/config.md; start from a shipped
example, `fojax examples` lists them), then check its structure and design observers.
The command enables 64-bit JAX for its own process (fojax computes in float64).
"""

EPILOG = """\
examples:
  fojax demo                            analyse, design and simulate thesis example 4.1.3
  fojax examples                        list the shipped example configs, one line each
  fojax check example_3_3_7             structure report of a shipped example
  fojax check my_model.toml             ... or of your own model file
  fojax design my_model.toml            design + verify the [[observer]]s, save them in a
                                        new folder under ./fojax-results
  fojax design my_model.toml --out runs --name first   choose the folder
  fojax --quiet design my_model.toml    only errors (exit code tells success)
  fojax study my_model.toml             Monte Carlo study + tuning (Ctrl-C: stop; continue
                                        with fojax study --resume <its folder>)

  fojax check --json my_model.toml      one JSON document on stdout (messages on stderr)

exit codes: 0 success; 1 a negative result: `check`: the model is not admissible or a
--require'd property does not hold; `design`: an observer could not be designed or failed
verification (the others are still designed and saved; each failure is named on stderr
and in the report); `study`, `demo`: a design failed verification; 2 usage or input
error (one-line reason on stderr; `fojax check a b c` checks every file and reports each
bad one); 3 command not available in this installation; 130/143 interrupted by SIGINT
(Ctrl-C) / SIGTERM: any command, at any moment, with one line on stderr; the files
written are complete (each is written atomically), an interrupted study is resumable. A
signal ignored when fojax starts stays ignored. 141: stdout closed by its reader.
--json: `check`, `design` and `study` print exactly one JSON document on stdout
({"command", "exit_code", "results": [...], "error" on exit code 2/3}); messages and
progress go to stderr. -q: only errors; -v: an error's full traceback too.
files: fojax writes only inside the results folder (names in a config and --name must
be plain file names: letters, digits, '.', '_', '-'), atomically, with the permissions
your umask gives, and lists what it wrote in the folder's fojax-manifest.json.
environment: FOJAX_DEBUG=1 prints the full Python traceback instead of the one-line
reason (attach it to bug reports). FOJAX_DEVICES=N (or auto: one per core): `fojax
study` on N JAX CPU devices (the same as --devices N; default 1).
Python: fojax.config.load_config, fojax.results.save_design / load_design.
"""


def _enable_x64():
    import jax

    jax.config.update("jax_enable_x64", True)


def _say(quiet: bool, *args):
    if not quiet:
        print(*args, flush=True)


def demo(quiet: bool = False) -> int:
    """Analyse, design for and simulate thesis example 4.1.3; print a summary."""
    _enable_x64()
    import jax.numpy as jnp
    import numpy as np

    import fojax
    from fojax.design import design_functional_observer, Disk

    t_start = time.perf_counter()
    ex = fojax.models.example_4_1_3()
    sys_ = ex.system
    L = np.asarray(ex.L)
    _say(quiet, "fojax demo: thesis example 4.1.3 (4 states, rank E = 3, 2 inputs, 3 outputs)\n")
    report = fojax.analysis.structure_report(sys_, L)
    _say(quiet, report, "\n")
    closed = fojax.DescriptorSystem(sys_.E, sys_.A + sys_.B @ jnp.asarray(L), sys_.B, sys_.C)
    poles_cl = fojax.analysis.finite_poles(closed)
    _say(quiet, "state feedback u = Lx: finite poles of (E, A + BL):", np.round(poles_cl, 3), "\n")

    _say(quiet, "designing a generalized functional observer for z = Lx of the stabilised plant "
                "(E, A + BL, B, C), error poles in disk(-2, 1) ...")
    t0 = time.perf_counter()
    design = design_functional_observer(closed, L, kind="generalized", region=Disk(-2.0, 1.0))
    _say(quiet, f"  done in {time.perf_counter() - t0:.2f} s")
    _say(quiet, design, "\n")

    _say(quiet, "simulating plant (E, A + BL) with u_r = step + sine and the observer (exact stepping) ...")
    ts = jnp.linspace(0.0, 10.0, 1001)
    u = fojax.Step(jnp.array([1.0, -0.5]), 1.0) + fojax.Sine(jnp.array([0.5, 0.2]), 2.0)
    t0 = time.perf_counter()
    sol = fojax.simulate(closed, jnp.asarray(ex.x0), ts, u, observers=(design.observer,))
    zhat = np.asarray(sol.estimates[0])
    z = np.asarray(sol.xs) @ L.T
    err = np.abs(zhat - z).max(axis=1)
    _say(quiet, f"  done in {time.perf_counter() - t0:.2f} s (includes compilation)")
    for t in (0.0, 1.0, 2.0, 5.0, 10.0):
        k = int(round(t / 0.01))
        _say(quiet, f"  t = {t:5.1f} s   max |zhat - z| = {err[k]:.3e}")
    resid = float(np.max(np.asarray(sol.stats["constraint_residual"])))
    _say(quiet, f"  algebraic constraint residual along the trajectory: {resid:.2e}")
    ok = bool(err[-1] < 1e-3 * max(1.0, err[0]) and design.report.passed)
    _say(quiet, f"\nsummary: design verified = {design.report.passed}, estimate converged = {ok}, "
                f"total {time.perf_counter() - t_start:.1f} s")
    return 0 if ok else 1


def _version() -> str:
    import importlib.metadata

    try:
        return importlib.metadata.version("fojax")
    except importlib.metadata.PackageNotFoundError:  # running from a source tree, not installed
        return "unknown (not installed)"


def _debug() -> bool:
    import os

    return os.environ.get("FOJAX_DEBUG", "") not in ("", "0")


def _error_line(err: BaseException, path: str | None = None) -> str:
    """The one-line reason printed for a failed command (``path`` is named if the message
    does not name it already)."""
    from fojax import FojaxError

    kind = "error" if isinstance(err, FojaxError | FileExistsError) else f"unexpected {type(err).__name__}"
    msg = " ".join(str(err).split("\n")[0].split()) if str(err) else ""
    if path is not None and path not in msg:
        msg = f"{path}: {msg}"
    return f"fojax: {kind}: {msg}"


def _each_config(configs: list[str], command) -> int:
    """Run ``command(config)`` for every config (`fojax check a b c`, `fojax design a b c`):
    a config that fails gets its one-line reason on stderr (naming the file when there are
    several) and the next one still runs; the exit code is the worst of all (2 for a failed
    config)."""
    from ._common import _Unavailable

    status = 0
    for config in configs:
        done = len(_JSON.doc["results"]) if _JSON.doc is not None else 0
        try:
            status = max(status, command(config))
        except _Unavailable:
            raise
        except Exception as err:
            if _debug():  # full traceback for bug reports
                raise
            _traceback(err)
            print(_error_line(err, config if len(configs) > 1 else None), file=sys.stderr, flush=True)
            if _JSON.doc is not None:
                del _JSON.doc["results"][done:]  # what the failed config had begun to record
                _JSON.doc["results"].append({"config": str(config), "ok": False, "error": type(err).__name__,
                                             "message": str(err)})
            status = 2
    return status


class _JsonOut:
    """The ``--json`` document of the command being run (None without ``--json``) and
    whether ``-v`` was given."""

    doc: dict | None = None
    verbose: bool = False


_JSON = _JsonOut()


def _traceback(err: BaseException) -> None:
    """With ``-v``: the full traceback of `err` on stderr (before its one-line reason)."""
    if _JSON.verbose:
        import traceback

        traceback.print_exception(err, file=sys.stderr)


class _UsageError(Exception):
    """A command line argparse refused (exit code 2)."""


class _Parser(argparse.ArgumentParser):
    def error(self, message):  # with --json the refusal is the JSON document's error too
        if _JSON.doc is not None:
            self.print_usage(sys.stderr)
            raise _UsageError(f"{self.prog}: {message}")
        super().error(message)


def _run(argv: list[str] | None) -> int:
    raw = argparse.RawDescriptionHelpFormatter
    argv = sys.argv[1:] if argv is None else list(argv)
    if "--json" in argv:  # before parsing: a refused command line is a JSON error document too
        _JSON.doc = {"command": None, "results": []}
    parser = _Parser(prog="fojax", description=DESCRIPTION, epilog=EPILOG, formatter_class=raw)
    parser.add_argument("--version", action="version", version=f"fojax {_version()}",
                        help="print the installed fojax version and exit")
    parser.add_argument("-q", "--quiet", action="store_true", help="print nothing but errors")
    parser.add_argument("-v", "--verbose", action="store_true",
                        help="more detail: an error's full Python traceback before its one-line reason")
    # `-q`/`-v` are accepted after the command too (default SUPPRESS keeps the global value)
    quiet = argparse.ArgumentParser(add_help=False)
    quiet.add_argument("-q", "--quiet", action="store_true", default=argparse.SUPPRESS,
                       help="print nothing but errors")
    quiet.add_argument("-v", "--verbose", action="store_true", default=argparse.SUPPRESS,
                       help="an error's full Python traceback too")
    as_json = argparse.ArgumentParser(add_help=False)
    as_json.add_argument("--json", action="store_true",
                         help="print one JSON document with the results on stdout (messages to stderr)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

    def add_out(p):
        p.add_argument("--out", metavar="DIR", default=None,
                       help="parent directory of the results folder (default: ./fojax-results)")

    def command(name, help, description, epilog):
        """A command taking -q/-v/--json whose `epilog` (its examples) prints as written."""
        return sub.add_parser(name, parents=[quiet, as_json], help=help, description=description,
                              epilog=epilog, formatter_class=raw)

    sub.add_parser(
        "demo",
        parents=[quiet],
        help="analyse, design an observer for and simulate thesis example 4.1.3",
        description="Structural analysis, verified LMI observer design and simulation of "
        "thesis example 4.1.3, with a printed summary.",
    )
    sub.add_parser(
        "examples", parents=[quiet], help="list the example configs shipped with fojax",
        description="List the shipped example configs (thesis examples) and their paths; "
        "copy one to start your own model file.",
    )
    from ._check import PROPERTIES

    p = command(
        "check",
        help="structural analysis report of the model in CONFIG",
        description="Regularity, index, poles, impulse-freeness, admissibility, observability "
        "and controllability notions and functional observability of L (Assumption 1), with a "
        "plain-language verdict. Exit code 0 when the model is admissible (every Takagi-Sugeno "
        "rule; the closed loop with model.feedback) and has every --require'd property, 1 when "
        "not (each failure named on stderr), 2 when a config cannot be read.",
        epilog="examples: fojax check example_3_3_7   (a shipped example; see `fojax examples`)\n"
        "          fojax check my.toml --require detectable --require functionally_observable\n"
        "          fojax check --json example_3_3_7 | python -m json.tool",
    )
    p.add_argument("config", metavar="CONFIG", nargs="+",
                   help="TOML model file(s), or shipped example names")
    p.add_argument("--require", metavar="PROPERTY", action="append", default=[], choices=PROPERTIES,
                   help="a property the model must have besides admissibility (repeatable): "
                   + ", ".join(PROPERTIES) + "; one the analysis cannot decide counts as failed")
    p = command(
        "design",
        help="design, verify and save the observers requested in CONFIG",
        description="Design every [[observer]] of CONFIG by LMI, verify it in float64, and "
        "save it (fojax.results.load_design reads it back bit-exactly) with a pole plot and a "
        "Markdown report into a NEW results folder: an earlier folder is never reused. An "
        "observer that cannot be designed (existence condition, LMI infeasible, verification) "
        "is reported by name on stderr, in report.md and in designs.json; the others are still "
        "designed and saved, and the exit code is 1.",
        epilog="example: fojax design example_4_1_3 --out runs\n"
        "         python -c \"import fojax.results as r; print(r.load_design('runs/<folder>/generalized.npz'))\"",
    )
    p.add_argument("config", metavar="CONFIG", nargs="+",
                   help="TOML model file(s), or shipped example names (one results folder each)")
    add_out(p)
    p.add_argument("--name", metavar="NAME", default=None,
                   help="results folder name, a plain file name (letters, digits, '.', '_', '-'; "
                   "default: design-<model name>-<UTC timestamp>)")
    p.add_argument("--overwrite", action="store_true",
                   help="replace the previous fojax run in an existing --name folder: the files "
                   "it wrote (listed in its fojax-manifest.json) are removed first, except any you "
                   "changed since; files fojax did not write stay untouched")
    p = command(
        "study",
        help="Monte Carlo robustness study (default: the built-in §3.3.7 benchmark)",
        description="Design, Monte Carlo study, tuning and comparison of the observers of "
        "CONFIG (default: the §3.3.7 benchmark), in a NEW results folder. Ctrl-C (or SIGTERM) "
        "stops it with the folder consistent; --resume FOLDER continues it.",
        epilog="example: fojax study --samples 64 --steps 50 --out runs\n"
        "         fojax study --resume runs/study-example_3_3_7-<UTC time>",
    )
    p.add_argument("config", metavar="CONFIG", nargs="?", default=None,
                   help="TOML model/study file (default: the built-in §3.3.7 benchmark)")
    add_out(p)
    p.add_argument("--samples", type=int, default=None, help="override [study] samples")
    p.add_argument("--horizon", type=float, default=None, help="override [study] horizon (s)")
    p.add_argument("--steps", type=int, default=None,
                   help="override [tuning] steps (0: no tuning)")
    p.add_argument("--resume", metavar="FOLDER", default=None,
                   help="continue an interrupted study in its results FOLDER: its config.toml and "
                   "options are reused, the tuning continues from its checkpoint, the files the run "
                   "regenerates are replaced (CONFIG, --samples, --horizon, --steps, if given, must "
                   "match the first run)")
    p.add_argument("--devices", metavar="N", type=_positive, default=None,
                   help="JAX CPU devices to spread the samples over: a number, or 'auto' (one per "
                   "core); default FOJAX_DEVICES, else 1 (faster on the default study; an XLA_FLAGS "
                   "that sets xla_force_host_platform_device_count wins). The same bits on any count")
    p.add_argument("--distributed", action="store_true",
                   help="one study over several processes/hosts (jax.distributed): start this same "
                   "command on every process with JAX_COORDINATOR_ADDRESS, JAX_NUM_PROCESSES, "
                   "JAX_PROCESS_ID set (not needed under SLURM); only process 0 writes the results "
                   "folder (see docs/distributed.md)")
    args = parser.parse_args(argv)
    _JSON.verbose = args.verbose
    if not getattr(args, "json", False):
        _JSON.doc = None  # "--json" was an option's value, or given to a command without it
    if args.command is None:  # plain `fojax`: what it can do, not a 20-second demo
        parser.print_help()
        return 0
    if _JSON.doc is not None:
        _JSON.doc["command"] = args.command
        with contextlib.redirect_stdout(sys.stderr):  # stdout holds the JSON document only
            return _command(parser, args)
    return _command(parser, args)


def _command(parser, args) -> int:
    """Run the parsed command."""
    from . import _check, _design, _study
    from ._common import resolve_config
    from ._signals import on_interrupt

    command = args.command
    results = _JSON.doc["results"] if _JSON.doc is not None else None

    def record() -> dict | None:  # one result of the JSON document
        if results is None:
            return None
        results.append({})
        return results[-1]

    if command == "demo":
        return demo(quiet=args.quiet)
    if command == "examples":
        return _check.examples(quiet=args.quiet)
    if command == "study":
        config = None if args.config is None else resolve_config(args.config)
        from ._devices import check_devices

        if args.distributed:
            from . import _distributed

            _distributed.initialize()
            _enable_x64()
            check_devices(args.devices)
            return _distributed.run(lambda: _study.study(
                config, args.out, samples=args.samples, horizon=args.horizon, steps=args.steps,
                resume=args.resume, quiet=args.quiet, distributed=True, result=record()))
        _enable_x64()
        check_devices(args.devices)
        return _study.study(config, args.out, samples=args.samples, horizon=args.horizon,
                            steps=args.steps, resume=args.resume, quiet=args.quiet, result=record())
    _enable_x64()
    if command == "design":
        on_interrupt("every file written so far is complete (each is written atomically); the "
                     "observers not reached yet are missing from the results folder")
    configs = [resolve_config(c) for c in args.config]
    if command == "check":
        return _each_config(configs, lambda c: _check.check(c, quiet=args.quiet, require=args.require,
                                                            result=record()))
    if command == "design" and args.name is not None and len(configs) > 1:
        parser.error("--name needs a single CONFIG (each config gets its own folder)")
    return _each_config(configs, lambda c: _design.design(
        c, args.out, name=args.name, overwrite=args.overwrite, quiet=args.quiet, result=record()))


def _positive(raw: str) -> int:
    from ._devices import _positive_int

    value = _positive_int(raw)
    if value is None:
        raise argparse.ArgumentTypeError(f"expected a positive integer or 'auto', got {raw!r}")
    return value


def main(argv: list[str] | None = None) -> int:
    """Run the ``fojax`` command with `argv` (default: ``sys.argv[1:]``) and return its exit code.

    SIGINT/SIGTERM end every command with one line on stderr and exit code 130/143 (see
    `fojax.cli._signals`). Called as the program (`argv` None: the ``fojax`` script,
    ``python -m _fojax_program``, ``python -m fojax.cli``), an interrupted command leaves with ``os._exit`` after its
    message, without the interpreter shutdown that crashes while jaxlib still compiles.
    """
    import os

    from ._signals import Interrupts

    _JSON.doc = None
    with Interrupts() as interrupts:
        try:
            try:
                code = _run(argv)
            except Exception as err:  # one-line reason, non-zero exit
                code = None if interrupts.signum is not None else _error(err)
                if _JSON.doc is not None and code is not None:
                    _JSON.doc["error"] = {"type": type(err).__name__, "message": str(err)}
            interrupts.finish()  # from here on a signal is only recorded
        except KeyboardInterrupt:
            if interrupts.signum is None:  # not a signal of this command
                raise
            interrupts.finish()
        if interrupts.signum is not None:  # also when the command ran on to its end
            code = interrupts.exit_code
            what = interrupts.message or "no file was written"
            print(f"fojax: interrupted; {what}", file=sys.stderr, flush=True)
            if _JSON.doc is not None:
                _JSON.doc["error"] = {"type": "Interrupted", "message": what}
    if _JSON.doc is not None:  # --json: the one document on stdout
        doc, _JSON.doc = _JSON.doc, None
        with contextlib.suppress(BrokenPipeError):
            print(json.dumps({"command": doc.pop("command"), "exit_code": code, **doc}, allow_nan=False),
                  flush=True)
    if argv is None and interrupts.signum is not None:
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    return code


def _error(err: Exception) -> int:
    """Print the one-line reason of a failed command; its exit code (2, or 3: unavailable)."""
    from ._common import _Unavailable

    if isinstance(err, _Unavailable):
        print(f"fojax: {err}", file=sys.stderr)
        return 3
    if isinstance(err, _UsageError):  # argparse's message, as it prints it without --json
        print(f"{err}", file=sys.stderr)
        return 2
    if isinstance(err, BrokenPipeError):  # `fojax examples | head -2`: the reader left
        import os

        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # no second error at exit
        return 128 + 13  # as a shell reports a process ended by SIGPIPE
    if _debug():  # FOJAX_DEBUG=1: full traceback for bug reports
        raise err
    _traceback(err)
    print(_error_line(err), file=sys.stderr)
    return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
