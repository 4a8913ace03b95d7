"""Small references that tasks pass instead of arrays or tables.

A :class:`Ref` names a file or a directory (a zarr store) and carries a content
digest. The small flows of single commands (``fringecal decode``, ``fringecal pose``)
pass refs; their cache keys are built from the refs' digests, the task's parameters
and the source digest of the fringecal modules the task runs, so a rerun with
unchanged inputs and code is all cache hits. (The pipeline's steps have their own
declared keys: :mod:`fringecal.steps.keys`.)
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from fringecal.digests import digest_path, digest_value, source_digest

__all__ = ["Ref", "digest_path", "digest_value", "ref_for", "cache_key"]


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


def cache_key(task_name: str, parameters: dict[str, Any], modules: tuple[str, ...]) -> str:
    """Cache key from a task name, its parameters (refs by digest) and the source of
    ``modules`` (and what they import)."""
    return f"{task_name}-{digest_value({'code': source_digest(modules), 'params': parameters})[:32]}"
