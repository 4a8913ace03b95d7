"""The one atomic writer: every file fringecal writes appears whole or not at all.

A file is written under a hidden temporary sibling (``.<name>.<unique>.tmp``) and
renamed onto its final name only when the write succeeded; a failure removes the
temporary and leaves any previous file untouched. Temporary names are unique per
call, so two threads writing the same file never write into each other's temporary.
:func:`atomic_paths` does the same for a group of files that belong together (the
calibration's outputs): all are written first, then renamed one after another.

>>> import tempfile, pathlib
>>> d = pathlib.Path(tempfile.mkdtemp())
>>> write_text(d / "a.txt", "hello").read_text()
'hello'
>>> try:
...     with atomic_path(d / "a.txt") as tmp:
...         _ = tmp.write_text("half")
...         raise RuntimeError("crash")
... except RuntimeError:
...     pass
>>> (d / "a.txt").read_text(), sorted(p.name for p in d.iterdir())
('hello', ['a.txt'])
"""

from __future__ import annotations

import json
import os
import uuid
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator, Sequence

__all__ = ["atomic_path", "atomic_paths", "write_bytes", "write_text", "write_json", "temporary_sibling"]


def temporary_sibling(path, tag: str = "tmp") -> Path:
    """A hidden, unique name next to ``path`` (hidden names are ignored by digests)."""
    path = Path(path)
    return path.parent / f".{path.name}.{uuid.uuid4().hex[:12]}.{tag}"


@contextmanager
def atomic_path(path) -> Iterator[Path]:
    """Yield a temporary path to write; on success it replaces ``path`` (parents are made)."""
    with atomic_paths([path]) as (tmp,):
        yield tmp


@contextmanager
def atomic_paths(paths: Sequence) -> Iterator[list[Path]]:
    """Temporary paths for several files; all are renamed into place once every one is written."""
    paths = [Path(p) for p in paths]
    for p in paths:
        p.parent.mkdir(parents=True, exist_ok=True)
    tmps = [temporary_sibling(p) for p in paths]
    try:
        yield tmps
        missing = [str(p) for p, t in zip(paths, tmps) if not t.exists()]
        if missing:
            raise FileNotFoundError(f"nothing was written for {', '.join(missing)}")
        for p, t in zip(paths, tmps):
            os.replace(t, p)
    finally:
        for t in tmps:
            t.unlink(missing_ok=True)


def write_bytes(path, data: bytes) -> Path:
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    return Path(path)


def write_text(path, text: str) -> Path:
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return Path(path)


def write_json(path, obj, indent: int = 2) -> Path:
    """JSON with ``indent``; numpy scalars and other objects become ``str`` only if not numbers."""
    return write_text(path, json.dumps(obj, indent=indent, default=_json_default) + "\n")


def _json_default(o):
    if hasattr(o, "item"):  # numpy scalar
        return o.item()
    if hasattr(o, "tolist"):
        return o.tolist()
    return str(o)
