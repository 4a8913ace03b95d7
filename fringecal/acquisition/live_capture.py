"""Run the scanner vendor's capture command and take its image stack only when whole.

The command is a template (``--capture``), split like a shell line (:func:`shlex.split`,
no shell runs) and filled per (measurement, scanner) with the placeholders

``{measurement}``  the measurement name (``poses_planned.csv``)
``{scanner}``      the scanner name (``sensors_prior.csv``)
``{out}``          the folder to write the stack into (exists, empty; required)
``{dataset}``      the data set folder

(``{{`` and ``}}`` for literal braces). The same values are in the environment as
``FRINGECAL_MEASUREMENT``, ``FRINGECAL_SCANNER``, ``FRINGECAL_OUT`` and
``FRINGECAL_DATASET``. The command runs in the data set folder, in a process group of
its own (a timeout or an interruption stops it and all its children), with stdout and
stderr kept per attempt in ``.acquire/logs/<measurement>-<scanner>-<id>.{stdout,stderr}.log``.

``{out}`` is a hidden staging folder next to the final one,
``measurements/<m>/.<scanner>.<id>.capture`` (:func:`staging_folder`; hidden entries are
ignored by :class:`~fringecal.dataset.DataSet`). The stack is taken when

1. the command has exited with status 0 (it may write asynchronously and return early;
   the stack then has until the timeout to become complete),
2. the folder listing (names, sizes, modification times) is unchanged over one poll,
3. :func:`~fringecal.fringe.importer.read_stack_spec` accepts the listing
   (``sequence.yaml`` valid, every frame present, nothing extra) and
   :func:`~fringecal.fringe.importer.read_frames` reads every frame (size, bit depth,
   not corrupt, not saturated),
4. the stack is the one expected: the camera's format of ``sensors_prior.csv``, the
   fringe sequence of the data set's other stacks, and the scanner and measurement
   named in ``sequence.yaml`` (if it names them).

Then the staging folder is renamed onto ``measurements/<m>/<scanner>/`` (one atomic
rename; the parent folder is synced). A command that exits non-zero, is still running
at the timeout (its process group is stopped), or leaves an incomplete or wrong stack
raises :class:`CaptureFailed`; the failed staging folder is kept for inspection and
removed by the next run. An interruption stops the command and removes its staging
folder.
"""

from __future__ import annotations

import os
import shlex
import shutil
import signal
import string
import subprocess
import time
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

from fringecal.fringe.importer import FrameStackError, StackSpec, read_frames, read_stack_spec
from fringecal.fringe.sequence import FringeSequence

__all__ = ["PLACEHOLDERS", "STAGING_SUFFIX", "CaptureTemplateError", "CaptureFailed", "CaptureCommand",
           "StackExpectation", "staging_folder", "is_staging", "remove_staging", "capture_stack"]

PLACEHOLDERS = ("measurement", "scanner", "out", "dataset")
STAGING_SUFFIX = ".capture"
#: a stale staging folder being removed (renamed first, so a leftover writer cannot reach it)
STALE_SUFFIX = ".stale"
#: seconds between looks at a running capture
POLL_S = 0.2
#: seconds a capture's process group gets between SIGTERM and SIGKILL
KILL_GRACE_S = 3.0
LOG_DIR = Path(".acquire") / "logs"


class CaptureTemplateError(ValueError):
    """A ``--capture`` template that cannot be run (found before anything moves)."""


class CaptureFailed(RuntimeError):
    """A capture that gave no usable stack. ``kind``: exit, timeout, incomplete, wrong-stack
    or interrupted."""

    def __init__(self, kind: str, message: str):
        super().__init__(message)
        self.kind = kind


