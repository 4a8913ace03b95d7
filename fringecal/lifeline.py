"""Helper processes that never outlive the command that started them.

``fringecal run`` starts helper processes: Prefect's temporary API server (about
260 MB) and, on a cold numba cache, the kernel warm-up (:mod:`fringecal.run.warmup`).
They must end with the command however the command ends -- normally, on an error,
on Ctrl-C or SIGTERM, or killed outright (``kill -9``, the OOM killer), when none of
the command's own code runs any more.

How: the first :func:`adopt` starts a *lifeline*, a small watcher process
(``python -m fringecal.lifeline``, standard library only) that holds the read end of
a pipe whose write end only the command holds (the pipe's descriptors are not
inherited by any other child). :func:`adopt` writes each helper's pid and start
time into the pipe. When the command ends, in whatever way, the kernel closes the
write end; the watcher reads end-of-file, sends SIGTERM to every adopted process
that is still alive *with the start time recorded for its pid* (a recycled pid is
never signalled), SIGKILL to any still alive 3 s later, and exits. The watcher runs
in a session of its own, so the Ctrl-C a terminal sends to the command's process
group cannot stop it before it has done its job.

Why not the alternatives: ``PR_SET_PDEATHSIG`` must be set in the child between
fork and exec (a ``preexec_fn``, unsafe once the caller runs threads, as fringecal
does), is Linux-only, and fires when the *thread* that started the child ends, not
the process. Finding orphans at the next command cleans up too late (an orphaned
server holds its memory until someone runs fringecal again). The watcher costs one
small process per command that starts helpers.

:func:`stop_all` stops the adopted processes at once (the interrupt handler of
``fringecal run`` calls it before it exits); :func:`process_start` identifies a
process by pid and start time (also used by :mod:`fringecal.run.resume`).
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time

__all__ = ["adopt", "stop", "stop_all", "process_start", "GRACE_SECONDS"]

#: Seconds between SIGTERM and SIGKILL, in the watcher and in :func:`stop_all`.
GRACE_SECONDS = 3.0

_lock = threading.Lock()
_pipe = None  # the write end, in the command
_adopted: list[subprocess.Popen] = []


def process_start(pid: int) -> str | None:
    """A token that identifies the process ``pid`` together with its pid (its start
    time), or None if no such process runs (a zombie counts as gone)."""
    try:
        with open(f"/proc/{pid}/stat", "rb") as f:
            fields = f.read().rsplit(b")", 1)[1].split()
        return None if fields[0] == b"Z" else fields[19].decode()  # state, starttime (fields 3 and 22)
    except FileNotFoundError:
        return None
    except (OSError, IndexError):  # no /proc (macOS): psutil if installed
        try:
            import psutil

            p = psutil.Process(pid)
            return None if p.status() == psutil.STATUS_ZOMBIE else repr(p.create_time())
        except Exception:
            return None


def adopt(proc: subprocess.Popen) -> None:
    """Tie ``proc`` (started by this process) to this process's life (see the module notes)."""
    _adopted.append(proc)  # first: stop_all sees it from now on
    start = process_start(proc.pid)
    if start is None:
        return
    with _lock:
        pipe = _watcher()
        try:
            pipe.write(f"{proc.pid} {start}\n")
            pipe.flush()
        except (OSError, ValueError):  # the watcher is gone: stop_all still works while we run
            pass


def stop(proc: subprocess.Popen | None, grace: float = GRACE_SECONDS) -> None:
    """SIGTERM ``proc`` if it still runs, SIGKILL after ``grace`` seconds; reap it."""
    if proc is not None:
        _terminate([proc], grace)


def stop_all(grace: float = GRACE_SECONDS) -> None:
    """Stop every adopted process that still runs (all at once; SIGKILL after ``grace`` s).

    Takes no lock: a signal handler calls it, maybe while its thread is inside :func:`adopt`.
    """
    _terminate(list(_adopted), grace)


def _terminate(procs: list[subprocess.Popen], grace: float) -> None:
    live = [p for p in procs if p.poll() is None]
    for p in live:
        try:
            p.terminate()
        except OSError:
            pass
    deadline = time.monotonic() + grace
    for p in live:
        try:
            p.wait(max(0.0, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            p.kill()
            try:  # bounded: the interrupted thread may hold the Popen's wait lock
                p.wait(1.0)
            except subprocess.TimeoutExpired:
                pass


def _watcher():
    """The write end of the lifeline, starting the watcher on first use (under ``_lock``)."""
    global _pipe
    if _pipe is None:
        read, write = os.pipe()  # not inheritable (PEP 446): only the watcher gets the read end
        try:
            subprocess.Popen([sys.executable, "-m", "fringecal.lifeline"], stdin=read, stdout=subprocess.DEVNULL,
                             stderr=subprocess.DEVNULL, start_new_session=True)
        finally:
            os.close(read)
        _pipe = os.fdopen(write, "w")
    return _pipe


# -- the watcher process ------------------------------------------------------------------

def watch(lines) -> None:
    """Read ``pid start`` lines until end-of-file, then stop those processes (if they
    are still the ones recorded)."""
    adopted: dict[int, str] = {}
    for line in lines:
        try:
            pid, start = line.split()
            adopted[int(pid)] = start
        except ValueError:
            continue
    kill_recorded(adopted)


def kill_recorded(adopted: dict[int, str], grace: float = GRACE_SECONDS) -> list[int]:
    """SIGTERM every process of ``adopted`` (pid -> start token) still alive with its
    recorded start, SIGKILL those left after ``grace`` s; returns the pids signalled."""

    def alive():
        return [pid for pid, start in adopted.items() if process_start(pid) == start]

    targets = alive()
    for pid in targets:
        _signal(pid, signal.SIGTERM)
    deadline = time.monotonic() + grace
    while (left := alive()) and time.monotonic() < deadline:
        time.sleep(0.05)
    for pid in left:
        _signal(pid, signal.SIGKILL)
    return targets


def _signal(pid: int, sig: int) -> None:
    try:
        os.kill(pid, sig)
    except OSError:
        pass


if __name__ == "__main__":  # pragma: no cover - run as a process by _watcher()
    for _sig in (signal.SIGINT, signal.SIGHUP):
        signal.signal(_sig, signal.SIG_IGN)
    watch(sys.stdin)
