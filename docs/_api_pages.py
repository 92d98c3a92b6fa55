"""The API reference pages, generated from the names fojax exports.

`mkdocs.yml` loads this file as a hook: `on_files` adds one page per subpackage of
`fojax` (``api/<name>.md``) and an index (``api/index.md``) for the top-level names, so
the reference follows `fojax/__init__.py` without a hand-kept list. `api_pages()` returns
the same pages as a dict; `tests/test_docs.py` uses it to check that every public name
is documented, without needing mkdocs.
"""

from __future__ import annotations

import importlib
import inspect
import pathlib
import types


try:
    from mkdocs.plugins import event_priority
except ImportError:  # the test imports this file without mkdocs
    def event_priority(priority):
        return lambda f: f


def public_names(module: types.ModuleType) -> list[str]:
    """The public names of `module`: its ``__all__``, else every attribute without a
    leading underscore (``from __future__ import annotations`` excluded)."""
    names = getattr(module, "__all__", None)
    if names is None:
        names = [n for n in vars(module) if not n.startswith("_")]
    return sorted(
        (n for n in names if not isinstance(getattr(module, n), __import__("__future__")._Feature)),
        key=str.lower,
    )


def subpackages(package: types.ModuleType) -> list[str]:
    """The public subpackages of `package`, in the order they are exported."""
    return [n for n in public_names(package) if isinstance(getattr(package, n), types.ModuleType)]


def _summary(obj) -> str:
    doc = inspect.getdoc(obj) if callable(obj) or inspect.isclass(obj) else None
    line = (doc or "").strip().split("\n\n")[0].replace("\n", " ")
    return line.replace("|", "\\|")


def _directive(path: str) -> list[str]:
    return [f"::: {path}", ""]


def api_pages(package_name: str = "fojax") -> dict[str, str]:
    """``{"api/index.md": markdown, "api/<sub>.md": markdown, ...}`` for `package_name`.

    Every public name of every public subpackage gets a ``::: fojax.<sub>.<name>``
    directive on its subpackage's page; a top-level name that is also exported by a
    subpackage links there from the index, the others are documented on the index.
    """
    package = importlib.import_module(package_name)
    subs = subpackages(package)
    pages: dict[str, str] = {}
    home: dict[int, str] = {}  # id(object) -> "sub.md#anchor" where it is documented
    for sub in subs:
        module = getattr(package, sub)
        names = [n for n in public_names(module) if not isinstance(getattr(module, n), types.ModuleType)]
        doc = (inspect.getdoc(module) or "").strip()
        lines = [f"# `{package_name}.{sub}`", ""]
        if doc:
            lines += [doc, ""]
        for n in names:
            lines += _directive(f"{package_name}.{sub}.{n}")
            home.setdefault(id(getattr(module, n)), f"{sub}.md#{package_name}.{sub}.{n}")
        pages[f"api/{sub}.md"] = "\n".join(lines)
    top = [n for n in public_names(package) if n not in subs]
    index = [
        "# API reference",
        "",
        f"Every name exported by `{package_name}` (generated from `{package_name}/__init__.py`). "
        "The subpackages have one page each:",
        "",
    ]
    index += [f"- [`{package_name}.{s}`]({s}.md)" for s in subs]
    index += ["", "## Top-level names", "", "| name | summary |", "|---|---|"]
    local = []
    for n in top:
        where = home.get(id(getattr(package, n)))
        if where is None:
            local.append(n)
            where = f"#{package_name}.{n}"
        index.append(f"| [`{package_name}.{n}`]({where}) | {_summary(getattr(package, n))} |")
    if local:
        index += ["", "## Documented here", ""]
        for n in local:
            index += _directive(f"{package_name}.{n}")
    pages["api/index.md"] = "\n".join(index)
    return pages


# ------------------------------------------------------------------ mkdocs hook
ROOT = pathlib.Path(__file__).resolve().parents[1]


def notebooks() -> list[str]:
    """The notebooks the site renders: every ``notebooks/*.ipynb`` of the repository."""
    return sorted(p.name for p in (ROOT / "notebooks").glob("*.ipynb"))


def on_config(config):
    """Expand the nav entries ``api/index.md`` (one page per subpackage) and
    ``notebooks/index.md`` (every notebook)."""

    def expand(items):
        out = []
        for item in items:
            if isinstance(item, dict):
                (title, value), = item.items()
                if value == "api/index.md":
                    value = ["api/index.md"] + [{f"fojax.{s}": f"api/{s}.md"} for s in _subs()]
                elif value == "notebooks/index.md":
                    value = [f"notebooks/{n}" for n in notebooks()]
                elif isinstance(value, list):
                    value = expand(value)
                out.append({title: value})
            else:
                out.append(item)
        return out

    config["nav"] = expand(config["nav"])
    return config


def _subs() -> list[str]:
    return subpackages(importlib.import_module("fojax"))


@event_priority(50)  # before mkdocs-jupyter's on_files, which wraps the notebooks
def on_files(files, config):
    from mkdocs.structure.files import File

    for path, text in api_pages().items():
        files.append(File.generated(config, path, content=text))
    for name in notebooks():
        files.append(File(f"notebooks/{name}", src_dir=str(ROOT), dest_dir=config["site_dir"],
                          use_directory_urls=config["use_directory_urls"]))
    return files
