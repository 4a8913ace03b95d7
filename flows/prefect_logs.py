"""Prefect's log lines go to the run's log file, not to the terminal.

A task that fails makes Prefect log its traceback at ERROR level, once for the task
run and again for the flow run (over a hundred lines for one corrupt frame), and a
Prefect server that went away makes its client threads warn every few seconds. None
of it is news for the person at the terminal: the command ends with one line saying
what is wrong (:func:`fringecal.flows.common.guarded`). So, once Prefect has
configured its logging, :func:`to_file` moves every handler that writes to the
terminal (Prefect's console handler on the root logger, the stream handlers of
``uvicorn`` and ``prefect._internal``) to one file handler on the run's log file
(``RUN_DIR/fringecal.log``, :attr:`fringecal.rundir.RunDir.log`), which keeps the
full detail: every traceback, every warning, and fringecal's own info lines (what each
step found: the bundle adjustment's F RMS, its sensor model, each sensor's share of its
format the control points covered; each store's valid share), which Prefect's level
(``PREFECT_LOGGING_LEVEL``, WARNING for a quiet run) would otherwise drop. fringecal's own
warnings (a sphere not fitted, a file recomputed) still reach the terminal, one line
each and without a traceback; its info lines do not, nor the Prefect server: its API
handler keeps the WARNING level it had, so a run posts no more lines than before the
file kept the info lines (about a hundred a run). ``--verbose`` leaves Prefect's
logging as it is.
"""

from __future__ import annotations

import logging
import sys
from pathlib import Path

__all__ = ["to_file", "restore"]

_FORMAT = "%(asctime)s | %(levelname)-7s | %(name)s - %(message)s"
_moved: list[tuple[logging.Logger, logging.Handler]] = []
_added: list[tuple[logging.Logger, logging.Handler]] = []
_levels: list[tuple[logging.Logger | logging.Handler, int]] = []


class _OneLine(logging.Formatter):
    """The message alone, no traceback (the log file has it)."""

    def format(self, record: logging.LogRecord) -> str:
        return f"{record.levelname.lower()}: {record.getMessage()}".splitlines()[0]


def _to_terminal(handler: logging.Handler) -> bool:
    stream = getattr(handler, "stream", None)
    if isinstance(handler, logging.FileHandler):
        return False
    if type(handler).__name__ == "PrefectConsoleHandler":
        return True
    return isinstance(handler, logging.StreamHandler) and stream in (sys.stderr, sys.stdout, sys.__stderr__,
                                                                       sys.__stdout__)


def to_file(log_path: Path) -> Path:
    """Route every terminal handler of the logging tree to ``log_path`` (appended; its
    folder is made) and keep fringecal's own warnings on the terminal, one line each."""
    restore()
    log_path = Path(log_path)
    log_path.parent.mkdir(parents=True, exist_ok=True)
    file_handler = logging.FileHandler(log_path, encoding="utf-8", delay=True)
    file_handler.setFormatter(logging.Formatter(_FORMAT))
    loggers = [logging.getLogger()] + [lg for lg in logging.Logger.manager.loggerDict.values()
                                       if isinstance(lg, logging.Logger)]
    for lg in loggers:
        terminal = [h for h in lg.handlers if _to_terminal(h)]
        for h in terminal:
            lg.removeHandler(h)
            _moved.append((lg, h))
        if terminal:
            lg.addHandler(file_handler)
            _added.append((lg, file_handler))
    ours = logging.getLogger("fringecal")
    _levels.append((ours, ours.level))
    ours.setLevel(logging.INFO)  # the file keeps fringecal's info lines, the terminal only its warnings
    for h in ours.handlers:  # Prefect's API handler (an extra logger's) keeps the warnings it had
        if type(h).__name__ == "APILogHandler" and h.level < logging.WARNING:
            _levels.append((h, h.level))
            h.setLevel(logging.WARNING)
    console = logging.StreamHandler(sys.stderr)
    console.setLevel(logging.WARNING)
    console.setFormatter(_OneLine())
    ours.addHandler(console)
    _added.append((ours, console))
    if not ours.propagate or not logging.getLogger().handlers:  # the file gets fringecal's lines too
        ours.addHandler(file_handler)
        _added.append((ours, file_handler))
    return log_path


def restore() -> None:
    """Undo :func:`to_file` (the command ends; in-process tests run several commands)."""
    while _added:
        lg, h = _added.pop()
        lg.removeHandler(h)
        if isinstance(h, logging.FileHandler):
            h.close()
    while _moved:
        lg, h = _moved.pop()
        lg.addHandler(h)
    while _levels:
        lg, level = _levels.pop()
        lg.setLevel(level)
