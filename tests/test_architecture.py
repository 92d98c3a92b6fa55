"""The floors of fojax (docs: CONTRIBUTING, `fojax/__init__.py`): every import inside `fojax/`
goes down the house, and no two modules import each other at module level.

Oracle: the import statements themselves, read from the source with `ast` (module level and
inside functions), not the interpreter's module cache, so a lazy import cannot hide an arrow up.
"""

import ast
import pathlib

import pytest

import fojax


ROOT = pathlib.Path(fojax.__file__).parent

#: bottom to top; a package may import only the ground floor and packages listed before it
FLOORS = (
    "ground",  # _errors, _dtype, _linalg, _io, _serialize, _small_linalg, _background, errors
    "plant",
    "models",
    "analysis",
    "observer",
    "design",
    "simulation",
    "interop",
    "control",
    "studies",
    "results",
    "tuning",
    "config",
    "cli",
)


def _module_name(path: pathlib.Path) -> str:
    parts = ("fojax",) + path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _floor(module: str) -> str:
    parts = module.split(".")
    if len(parts) == 1:
        return "fojax"
    return "ground" if parts[1].startswith("_") or parts[1] == "errors" else parts[1]


def _imports(path: pathlib.Path, top_level_only: bool):
    """``(imported fojax module, line)`` of every import in ``path``."""
    name = _module_name(path)
    package = name if path.name == "__init__.py" else name.rsplit(".", 1)[0]
    tree = ast.parse(path.read_text(encoding="utf-8"))
    nodes = tree.body if top_level_only else ast.walk(tree)
    for node in nodes:
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                module = ".".join(base + ([node.module] if node.module else []))
            else:
                module = node.module or ""
            if module == "fojax" or module.startswith("fojax."):
                # `from . import x` names a submodule when one exists
                subs = [f"{module}.{a.name}" for a in node.names if _exists(f"{module}.{a.name}")]
                for target in subs or [module]:
                    yield target, node.lineno
        elif isinstance(node, ast.Import):
            for a in node.names:
                if a.name == "fojax" or a.name.startswith("fojax."):
                    yield a.name, node.lineno


def _exists(module: str) -> bool:
    rel = pathlib.Path(*module.split(".")[1:])
    return (ROOT / rel).with_suffix(".py").is_file() or (ROOT / rel / "__init__.py").is_file()


SOURCES = sorted(ROOT.rglob("*.py"))


def test_the_floor_list_covers_every_package():
    packages = {_floor(_module_name(p)) for p in SOURCES} - {"fojax"}
    assert packages == set(FLOORS)


def test_no_import_goes_up_a_floor():
    rank = {f: i for i, f in enumerate(FLOORS)}
    up = []
    for path in SOURCES:
        here = _floor(_module_name(path))
        if here == "fojax":  # the top-level package re-exports every floor
            continue
        for target, line in _imports(path, top_level_only=False):
            there = _floor(target)
            if there == "fojax":  # the umbrella package (every floor below cli) is for cli only
                there = "config" if here == "cli" else "cli"
            if rank[there] > rank[here]:
                up.append(f"{path.relative_to(ROOT)}:{line} ({here}) imports {target} ({there})")
    assert not up, "imports that go up the house:\n" + "\n".join(up)


def test_no_module_level_import_cycle():
    graph = {_module_name(p): {t for t, _ in _imports(p, top_level_only=True)} for p in SOURCES}
    index, low, stack, on_stack, cycles = {}, {}, [], set(), []

    def visit(v):  # Tarjan's strongly connected components
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                cycles.append(sorted(component))

    for v in graph:
        if v not in index:
            visit(v)
    assert cycles == []


@pytest.mark.parametrize("path", SOURCES, ids=lambda p: str(p.relative_to(ROOT)))
def test_no_file_is_longer_than_700_lines(path):
    assert len(path.read_text(encoding="utf-8").splitlines()) <= 700
