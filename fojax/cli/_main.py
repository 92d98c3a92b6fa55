"""``fojax`` command: ``fojax demo`` runs the built-in demonstration.

The CLI enables 64-bit JAX for its own process (it is an application, not a library
import), and says so in ``--help``.
"""

from __future__ import annotations

import argparse
import sys
import time


DESCRIPTION = """\
fojax: functional observers for descriptor systems E x' = A x + B u, y = C x, z = L x.

The command enables 64-bit JAX for its own process (fojax computes in float64).
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


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="fojax", description=DESCRIPTION, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--quiet", action="store_true", help="print nothing but errors")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.add_parser(
        "demo",
        help="analyse, design an observer for and simulate thesis example 4.1.3",
        description="Structural analysis, verified LMI observer design and simulation of "
        "thesis example 4.1.3, with a printed summary.",
    )
    args = parser.parse_args(argv)
    command = args.command or "demo"
    try:
        if command == "demo":
            return demo(quiet=args.quiet)
    except Exception as err:  # one-line reason, non-zero exit
        from fojax import FojaxError

        kind = "error" if isinstance(err, FojaxError) else f"unexpected {type(err).__name__}"
        print(f"fojax: {kind}: {str(err).splitlines()[0] if str(err) else ''}", file=sys.stderr)
        return 2
    parser.print_help()
    return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
