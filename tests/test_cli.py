"""The `fojax` program's commands and their output: ``demo`` (the README's first command),
``--help``/``--version``, ``examples``, ``check`` exit codes, ``--json`` on check/design/study,
``-q``/``-v``, several files in one call, a closed pipe, and the design reader of a resumed study.
(`fojax study` on model files, signals, devices and Takagi–Sugeno files: ``test_cli_config.py``,
``test_cli_signals.py``, ``test_cli_devices.py``, ``test_cli_ts.py``.)

Oracles: the demo's printed verification and the thesis's printed open-loop pole (1.79487);
``importlib.metadata`` for the version and the example TOML files read with ``tomllib`` for the
descriptions; the committed design files of ``tests/data/designs_v2`` (bit-equal arrays) for the
design reader; for ``check`` and ``--json``: a closed form (E = [[0, 1], [0, 0]], A = I: det(sE - A) = 1 is a nonzero
constant, so the pencil is regular with no finite pole and, as deg det(sE - A) = 0 <
rank E = 1, impulsive: not admissible); the Kalman rank test of controllability computed
here with NumPy for an E = I model; Python's own JSON parser (`json.loads`) for the
documents; the folders' listings for what design/study wrote.
"""

import json
import subprocess
import sys

import numpy as np
import pytest

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
    r = subprocess.run([sys.executable, "-m", "_fojax_program", "--help"], capture_output=True, text=True)
    assert r.returncode == 0 and "demo" in r.stdout and "64-bit" in r.stdout
    r = subprocess.run([sys.executable, "-m", "_fojax_program", "nonsense"], capture_output=True, text=True)
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
    with pytest.raises(fojax.errors.ConfigError, match="not valid TOML"):
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


# ------------------------------------------------------------ resuming from saved designs
# Oracle: the design saved by the first run itself (every array bit-identical after the
# round trip, `helpers.assert_designs_identical`), and the spec it was saved for.


def test_saved_design_of_a_finite_time_observer_is_reloaded(tmp_path):
    """Regression: `_saved_design` (a resumed study reloads each observer's design) read
    ``d.kind`` and ``d.solver``, which a finite-time design (a pair of designs) does not
    have, and compared its two disks with the unused ``region``: it raised for every
    finite-time design. It now takes any `fojax.design.AbstractDesign`."""
    import dataclasses

    import pytest
    from helpers import assert_designs_identical

    import fojax

    # private: the CLI's design reader is tested itself
    from fojax.cli._study import _saved_design
    from fojax.config import ObserverSpec
    from fojax.design import Disk

    ex = fojax.models.example_3_1_2()
    regions = (Disk(-5.0, 0.5), Disk(-2.0, 0.5))
    d = fojax.design_finite_time_observer(ex.system, ex.L, h=0.5, regions=regions)
    path = d.save(tmp_path / "ft.npz", metadata={"observer": "ft"})
    spec = ObserverSpec("ft", "finite-time", Disk(-2.0, 1.0), delay=0.5, regions=regions)
    loaded = _saved_design(path, spec)
    assert assert_designs_identical(d, loaded) >= 60
    assert all("saved" not in inner.solver for inner in loaded.designs)  # the file's metadata dropped
    for other in (dataclasses.replace(spec, name="other"),
                  dataclasses.replace(spec, regions=(Disk(-5.0, 0.5), Disk(-3.0, 0.5))),
                  dataclasses.replace(spec, kind="generalized")):
        with pytest.raises(fojax.errors.InputError, match=r"is not the design of observer"):
            _saved_design(path, other)


