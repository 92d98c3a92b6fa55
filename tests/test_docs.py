"""The documentation covers the package; the package's docstrings document, not narrate.

Oracles:
- the public names of fojax and of each public subpackage are read from the source of their
  ``__init__.py`` (``from ._x import Y as Y`` re-exports, parsed with `ast`), independently of
  the generator of the API pages (`docs/_api_pages.py`, which reads the imported modules);
  each must appear on a page as a ``::: fojax.<...>`` directive that resolves to the same
  object (the idea of optax's ``docs/ext/coverage_check.py``). mkdocs itself is not needed.
- every page of the navigation in ``mkdocs.yml`` exists, and every notebook is stored with
  its outputs (the site renders them as stored: ``docs/execute_notebooks.py``).
- lab notes in ``fojax/`` (timings under load, machine names, internal issue numbers,
  dated measurements) are counted by regular expressions on the source text.
- every test module names its oracle at the top and is on the map of ``tests/README.md``
  (the module docstrings parsed with `ast`).
"""

from __future__ import annotations

import ast
import collections
import importlib
import importlib.util
import json
import pathlib
import re


ROOT = pathlib.Path(__file__).resolve().parents[1]


def _api_module():
    spec = importlib.util.spec_from_file_location("_fojax_api_pages", ROOT / "docs" / "_api_pages.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _reexports(init: pathlib.Path) -> set[str]:
    """Names an ``__init__.py`` re-exports: ``from x import Y as Y`` and ``from . import y as y``."""
    names = set()
    for node in ast.walk(ast.parse(init.read_text())):
        if isinstance(node, ast.ImportFrom):
            names |= {a.asname for a in node.names if a.asname and a.asname == a.name and not a.name.startswith("_")}
    return names


def _resolve(path: str):
    parts = path.split(".")
    obj = importlib.import_module(parts[0])
    for p in parts[1:]:
        obj = getattr(obj, p)
    return obj


def test_every_public_name_is_on_an_api_page():
    import fojax

    pages = _api_module().api_pages()
    directives = collections.defaultdict(list)  # id(object) -> ["fojax.x.Y", ...]
    text = "\n".join(pages.values())
    for path in re.findall(r"^::: (\S+)$", text, flags=re.M):
        directives[id(_resolve(path))].append(path)
    top = _reexports(ROOT / "fojax" / "__init__.py")
    assert top, "no re-exports found in fojax/__init__.py"
    missing = []
    for name in sorted(top):
        obj = getattr(fojax, name)
        if isinstance(obj, type(fojax)):  # a subpackage: its own page and names
            assert f"api/{name}.md" in pages, name
            for sub in sorted(_reexports(ROOT / "fojax" / name / "__init__.py")):
                if not isinstance(getattr(obj, sub), type(fojax)) and id(getattr(obj, sub)) not in directives:
                    missing.append(f"fojax.{name}.{sub}")
        elif id(obj) not in directives:
            missing.append(f"fojax.{name}")
    assert not missing, f"public names without an API entry: {missing}"


def test_the_api_index_links_every_top_level_name():
    import fojax

    index = _api_module().api_pages()["api/index.md"]
    for name in _reexports(ROOT / "fojax" / "__init__.py"):
        if not isinstance(getattr(fojax, name), type(fojax)):
            assert f"[`fojax.{name}`]" in index, name


def _nav_pages() -> list[str]:
    return re.findall(r"^\s*- (?:[^:\n]+: )?([\w./-]+\.(?:md|ipynb))\s*$", (ROOT / "mkdocs.yml").read_text(), flags=re.M)


def test_every_page_of_the_navigation_exists():
    pages = _nav_pages()
    assert len(pages) >= 15
    generated = {"api/index.md", "notebooks/index.md"}  # expanded by docs/_api_pages.py
    assert generated <= set(pages)
    for page in set(pages) - generated:
        assert (ROOT / "docs" / page).is_file(), page
    # the hook expands the generated entries into one page per subpackage and per notebook
    api = _api_module()
    nav = api.on_config({"nav": [{"API reference": "api/index.md"}, {"Notebooks": "notebooks/index.md"}]})["nav"]
    assert nav[0]["API reference"][0] == "api/index.md"
    assert {next(iter(d.values())) for d in nav[0]["API reference"][1:]} == {
        p for p in api.api_pages() if p != "api/index.md"}
    assert nav[1]["Notebooks"] == [f"notebooks/{n}" for n in api.notebooks()]


def test_notebooks_are_stored_with_their_outputs():
    notebooks = sorted((ROOT / "notebooks").glob("*.ipynb"))
    with_figures = 0
    for path in notebooks:
        nb = json.loads(path.read_text())
        code = [c for c in nb["cells"] if c["cell_type"] == "code" and "".join(c["source"]).strip()]
        counts = [c.get("execution_count") for c in code]
        fix = f"run `python docs/execute_notebooks.py {path.relative_to(ROOT)}`"
        assert counts == list(range(1, len(code) + 1)), f"{path.name} is not stored executed in order: {fix}"
        outputs = [o for c in code for o in c.get("outputs", [])]
        assert not [o for o in outputs if o.get("output_type") == "error"], f"{path.name} stored with an error"
        with_figures += any("image/png" in o.get("data", {}) for o in outputs)
        assert "matplotlib.use(" not in "".join("".join(c["source"]) for c in code), (
            f"{path.name}: select no backend, the inline one draws the figures into the page")
    assert with_figures >= 4


# ------------------------------------------------------------------------------- lab notes
LAB_NOTES = {
    # "measured" as a lab note (a measurement narrated), not "the measured output/signal"
    "measured": re.compile(
        r"(?<!the )(?<!same )(?<!a )(?<!not )(?<!\*)\b[Mm]easured\b"
        r"(?!\*|\(| (?:signals?|outputs?|data|inputs?|values?|vector|premise|from|by|directions|\$|\\Delta))"),
    "load": re.compile(r"under (?:heavy |light )?load|load average|\bat (?:light )?load\b|loaded machine|\bload \d",
                       re.I),
    "issue number": re.compile(r"\bissues? #?\d+", re.I),
    "machine": re.compile(r"\b(?:Xeon|EPYC|Haswell|Sandybridge|Ryzen|Skylake)\b"),
    "date": re.compile(r"\b20\d\d-\d\d-\d\d\b"),
    "CPU time": re.compile(r"\d s of CPU|\bCPU seconds\b|\bseconds of CPU\b"),
}


def lab_notes(files=None) -> list[tuple[str, int, str, str]]:
    """``(file, line, kind, text)`` of every lab-note phrase in ``fojax/**/*.py``."""
    out = []
    for f in files or sorted((ROOT / "fojax").rglob("*.py")):
        for i, line in enumerate(f.read_text(encoding="utf-8").splitlines(), 1):
            for kind, pattern in LAB_NOTES.items():
                out += [(str(f.relative_to(ROOT)), i, kind, line.strip()) for _ in pattern.finditer(line)]
    return out


# files no other area owns; their docstrings and comments carry no lab note
CLEAN = ["fojax/_io.py", "fojax/_dtype.py", "fojax/_background.py", "fojax/results/__init__.py",
         "fojax/design/_parameterization.py", "fojax/design/_takagi_sugeno.py", "fojax/design/_fault.py",
         "fojax/design/_finite_time.py", "fojax/design/_base.py", "fojax/design/_regions.py",
         "fojax/design/_gain_parameterization.py", "fojax/design/_legacy_io.py"]


def test_no_lab_notes_in_the_ground_floor_files():
    files = [ROOT / f for f in CLEAN if (ROOT / f).exists()]
    assert not lab_notes(files), lab_notes(files)


def test_at_most_five_lab_notes_in_fojax():
    found = lab_notes()
    assert len(found) <= 5, "\n".join(f"{f}:{i}: [{k}] {t}" for f, i, k, t in found)


if __name__ == "__main__":  # python tests/test_docs.py: the lab notes left, per file and kind
    found = lab_notes()
    print(len(found), dict(collections.Counter(k for _, _, k, _ in found)))
    for f, n in collections.Counter(f for f, _, _, _ in found).most_common():
        print(f"{n:4d} {f}")


# ------------------------------------------------------------------------------ the site
def test_every_test_module_names_its_oracle_and_is_on_the_map():
    """Each test module opens with a docstring naming its independent oracle, and
    ``tests/README.md`` (the map of public concepts to test modules) lists it."""
    tests = ROOT / "tests"
    readme = (tests / "README.md").read_text()
    for path in sorted(tests.glob("test_*.py")):
        doc = ast.get_docstring(ast.parse(path.read_text())) or ""
        assert re.search(r"[Oo]racle|[Ii]ndependent", doc), f"{path.name}: the module docstring names no oracle"
        assert f"`{path.name}`" in readme, f"{path.name} is not on the map in tests/README.md"


def test_the_site_builds_strictly(tmp_path):
    """``mkdocs build --strict`` (mkdocs-material, mkdocstrings, mkdocs-jupyter: the ``docs``
    extra, part of ``test``): every page, cross-reference and API directive resolves."""
    import os
    import subprocess
    import sys

    env = dict(os.environ, NO_MKDOCS_2_WARNING="1")
    r = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--quiet",
                        "--site-dir", str(tmp_path / "site")],
                       cwd=ROOT, env=env, capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, r.stdout[-4000:] + r.stderr[-4000:]
    assert (tmp_path / "site" / "index.html").exists()
    assert (tmp_path / "site" / "api" / "index.html").exists()
