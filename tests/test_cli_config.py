"""The `fojax check` / `fojax design` / `fojax study` commands, run as subprocesses."""

import re
import subprocess
import sys

import matplotlib.image as mpimg
import numpy as np
import pytest
from test_config import _mutate, dumps, MALFORMED

from fojax.config import example_names, example_path
from fojax.design import TakagiSugenoObserverDesign
from fojax.results import load_design, read_design_metadata


try:  # the Monte Carlo runner may not be part of this version: then `fojax study` exits 3
    import fojax.studies  # noqa: F401

    STUDIES = True
except ImportError:
    STUDIES = False
try:
    import fojax.tuning  # noqa: F401

    TUNING = True
except ImportError:
    TUNING = False


# 8 of the malformed configs of test_config.py, through the command line
CLI_MALFORMED = [MALFORMED[i] for i in (0, 1, 2, 3, 9, 11, 17, 22)]


def fojax(*args, cwd=None):
    return subprocess.run(
        [sys.executable, "-m", "fojax.cli", *map(str, args)], capture_output=True, text=True, cwd=cwd
    )


class _Run:
    """A subprocess started at once; `.returncode`, `.stdout`, `.stderr` wait for it."""

    def __init__(self, *args):
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "fojax.cli", *map(str, args)],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        )
        self._out = None

    def _wait(self):
        if self._out is None:
            self._out = self.proc.communicate(timeout=600)
        return self._out

    @property
    def stdout(self):
        return self._wait()[0]

    @property
    def stderr(self):
        return self._wait()[1]

    @property
    def returncode(self):
        self._wait()
        return self.proc.returncode


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """Every independent command, started concurrently (the CI machine has 2 cores, and
    most of each run is importing JAX)."""
    tmp = tmp_path_factory.mktemp("cli")
    bad = {}
    for i, (path, value, key, _) in enumerate(CLI_MALFORMED):
        p = tmp / f"bad{i}.toml"
        p.write_text(dumps(_mutate(path, value)))
        bad[key] = p
    radius0 = tmp / "radius0.toml"
    radius0.write_text(dumps(_mutate(("observer", 0, "region", "disk", "radius"), 0.0)))
    r = {
        "check": _Run("check", *example_names()),
        "design": _Run("design", *example_names(), "--out", tmp / "runs"),
        "quiet": _Run("check", "example_3_1_3", "--quiet"),
        "help": _Run("--help"),
        "design_help": _Run("design", "--help"),
        "examples": _Run("examples"),
        "study": _Run("study", "--samples", "4", "--horizon", "2", "--steps", "2", "--out", tmp / "study"),
        "ts_study": _Run("study", "robot_arm_ts", "--out", tmp / "ts-study"),
        "missing": _Run("check", tmp / "missing.toml"),
        "radius0": _Run("design", radius0, "--out", tmp / "radius0-out"),
    }
    r |= {f"bad:{k}": _Run("check", p) for k, p in bad.items()}
    r["tmp"], r["bad"] = tmp, bad
    yield r
    for v in r.values():
        if isinstance(v, _Run) and v.proc.poll() is None:
            v.proc.kill()


@pytest.fixture(scope="module")
def checked(runs):
    return runs["check"]


@pytest.fixture(scope="module")
def designed(runs):
    return runs["design"], runs["tmp"] / "runs"


def test_check_every_example(checked):
    assert checked.returncode == 0, checked.stderr
    out = checked.stdout
    for name in example_names():
        assert f"fojax check: {name} ({example_path(name)})" in out
    # one verdict per plant, per fault-augmented system and per T-S rule
    assert out.count("Verdict: ") == len(example_names()) + 4 + 1
    assert "Takagi-Sugeno rule 2 of 2" in out
    # §3.1.2: the thesis's open-loop pole 3.06 (after the documented A[3,0] typo fix)
    assert "max Re = 3.064" in out
    assert "Assumption 1 yes" in out and "Assumption 1 NO" not in out


def test_design_every_example(designed):
    r, out = designed
    assert r.returncode == 0, r.stderr
    folders = sorted(p for p in out.iterdir() if p.is_dir())
    assert len(folders) == len(example_names()) == 8
    for name in example_names():
        (folder,) = [f for f in folders if f.name.startswith(f"design-{name}-")]
        assert (folder / "config.toml").read_bytes() == example_path(name).read_bytes()
        report = (folder / "report.md").read_text()
        assert report.startswith(f"# fojax design: {name}")
        npz = sorted(folder.glob("*.npz"))
        assert npz and len(npz) == len(list(folder.glob("poles-*.png")))
        for path in npz:
            d = load_design(path)
            assert d.report.passed
            assert read_design_metadata(path)["user"]["config_name"] == name
            assert f"![Error poles of '{path.stem}'](poles-{path.stem}.png)" in report
            img = mpimg.imread(folder / f"poles-{path.stem}.png")
            assert img.shape[:2] == (600, 800) and img[..., :3].std() > 0.01
    assert "verified" in r.stdout and "NO" not in r.stdout.split("verified")[-1]


def test_design_of_the_takagi_sugeno_example(designed):
    r, out = designed
    (folder,) = out.glob("design-robot_arm_ts-*")
    d = load_design(folder / "generalized.npz")
    assert type(d) is TakagiSugenoObserverDesign and d.report.passed
    assert d.observer.num_rules == 2 and d.structure.psi == "output"  # w = y (eq. 3.152)
    # the functional of the config, estimated with every rule's error poles in the disk
    assert np.array_equal(d.L, np.eye(5)[[1, 3]])
    assert np.all(np.abs(d.report.eigenvalues + 2.0) < 1.0) and d.report.eigenvalues.size == 8
    assert d.report.extra["lyapunov_max_eig"] < 0  # common certificate: time-varying weights
    # the verification is printed
    block = r.stdout.split("fojax design: robot_arm_ts")[1].split("results:")[0]
    assert "Takagi-Sugeno model with 2 rules" in block and "2 rules, common T" in block
    assert "verification PASSED" in block and "lyapunov_max_eig" in block


