"""``fringecal serve`` stops as it says: one line, within seconds, however it ends.

Once serving, the command's terminal shows one line per event that ends it; all the
rest -- Prefect's runner, the served runs' progress and their tracebacks, the
client's warnings while the server is unreachable -- goes to ``OUT/fringecal.log``
(:func:`detach`: the process's standard output and error, which the served runs'
processes inherit, are the log file from then on).

* **The server goes away.** A watchdog thread asks the server's ``/health`` every
  :data:`POLL_SECONDS`; after :data:`MISSES` failed answers in a row it prints
  ``error: the Prefect server at URL stopped answering ...``, stops the run in
  progress (its finished step instances are kept in OUT: the next run resumes them,
  :mod:`fringecal.run.resume`) and ends serving with status 1.
* **Ctrl-C or SIGTERM.** One line (``stopped serving ...``), the run in progress
  stopped the same way, status 130 or 143 -- within :data:`GRACE_SECONDS` plus a
  moment, never the minute Prefect's runner waits for its runs.

Why not unwind: Prefect's runner waits for its flow-run processes and its event
loop's tasks; nothing needs unwinding, since every output is written atomically. So
the handlers print their line to the terminal, stop every process serve started
(SIGTERM, SIGKILL after :data:`GRACE_SECONDS`) and end the process (``os._exit``).
"""

from __future__ import annotations

import os
import signal
import threading
import time
from pathlib import Path

__all__ = ["detach", "watch_server", "arm_signals", "POLL_SECONDS", "MISSES", "GRACE_SECONDS", "EXIT_SERVER_GONE"]

POLL_SECONDS = 2.0
MISSES = 3
GRACE_SECONDS = 2.0
#: exit status when the Prefect server stopped answering
EXIT_SERVER_GONE = 1

_terminal: int | None = None  # a duplicate of the terminal's stderr, once detached
_ending = threading.Lock()


def detach(log_path: Path) -> None:
    """From now on the process's stdout and stderr (and so those of the runs it starts)
    append to ``log_path``; :func:`_say` still reaches the terminal."""
    global _terminal
    log_path = Path(log_path)
    log_path.parent.mkdir(parents=True, exist_ok=True)
    _terminal = os.dup(2)
    fd = os.open(log_path, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
    for target in (1, 2):
        os.dup2(fd, target)
    os.close(fd)


def _say(line: str) -> None:
    fd = _terminal if _terminal is not None else 2
    try:
        os.write(fd, (line.rstrip("\n") + "\n").encode())
    except OSError:
        pass


def _descendants(pid: int) -> list[int]:
    """Every process below ``pid`` (from /proc; children first found first)."""
    parents: dict[int, list[int]] = {}
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat", "rb") as f:
                ppid = int(f.read().rsplit(b")", 1)[1].split()[1])
        except (OSError, IndexError, ValueError):
            continue
        parents.setdefault(ppid, []).append(int(entry))
    out, todo = [], [pid]
    while todo:
        for child in parents.get(todo.pop(), []):
            out.append(child)
            todo.append(child)
    return out


def _stop_children() -> None:
    """SIGTERM every process serve started, SIGKILL those left after GRACE_SECONDS."""
    kids = _descendants(os.getpid())
    for pid in kids:
        try:
            os.kill(pid, signal.SIGTERM)
        except OSError:
            pass
    deadline = time.monotonic() + GRACE_SECONDS
    while time.monotonic() < deadline and any(_alive(p) for p in kids):
        time.sleep(0.1)
    for pid in kids:
        if _alive(pid):
            try:
                os.kill(pid, signal.SIGKILL)
            except OSError:
                pass


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat", "rb") as f:
            return f.read().rsplit(b")", 1)[1].split()[0] != b"Z"
    except OSError:
        return False


def _end(line: str, code: int) -> None:
    """Print ``line`` on the terminal, stop the runs, end the process (once)."""
    if not _ending.acquire(blocking=False):
        return
    for s in (signal.SIGINT, signal.SIGTERM):
        try:
            signal.signal(s, signal.SIG_IGN)
        except ValueError:  # not the main thread: the process ends below all the same
            pass
    _say(line)
    _stop_children()
    os._exit(code)


def arm_signals(run_dir: Path) -> None:
    """Ctrl-C and SIGTERM end serving at once with one line (main thread only)."""

    def handler(signum, frame):  # pragma: no cover - runs in a subprocess in the tests
        _end(f"stopped serving ({signal.Signals(signum).name}); a run in progress was stopped, its finished steps "
             f"are kept in {run_dir} for the next run", 128 + signum)

    for s in (signal.SIGINT, signal.SIGTERM):
        signal.signal(s, handler)
    # Prefect's runner puts its own SIGTERM handler in place when it starts (a graceful
    # shutdown that waits for the runs): it gets this one instead
    from prefect.runner.runner import Runner

    Runner.handle_sigterm = lambda self, *args, **kwargs: handler(signal.SIGTERM, None)


def watch_server(api: str, run_dir: Path, log_path: Path, poll_seconds: float = POLL_SECONDS, misses: int = MISSES,
                 get=None) -> threading.Thread:
    """A daemon thread that ends serving with one line when the server at ``api`` has not
    answered ``/health`` ``misses`` times in a row (``get``: an ``httpx.get`` stand-in)."""
    if get is None:
        import httpx

        def get(url, timeout):
            return httpx.get(url, timeout=timeout)

    url = api.rstrip("/") + "/health"

    def watch():
        failed, since = 0, None
        while True:
            time.sleep(poll_seconds)
            try:
                ok = get(url, timeout=poll_seconds).status_code == 200
            except Exception:  # noqa: BLE001 - any failure to answer counts as a miss
                ok = False
            if ok:
                failed, since = 0, None
                continue
            failed += 1
            since = since or time.strftime("%H:%M:%S")
            if failed >= misses:
                _end(f"error: the Prefect server at {api} stopped answering (since {since}): serving ended; a run "
                     f"in progress was stopped, its finished steps are kept in {run_dir} for the next run; start "
                     f"the server again, then `fringecal serve` again (details: {log_path})", EXIT_SERVER_GONE)
                return

    thread = threading.Thread(target=watch, name="fringecal-server-watchdog", daemon=True)
    thread.start()
    return thread
