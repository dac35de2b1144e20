"""The house's layering, kept: hostd's rooms stand on floors, and imports run down.

A room is a package under hostd/ (hostd/codec/, hostd/service/, ...) or a top-level module
(hostd/cliopts.py). FLOORS below is the layering, lowest first; docs/conventions.md points here.
The rules this file holds, read from the source's own imports (ast, nothing is imported):

- no import circle between modules through module-level imports (a circle makes import order
  matter and breaks lazy loading);
- a module-level import never runs from a room to a room on a higher floor;
- an import inside a function may reach up (a command loads its room lazily), but the number of
  such upward arrows may only fall: UPWARD_ARROWS_MAX is the count today;
- codec, perception and render never import service, device, corpus, experiment or fleet, at
  any depth; texture imports no command module; the service never imports the fleet room.
"""

from __future__ import annotations

import ast
import collections
from pathlib import Path

import pytest

HOSTD = Path(__file__).resolve().parent.parent / "hostd"

# Lowest first. Rooms on one floor may import each other at module level only without a circle.
FLOORS: tuple[frozenset[str], ...] = tuple(frozenset(f) for f in (
    {"hostd", "errors", "paths", "compiled", "pocketfft", "tty", "helptext", "tomlfile", "sqlitewal",
     "cyclestate", "procstat"},
    {"extras", "plotting", "fileio", "docgen"},
    {"render"},
    {"texture"},
    {"perception"},
    {"codec"},
    {"quality"},
    {"cliopts"},
    {"sim"},
    {"device", "corpus"},
    {"service"},
    {"api"},
    {"experiment", "bench", "fleet"},
    {"demo", "report"},
    {"commands", "export_cli"},
    {"parser"},
    {"cli", "__main__"},
))
COMMAND_MODULES = frozenset({"cliopts", "commands", "parser", "cli", "export_cli"})
NEVER = {  # room -> rooms it never imports, at any depth
    "codec": {"service", "device", "corpus", "experiment", "fleet"},
    "perception": {"service", "device", "corpus", "experiment", "fleet"},
    "render": {"service", "device", "corpus", "experiment", "fleet"},
    "texture": COMMAND_MODULES,
    "service": {"fleet"},
}
UPWARD_ARROWS_MAX = 7  # function-level imports from a room to a higher floor (room pairs), today


def _module_name(path: Path, root: Path = HOSTD) -> str:
    parts = list(path.relative_to(root.parent).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def room_of(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else "hostd"


def floor_of(room: str) -> int:
    for i, rooms in enumerate(FLOORS):
        if room in rooms:
            return i
    raise AssertionError(f"room {room!r} is on no floor: add it to FLOORS in {Path(__file__).name}")


def read_imports(root: Path = HOSTD) -> tuple[dict[str, set[str]], dict[str, set[str]]]:
    """(module-level, function-level) imports between hostd's own modules, as module -> modules.
    Imports under `if TYPE_CHECKING:` are left out: they never run."""
    mods = {_module_name(p, root): p for p in root.rglob("*.py")}
    top: dict[str, set[str]] = collections.defaultdict(set)
    inner: dict[str, set[str]] = collections.defaultdict(set)
    for mod, path in mods.items():
        pkg = mod if path.name == "__init__.py" else mod.rpartition(".")[0]

        def visit(node: ast.AST, at_top: bool, mod: str = mod, pkg: str = pkg) -> None:
            for child in ast.iter_child_nodes(node):
                if isinstance(child, ast.If) and getattr(child.test, "id", None) == "TYPE_CHECKING":
                    continue
                child_top = at_top and not isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef,
                                                              ast.Lambda))
                names: list[str] = []
                if isinstance(child, ast.Import):
                    names = [a.name for a in child.names]
                elif isinstance(child, ast.ImportFrom):
                    if child.level:
                        base = pkg.split(".")[: len(pkg.split(".")) - child.level + 1]
                        src = ".".join(base + ([child.module] if child.module else []))
                    else:
                        src = child.module or ""
                    # `from pkg import sub` imports the module pkg.sub; `from mod import name`, mod
                    names = [f"{src}.{a.name}" if f"{src}.{a.name}" in mods else src
                             for a in child.names]
                for name in names:
                    # a module's own packages are initialised before it: no arrow to them
                    if name in mods and name != mod and not mod.startswith(name + "."):
                        (top if child_top else inner)[mod].add(name)
                visit(child, child_top)

        visit(ast.parse(path.read_text(encoding="utf-8"), str(path)), True)
    return top, inner