def test_study_of_takagi_sugeno_is_refused_with_one_line(runs):
    r = runs["ts_study"]
    if not STUDIES:
        assert r.returncode == 3
        return
    assert r.returncode == 2 and r.stdout == ""
    assert r.stderr.count("\n") == 1
    assert "[takagi_sugeno] studies of Takagi-Sugeno models are not available" in r.stderr
    assert not (runs["tmp"] / "ts-study").exists()


def test_second_design_never_destroys_the_first(tmp_path):
    first = fojax("--quiet", "design", "example_4_2_2", "--out", tmp_path, "--name", "run")
    assert first.returncode == 0 and first.stdout == "", first.stderr
    folder = tmp_path / "run"
    snapshot = {p.name: p.read_bytes() for p in folder.iterdir()}
    assert {"config.toml", "report.md", "designs.json", "generalized.npz", "poles-generalized.png"} <= set(snapshot)
    again = fojax("design", "example_4_2_2", "--out", tmp_path, "--name", "run")
    assert again.returncode == 2
    assert "run already exists and is not empty" in again.stderr and "--overwrite" in again.stderr
    timestamped = fojax("design", "example_4_2_2", "--out", tmp_path, "--quiet")
    assert timestamped.returncode == 0
    assert len([p for p in tmp_path.iterdir() if p.is_dir()]) == 2
    assert {p.name: p.read_bytes() for p in folder.iterdir()} == snapshot


@pytest.mark.parametrize("key,what", [(m[2], m[3]) for m in CLI_MALFORMED], ids=[m[2] for m in CLI_MALFORMED])
def test_malformed_config_fails_with_key(runs, key, what):
    r, p = runs[f"bad:{key}"], runs["bad"][key]
    assert r.returncode == 2 and r.stdout == ""
    line = r.stderr.strip()
    assert "\n" not in line
    assert line.startswith(f"fojax: error: {p}: [{key}] ")
    assert re.search(what, line)


def test_design_reports_bad_config_before_creating_a_folder(runs):
    r = runs["radius0"]
    assert r.returncode == 2
    assert "[observer[0].region.disk.radius] expected a positive number, got 0.0" in r.stderr
    assert not (runs["tmp"] / "radius0-out").exists()


def test_quiet_help_examples_and_study_placeholder(runs):
    r = runs["quiet"]
    assert r.returncode == 0 and r.stdout == "" and r.stderr == ""
    r = runs["help"]
    assert r.returncode == 0
    for word in ("check", "design", "study", "fojax examples", "docs/config.md", "64-bit"):
        assert word in r.stdout
    h = runs["design_help"]
    assert h.returncode == 0 and "example:" in h.stdout and "--overwrite" in h.stdout
    r = runs["examples"]
    assert r.returncode == 0 and all(n in r.stdout for n in example_names())
    r = runs["missing"]
    assert r.returncode == 2 and "[(file)] does not exist" in r.stderr


def test_design_npz_round_trip_bit_identical_from_cli(designed):
    _, out = designed
    path = next(out.glob("design-example_3_3_7-*/FGDO.npz"))
    d = load_design(path)
    with np.load(path, allow_pickle=False) as data:
        assert np.array_equal(np.asarray(d.observer.N), data["observer/N"])
        assert np.array_equal(d.X, data["X"])
    assert d.kind == "generalized" and d.structure.E.shape == (9, 9)


def test_default_study_and_a_second_run_keeps_the_first(runs):
    r = runs["study"]
    if not STUDIES:
        assert r.returncode == 3 and "not available yet" in r.stderr
        return
    assert r.returncode == 0, r.stderr
    assert "example_3_3_7" in r.stdout and "(mean IAE)" in r.stdout
    (first,) = list((runs["tmp"] / "study").iterdir())
    names = {p.name for p in first.iterdir()}
    assert {"PO.npz", "FGDO.npz", "report.md", "metrics.json", "metrics.npz", "study.npz",
            "error-bands.png", "iae.png", "poles-PO.png", "config.toml"} <= names
    for png in first.glob("*.png"):
        img = mpimg.imread(png)
        assert img.shape[:2] == (600, 800) and img[..., :3].std() > 0.01
    report = (first / "report.md").read_text()
    assert "| PO |" in report and "| FGDO |" in report and "![IAE per sample" in report
    if TUNING:
        assert {"FGDO-tuned.npz", "tuning-FGDO.png", "tuning-FGDO.npz"} <= names
        assert load_design(first / "FGDO-tuned.npz").report.passed
        assert "| FGDO-tuned |" in report and "Tuning (held-out mean IAE loss)" in report
    snapshot = {p.name: p.read_bytes() for p in first.iterdir()}
    again = fojax("--quiet", "study", "--samples", "4", "--horizon", "2", "--steps", "0",
                  "--out", runs["tmp"] / "study")
    assert again.returncode == 0 and again.stdout == "", again.stderr
    folders = sorted((runs["tmp"] / "study").iterdir())
    assert len(folders) == 2 and first in folders
    assert {p.name: p.read_bytes() for p in first.iterdir()} == snapshot