@dataclass(frozen=True)
class CaptureCommand:
    """A checked capture template: ``argv`` holds the tokens with their placeholders."""

    template: str
    argv: tuple[str, ...]
    program: str

    @classmethod
    def parse(cls, template: str, cwd: Path | None = None) -> "CaptureCommand":
        """Split and check ``template``; the program must exist (on PATH, or a path
        relative to ``cwd``, where the command will run).

        Raises
        ------
        CaptureTemplateError
        """
        where = f"--capture {template!r}"
        try:
            argv = tuple(shlex.split(template))
        except ValueError as err:
            raise CaptureTemplateError(f"{where}: cannot split it like a shell line ({err})") from None
        if not argv:
            raise CaptureTemplateError(f"{where}: empty command")
        used = set()
        for token in argv:
            try:
                fields = [f for _, f, _, _ in string.Formatter().parse(token) if f is not None]
            except ValueError as err:
                raise CaptureTemplateError(f"{where}: bad placeholder in {token!r} ({err}; write {{{{ and }}}} "
                                           "for literal braces)") from None
            for f in fields:
                if f not in PLACEHOLDERS:
                    raise CaptureTemplateError(f"{where}: unknown placeholder {{{f}}}; known: "
                                               + ", ".join(f"{{{p}}}" for p in PLACEHOLDERS))
            used.update(fields)
        if "out" not in used:
            raise CaptureTemplateError(f"{where}: no {{out}} placeholder; the command must be told the folder "
                                       "to write the image stack into")
        if "{" in argv[0]:
            raise CaptureTemplateError(f"{where}: the program name may not hold a placeholder")
        if os.sep in argv[0]:
            p = Path(argv[0]) if Path(argv[0]).is_absolute() else (cwd or Path.cwd()) / argv[0]
            program = str(p) if p.is_file() and os.access(p, os.X_OK) else None
        else:
            program = shutil.which(argv[0])
        if program is None:
            raise CaptureTemplateError(f"{where}: program {argv[0]!r} not found or not executable")
        return cls(template, argv, program)

    def render(self, measurement: str, scanner: str, out: Path, dataset: Path) -> list[str]:
        """The command line for one capture."""
        values = {"measurement": measurement, "scanner": scanner, "out": str(out), "dataset": str(dataset)}
        return [token.format(**values) for token in self.argv]


@dataclass(frozen=True)
class StackExpectation:
    """What the stack of (``measurement``, ``scanner``) must be: the camera format
    (``width_px`` x ``height_px``) and, once the data set has a stack, its ``sequence``
    (that of the stack ``sequence_source``)."""

    measurement: str
    scanner: str
    width_px: int
    height_px: int
    sequence: Optional[FringeSequence] = None
    sequence_source: Optional[Path] = None

    @property
    def label(self) -> str:
        return f"measurement {self.measurement}, scanner {self.scanner}"

    def check(self, folder: Path, spec: StackSpec) -> None:
        """Raise :class:`CaptureFailed` (``wrong-stack``) when ``spec`` is not the stack expected."""
        problems = []
        if (spec.width_px, spec.height_px) != (self.width_px, self.height_px):
            problems.append(f"images are {spec.width_px}x{spec.height_px} px, but the camera of scanner "
                            f"{self.scanner!r} in sensors_prior.csv is {self.width_px}x{self.height_px} px")
        if self.sequence is not None and spec.sequence != self.sequence:
            problems.append(f"fringe sequence {spec.sequence.to_dict()} differs from {self.sequence.to_dict()} of "
                            f"{self.sequence_source or 'the data set'}")
        for key, want in (("scanner", self.scanner), ("measurement", self.measurement)):
            got = getattr(spec, key)
            if got is not None and got != want:
                problems.append(f"sequence.yaml names {key} {got!r}, not {want!r}")
        if problems:
            raise CaptureFailed("wrong-stack", f"{self.label}: wrong image stack in {folder}: " + "; ".join(problems))


def staging_folder(final: Path, attempt: str) -> Path:
    """The hidden staging folder of one attempt next to ``final`` (``.<scanner>.<attempt>.capture``)."""
    return final.parent / f".{final.name}.{attempt}{STAGING_SUFFIX}"


def is_staging(entry: Path) -> bool:
    """True for a staging folder this module made (any scanner, any attempt, or one being removed)."""
    return entry.name.startswith(".") and entry.name.endswith((STAGING_SUFFIX, STALE_SUFFIX))


def remove_staging(folder: Path) -> None:
    """Remove a stale staging folder: rename it first (a capture command still running
    from a killed acquisition can no longer write into it), then delete it."""
    trash = folder
    if folder.name.endswith(STAGING_SUFFIX):
        trash = folder.with_name(folder.name[: -len(STAGING_SUFFIX)] + STALE_SUFFIX)
        try:
            os.rename(folder, trash)
        except FileNotFoundError:
            return
    shutil.rmtree(trash, ignore_errors=True)


