"""Content digests of files, directories (zarr stores) and JSON-like values.

They identify what a step computed from: cache keys of the pipeline's tasks and the
up-to-date check of a run directory are built from them.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path
from typing import Any

__all__ = ["digest_path", "digest_value", "CODE_VERSION"]

#: Bump when a change in fringecal alters results (or what a run writes) without changing
#: the inputs or settings a step is keyed on: cached steps and up-to-date runs are redone.
CODE_VERSION = "3"

_CHUNK = 1 << 20


def _hash_file(h, path: Path) -> None:
    with open(path, "rb") as f:
        while chunk := f.read(_CHUNK):
            h.update(chunk)


def digest_path(path) -> str:
    """SHA-256 of a file, or of a directory's relative paths and file contents.

    Hidden entries (names starting with '.') are ignored so temporary files and
    lock files do not change a store's digest.
    """
    path = Path(path)
    h = hashlib.sha256()
    if path.is_dir():
        for root, dirs, files in os.walk(path):
            dirs[:] = sorted(d for d in dirs if not d.startswith("."))
            for name in sorted(f for f in files if not f.startswith(".")):
                p = Path(root) / name
                h.update(str(p.relative_to(path)).encode())
                h.update(b"\0")
                _hash_file(h, p)
    else:
        _hash_file(h, path)
    return h.hexdigest()


def digest_value(value: Any) -> str:
    """SHA-256 of a JSON-serialisable value; references (objects with a ``digest``
    attribute) count by their digest, pydantic models by their JSON dump."""
    text = json.dumps(value, sort_keys=True, default=_json_default)
    return hashlib.sha256(text.encode()).hexdigest()


def _json_default(o):
    if hasattr(o, "digest") and hasattr(o, "path"):
        return {"ref": o.digest}
    if isinstance(o, Path):
        return str(o)
    if hasattr(o, "model_dump"):
        return o.model_dump(mode="json")
    if hasattr(o, "tolist"):
        return o.tolist()
    raise TypeError(f"cannot digest {type(o).__name__}")
