"""The layers of docs/architecture.md, enforced on the source.

Every module of the installed package (``fringecal`` with ``fringecal.flows``,
``fringecal.tasks`` and ``fringecal.schemas``) belongs to one layer; a module imports
only from its own layer or the layers below, function-local imports included, and no
set of modules imports itself in a circle. A function-local import of a fringecal
module is allowed in the command-line modules (each command loads its work when it
runs, so that ``--help`` and small commands answer at once) and elsewhere only with
its reason: a comment on its line or on the line above its block.
"""

from __future__ import annotations

import ast
import re
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

#: folder of the repository -> its name in the installed package
FACES = {"fringecal": "fringecal", "flows": "fringecal.flows", "tasks": "fringecal.tasks",
         "schemas": "fringecal.schemas"}

#: top to bottom; a module may import its own layer and every layer below it
LAYERS = (
    ("fringecal.flows",),
    ("fringecal.tasks",),
    ("fringecal.run",),
    ("fringecal.steps",),
    ("fringecal.simulate", "fringecal.acquisition", "fringecal.dataset"),
    ("fringecal.acceptance", "fringecal.report", "fringecal.measure", "fringecal.interop"),
    ("fringecal.verification",),
    ("fringecal.rundir",),
    ("fringecal.spheres",),
    ("fringecal.calibration",),
    ("fringecal.fringe", "fringecal.engineering", "fringecal.hexapod"),
    ("fringecal.rig", "fringecal.artefact", "fringecal.pointcloud", "fringecal.registration", "fringecal.scancloud"),
    ("fringecal.schemas",),
    ("fringecal.sensor", "fringecal.frames", "fringecal.rotation", "fringecal.lens", "fringecal.triangulation"),
    ("fringecal.atomic", "fringecal.store", "fringecal.digests", "fringecal.config", "fringecal.lifeline",
     "fringecal.compile_clock", "fringecal.threads", "fringecal.configs", "fringecal.names"),
    ("fringecal",),
)

#: modules whose functions may import lazily without a comment: the command line
LAZY_MODULES = re.compile(r"^fringecal\.flows\.cli\w*$")


@dataclass(frozen=True)
class Import:
    module: str  # the importing module
    target: str  # the fringecal module imported
    line: int
    local: bool  # inside a function
    reason: bool  # a comment gives its reason


def modules(root: Path) -> dict[str, Path]:
    out = {}
    for folder, name in FACES.items():
        for path in sorted((root / folder).rglob("*.py")):
            parts = [name, *path.relative_to(root / folder).with_suffix("").parts]
            if parts[-1] == "__init__":
                parts.pop()
            out[".".join(parts)] = path
    return out


def imports(root: Path) -> list[Import]:
    """Every import of a fringecal module by a fringecal module."""
    mods = modules(root)
    out = []
    for name, path in mods.items():
        text = path.read_text(encoding="utf-8")
        lines = text.splitlines()
        tree = ast.parse(text, str(path))
        local = {id(n) for f in ast.walk(tree) if isinstance(f, (ast.FunctionDef, ast.AsyncFunctionDef))
                 for n in ast.walk(f) if isinstance(n, (ast.Import, ast.ImportFrom))}
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    package = name.split(".") if path.name == "__init__.py" else name.split(".")[:-1]
                    base = ".".join(package[:len(package) - node.level + 1] + ([base] if base else []))
                targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in mods else base for a in node.names]
            else:
                continue
            for target in targets:
                if target.split(".")[0] != "fringecal":
                    continue
                while target not in mods and "." in target:
                    target = target.rsplit(".", 1)[0]
                if target != name:
                    out.append(Import(name, target, node.lineno, id(node) in local, _has_reason(lines, node)))
    return out


def _has_reason(lines: list[str], node) -> bool:
    if "#" in lines[node.lineno - 1]:
        return True
    k = node.lineno - 2  # the comment above the block of imports this one belongs to
    while k >= 0 and re.match(r"\s*(from|import)\s", lines[k]) and "#" not in lines[k]:
        k -= 1
    return k >= 0 and lines[k].strip().startswith("#")


def layer(module: str) -> int | None:
    for i, group in enumerate(LAYERS):
        # the package itself is the last layer; its modules are each named above
        if any(module == g or (g != "fringecal" and module.startswith(g + ".")) for g in group):
            return i
    return None


def upward(found: list[Import]) -> list[str]:
    return [f"{i.module}:{i.line} imports {i.target}{' (in a function)' if i.local else ''}, a layer above it"
            for i in found if layer(i.target) < layer(i.module)]


