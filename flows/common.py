"""Console and error handling shared by every CLI module.

Sub-apps (``flows/cli_<area>.py``) import from here, never from ``fringecal.flows.cli``, so
``python -m fringecal.flows.cli`` cannot import the CLI twice.
"""

from __future__ import annotations

import functools
import os
import tomllib
from pathlib import Path

import typer
from rich.console import Console

__all__ = ["console", "err_console", "UserInputError", "fail", "guarded", "user_errors", "configured_prefect_api",
           "no_prefect_telemetry"]

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
    # lazy: every command imports this module; each loads the readers only when it fails
    from fringecal.calibration.file import CalibrationFileError
    from fringecal.config import ConfigError
    from fringecal.dataset import DataSetError
    from fringecal.fringe.importer import FrameStackError
    from fringecal.fringe.sequence import SequenceError
    from fringecal.schemas import TableError
    from fringecal.store import StoreError

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


def configured_prefect_api() -> str | None:
    """The Prefect API URL the user configured, or None when Prefect would start its
    own temporary server.

    Looked up where Prefect looks, without importing Prefect (about a second): the
    environment (``PREFECT_API_URL``), the active profile of ``profiles.toml``
    (``PREFECT_PROFILES_PATH``, else ``PREFECT_HOME``/profiles.toml, ``PREFECT_PROFILE``
    naming the profile) and ``prefect.toml`` in the working directory (``[api] url``).
    Small commands run their steps directly unless a server is configured, in which
    case they run as flows on it (runs visible in its UI, results cached).
    """
    url = os.environ.get("PREFECT_API_URL")
    if url:
        return url
    home = Path(os.environ.get("PREFECT_HOME", "~/.prefect")).expanduser()
    profiles = Path(os.environ.get("PREFECT_PROFILES_PATH", home / "profiles.toml")).expanduser()
    for path, find in ((profiles, _profile_url), (Path("prefect.toml"), _toml_url)):
        try:
            url = find(tomllib.loads(path.read_text()))
        except (OSError, tomllib.TOMLDecodeError, AttributeError, TypeError):
            continue
        if url:
            return str(url)
    return None


def no_prefect_telemetry() -> None:
    """No usage telemetry from the Prefect runs a command starts, and so no notice about
    it on a first run: Prefect 3 reads ``PREFECT_SERVER_ANALYTICS_ENABLED`` (its
    server) and ``DO_NOT_TRACK`` (its client); a value the user set is kept. Call before
    Prefect is imported."""
    os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
    os.environ.setdefault("DO_NOT_TRACK", "1")


def _profile_url(doc: dict):
    name = os.environ.get("PREFECT_PROFILE") or doc.get("active")
    return doc.get("profiles", {}).get(name, {}).get("PREFECT_API_URL") if name else None


def _toml_url(doc: dict):
    return doc.get("api", {}).get("url")
