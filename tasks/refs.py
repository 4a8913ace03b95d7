"""Small references that tasks pass instead of arrays or tables.

A :class:`Ref` names a file or a directory (a zarr store) and carries a content
digest. Prefect results hold only refs; cache keys are built from the refs' digests,
the task's parameters and a code version, so a rerun with unchanged inputs is all
cache hits and a changed input reruns exactly what depends on it.
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

__all__ = ["Ref", "digest_path", "digest_value", "ref_for", "cache_key", "CODE_VERSION"]

#: Bump when a change in fringecal alters results without changing task signatures.
CODE_VERSION = "1"

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
    """SHA-256 of a JSON-serialisable value (configs, parameters)."""
    text = json.dumps(value, sort_keys=True, default=_json_default)
    return hashlib.sha256(text.encode()).hexdigest()


def _json_default(o):
    if isinstance(o, Ref):
        return {"ref": o.digest}
    if isinstance(o, Path):
        return str(o)
    if hasattr(o, "model_dump"):
        return o.model_dump(mode="json")
    if hasattr(o, "tolist"):
        return o.tolist()
    raise TypeError(f"cannot digest {type(o).__name__}")


@dataclass(frozen=True)
class Ref:
    """A file or directory with its content digest.

    ``kind`` says what it holds (``"table"``, ``"store"``, ``"calibration"``...).
    """

    path: str
    digest: str
    kind: str = "file"

    def exists_unchanged(self) -> bool:
        """True if the path still exists with the same content."""
        p = Path(self.path)
        return p.exists() and digest_path(p) == self.digest

    def to_dict(self) -> dict:
        return asdict(self)


def ref_for(path, kind: str = "file") -> Ref:
    """Reference an existing file or directory."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"cannot reference {path}: it does not exist")
    return Ref(str(path), digest_path(path), kind)


def cache_key(task_name: str, parameters: dict[str, Any]) -> str:
    """Cache key from a task name, the code version and its parameters (refs by digest)."""
    return f"{task_name}-{digest_value({'code': CODE_VERSION, 'params': parameters})[:32]}"
