"""The house rules of the tree (docs/design.md, "The map of the tree"): no import circles, and
every import of swarmloc/, agents/ and netsim/ in a direction the room table allows; and every
file, class and method the page names exists.

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


# --------------------------------------------------------------------------- the page names real code
#
# docs/design.md names files, classes and methods ("`NetsimServer._lockstep_tick` hands the round
# to `Simulation.exchange_batch`"); a rename must not leave the page pointing at nothing. Only
# backticks that are code by their shape are checked, one line each (no code name here spans two):
#   - a path: `netsim/sim.py`, `netsim/channel/`; in the room table a bare `chains.py` or
#     `scenarios/*.yaml` is taken from the row's room;
#   - a dotted name whose head is code: a package (`swarmloc.wire.decode`), a class
#     (`Simulation.offer`) or a module of the tree by its last name (`auth.check_delivery`),
#     with or without a call after it (`UkfDclNode.receive(1, token)`);
#   - a call (`step(sensors)`), a CamelCase class (`Outbox`) or a private name (`_on_tx`).
# Everything else in backticks is prose for this test: scenario fields (`clock.mode`),
# estimator names (`ekf-ci`), keys (`radio/rx/2`), message types (`radio.nack`), files of a run
# (`run.mcap`), commands.

DESIGN = ROOT / "docs" / "design.md"
TICKS = re.compile(r"`([^`\n]+)`")
IDENT = r"[A-Za-z_]\w*"
CALL = re.compile(rf"({IDENT}(?:\.{IDENT})*)\(.*\)")
DOTTED = re.compile(rf"{IDENT}(?:\.{IDENT})+")
CAMEL = re.compile(r"[A-Z][a-z0-9]+(?:[A-Z][a-z0-9]*)*")
PRIVATE = re.compile(r"_[a-z]\w*")
DATA_FILES = (".json", ".mcap", ".yaml", ".yml", ".md", ".npz", ".png")
# Code-shaped names that are not a module's or a class's attribute, each with why.
NOT_CODE = {
    "node.drops": "a node object's counter (Node.drops, set in Node.__init__), written as the reader meets it",
}


@functools.cache
def code_index():
    """(module -> its top-level names, class name -> [(members, base names)], every def and class
    name anywhere). A class's members are its defs, class attributes and the self.x its methods
    assign."""
    top, classes, names = {}, {}, set()
    for mod, path in MODULES.items():
        tree = _tree(path)
        mine = set()
        for node in tree.body:
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                mine.add(node.name)
            elif isinstance(node, (ast.Assign, ast.AnnAssign)):
                for t in node.targets if isinstance(node, ast.Assign) else [node.target]:
                    mine.update(n.id for n in ast.walk(t) if isinstance(n, ast.Name))
            elif isinstance(node, (ast.Import, ast.ImportFrom)):
                mine.update((a.asname or a.name).split(".")[0] for a in node.names)
        top[mod] = mine
        for node in ast.walk(tree):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                names.add(node.name)
            if isinstance(node, ast.ClassDef):
                members = set()
                for n in ast.walk(node):
                    if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                        members.add(n.name)
                    elif isinstance(n, ast.Name) and isinstance(n.ctx, ast.Store):
                        members.add(n.id)
                    elif isinstance(n, ast.Attribute) and isinstance(n.ctx, ast.Store) \
                            and isinstance(n.value, ast.Name) and n.value.id == "self":
                        members.add(n.attr)
                bases = [b.id if isinstance(b, ast.Name) else b.attr for b in node.bases
                         if isinstance(b, (ast.Name, ast.Attribute))]
                classes.setdefault(node.name, []).append((members, bases))
    return top, classes, names


def class_has(cls: str, member: str, seen=()) -> bool:
    _, classes, _ = code_index()
    for members, bases in classes.get(cls, []):
        if member in members or any(class_has(b, member, seen + (cls,)) for b in bases if b not in seen):
            return True
    return False


def dotted_exists(name: str) -> bool | None:
    """Whether a dotted name is defined in the tree; None: its head is not code (prose)."""
    top, classes, _ = code_index()
    parts = name.split(".")
    if parts[0] in PACKAGES:
        for n in range(len(parts), 0, -1):
            mod = ".".join(parts[:n])
            if mod in MODULES:
                rest = parts[n:]
                if not rest:
                    return True
                if rest[0] not in top[mod]:
                    return False
                return len(rest) == 1 or class_has(rest[0], rest[1])
        return False
    if parts[0] in classes:
        return len(parts) == 2 and class_has(parts[0], parts[1])
    by_last = [m for m in MODULES if m.rsplit(".", 1)[-1] == parts[0]]
    if by_last:
        return len(parts) == 2 and any(parts[1] in top[m] for m in by_last)
    return None


def room_dir(room: str) -> Path:
    path = ROOT / Path(*room.split("."))
    return path if path.is_dir() else MODULES[room].parent


def design_names() -> list[tuple[int, str, Path | None]]:
    """(line, backticked text, the room's directory on a row of the room table, else None)."""
    out, rows = [], False
    for i, line in enumerate(DESIGN.read_text().splitlines(), 1):
        rows = rows and line.startswith("|") or "<!-- rooms: read by tests/test_layout.py -->" in line
        cells = [c.strip() for c in line.strip("|").split("|")] if rows else []
        m = re.fullmatch(r"`([\w.]+)`", cells[0]) if cells else None
        base = room_dir(m.group(1)) if m and m.group(1) in ROOMS else None
        out += [(i, t, base) for t in TICKS.findall(line)]
    return out


def missing_in_code(text: str, base: Path | None) -> str | None:
    """Why a backticked text names nothing in the tree; None when it does or is not code."""
    _, _, names = code_index()
    if text in NOT_CODE:
        return None
    if re.fullmatch(r"[\w./*-]+\.py|[\w./*-]*/[\w./*-]*\*[\w./*-]*|(?:[\w.-]+/)+", text):
        if "/" not in text.rstrip("/") and not text.endswith("/"):  # a bare file name
            if base is None:
                return None if any(p.name == text for p in ROOT.glob(f"*/**/{text}")) else "no such file"
            where = base
        else:
            where = ROOT if base is None or text.split("/")[0] in PACKAGES + ("tests", "docs", "benchmarks") else base
        return None if list(where.glob(text.rstrip("/"))) else f"no such file or directory under {where.relative_to(ROOT)}/"
    if text.endswith(DATA_FILES):
        return None
    call = CALL.fullmatch(text)
    head = call.group(1) if call else text
    if DOTTED.fullmatch(head):
        found = dotted_exists(head)
        return None if found in (True, None) else "not defined in swarmloc/, agents/ or netsim/"
    if call or CAMEL.fullmatch(head) or PRIVATE.fullmatch(head):
        return None if head in names else "no def or class of that name in swarmloc/, agents/ or netsim/"
    return None


def test_every_file_class_and_method_the_design_page_names_exists():
    names = design_names()
    assert len(names) > 100, "found no backticks in docs/design.md"
    wrong = [f"docs/design.md:{i}: `{t}`: {why}" for i, t, base in names if (why := missing_in_code(t, base))]
    assert not wrong, "docs/design.md names what the code does not have:\n" + "\n".join(wrong)
    checked = {t for _, t, _ in names}
    assert {"Simulation.exchange_batch", "netsim/server.py", "_on_tx", "step(sensors)"} <= checked


@pytest.mark.parametrize("text, base", [
    ("Simulation.exchange_nowhere", None), ("NetsimServer._gone", None), ("swarmloc.wire.decodes", None),
    ("auth.check_nothing", None), ("_on_nothing", None), ("nowhere(x)", None), ("NoSuchClass", None),
    ("netsim/nowhere.py", None), ("netsim/nowhere/", None), ("gone.py", ROOT / "swarmloc" / "filters"),
])
def test_the_design_page_check_catches_a_stale_name(text, base):
    assert missing_in_code(text, base)


@pytest.mark.parametrize("text", ["clock.mode", "radio.nack", "msgspec.Struct", "run.mcap", "metrics.json",
                                  "ekf-ci", "radio/rx/2", "swarmloc/<swarm>/", "python -m agents", "il", "P_ij",
                                  "p = 2N+1 .. 4N", "tick_timeouts"])
def test_the_design_page_check_leaves_prose_alone(text):
    assert missing_in_code(text, None) is None
