"""Small references that tasks pass instead of arrays or tables.

A :class:`Ref` names a file or a directory (a zarr store) and carries a content
digest. Prefect results hold only refs; cache keys are built from the refs' digests,
the task's parameters and a code version, so a rerun with unchanged inputs is all
cache hits and a changed input reruns exactly what depends on it.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from fringecal.digests import CODE_VERSION, digest_path, digest_value

__all__ = ["Ref", "digest_path", "digest_value", "ref_for", "cache_key", "CODE_VERSION"]


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