def test_saved_design_of_the_other_kinds_is_reloaded(tmp_path):
    """The same function on the committed designs of thesis examples (`tests/data/designs_v2`,
    see `test_design_base`; no LMI solved): a generalized design (§4.1.3) and an
    unknown-input design (§4.1.3 with D = e3), each refused for another kind."""
    import dataclasses
    import pathlib

    import pytest
    from helpers import assert_designs_identical

    import fojax

    # private: the CLI's design reader is tested itself
    from fojax.cli._study import _saved_design
    from fojax.config import ObserverSpec

    v2 = pathlib.Path(__file__).parent / "data" / "designs_v2"
    for case, kind in (("functional", None), ("uio", "unknown-input")):
        d = fojax.load_design(v2 / f"{case}.npz")
        path = d.save(tmp_path / f"{case}.npz", metadata={"observer": case})
        spec = ObserverSpec(case, kind or d.kind, d.region)
        loaded = _saved_design(path, spec)
        assert assert_designs_identical(d, loaded) >= 30
        assert "saved" not in loaded.solver
        other = "generalized" if kind else "unknown-input"
        with pytest.raises(fojax.errors.InputError, match=r"is not the design of observer"):
            _saved_design(path, dataclasses.replace(spec, kind=other))


# ==================================================================================================
# `fojax check` exit codes, `--json` on check/design/study, `-q`/`-v`.
# ==================================================================================================


IMPULSIVE = """\
name = "impulsive"
[model]
E = [[0, 1], [0, 0]]
A = [[1, 0], [0, 1]]
B = [[1], [0]]
C = [[1, 0]]
L = [[1, 0]]
"""


@pytest.fixture
def impulsive(tmp_path):
    path = tmp_path / "impulsive.toml"
    path.write_text(IMPULSIVE)
    return str(path)


def _json(capsys, *argv):
    code = main(list(argv))
    out, err = capsys.readouterr()
    doc = json.loads(out)  # exactly one document: json.loads refuses anything after it
    assert doc["exit_code"] == code
    return code, doc, err


def test_check_exits_1_on_an_impulsive_model(impulsive, capsys):
    assert main(["check", impulsive]) == 1
    out, err = capsys.readouterr()
    assert "NOT admissible" in out or "not admissible" in out.lower()
    assert "required but not established: admissible" in err
    code, doc, err = _json(capsys, "check", "--json", impulsive)
    assert code == 1 and doc["command"] == "check"
    [res] = doc["results"]
    assert res["ok"] is False and res["failed"] == ["admissible"]
    [system] = res["systems"]
    assert system["regular"] is True and system["impulse_free"] is False and system["admissible"] is False
    assert system["n_finite"] == 0
    assert "fojax check: impulsive" in err  # the human report went to stderr


