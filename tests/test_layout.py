"""The house rules of the tree (docs/design.md, "The map of the tree"): no import circles, and
every import of swarmloc/, agents/ and netsim/ in a direction the room table allows.

The table is read from the doc, so the doc and the code cannot drift apart. Imports are read
with ast, those inside functions too: an import deferred to save start-up time is still a
dependency."""

import ast
import functools
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("swarmloc", "agents", "netsim")


def module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES = {module_name(f): f for pkg in PACKAGES for f in (ROOT / pkg).rglob("*.py")}


@functools.cache
def _tree(path: Path) -> ast.AST:
    return ast.parse(path.read_text(), str(path))


def imports_of(name: str, path: Path):
    """(imported name, line) for every import in the file, relative ones resolved; a
    `from package import module` counts as importing the module."""
    package = name.split(".") if path.name == "__init__.py" else name.split(".")[:-1]
    for node in ast.walk(_tree(path)):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield alias.name, node.lineno
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                base = ".".join(package[: len(package) - node.level + 1] + ([base] if base else []))
            for alias in node.names:
                sub = f"{base}.{alias.name}"
                yield (sub if sub in MODULES else base), node.lineno


@functools.cache
def edges() -> dict[str, dict[str, int]]:
    """module -> {project module it imports: first line}."""
    out = {}
    for name, path in MODULES.items():
        mine = {}
        for target, line in imports_of(name, path):
            while target and target not in MODULES:  # `import a.b.c` of a name inside a module
                target = target.rpartition(".")[0]
            if target and target != name:
                mine.setdefault(target, line)
        out[name] = mine
    return out


def room_table() -> dict[str, set[str]]:
    text = (ROOT / "docs" / "design.md").read_text()
    block = text.split("<!-- rooms: read by tests/test_layout.py -->", 1)[1]
    rooms = {}
    for line in block.strip().splitlines():
        if not line.startswith("|"):
            break
        cells = [c.strip() for c in line.strip("|").split("|")]
        m = re.fullmatch(r"`([\w.]+)`", cells[0])
        if m:
            rooms[m.group(1)] = set(re.findall(r"`([\w.]+)`", cells[-1]))
    return rooms


ROOMS = room_table()


def room_of(module: str) -> str:
    """The room a module is in: its own name if it is a room (swarmloc.node), else the longest
    room whose package holds it."""
    if module in ROOMS:
        return module
    parts = module.split(".")
    for n in range(len(parts) - 1, 0, -1):
        if ".".join(parts[:n]) in ROOMS:
            return ".".join(parts[:n])
    raise AssertionError(f"{module} is in no room of docs/design.md's table")


def test_the_table_names_real_rooms_and_every_module_has_one():
    assert len(ROOMS) >= 15, "the room table was not found in docs/design.md"
    for room, allowed in ROOMS.items():
        assert room in MODULES or any(m.startswith(room + ".") for m in MODULES), f"no code in room {room}"
        assert allowed <= set(ROOMS), f"{room} may import {sorted(allowed - set(ROOMS))}, which are not rooms"
    for m in MODULES:
        room_of(m)


def test_no_import_circles():
    graph = {m: set(t) for m, t in edges().items()}
    index, low, stack, on, circles, counter = {}, {}, [], set(), [], [0]

    def connect(v):  # Tarjan: strongly connected components
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in graph[v]:
            if w not in index:
                connect(w)
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
                circles.append(sorted(comp))

    for v in graph:
        if v not in index:
            connect(v)
    assert not circles, f"import circles: {circles}"


def test_every_import_goes_a_documented_direction():
    wrong = []
    for module, targets in edges().items():
        src = room_of(module)
        for target, line in targets.items():
            dst = room_of(target)
            if dst != src and dst not in ROOMS[src]:
                wrong.append(f"{MODULES[module].relative_to(ROOT)}:{line}: {module} ({src}) imports {target} ({dst})")
    assert not wrong, "imports against docs/design.md's room table:\n" + "\n".join(wrong)


def test_rooms_do_not_import_each_other_both_ways():
    both = sorted({tuple(sorted((a, b))) for a, allowed in ROOMS.items() for b in allowed if a in ROOMS.get(b, ())})
    assert not both, f"rooms allowed to import each other: {both}"


@pytest.mark.parametrize("forbidden", ["zenoh", "socket"])
def test_the_core_opens_no_session_and_no_socket(forbidden):
    hits = [f"{MODULES[m].relative_to(ROOT)}:{line}" for m, path in MODULES.items() if m.split(".")[0] == "swarmloc"
            for target, line in imports_of(m, path) if target.split(".")[0] == forbidden]
    assert not hits, f"swarmloc/ imports {forbidden}: {hits}"