@pytest.fixture(scope="module")
def imports():
    return read_imports()


def test_every_room_stands_on_a_floor(imports):
    rooms = {room_of(_module_name(p)) for p in HOSTD.rglob("*.py")}
    for room in sorted(rooms):
        floor_of(room)


def _circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    circles: list[list[str]] = []

    def strong(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                strong(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                circles.append(sorted(comp))

    for v in sorted(set(graph) | {w for ws in graph.values() for w in ws}):
        if v not in index:
            strong(v)
    return circles


def test_no_import_circle_at_all(imports):
    """Not even through imports inside functions: a module that reaches back to one that reaches
    it is a circle a maintainer trips on, lazily loaded or not."""
    top, inner = imports
    graph: dict[str, set[str]] = {}
    for edges in (top, inner):
        for a, bs in edges.items():
            graph.setdefault(a, set()).update(bs)
    circles = _circles(graph)
    assert not circles, f"import circles (module- and function-level imports): {circles}"


def test_no_import_circle_through_module_level_imports(imports):
    top, _ = imports
    circles = _circles(top)
    assert not circles, f"import circles through module-level imports: {circles}"


def test_module_level_imports_never_reach_a_higher_floor(imports):
    top, _ = imports
    up = sorted(f"{a} -> {b}" for a, bs in top.items() for b in bs
                if floor_of(room_of(b)) > floor_of(room_of(a)))
    assert not up, ("module-level imports from a lower room to a higher one (import inside the "
                    "function that needs it, or move the code to its floor): " + "; ".join(up))


def test_rooms_never_import_what_they_must_not(imports):
    top, inner = imports
    bad = []
    for edges in (top, inner):
        for a, bs in edges.items():
            for b in bs:
                if room_of(b) in NEVER.get(room_of(a), ()):
                    bad.append(f"{a} -> {b}")
    assert not bad, "imports the layering forbids: " + "; ".join(sorted(bad))


def test_upward_arrows_inside_functions_do_not_grow(imports):
    _, inner = imports
    arrows = {(room_of(a), room_of(b)) for a, bs in inner.items() for b in bs
              if floor_of(room_of(b)) > floor_of(room_of(a))}
    assert len(arrows) <= UPWARD_ARROWS_MAX, (
        f"{len(arrows)} room pairs import upward inside functions (at most {UPWARD_ARROWS_MAX}): "
        + "; ".join(f"{a} -> {b}" for a, b in sorted(arrows)))


def test_the_checker_sees_a_planted_circle_and_an_upward_import(tmp_path):
    """The reader is not blind: a tree with a circle and a codec -> service import is caught."""
    pkg = tmp_path / "hostd"
    (pkg / "codec").mkdir(parents=True)
    (pkg / "service").mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "codec" / "__init__.py").write_text("")
    (pkg / "service" / "__init__.py").write_text("")
    (pkg / "codec" / "a.py").write_text("from hostd.codec import b\n")
    (pkg / "codec" / "b.py").write_text("from . import a\n\ndef f():\n    import hostd.service.x\n")
    (pkg / "service" / "x.py").write_text("")
    top, inner = read_imports(pkg)
    assert "hostd.codec.b" in top["hostd.codec.a"] and "hostd.codec.a" in top["hostd.codec.b"]
    assert "hostd.service.x" in inner["hostd.codec.b"]


def test_the_readme_layout_map_names_every_room():
    """The README's "Layout (the data flow)" map is the first one a newcomer reads: every
    package of hostd/ and every top-level module of 150 lines or more stands in it."""
    readme = (HOSTD.parent / "README.md").read_text(encoding="utf-8")
    section = readme.split("## Layout (the data flow)", 1)[1].split("\n## ", 1)[0]
    missing = [f"hostd/{p.name}" for p in sorted(HOSTD.iterdir())
               if p.is_dir() and (p / "__init__.py").exists() and f"hostd/{p.name}" not in section]
    missing += [f"hostd/{p.name}" for p in sorted(HOSTD.glob("*.py"))
                if len(p.read_text(encoding="utf-8").splitlines()) >= 150
                and f"hostd/{p.name}" not in section]
    assert not missing, f"README.md's layout map does not name: {', '.join(missing)}"
