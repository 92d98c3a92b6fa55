"""The `fojax` command: the README's first command runs `fojax demo`."""

import subprocess
import sys

from fojax.cli import main


def test_demo_runs_and_converges(capsys):
    # In-process (64-bit JAX is already on in the tests): the demo designs a verified
    # observer for example 4.1.3 and reports convergence of the simulated estimate.
    assert main(["demo"]) == 0
    out = capsys.readouterr().out
    assert "verification PASSED" in out
    assert "design verified = True, estimate converged = True" in out
    # the structure report printed by the demo matches the thesis's open-loop poles
    assert "1.79487" in out


def test_help_and_bad_command():
    r = subprocess.run([sys.executable, "-m", "fojax.cli", "--help"], capture_output=True, text=True)
    assert r.returncode == 0 and "demo" in r.stdout and "64-bit" in r.stdout
    r = subprocess.run([sys.executable, "-m", "fojax.cli", "nonsense"], capture_output=True, text=True)
    assert r.returncode != 0 and "invalid choice" in r.stderr
