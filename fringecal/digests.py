"""Content digests of files, folders (zarr stores), values and source code.

They decide what a pipeline step has to recompute (:mod:`fringecal.steps.keys`): a
step's cache key is built from the digests of the files it reads, of the settings it
uses and of the source of the fringecal modules it runs.

* :func:`digest_path` hashes a file, or a folder's relative paths and file contents
  (hidden entries are skipped, so temporaries and lock files never count).
* :class:`DigestCache` remembers digests by each file's size, modification time,
  change time and inode, as git's index does, so an unchanged 100 MB store or a
  98-frame image stack is hashed once, not at every check. A file changed in place
  gets a new change time (ctime), which, unlike the modification time, no program can
  set back: a same-size rewrite whose mtime was restored is hashed again. Entries for files modified within two seconds of hashing are not
  kept (a second write within the file system's timestamp resolution could
  otherwise go unseen).
* :func:`source_digest` hashes the source files of modules and of every fringecal or
  schemas module they import (the import graph is read from the source, imports
  inside functions included), so editing a module changes the key of exactly the
  steps that can run it.
"""

from __future__ import annotations

import ast
import hashlib
import json
import os
import threading
import time
from functools import lru_cache
from pathlib import Path
from typing import Any, Iterable

import fringecal
from fringecal.atomic import write_json

__all__ = ["digest_path", "digest_value", "DigestCache", "source_digest", "module_files", "code_digest",
           "INFRASTRUCTURE_MODULES"]

_CHUNK = 1 << 20
_RACY_NS = 2_000_000_000

#: Modules that decide where files go and how keys are built, not what a step
#: computes: they are left out of source digests so that, say, a new accessor in the
#: run directory does not redo twelve minutes of rendering. A renamed output is still
#: caught, because a step's record must list exactly the outputs it declares now.
INFRASTRUCTURE_MODULES = frozenset({
    "fringecal", "fringecal.atomic", "fringecal.digests", "fringecal.rundir", "fringecal.config",
    "fringecal.run.config", "fringecal.steps", "fringecal.steps.base", "fringecal.steps.keys",
})


def _hash_file(h, path: Path) -> None:
    with open(path, "rb") as f:
        while chunk := f.read(_CHUNK):
            h.update(chunk)


def _files(path: Path) -> list[Path]:
    out = []
    for root, dirs, files in os.walk(path):
        dirs[:] = sorted(d for d in dirs if not d.startswith("."))
        out += [Path(root) / f for f in sorted(files) if not f.startswith(".")]
    return out


def digest_path(path) -> str:
    """SHA-256 of a file, or of a folder's relative paths and file contents.

    Hidden entries (names starting with '.') are ignored so temporary files and
    lock files do not change a store's digest.
    """
    path = Path(path)
    h = hashlib.sha256()
    if path.is_dir():
        for p in _files(path):
            h.update(str(p.relative_to(path)).encode())
            h.update(b"\0")
            _hash_file(h, p)
    else:
        _hash_file(h, path)
    return h.hexdigest()


def digest_value(value: Any) -> str:
    """SHA-256 of a JSON-serialisable value; references (objects with ``path`` and
    ``digest``) count by their digest, pydantic models by their JSON dump, paths by
    their text, arrays by their values."""
    text = json.dumps(value, sort_keys=True, default=_json_default)
    return hashlib.sha256(text.encode()).hexdigest()


def _json_default(o):
    if hasattr(o, "digest") and hasattr(o, "path"):  # a reference to a file counts by its content
        return {"ref": o.digest}
    if isinstance(o, Path):
        return str(o)
    if hasattr(o, "model_dump"):
        return o.model_dump(mode="json")
    if hasattr(o, "tolist"):
        return o.tolist()
    raise TypeError(f"cannot digest {type(o).__name__}")


