"""`fojax check` exit codes, `--json` on check/design/study, `-q`/`-v`.

Oracles: a closed form (E = [[0, 1], [0, 0]], A = I: det(sE - A) = 1 is a nonzero
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
