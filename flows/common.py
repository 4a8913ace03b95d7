"""Console and error handling shared by every CLI module.

Sub-apps (``flows/cli_<area>.py``) import from here, never from ``flows.cli``, so
``python -m flows.cli`` cannot import the CLI twice.
"""

from __future__ import annotations

import functools

import typer
from rich.console import Console

__all__ = ["console", "err_console", "UserInputError", "fail", "guarded", "user_errors"]

console = Console()
err_console = Console(stderr=True)


class UserInputError(Exception):
    """Bad input the user can fix; printed without a traceback."""


def fail(message: str, code: int = 2):
    """Print one error line (no traceback) and exit with ``code``."""
    err_console.print(f"[bold red]error:[/] {message}", highlight=False, soft_wrap=True)
    raise typer.Exit(code)


def user_errors() -> tuple[type[BaseException], ...]:
    """Exceptions that mean "the input is wrong": tables, configs, data sets, files, stores, frames."""
    from fringecal.calibration_file import CalibrationFileError
    from fringecal.config import ConfigError
    from fringecal.dataset import DataSetError
    from fringecal.fringe.importer import FrameStackError
    from fringecal.fringe.sequence import SequenceError
    from fringecal.store import StoreError
    from schemas import TableError

    return (UserInputError, TableError, ConfigError, DataSetError, FileNotFoundError, CalibrationFileError,
            FrameStackError, SequenceError, StoreError)


def guarded(fn=None, *, extra: tuple[type[BaseException], ...] = ()):
    """Decorator: user errors (plus ``extra``) become one message and exit status 2."""

    def decorate(f):
        @functools.wraps(f)
        def wrapper(*args, **kwargs):
            try:
                return f(*args, **kwargs)
            except user_errors() + tuple(extra) as err:
                fail(str(err.args[0]) if isinstance(err, KeyError) else str(err))

        return wrapper

    return decorate(fn) if fn is not None else decorate