class DigestCache:
    """:func:`digest_path` with memory: digests keyed by the files' stat signatures.

    Parameters
    ----------
    folder : path or None
        Where entries persist between processes (one small JSON file per path);
        None keeps them in memory only.

    >>> import tempfile, pathlib
    >>> d = pathlib.Path(tempfile.mkdtemp())
    >>> _ = (d / "t.csv").write_text("a,b\\n1,2\\n")
    >>> cache = DigestCache(d / ".digests")
    >>> cache.digest(d / "t.csv") == digest_path(d / "t.csv")
    True
    """

    def __init__(self, folder=None):
        self.folder = None if folder is None else Path(folder)
        self._memory: dict[str, tuple[str, str]] = {}
        self._lock = threading.Lock()

    @staticmethod
    def signature(path: Path) -> tuple[str, int]:
        """(hash of every file's relative path, size, mtime, ctime and inode; newest of
        the mtimes and ctimes)."""
        files = _files(path) if path.is_dir() else [path]
        h = hashlib.sha256()
        newest = 0
        for p in files:
            st = p.stat()
            newest = max(newest, st.st_mtime_ns, st.st_ctime_ns)
            h.update(f"{p.relative_to(path) if p != path else ''}\0{st.st_size}\0{st.st_mtime_ns}\0"
                     f"{st.st_ctime_ns}\0{st.st_ino}\n".encode())
        return h.hexdigest(), newest

    def _entry_file(self, key: str) -> Path | None:
        return None if self.folder is None else self.folder / f"{hashlib.sha256(key.encode()).hexdigest()[:32]}.json"

    def digest(self, path) -> str:
        """The content digest of ``path`` (hashed again only if its signature changed)."""
        path = Path(path).resolve()
        key = str(path)
        if not path.exists():
            raise FileNotFoundError(f"{path}: does not exist")
        sig, newest = self.signature(path)
        with self._lock:
            hit = self._memory.get(key)
        if hit is None and (entry := self._entry_file(key)) is not None and entry.exists():
            try:
                doc = json.loads(entry.read_text())
                hit = (doc["signature"], doc["digest"]) if doc.get("path") == key else None
            except (ValueError, KeyError, OSError):
                hit = None
        if hit is not None and hit[0] == sig:
            return hit[1]
        digest = digest_path(path)
        if time.time_ns() - newest > _RACY_NS:
            with self._lock:
                self._memory[key] = (sig, digest)
            if (entry := self._entry_file(key)) is not None:
                write_json(entry, {"path": key, "signature": sig, "digest": digest})
        return digest


# -- source code ----------------------------------------------------------------------

#: subpackages that run the steps rather than compute: left out of :func:`code_digest`
_FACES = ("flows", "tasks")


@lru_cache(maxsize=None)
def _package_roots() -> tuple[Path, ...]:
    """Where fringecal's modules live: the package folder, and in a source checkout the
    checkout itself, whose flows/, tasks/ and schemas/ the package maps in."""

    return tuple(Path(p).resolve() for p in fringecal.__path__)


@lru_cache(maxsize=None)
def _module_file(name: str) -> Path | None:
    top, _, rest = name.partition(".")
    if top != "fringecal":
        return None
    for root in _package_roots():
        base = root.joinpath(*rest.split(".")) if rest else root
        for candidate in (base.with_suffix(".py"), base / "__init__.py"):
            if candidate.is_file():
                return candidate
    return None


def _resolve(module: str, is_package: bool, node: ast.ImportFrom | ast.Import) -> list[str]:
    if isinstance(node, ast.Import):
        return [a.name for a in node.names]
    if node.level == 0:
        base = node.module or ""
    else:
        parts = module.split(".")
        keep = len(parts) - node.level + (1 if is_package else 0)
        base = ".".join(parts[:keep] + ([node.module] if node.module else []))
    # ``from pkg import name``: name may be a submodule or an attribute of pkg
    return [base] + [f"{base}.{a.name}" for a in node.names]


#: one ast.parse at a time: CPython 3.11 (before 3.11.8) tracks the AST constructor's
#: recursion depth per interpreter, so two threads parsing at once (the step instances a
#: pool keys together) can fail with "SystemError: AST constructor recursion depth
#: mismatch" (python/cpython gh-106905)
_PARSING = threading.RLock()


