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


# ------------------------------------------------------------ CLI niceties (issue 17)
# Oracles: importlib.metadata for the version, the example TOML files read with tomllib for
# the descriptions, and the ConfigError messages of each bad file.


def test_version_prints_the_installed_version(capsys):
    import importlib.metadata

    import pytest

    with pytest.raises(SystemExit) as e:
        main(["--version"])
    assert e.value.code == 0
    assert capsys.readouterr().out.strip() == f"fojax {importlib.metadata.version('fojax')}"


def test_plain_fojax_prints_the_commands_and_does_not_run_the_demo(capsys):
    assert main([]) == 0
    out = capsys.readouterr().out
    assert out.startswith("usage: fojax")
    for command in ("demo", "check", "design", "study", "examples"):
        assert f"\n    {command}" in out  # the command list of the help
    assert "fojax demo: thesis example" not in out  # what the demo prints first


def test_help_documents_fojax_debug(capsys):
    import pytest

    with pytest.raises(SystemExit):
        main(["--help"])
    assert "FOJAX_DEBUG=1" in " ".join(capsys.readouterr().out.split())


def test_examples_lists_one_line_description_per_example(capsys):
    import tomllib

    from fojax.config import example_names, example_path

    assert main(["examples"]) == 0
    lines = capsys.readouterr().out.splitlines()
    for name in example_names():
        with open(example_path(name), "rb") as f:
            description = tomllib.load(f)["description"]
        assert description
        [line] = [ln for ln in lines if ln.split() and ln.split()[0] == name]
        assert line.split(None, 1)[1] == description


def test_check_checks_every_file_and_reports_each_bad_one(tmp_path, capsys, monkeypatch):
    import pytest

    import fojax

    bad_syntax = tmp_path / "bad_syntax.toml"
    bad_syntax.write_text("[model\n")
    bad_key = tmp_path / "bad_key.toml"
    bad_key.write_text("[model]\nE = [[1.0]]\nA = [[-1.0]]\nB = [[1.0]]\nC = [[1.0]]\n")  # no L
    missing = tmp_path / "missing.toml"
    code = main(["check", str(bad_syntax), "example_3_1_3", str(bad_key), str(missing)])
    out, err = capsys.readouterr()
    assert code == 2  # an error, reported after every file was checked
    assert out.count("fojax check: ") == 1 and "fojax check: example_3_1_3" in out
    err_lines = err.strip().splitlines()
    assert len(err_lines) == 3
    for line, path, what in zip(err_lines, (bad_syntax, bad_key, missing),
                                ("not valid TOML", "'L'", "does not exist")):
        assert line.startswith(f"fojax: error: {path}: ") and what in line
    # all good: exit 0; FOJAX_DEBUG=1: the full exception instead of the one line
    assert main(["check", "example_3_1_3", "--quiet"]) == 0
    monkeypatch.setenv("FOJAX_DEBUG", "1")
    with pytest.raises(fojax.ConfigError, match="not valid TOML"):
        main(["check", str(bad_syntax), "example_3_1_3"])


def test_design_of_several_configs_goes_on_after_a_bad_one(tmp_path, capsys):
    # `fojax design a b`: a config that cannot be loaded is named on stderr and the next one
    # is still designed (on main the first error ended the command)
    bad = tmp_path / "bad.toml"
    bad.write_text("[model]\nE = [[1.0]]\nA = [[-1.0]]\nB = [[1.0]]\nC = [[1.0]]\n")  # no L
    code = main(["design", str(bad), "example_3_1_3", "--out", str(tmp_path / "runs"), "--quiet"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2
    assert len(err) == 1 and err[0].startswith(f"fojax: error: {bad}: ") and "'L'" in err[0]
    [folder] = (tmp_path / "runs").iterdir()  # the good config's results folder
    assert folder.name.startswith("design-") and (folder / "report.md").is_file()
    assert list(folder.glob("*.npz"))


def test_output_into_a_closed_pipe_ends_quietly():
    # `fojax examples | head -1`: the reader leaves; no "unexpected BrokenPipeError" line,
    # exit status 141 (128 + SIGPIPE, what a shell reports for such a writer)
    script = (
        "import os, sys\n"
        "r, w = os.pipe(); os.close(r)\n"  # a pipe whose reader is gone
        "os.dup2(w, 1)\n"
        "import signal; signal.signal(signal.SIGPIPE, signal.SIG_IGN)\n"  # EPIPE, not a kill
        "from fojax.cli import main\n"
        "sys.exit(main(['examples']))\n"
    )
    r = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300)
    assert r.returncode == 141, r.stderr
    assert r.stderr == ""