def circles(found: list[Import]) -> list[list[str]]:
    """The strongly connected sets of more than one module (Tarjan)."""
    graph: dict[str, set[str]] = {}
    for i in found:
        graph.setdefault(i.module, set()).add(i.target)
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    out = []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            group = []
            while True:
                w = stack.pop()
                group.append(w)
                if w == v:
                    break
            if len(group) > 1:
                out.append(sorted(group))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def unexplained_local(found: list[Import]) -> list[str]:
    return [f"{i.module}:{i.line} imports {i.target} inside a function without a reason"
            for i in found if i.local and not i.reason and not LAZY_MODULES.match(i.module)]


@pytest.fixture(scope="module")
def found() -> list[Import]:
    return imports(ROOT)


def test_every_module_has_a_layer():
    assert [m for m in modules(ROOT) if layer(m) is None] == []


def test_imports_only_go_down(found):
    assert upward(found) == []


def test_no_circles(found):
    assert circles(found) == []


def test_function_local_imports_say_why(found):
    assert unexplained_local(found) == []


def test_the_core_never_imports_prefect():
    below_tasks = {m: p for m, p in modules(ROOT).items() if layer(m) > layer("fringecal.tasks")}
    offenders = [m for m, p in below_tasks.items()
                 if re.search(r"^\s*(from|import)\s+prefect\b", p.read_text(encoding="utf-8"), re.M)]
    assert offenders == []


def test_a_short_package_root_and_one_ballbar_package():
    root_modules = [p for p in (ROOT / "fringecal").glob("*.py") if p.name != "__init__.py"]
    assert len(root_modules) <= 20, sorted(p.name for p in root_modules)
    ballbar = [m for m in modules(ROOT) if re.search(r"ballbar|length_uncertainty|verification", m)
               and not m.startswith(("fringecal.verification", "fringecal.steps.", "fringecal.flows.",
                                     "fringecal.report.sections."))]
    assert ballbar == []


def test_nothing_cites_a_document_outside_the_repository():
    pattern = re.compile(r"DESIGN\.md|\.\./shared|shared/(DESIGN|REFERENCES)")
    files = [p for folder in (*FACES, "tests", "benchmarks", "docs", "docs_hooks", "configs")
             for p in (ROOT / folder).rglob("*") if p.is_file() and p.suffix in {".py", ".md", ".yaml", ".j2"}]
    files += [ROOT / "README.md"]
    assert [str(p.relative_to(ROOT)) for p in files if pattern.search(p.read_text(encoding="utf-8"))] == []


def _write(root: Path, rel: str, text: str = "") -> None:
    path = root / rel
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)


def test_the_checks_catch_an_upward_import_a_circle_and_an_unexplained_local_import(tmp_path):
    for folder in FACES:
        _write(tmp_path, f"{folder}/__init__.py")
    _write(tmp_path, "fringecal/rig.py", "def f():\n    from fringecal.steps import base\n")
    _write(tmp_path, "fringecal/steps/__init__.py")
    _write(tmp_path, "fringecal/steps/base.py", "from fringecal.steps import keys\n")
    _write(tmp_path, "fringecal/steps/keys.py", "from fringecal.steps.base import x\n")
    _write(tmp_path, "fringecal/sensor.py", "def f():\n    # lazy: a reason\n    from fringecal import atomic\n")
    _write(tmp_path, "fringecal/atomic.py")
    found = imports(tmp_path)
    assert upward(found) == ["fringecal.rig:2 imports fringecal.steps.base (in a function), a layer above it"]
    assert circles(found) == [["fringecal.steps.base", "fringecal.steps.keys"]]
    assert unexplained_local(found) == ["fringecal.rig:2 imports fringecal.steps.base inside a function without "
                                        "a reason"]


def test_every_ast_parse_is_serialised_where_the_interpreter_races():
    """CPython 3.11 before 3.11.8 (gh-106905): two threads in ast.parse at once can fail;
    once fringecal.digests is imported, every parse of the process takes one lock there,
    and two threads parsing at once both get their trees."""
    import ast
    import sys
    import threading

    import fringecal.digests as digests

    racy = sys.version_info[:2] == (3, 11) and sys.version_info < (3, 11, 8)
    assert getattr(ast.parse, "fringecal_serialised", False) is racy
    assert digests.serialise_ast_parse() is racy  # a second call changes nothing
    source = "\n".join(f"def f{i}(x):\n    return [y for y in range(x) if y % {i + 2}]" for i in range(300))
    trees = []
    threads = [threading.Thread(target=lambda: trees.append(ast.parse(source))) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(trees) == 4 and all(len(t.body) == 300 for t in trees)