def capture_stack(command: CaptureCommand, expect: StackExpectation, final: Path, dataset: Path,
                  timeout_s: float, stop, poll_s: float = POLL_S) -> StackSpec:
    """Run one capture and rename its complete stack onto ``final``.

    Parameters
    ----------
    command : CaptureCommand
    expect : StackExpectation
    final : Path
        ``measurements/<m>/<scanner>``; must not exist.
    dataset : Path
        The data set folder (the command's working directory).
    timeout_s : float
        From the start of the command until the stack is complete.
    stop : StopRequest
        An interruption request (:class:`~fringecal.acquisition.live.StopRequest`, or
        anything with ``is_set()`` and ``wait(seconds)``).
    poll_s : float

    Returns
    -------
    StackSpec
        The stack's ``sequence.yaml``.

    Raises
    ------
    CaptureFailed
    """
    if final.exists():
        raise FileExistsError(f"{final}: already exists; a complete stack is never captured again")
    attempt = uuid.uuid4().hex[:12]
    staging = staging_folder(final, attempt)
    staging.mkdir(parents=True)
    logs = dataset / LOG_DIR
    logs.mkdir(parents=True, exist_ok=True)
    log = f"{expect.measurement}-{expect.scanner}-{attempt}"
    err_log = logs / f"{log}.stderr.log"
    argv = command.render(expect.measurement, expect.scanner, staging, dataset)
    env = {**os.environ, "FRINGECAL_MEASUREMENT": expect.measurement, "FRINGECAL_SCANNER": expect.scanner,
           "FRINGECAL_OUT": str(staging), "FRINGECAL_DATASET": str(dataset)}
    with open(logs / f"{log}.stdout.log", "wb") as out, open(err_log, "wb") as err:
        try:
            proc = subprocess.Popen(argv, cwd=dataset, env=env, stdin=subprocess.DEVNULL, stdout=out, stderr=err,
                                    start_new_session=True)
        except OSError as exc:
            shutil.rmtree(staging, ignore_errors=True)
            raise CaptureFailed("exit", f"{expect.label}: cannot start the capture command {argv[0]!r}: {exc}") \
                from None
    try:
        spec = _wait_for_stack(proc, staging, expect, time.monotonic() + timeout_s, timeout_s, stop, poll_s, err_log)
    except CaptureFailed as exc:
        _stop_group(proc)
        if exc.kind == "interrupted":
            shutil.rmtree(staging, ignore_errors=True)
        else:
            exc.args = (f"{exc} (the failed stack is kept in {staging}; the next run removes it)",)
        raise
    except BaseException:
        _stop_group(proc)
        shutil.rmtree(staging, ignore_errors=True)
        raise
    os.rename(staging, final)
    _sync_folder(final.parent)
    return spec


def _wait_for_stack(proc, staging: Path, expect: StackExpectation, deadline: float, timeout_s: float, stop,
                    poll_s: float, err_log: Path) -> StackSpec:
    """Poll until the stack is complete (see the module notes); raise CaptureFailed otherwise."""
    previous, tried, problem = None, None, "nothing written"
    while True:
        if stop.is_set():
            raise CaptureFailed("interrupted", f"{expect.label}: capture interrupted")
        rc = proc.poll()
        if rc not in (None, 0):
            raise CaptureFailed("exit", f"{expect.label}: the capture command exited with status {rc}"
                                + _tail(err_log))
        listing = _listing(staging)
        if rc == 0 and listing == previous and listing != tried:
            tried = listing
            try:
                spec, _, _ = read_stack_spec(staging)
                read_frames(staging, threads=2)
            except FrameStackError as err:
                problem = str(err)
            else:
                expect.check(staging, spec)
                return spec
        previous = listing
        if time.monotonic() > deadline:
            if rc is None:
                raise CaptureFailed("timeout", f"{expect.label}: the capture command was still running "
                                    f"{timeout_s:g} s after it started (--timeout); stopped it" + _tail(err_log))
            raise CaptureFailed("incomplete", f"{expect.label}: incomplete image stack {timeout_s:g} s after the "
                                f"capture started (--timeout): {problem}")
        stop.wait(poll_s)


def _listing(folder: Path) -> tuple:
    """(name, size, mtime_ns) of every file in ``folder``; changes while anything is written."""
    out = []
    try:
        with os.scandir(folder) as it:
            for e in it:
                try:
                    st = e.stat()
                except FileNotFoundError:
                    continue
                out.append((e.name, st.st_size, st.st_mtime_ns))
    except FileNotFoundError:
        return ()
    return tuple(sorted(out))


def _tail(path: Path, lines: int = 5, chars: int = 600) -> str:
    try:
        text = path.read_text(errors="replace")
    except OSError:
        return ""
    kept = [ln for ln in text.splitlines() if ln.strip()][-lines:]
    tail = " | ".join(kept)[-chars:]
    return f"; its stderr ends: {tail}" if tail else "; it wrote nothing to stderr"


def _stop_group(proc: subprocess.Popen) -> None:
    """Stop the capture's process group: SIGTERM, then SIGKILL after a grace period."""
    if proc.poll() is not None:
        _signal_group(proc, signal.SIGKILL)  # children it may have left behind
        return
    _signal_group(proc, signal.SIGTERM)
    try:
        proc.wait(KILL_GRACE_S)
    except subprocess.TimeoutExpired:
        pass
    _signal_group(proc, signal.SIGKILL)
    proc.wait()


def _signal_group(proc: subprocess.Popen, sig) -> None:
    try:
        os.killpg(proc.pid, sig)
    except (ProcessLookupError, PermissionError):
        pass


def _sync_folder(folder: Path) -> None:
    """Make a rename in ``folder`` durable (best effort where directories cannot be opened)."""
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)
