"""What an interrupted run leaves behind, and how the next run of the same directory picks it up.

Every file fringecal writes appears whole or not at all (:mod:`fringecal.atomic`,
:mod:`fringecal.store`): a run killed midway leaves complete outputs, which the next
run reuses (their step records are current, :mod:`fringecal.steps.keys`), and at most
the hidden temporaries of the writes that were in progress -- ``.<name>.<id>.tmp``
files, ``.<id>.zarr.tmp-<id>`` stores being written and ``.<id>.zarr.old-<id>``
stores being replaced. Nothing reads them. :func:`begin` removes them when the next
run of the directory starts, before it submits any step, so no writer of that run
can be disturbed.

:func:`begin` also records the run in ``RunDir.in_progress`` (pid and start of the
process, host, time, command) and :func:`finish` removes the record when the run
ends (normally or with an error). A run that finds a record left by a process that
no longer runs knows the previous run was interrupted, and reports what it reused.
A record of a process that still runs on this host means another run is writing
the directory: :func:`busy` says so, and ``fringecal run`` refuses to start rather
than remove that run's temporaries under it.

The record alone leaves a window: two commands started together both find no
record. :func:`claim` closes it: the process that runs the flow holds an exclusive
``flock`` on ``RunDir.lock`` from before Prefect starts to its end (the operating
system releases it when the process ends, even by ``kill -9``); a second process
cannot take it and is refused with :class:`RunDirBusy` -- before Prefect starts when
``fringecal run`` claims the directory, inside the flow for a served run.
"""

from __future__ import annotations

import datetime as _dt
import fcntl
import os
import re
import shutil
import socket
from pathlib import Path

from fringecal.lifeline import process_start
from fringecal.rundir import RunDir

__all__ = ["leftovers", "remove_leftovers", "busy", "begin", "finish", "RunDirBusy", "claim", "release"]

#: Hidden temporaries of the atomic writers: ``.<name>.<12 hex>.tmp`` (fringecal.atomic),
#: ``.<name>.tmp-<12 hex>`` and ``.<name>.old-<12 hex>`` (fringecal.store), any hidden ``*.tmp``.
_TEMPORARY = re.compile(r"^\..+(\.(tmp|old)-[0-9a-f]{12}|\.tmp)$")


class RunDirBusy(ValueError):
    """Another run is writing the run directory; the message names it and the process."""


def leftovers(root) -> list[Path]:
    """The hidden temporaries of interrupted writes anywhere under ``root`` (complete
    stores are not searched: their files are written before the store is renamed)."""
    found = []
    for here, dirs, files in os.walk(root):
        for name in list(dirs):
            if _TEMPORARY.match(name):
                found.append(Path(here, name))
                dirs.remove(name)
            elif name.endswith(".zarr"):
                dirs.remove(name)
        found += [Path(here, f) for f in files if _TEMPORARY.match(f)]
    return sorted(found)


def remove_leftovers(root) -> list[Path]:
    """Remove :func:`leftovers` of ``root``; returns what was removed."""
    gone = leftovers(root)
    for p in gone:
        if p.is_dir() and not p.is_symlink():
            shutil.rmtree(p, ignore_errors=True)
        else:
            p.unlink(missing_ok=True)
    return gone


def _record(rd: RunDir) -> dict | None:
    """The in-progress record, ``{}`` if unreadable, None if absent."""
    if not rd.in_progress.exists():
        return None
    try:
        doc = rd.in_progress.load()
    except (OSError, ValueError):
        return {}
    return doc if isinstance(doc, dict) else {}


def busy(rd: RunDir) -> dict | None:
    """The record of another process of this host that is still writing ``rd``, else None."""
    doc = _record(rd)
    if not doc or doc.get("host") != socket.gethostname():
        return None
    pid = doc.get("pid")
    if not isinstance(pid, int) or pid == os.getpid():
        return None
    return doc if doc.get("start") is not None and process_start(pid) == doc["start"] else None


def describe_busy(rd: RunDir, doc: dict) -> str:
    return (f"{rd.root}: another fringecal run is writing this run directory (pid {doc['pid']}, "
            f"{doc.get('command', 'fringecal run')!r}, since {doc.get('started_utc', '?')}); "
            "wait for it to end or stop it, then rerun")


#: run directories whose lock this process holds: resolved root -> the locked file descriptor
_held: dict[str, int] = {}


def claim(rd: RunDir) -> None:
    """Take ``rd``'s lock for this process (a no-op when it holds it already); raise
    :class:`RunDirBusy` when another process holds it. The folder is made if missing."""
    key = str(rd.root.resolve())
    if key in _held:
        return
    rd.root.mkdir(parents=True, exist_ok=True)
    fd = os.open(rd.lock.path, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        os.close(fd)
        doc = _record(rd) or {}
        if doc.get("pid"):
            raise RunDirBusy(describe_busy(rd, doc)) from None
        raise RunDirBusy(f"{rd.root}: another fringecal run is writing this run directory (it holds "
                         f"{rd.lock.rel}); wait for it to end or stop it, then rerun") from None
    _held[key] = fd


def release(rd: RunDir) -> None:
    """Give up ``rd``'s lock (if this process holds it)."""
    fd = _held.pop(str(rd.root.resolve()), None)
    if fd is not None:
        os.close(fd)


def begin(rd: RunDir, command: str) -> dict | None:
    """Start a run of ``rd``: refuse if another run writes it, remove the leftovers of
    interrupted writes, and record this run. Returns the record of the interrupted
    run it resumes (``{}`` if that record was unreadable), or None."""
    claim(rd)
    if (doc := busy(rd)) is not None:
        release(rd)
        raise RunDirBusy(describe_busy(rd, doc))
    previous = _record(rd)
    remove_leftovers(rd.root)
    rd.in_progress.save({"pid": os.getpid(), "start": process_start(os.getpid()), "host": socket.gethostname(),
                         "started_utc": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
                         "command": command})
    return previous


def finish(rd: RunDir) -> None:
    """The run of ``rd`` ended (normally or with an error): remove its record and give
    up its lock."""
    rd.in_progress.remove()
    release(rd)
