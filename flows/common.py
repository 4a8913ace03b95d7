"""Console and error handling shared by every CLI module.

Sub-apps (``flows/cli_<area>.py``) import from here, never from ``fringecal.flows.cli``, so
``python -m fringecal.flows.cli`` cannot import the CLI twice.
"""

from __future__ import annotations

import errno
import functools
import os
import tomllib
from pathlib import Path

import typer
from rich.console import Console

__all__ = ["console", "err_console", "UserInputError", "fail", "guarded", "user_errors", "configured_prefect_api",
           "no_prefect_telemetry", "needs_space", "os_error_line", "log_failures_to"]

console = Console()
err_console = Console(stderr=True)


class UserInputError(Exception):
    """Bad input the user can fix; printed without a traceback."""


def fail(message: str, code: int = 2):
    """Print one error line (no traceback) and exit with ``code``."""
    err_console.print(f"[bold red]error:[/] {message}", highlight=False, soft_wrap=True)
    raise typer.Exit(code)


def user_errors() -> tuple[type[BaseException], ...]:
    """Exceptions that mean "the input is wrong": tables, configs, data sets, files, stores, frames,
    names, a run directory another run writes or whose files changed, data that cannot give
    what a step needs."""
    # lazy: every command imports this module; each loads the readers only when it fails
    from fringecal.calibration.file import CalibrationFileError
    from fringecal.config import ConfigError
    from fringecal.dataset import DataSetError
    from fringecal.fringe.importer import FrameStackError
    from fringecal.fringe.sequence import SequenceError
    from fringecal.names import OutsideFolderError, UnsafeNameError
    from fringecal.run.resume import RunDirBusy
    from fringecal.scancloud import CloudFileError
    from fringecal.schemas import TableError
    from fringecal.steps.base import DataProblem
    from fringecal.steps.keys import RunFileChanged
    from fringecal.store import StoreError

    return (UserInputError, TableError, ConfigError, DataSetError, FileNotFoundError, CalibrationFileError,
            FrameStackError, SequenceError, StoreError, UnsafeNameError, OutsideFolderError, RunDirBusy,
            RunFileChanged, DataProblem, CloudFileError)


#: where the command writes and roughly how much (``needs_space``), for a full disk's line
_space: dict = {}


def needs_space(folder, n_bytes, what: str) -> None:
    """Say that the command is about to write about ``n_bytes`` (a number, or a function
    giving it, called only when the disk is full) into ``folder`` (``what``: "the run",
    "the store"): a full disk then says roughly how much the command needs."""
    _space.update(folder=Path(folder), bytes=n_bytes, what=what)


def _needed() -> float | None:
    n = _space.get("bytes")
    try:
        return float(n()) if callable(n) else (None if n is None else float(n))
    except Exception:  # noqa: BLE001 - an estimate that fails is left out of the line
        return None


def _size(n: float) -> str:
    for unit in ("bytes", "kB", "MB", "GB", "TB"):
        if n < 1000 or unit == "TB":
            return f"{n:.0f} {unit}" if unit == "bytes" else f"{n:.3g} {unit}"
        n /= 1000
    return f"{n:.3g} TB"


def _free(path) -> str:
    p = Path(path or ".").absolute()
    while not p.exists() and p != p.parent:
        p = p.parent
    try:
        st = os.statvfs(p)
    except OSError:
        return "unknown"
    return _size(st.f_bavail * st.f_frsize)


def os_error_line(err: OSError) -> str:
    """One line for a failed file operation: the path, what the system said and, for a
    full disk, the free space and roughly what the command needs."""
    path = err.filename or _space.get("folder") or "?"
    if err.errno == errno.ENOSPC or err.errno == errno.EDQUOT:
        n = _needed()
        need = f"; {_space['what']} needs roughly {_size(n)} in {_space['folder']}" if n else ""
        return (f"{path}: no space left on the device ({_free(path)} free){need}: free some space or choose "
                "another output folder, then rerun the same command (nothing half-written is kept or trusted)")
    strerror = err.strerror or str(err)
    return f"{path}: {strerror}" + (f" (and {err.filename2})" if err.filename2 else "")


def _chain(err: BaseException):
    """``err`` and the exceptions it was raised from or during, outermost first."""
    seen = set()
    while err is not None and id(err) not in seen:
        seen.add(id(err))
        yield err
        err = err.__cause__ or err.__context__


def _message(err: BaseException) -> str:
    return str(err.args[0]) if isinstance(err, KeyError) and err.args else str(err)


def _passes(err: BaseException) -> bool:
    """What a command raises on purpose to end: typer's and click's Exit and Abort, and
    usage errors."""
    import click

    return isinstance(err, (typer.Exit, typer.Abort, click.exceptions.Exit, click.exceptions.Abort,
                            click.ClickException))


#: set by a command that runs the flow: where the traceback of an unexpected error goes
_log_file: dict = {}


def log_failures_to(path) -> None:
    """Tracebacks of unexpected errors go to ``path`` (the run's log file)."""
    _log_file["path"] = Path(path)


def _internal(err: BaseException) -> str:
    """One line for an error that is fringecal's, not the input's: what it was, where the
    traceback went (the run's log file, else FRINGECAL_TRACEBACK=1 prints it)."""
    import traceback

    text = "".join(traceback.format_exception(err))
    step = getattr(err, "fringecal_step", None)
    where = f" in step {step}" if step else ""
    first = " ".join(str(err).split())[:300]
    line = f"internal error{where}: {type(err).__name__}: {first}"
    if os.environ.get("FRINGECAL_TRACEBACK"):
        err_console.print(text, highlight=False, markup=False)
        return line
    path = _log_file.get("path")
    if path is not None:
        try:
            with open(path, "a", encoding="utf-8") as f:
                f.write(text)
            return f"{line} (a fringecal fault, not your input: the traceback is in {path}; please report it)"
        except OSError:
            pass
    return f"{line} (a fringecal fault, not your input: FRINGECAL_TRACEBACK=1 prints the traceback; please report it)"


def guarded(fn=None, *, extra: tuple[type[BaseException], ...] = (), passing: tuple[type[BaseException], ...] = ()):
    """Decorator: whatever fails ends the command with one line on stderr and no traceback.

    User errors (plus ``extra``; also when they caused another exception, as a step's
    error inside Prefect's) exit with status 2, naming the file, folder or option; a
    failed file operation (a full disk: with the free space and roughly what the
    command needs) with 2, naming the path; out of memory with 2; anything else is a
    fringecal fault: status 1, the traceback in the run's log file
    (:func:`log_failures_to`) or printed with ``FRINGECAL_TRACEBACK=1``. Exceptions of
    ``passing`` go through to the caller (a hexapod fault, which has a status of its own).
    """

    def decorate(f):
        @functools.wraps(f)
        def wrapper(*args, **kwargs):
            _space.clear()
            _log_file.clear()
            try:
                return f(*args, **kwargs)
            except BaseException as err:  # noqa: BLE001 - every failure gets its one line
                if _passes(err) or isinstance(err, (KeyboardInterrupt, SystemExit, GeneratorExit) + tuple(passing)):
                    raise
                known = user_errors() + tuple(extra)
                for e in _chain(err):
                    if isinstance(e, known):
                        fail(_message(e))
                for e in _chain(err):
                    if isinstance(e, OSError):
                        fail(os_error_line(e))
                    if isinstance(e, MemoryError):
                        fail("out of memory: the input is larger than this machine can process at once "
                             f"({type(e).__name__}{': ' + str(e) if str(e) else ''})")
                fail(_internal(err), code=1)

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