def serialise_ast_parse() -> bool:
    """On CPython 3.11 before 3.11.8, make every ``ast.parse`` of this process take
    :data:`_PARSING`, the parses of other libraries included: a scheduled flow run
    failed once in five test commands with gh-106905's SystemError after fringecal's own
    parses were already serialised, Prefect parsing flow and task sources in other
    threads (prefect/flows.py, prefect/utilities/callables). Returns whether the parse
    is serialised (always False on interpreters without the race)."""
    import sys

    if sys.version_info[:2] != (3, 11) or sys.version_info >= (3, 11, 8):
        return False
    if getattr(ast.parse, "fringecal_serialised", False):
        return True
    original = ast.parse

    def parse(*args, **kwargs):
        with _PARSING:
            return original(*args, **kwargs)

    parse.fringecal_serialised = True
    parse.__doc__ = original.__doc__
    ast.parse = parse
    return True


serialise_ast_parse()


@lru_cache(maxsize=None)
def _imports(name: str) -> tuple[str, ...]:
    path = _module_file(name)
    if path is None:
        return ()
    with _PARSING:
        tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            for target in _resolve(name, path.name == "__init__.py", node):
                if _module_file(target) is not None:
                    out.add(target)
    return tuple(sorted(out))


def module_files(modules: Iterable[str]) -> dict[str, Path]:
    """Module name -> source file of ``modules`` and every fringecal module
    they import, directly or not, leaving out :data:`INFRASTRUCTURE_MODULES`."""
    seen: dict[str, Path] = {}
    todo = [m for m in modules]
    while todo:
        name = todo.pop()
        if name in seen or name in INFRASTRUCTURE_MODULES:
            continue
        path = _module_file(name)
        if path is None:
            raise ModuleNotFoundError(f"{name}: not a fringecal module")
        seen[name] = path
        todo += _imports(name)
    return dict(sorted(seen.items()))


def _template_files(package_init: Path) -> list[Path]:
    """The files of a package's ``templates/`` folder (the report's jinja2 templates and
    style sheet): they are source as much as its modules are."""
    folder = package_init.parent / "templates"
    if package_init.name != "__init__.py" or not folder.is_dir():
        return []
    return sorted(p for p in folder.rglob("*") if p.is_file() and "__pycache__" not in p.parts)


def source_digest(modules: Iterable[str]) -> str:
    """SHA-256 over the source files of :func:`module_files` ``(modules)``, with the
    ``templates/`` folder of each package among them."""
    h = hashlib.sha256()
    for name, path in module_files(modules).items():
        for file in [path, *_template_files(path)]:
            st = file.stat()
            label = name if file == path else f"{name}:{file.relative_to(path.parent).as_posix()}"
            h.update(label.encode() + b"\0" + _source_file_digest(str(file), st.st_size, st.st_mtime_ns).encode())
    return h.hexdigest()


@lru_cache(maxsize=None)
def _source_file_digest(path: str, size: int, mtime_ns: int) -> str:
    return digest_path(path)


def _computing_sources() -> list[tuple[str, Path]]:
    """(label, file) of every module that computes: the package and its table schemas,
    without the command line and the Prefect adapter."""
    package, *beside = _package_roots()
    out = [(p.relative_to(package).as_posix(), p) for p in package.rglob("*.py")
           if p.relative_to(package).parts[0] not in _FACES]
    for root in beside:  # a source checkout: only its schemas/ belong to the package
        out += [(p.relative_to(root).as_posix(), p) for p in (root / "schemas").rglob("*.py")]
    return sorted(out)


def code_digest() -> str:
    """One digest of every computing source file of fringecal (provenance in the manifest)."""
    h = hashlib.sha256()
    for label, p in _computing_sources():
        for file in [p, *_template_files(p)]:
            h.update((label if file == p else f"{label}:{file.relative_to(p.parent).as_posix()}").encode() + b"\0")
            _hash_file(h, file)
    return h.hexdigest()
