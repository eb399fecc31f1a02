"""The package's layers: no module of ``flatserve`` imports, directly or through others,
a module that imports it back (an import circle). Imports inside functions count: a
circle closed by a late import is still two modules that each need the other. And the
calls between the cluster's processes are the methods of Protocols that mypy checks
(:mod:`flatserve.service.cluster.wire`).

The graph is read from the source (``ast``), not from ``sys.modules``: nothing is
imported, and an import that only runs in some process (a Ray actor's) counts too.
"""
from __future__ import annotations

import ast
import re
import subprocess
import sys
import textwrap
from pathlib import Path

import flatserve

ROOT = Path(flatserve.__file__).resolve().parent


def modules(root: Path = ROOT) -> dict[str, Path]:
    """Every module of the package under ``root``, by dotted name (a package by its
    ``__init__.py``)."""
    out = {}
    for path in sorted(root.rglob("*.py")):
        parts = list(path.relative_to(root.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts.pop()
        out[".".join(parts)] = path
    return out


def is_extension(package: Path, name: str) -> bool:
    """``name`` in the package directory ``package`` is a compiled extension (or its stub)."""
    return (package / f"{name}.pyi").exists() or any(package.glob(f"{name}.*.so"))


def imports(name: str, path: Path, mods: dict[str, Path]) -> set[str]:
    """The package's modules that module ``name`` (at ``path``) imports, anywhere in it."""
    is_pkg = path.name == "__init__.py"
    out: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names if a.name in mods)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = name.split(".") if is_pkg else name.split(".")[:-1]
                base = base[:len(base) - (node.level - 1)]
                src = ".".join(base + ([node.module] if node.module else []))
            else:
                src = node.module or ""
            for a in node.names:
                if f"{src}.{a.name}" in mods:  # a submodule
                    out.add(f"{src}.{a.name}")
                elif src in mods and not is_extension(mods[src].parent, a.name):
                    out.add(src)  # a name of a module
    out.discard(name)
    return out


def import_graph(root: Path = ROOT) -> dict[str, set[str]]:
    """Module -> the package's modules it imports."""
    mods = modules(root)
    return {m: imports(m, p, mods) for m, p in mods.items()}


def circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected groups of more than one module (Tarjan's, iterative):
    each is at least one import circle."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []
    for start in graph:
        if start in index:
            continue
        work = [(start, iter(sorted(graph[start])))]
        index[start] = low[start] = len(index)
        stack.append(start)
        on.add(start)
        while work:
            v, it = work[-1]
            w = next(it, None)
            if w is not None:
                if w not in index:
                    index[w] = low[w] = len(index)
                    stack.append(w)
                    on.add(w)
                    work.append((w, iter(sorted(graph[w]))))
                elif w in on:
                    low[v] = min(low[v], index[w])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[v])
            if low[v] == index[v]:
                group = []
                while True:
                    w = stack.pop()
                    on.discard(w)
                    group.append(w)
                    if w == v:
                        break
                if len(group) > 1:
                    out.append(sorted(group))
    return out


def test_the_graph_sees_the_service_and_the_cluster_wing():
    g = import_graph()
    assert "flatserve.service.rooms.applier" in g["flatserve.service.rooms.replica"]
    # a late import (inside a function) counts
    assert "flatserve.service.cluster.front.home" in g["flatserve.service.assembly"]
    # the extension is not a module of the package: no edge to the package itself
    assert "flatserve" not in g["flatserve._native"]


def test_circles_are_found():
    assert circles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert circles({"a": {"b"}, "b": set()}) == []


def test_no_import_circle_in_flatserve():
    found = circles(import_graph())
    assert found == [], "import circles: " + "; ".join(" <-> ".join(c) for c in found)


def test_mypy_checks_the_wire(tmp_path):
    """A shard worker and a tile's actor implement the calls between processes
    (:mod:`flatserve.service.cluster.wire`), checked by mypy as the field contract is;
    a class that lacks one fails, and a tile's proxy reads with the tile's own
    signatures (a read called with a missing argument fails)."""
    path = tmp_path / "check.py"
    path.write_text(textwrap.dedent("""
        from flatserve.service.cluster.worker.shard import ShardWorker
        from flatserve.service.cluster.worker.tile_actor import TileActor
        from flatserve.service.cluster.worker.tiles import RemoteTile
        from flatserve.service.cluster.wire import ShardCalls, TileCalls


        def check(worker: ShardWorker, tile: TileActor, proxy: RemoteTile) -> None:
            shard: ShardCalls = worker
            held: TileCalls = tile
            n: int = proxy.count_cells()
            proxy.within([[0.0]], 1.0)


        class NoParts:
            def query(self, work: list, kw: dict, at_position: int, timeout: float) -> list:
                return []

            def applied(self, position: int, timeout: float) -> dict:
                return {}

            def status(self) -> dict:
                return {}


        wrong: ShardCalls = NoParts()
    """))
    got = subprocess.run(
        [sys.executable, "-m", "mypy", "--follow-imports=silent", "--ignore-missing-imports",
         "--no-error-summary", "--cache-dir", str(tmp_path / "cache"), str(path)],
        capture_output=True, text=True, timeout=600, cwd=ROOT.parent)
    errors = [line for line in got.stdout.splitlines() if ": error:" in line]
    assert len(errors) == 2 and "check.py:12: error: Too few arguments" in errors[0], \
        got.stdout
    assert "check.py:26" in errors[1] and "parts" in got.stdout, got.stdout


SERVICE = ROOT / "service"
#: the most modules directly in ``flatserve/service/`` (the rest are in its rooms by
#: process: ``http/``, ``rooms/``, ``log/``, ``cluster/``)
MAX_TOP_MODULES = 15
#: the most lines of one service module
MAX_MODULE_LINES = 600


def test_the_service_is_laid_out_by_process():
    top = sorted(p.name for p in SERVICE.glob("*.py"))
    assert len(top) <= MAX_TOP_MODULES, top
    for room in ("http", "rooms", "log", "cluster", "cluster/front", "cluster/worker"):
        assert (SERVICE / room / "__init__.py").exists(), room


def test_no_service_module_is_longer_than_the_cap():
    long = {str(p.relative_to(ROOT)): n for p in SERVICE.rglob("*.py")
            if (n := len(p.read_text().splitlines())) > MAX_MODULE_LINES}
    assert long == {}, long


def calls_of(path: Path, name: str) -> int:
    """Calls of a method or function named ``name`` in the module at ``path``."""
    return sum(1 for node in ast.walk(ast.parse(path.read_text()))
               if isinstance(node, ast.Call)
               and getattr(node.func, "attr", getattr(node.func, "id", None)) == name)


def test_one_service_module_reads_the_log():
    """The follower reads the shared log (a shard worker runs the same follower); the
    storage room only implements the reading."""
    readers = sorted(str(p.relative_to(SERVICE)) for p in SERVICE.rglob("*.py")
                     if "log" not in p.relative_to(SERVICE).parts[:1]
                     and (calls_of(p, "read_log") or calls_of(p, "wait_for_change")))
    assert readers == ["rooms/replica.py"], readers


def test_no_call_between_processes_is_named_by_a_string():
    """The cluster wing calls no method by a computed name (``getattr(actor, name)``):
    every call between processes is a method of a Protocol (:mod:`..cluster.wire`)."""
    found = []
    for path in (SERVICE / "cluster").rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if (isinstance(node, ast.Call) and getattr(node.func, "id", None) == "getattr"
                    and not (len(node.args) > 1 and isinstance(node.args[1], ast.Constant))):
                found.append(f"{path.name}:{node.lineno}")
    assert found == [], found


#: per room of the service, the rooms (and top-level modules) it must not import: the
#: face talks to the domain only, the domain never to the face or the cluster, storage
#: to nothing of the service but its errors; what runs in actors never needs the front
FORBIDDEN = {
    "log": ("http", "rooms", "cluster", "assembly", "app", "server", "reports", "schemas"),
    "rooms": ("http", "cluster", "assembly", "app", "server", "supervisor", "demo"),
    "http": ("log", "cluster", "assembly", "server", "supervisor"),
    "cluster.worker": ("http", "cluster.front", "assembly", "app", "server"),
    "cluster.front": ("http", "log", "assembly", "app", "server"),
}


def room_of(module: str) -> str | None:
    """The room of a module of the service (``http``, ``rooms``, ``log``,
    ``cluster.front``, ``cluster.worker``, ``cluster`` for its shared modules, or a
    top-level module's own name); None outside the service."""
    prefix = "flatserve.service."
    if not module.startswith(prefix):
        return None
    parts = module[len(prefix):].split(".")
    if parts[0] == "cluster" and len(parts) > 1 and parts[1] in ("front", "worker"):
        return f"cluster.{parts[1]}"
    return parts[0]


def test_each_room_imports_only_what_its_process_and_layer_allow():
    g = import_graph()
    wrong = sorted(f"{m} -> {d}" for m, deps in g.items() for d in deps
                   if (r := room_of(m)) in FORBIDDEN and room_of(d) in FORBIDDEN[r])
    assert wrong == [], wrong


def defined_names(path: Path) -> set[str]:
    """The names a module defines at any level (classes, functions, assignments,
    attributes set on ``self``), and those it publishes from elsewhere (its
    ``__all__``; a package's ``__init__``, every name it imports: ``flatserve.Field``)."""
    names: set[str] = set()
    tree = ast.parse(path.read_text())
    for node in tree.body:
        if (isinstance(node, ast.Assign) and any(getattr(t, "id", None) == "__all__"
                                                 for t in node.targets)
                and isinstance(node.value, (ast.List, ast.Tuple))):
            names.update(e.value for e in node.value.elts if isinstance(e, ast.Constant))
    for node in ast.walk(tree):
        if isinstance(node, (ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)):
            names.add(node.name)
        elif isinstance(node, (ast.Assign, ast.AnnAssign)):
            for t in (node.targets if isinstance(node, ast.Assign) else [node.target]):
                if isinstance(t, ast.Name):
                    names.add(t.id)
                elif isinstance(t, ast.Attribute):
                    names.add(t.attr)
        elif isinstance(node, (ast.Import, ast.ImportFrom)) and path.name == "__init__.py":
            names.update((a.asname or a.name).split(".")[0] for a in node.names)
    return names


REFERENCE = re.compile(r":(?:mod|class|func|meth|data|attr|exc):`~?([.\w]+)`")


def test_the_module_docs_cross_references_resolve():
    """Every ``:class:`~.x.Y``` (relative, or ``flatserve.``) of the package's docs names
    a module that exists and a name it defines (not one it imports from elsewhere): a
    module or a class moved takes its readers along."""
    mods = modules()
    names = {m: defined_names(p) for m, p in mods.items()}
    bad = []
    for m, path in mods.items():
        base = m.split(".") if path.name == "__init__.py" else m.split(".")[:-1]
        for lineno, line in enumerate(path.read_text().splitlines(), 1):
            for ref in REFERENCE.findall(line):
                if ref.startswith("."):
                    level = len(ref) - len(ref.lstrip("."))
                    full = ".".join(base[:len(base) - (level - 1)] + [ref.lstrip(".")]).rstrip(".")
                elif ref.startswith("flatserve."):
                    full = ref
                else:
                    continue
                parts = full.split(".")
                found = next((k for k in range(len(parts), 0, -1)
                              if ".".join(parts[:k]) in mods), None)
                if found is None or (parts[found:] and
                                     parts[found] not in names[".".join(parts[:found])]):
                    bad.append(f"{path.relative_to(ROOT.parent)}:{lineno}: {ref}")
    assert bad == [], "\n".join(bad)
