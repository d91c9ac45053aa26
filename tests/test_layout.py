"""The layout contract (docs/architecture.md): wings in layer order, no cycles, few local imports.

Every import statement of the two packages is read with :mod:`ast`, the ones inside functions
included, and checked against the layer order of ``docs/architecture.md``:

- ``rectify`` never imports ``stereo``; neither imports ``tests``;
- a module imports only from its own wing or a lower one (same-rank wings do not import each other);
- the import graph of the modules has no cycle;
- at most :data:`MAX_LOCAL_IMPORTS` imports inside functions, each with a one-line reason
  (a ``#`` comment on its line or the line above);
- ``rasterio`` is imported only under ``rectify/raster/`` (and by ``rectify/cli/options.py``, which maps
  its errors to one-line messages); ``pyproj`` only by ``rectify/geometry/crs.py``;
- no module is longer than :data:`MAX_LINES` lines.
"""

from __future__ import annotations

import ast
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
MAX_LOCAL_IMPORTS = 20
MAX_LINES = 900

#: rank of each wing (first name under the package); a module may import its own wing or a lower rank.
#: Wings of equal rank are independent of each other.
RECTIFY_RANKS = {"__init__": 0, "errors": 0, "atomic": 1, "geometry": 2, "raster": 3, "features": 4,
                 "formats": 4, "report": 5, "view": 5, "actions": 6, "cli": 7}
STEREO_RANKS = {"__init__": 0, "relative": 1, "calibration": 1, "pair": 2, "block": 3, "dense": 3,
                "features": 4, "formats": 5, "report": 5, "actions": 6, "cli": 7}
RANKS = {"rectify": RECTIFY_RANKS, "stereo": STEREO_RANKS}
RASTERIO_ALLOWED = ("rectify/raster/", "rectify/cli/options.py")
PYPROJ_ALLOWED = ("rectify/geometry/crs.py",)


@dataclass(frozen=True)
class Import:
    module: str  # importing module
    path: str  # its file, relative to the repository
    target: str  # absolute name of what is imported (module, or module.attribute)
    line: int
    local: bool  # inside a function
    reason: bool  # a comment on the line or the line above
    type_only: bool  # under ``if TYPE_CHECKING:``


def _modules() -> dict[str, Path]:
    out = {}
    for pkg in ("rectify", "stereo"):
        for p in sorted((ROOT / pkg).rglob("*.py")):
            parts = list(p.relative_to(ROOT).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            out[".".join(parts)] = p
    return out


def _imports(modules: dict[str, Path]) -> list[Import]:
    found = []
    for name, path in modules.items():
        src = path.read_text()
        lines = src.splitlines()
        tree = ast.parse(src)
        parents: dict[ast.AST, ast.AST] = {}
        for node in ast.walk(tree):
            for child in ast.iter_child_nodes(node):
                parents[child] = node
        for node in ast.walk(tree):
            if not isinstance(node, (ast.Import, ast.ImportFrom)):
                continue
            local = type_only = False
            up = parents.get(node)
            while up is not None:
                if isinstance(up, (ast.FunctionDef, ast.AsyncFunctionDef)):
                    local = True
                if isinstance(up, ast.If) and "TYPE_CHECKING" in ast.unparse(up.test):
                    type_only = True
                up = parents.get(up)
            here = lines[node.lineno - 1]
            above = lines[node.lineno - 2].strip() if node.lineno > 1 else ""
            reason = "#" in here or above.startswith("#")
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            else:
                if node.level:
                    base = name.split(".")
                    if path.name != "__init__.py":
                        base = base[:-1]
                    base = base[: len(base) - (node.level - 1)]
                    mod = ".".join(base + ([node.module] if node.module else []))
                else:
                    mod = node.module or ""
                targets = [f"{mod}.{a.name}" if f"{mod}.{a.name}" in modules else mod for a in node.names]
            rel = path.relative_to(ROOT).as_posix()
            found += [Import(name, rel, t, node.lineno, local, reason, type_only) for t in targets]
    return found


MODULES = _modules()
IMPORTS = _imports(MODULES)


def _owner(target: str) -> str | None:
    """The project module that ``target`` names (itself, or the module holding the attribute)."""
    while target and target not in MODULES:
        if "." not in target:
            return None
        target = target.rsplit(".", 1)[0]
    return target or None


def _wing(module: str) -> tuple[str, str]:
    parts = module.split(".")
    return parts[0], (parts[1] if len(parts) > 1 else "__init__")


def test_every_module_is_in_a_wing() -> None:
    unknown = sorted(m for m in MODULES if _wing(m)[1] not in RANKS[_wing(m)[0]])
    assert unknown == [], f"modules outside the wings of docs/architecture.md: {unknown}"


def test_rectify_never_imports_stereo_and_no_package_imports_tests() -> None:
    bad = [f"{i.path}:{i.line} imports {i.target}" for i in IMPORTS
           if i.target.split(".")[0] == "tests"
           or (i.module.startswith("rectify") and i.target.split(".")[0] == "stereo")]
    assert bad == []


def test_no_wing_imports_a_higher_or_sibling_wing() -> None:
    bad = []
    for i in IMPORTS:
        owner = _owner(i.target)
        if owner is None:
            continue
        (pkg, wing), (tpkg, twing) = _wing(i.module), _wing(owner)
        if pkg != tpkg or wing == twing:
            continue  # stereo may use any rectify wing; a wing may use itself
        ranks = RANKS[pkg]
        if ranks[twing] >= ranks[wing]:
            bad.append(f"{i.path}:{i.line}: {wing} (rank {ranks[wing]}) imports {owner} ({twing}, rank {ranks[twing]})")
    assert bad == [], "\n".join(bad)


def test_no_import_cycles() -> None:
    edges: dict[str, set[str]] = {m: set() for m in MODULES}
    for i in IMPORTS:
        owner = _owner(i.target)
        if owner is not None and owner != i.module and not i.type_only:
            edges[i.module].add(owner)
            # importing a.b.c runs a/__init__ and a/b/__init__ too
            parts = owner.split(".")
            for k in range(1, len(parts)):
                parent = ".".join(parts[:k])
                if parent in MODULES and parent != i.module and not i.module.startswith(parent + "."):
                    edges[i.module].add(parent)
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    cycles: list[list[str]] = []

    def visit(v: str) -> None:  # Tarjan's strongly connected components
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in sorted(edges[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                cycles.append(sorted(comp))

    for v in sorted(MODULES):
        if v not in index:
            visit(v)
    assert cycles == []


def test_few_local_imports_each_with_a_reason() -> None:
    local = [i for i in IMPORTS if i.local]
    statements = {(i.path, i.line) for i in local}
    assert len(statements) <= MAX_LOCAL_IMPORTS, sorted(statements)
    unexplained = sorted({f"{i.path}:{i.line}" for i in local if not i.reason})
    assert unexplained == [], "local imports without a one-line reason"


@pytest.mark.parametrize(("library", "allowed"), [("rasterio", RASTERIO_ALLOWED), ("pyproj", PYPROJ_ALLOWED)])
def test_library_behind_its_one_door(library: str, allowed: tuple[str, ...]) -> None:
    bad = sorted({f"{i.path}:{i.line}" for i in IMPORTS
                  if i.target.split(".")[0] == library and not i.path.startswith(allowed)})
    assert bad == [], f"{library} imported outside {allowed}"


def test_no_module_over_the_line_limit() -> None:
    long = sorted((n, p.relative_to(ROOT).as_posix()) for p in MODULES.values()
                  if (n := len(p.read_text().splitlines())) > MAX_LINES)
    assert long == []