def test_check_json_of_a_shipped_example_in_a_fresh_process():
    r = subprocess.run([sys.executable, "-m", "fojax.cli", "check", "--json", "example_3_3_7"],
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    doc = json.loads(r.stdout)
    assert doc["command"] == "check" and doc["exit_code"] == 0
    [res] = doc["results"]
    assert res["ok"] is True and res["failed"] == [] and res["required"] == ["admissible"]
    assert res["verdicts"][0].startswith("admissible")
    assert res["systems"][0]["admissible"] is True and res["fault_augmented"]["n"] > res["systems"][0]["n"]
    assert "fojax check: example_3_3_7" in r.stderr


def test_require_a_property_the_model_lacks(tmp_path, capsys):
    # E = I: (A, B) controllable iff rank [B, AB] = n (Kalman); (C, A) observable iff
    # rank [C; CA] = n
    A, B, C = np.diag([-1.0, -2.0]), np.array([[1.0], [0.0]]), np.array([[1.0, 1.0]])
    assert np.linalg.matrix_rank(np.hstack([B, A @ B])) == 1  # not controllable
    assert np.linalg.matrix_rank(np.vstack([C, C @ A])) == 2  # observable, hence detectable
    path = tmp_path / "stable.toml"
    path.write_text('name = "stable"\n[model]\nE = [[1, 0], [0, 1]]\nA = [[-1, 0], [0, -2]]\n'
                    'B = [[1], [0]]\nC = [[1, 1]]\nL = [[1, 0]]\n')
    assert main(["-q", "check", str(path), "--require", "detectable"]) == 0
    code, doc, err = _json(capsys, "check", str(path), "--json", "--require", "c_controllable",
                           "--require", "detectable")
    assert code == 1
    [res] = doc["results"]
    assert res["required"] == ["admissible", "c_controllable", "detectable"]
    assert res["failed"] == ["c_controllable"] and res["systems"][0]["admissible"] is True
    assert "required but not established: c_controllable" in err


def test_json_errors_are_documents_too(impulsive, tmp_path, capsys):
    code, doc, err = _json(capsys, "check", "--json", "--require", "bogus", "example_3_3_7")
    assert code == 2 and doc["error"]["type"] == "_UsageError" and "bogus" in doc["error"]["message"]
    assert "usage:" in err and "results" in doc and doc["results"] == []
    code, doc, err = _json(capsys, "check", "--json", impulsive, str(tmp_path / "missing.toml"))
    assert code == 2
    assert [r["ok"] for r in doc["results"]] == [False, False]
    assert doc["results"][0]["failed"] == ["admissible"] and "error" in doc["results"][1]
    assert "missing.toml" in err


def test_quiet_and_verbose(impulsive, tmp_path, capsys):
    assert main(["-q", "check", "example_3_1_3"]) == 0
    out, err = capsys.readouterr()
    assert out == "" and err == ""
    assert main(["check", str(tmp_path / "missing.toml"), "-v"]) == 2
    err = capsys.readouterr().err
    assert "Traceback (most recent call last)" in err and err.rstrip().splitlines()[-1].startswith("fojax: error")
    assert main(["check", str(tmp_path / "missing.toml")]) == 2
    assert "Traceback" not in capsys.readouterr().err


def test_design_json(tmp_path, capsys):
    code, doc, err = _json(capsys, "design", "example_4_2_2", "--json", "--out", str(tmp_path))
    assert code == 0 and doc["command"] == "design"
    [res] = doc["results"]
    folder = tmp_path / res["folder"].rsplit("/", 1)[-1]
    assert res["ok"] is True and folder.is_dir() and (folder / "report.md").is_file()
    assert res["designs"] and all(d["status"] == "verified" for d in res["designs"])
    assert {f"{d['name']}.npz" for d in res["designs"]} <= {p.name for p in folder.iterdir()}
    assert json.loads((folder / "designs.json").read_text())["designs"] == res["designs"]
    assert "fojax design" in err


def test_study_json(tmp_path, capsys):
    code, doc, err = _json(capsys, "study", "example_4_1_3", "--json", "--samples", "4", "--horizon", "1",
                           "--steps", "0", "--out", str(tmp_path))
    assert code == 0 and doc["command"] == "study"
    [res] = doc["results"]
    assert res["ok"] is True and (tmp_path / res["folder"].rsplit("/", 1)[-1] / "metrics.json").is_file()
    assert res["observers"] and all(o["verified"] for o in res["observers"].values())
    metrics = json.loads((tmp_path / res["folder"].rsplit("/", 1)[-1] / "metrics.json").read_text())
    for name, o in res["observers"].items():
        assert o["mean_iae"] == pytest.approx(np.mean(np.asarray(metrics["iae"][name]), axis=0).tolist())


def test_design_without_matplotlib_writes_everything_but_the_figures(tmp_path, capsys, monkeypatch):
    # private: Matplotlib's absence is simulated in the plots module
    import fojax.results._plots as plots

    monkeypatch.setattr(plots, "matplotlib_available", lambda: False)
    assert main(["design", "example_4_2_2", "--out", str(tmp_path), "--name", "run"]) == 0
    err = capsys.readouterr().err
    assert "no figures are written" in err and "pip install 'fojax[plot]'" in err
    names = {p.name for p in (tmp_path / "run").iterdir()}
    assert {"report.md", "designs.json", "config.toml"} <= names and not any(n.endswith(".png") for n in names)
    assert "## Figures" not in (tmp_path / "run" / "report.md").read_text()
