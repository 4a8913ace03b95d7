"""Ctrl-C and SIGTERM during ``fringecal run`` and ``fringecal reproduce``.

Within :func:`armed` (the command's flow call), SIGINT and SIGTERM end the command
within seconds: one line on stderr (``interrupted: N step instances finished and
kept in RUN_DIR; rerun the same command to resume``), every helper process stopped
(Prefect's temporary server, the kernel warm-up, local Dask workers;
:mod:`fringecal.lifeline`), exit status 130 (SIGINT) or 143 (SIGTERM), as a shell
reports a command ended by that signal.

Why not unwind: the steps run in worker threads, in numba kernels that cannot be
interrupted, and Prefect's own SIGTERM handling (a ``TerminationSignal`` raised in
the flow) waits for every running task to finish -- over a minute -- while its
background threads print connection errors once the server has gone. Nothing needs
unwinding: every output is written atomically, so the handler prints its line,
silences the process's stdout and stderr, stops the helpers and ends the process
at once (``os._exit``). A step interrupted mid-write leaves at most a hidden
temporary, removed by the next run (:mod:`fringecal.run.resume`), which reuses every
finished step instance.

Prefect installs its SIGTERM handler while a flow runs; the flow calls
:func:`reassert` first thing to put this one back (a no-op when not armed, e.g. in
a served deployment, where Prefect's handling applies).
"""

from __future__ import annotations

import os
import signal
import sys
import threading
from contextlib import contextmanager
from pathlib import Path

from fringecal import lifeline  # here, not in the handler: no import while a signal is handled

__all__ = ["armed", "reassert", "track", "SIGNALS"]

SIGNALS = (signal.SIGINT, signal.SIGTERM)


class _Armed:
    def __init__(self, run_dir: Path):
        self.run_dir = run_dir
        self.runner = None  # the flow's StepRunner, once it exists (its ``finished`` count)


_current: _Armed | None = None


def _main_thread() -> bool:
    return threading.current_thread() is threading.main_thread()


@contextmanager
def armed(run_dir: Path):
    """SIGINT and SIGTERM end the command at once while inside (main thread only)."""
    global _current
    if not _main_thread():
        yield
        return
    previous = {s: signal.getsignal(s) for s in SIGNALS}
    _current = _Armed(Path(run_dir))
    for s in SIGNALS:
        signal.signal(s, _handler)
    try:
        yield
    finally:
        _current = None
        for s, h in previous.items():
            signal.signal(s, h if h is not None else signal.SIG_DFL)


def reassert() -> None:
    """Put the handler back in place of Prefect's (called by the flow; no-op unless armed)."""
    if _current is not None and _main_thread():
        for s in SIGNALS:
            if signal.getsignal(s) is not _handler:
                signal.signal(s, _handler)


def track(runner) -> None:
    """The flow's step runner, whose ``finished`` count the interruption line reports."""
    if _current is not None:
        _current.runner = runner


def _handler(signum, frame) -> None:  # pragma: no cover - runs in a subprocess in the tests
    for s in SIGNALS:  # a second Ctrl-C while stopping changes nothing
        signal.signal(s, signal.SIG_IGN)
    state = _current
    run_dir = state.run_dir if state else Path(".")
    n = getattr(state.runner, "finished", 0) if state else 0
    line = (f"interrupted: {n} step instance{'' if n == 1 else 's'} finished and kept in {run_dir}; "
            "rerun the same command to resume\n")
    try:
        err = os.dup(2)
        tty = os.isatty(err)
        # from here on nothing else reaches the terminal: no progress redraw, no connection
        # error from Prefect's threads while its server stops (no Python-level locks taken)
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, 1)
        os.dup2(devnull, 2)
        if tty:  # below the progress bars, in yellow, with the cursor the live display hid
            line = "\n\x1b[1;33minterrupted:\x1b[0m" + line[len("interrupted:"):] + "\x1b[?25h"
        os.write(err, line.encode())
    except OSError:  # no stderr to write to: stop all the same
        pass
    lifeline.stop_all()
    if (mp := sys.modules.get("multiprocessing")) is not None:  # a local Dask cluster's workers
        for child in mp.active_children():
            child.terminate()
    os._exit(128 + signum)
