"""Progress of a run, kept out of the flow's parameters.

The command installs a reporter; flows call :func:`step` and :func:`advance`, which do
nothing when none is installed (tests, deployments, Dask workers). :func:`choose` picks
the reporter: on a terminal rich progress bars (:class:`RichProgress`), otherwise (CI,
``nohup``, a scheduler's log) one timestamped line per step start and end and a line at
least every :data:`PlainProgress.every` seconds while work goes on (:class:`PlainProgress`),
or nothing (``none``). ``--progress`` or ``FRINGECAL_PROGRESS`` (``rich``, ``plain``,
``none``) forces one. Both reporters show numba compiling kernels (a first run on a
machine) on a line whose seconds tick while it compiles.
"""

from __future__ import annotations

import os
import threading
import time
from contextlib import contextmanager

__all__ = ["install", "step", "advance", "say", "choose", "MODES", "ENV", "HELP", "RichProgress", "PlainProgress", "Silent"]

_reporter = None
#: The progress line that appears while numba compiles kernels.
COMPILING = "compiling kernels (first run only)"
#: ``--progress`` values; ``auto``: rich on a terminal, plain lines otherwise
MODES = ("auto", "rich", "plain", "none")
#: the environment variable that forces a mode where the option is not given
ENV = "FRINGECAL_PROGRESS"
#: the help of ``--progress``
HELP = (f"rich (bars), plain (timestamped lines, e.g. for a log file) or none; default: ${ENV}, else rich on "
        "a terminal and plain otherwise.")


def install(reporter) -> None:
    global _reporter
    _reporter = reporter


def step(name: str, total: int = 1) -> None:
    if _reporter is not None:
        _reporter.step(name, total)


def advance(name: str, n: int = 1) -> None:
    if _reporter is not None:
        _reporter.advance(name, n)


def say(text: str) -> None:
    """One status line, when a reporter is installed."""
    if _reporter is not None:
        _reporter.say(text)


def choose(mode: str | None, console):
    """The reporter for ``mode`` (None: ``$FRINGECAL_PROGRESS``, else ``auto``) writing to
    ``console`` (a rich Console). Raises ValueError for an unknown mode."""
    mode = (mode or os.environ.get(ENV) or "auto").strip().lower()
    if mode not in MODES:
        raise ValueError(f"progress mode must be one of {', '.join(MODES)}, not {mode!r}")
    if mode == "auto":
        mode = "rich" if console.is_terminal else "plain"
    return {"rich": RichProgress, "plain": PlainProgress, "none": Silent}[mode](console)


def compile_text(kernels: int, seconds: float) -> str:
    return f"{COMPILING}: {seconds:.0f} s, {kernels} kernel{'' if kernels == 1 else 's'} compiled"


class Silent:
    """No progress and no status lines (``--progress none``)."""

    def __init__(self, console=None):
        self.console = console
        self.clock = None
        self.kernels = 0
        self._stop = threading.Event()

    def say(self, text: str) -> None:
        """One status line (what is being loaded or started)."""

    def step(self, name: str, total: int) -> None:
        pass

    def advance(self, name: str, n: int = 1) -> None:
        pass

    def compiling(self, event: str, kernel: str, seconds: float) -> None:
        """Observer of :mod:`fringecal.compile_clock` (``start`` or ``end`` of a kernel)."""
        if event == "end":
            self.kernels += 1

    def tick(self) -> None:
        """Called once a second while the run goes on."""

    def _open(self) -> None:
        pass

    def _close(self) -> None:
        pass

    def _ticking(self) -> None:
        while not self._stop.wait(1.0):
            self.tick()

    @contextmanager
    def running(self):
        """Report the flow's steps and numba's compilations until the block ends."""
        from fringecal import compile_clock  # lazy: numba loads when a run shows its progress

        self.clock = compile_clock.install()
        install(self)
        self.clock.observer = self.compiling
        self._open()
        timer = threading.Thread(target=self._ticking, name="fringecal-progress", daemon=True)
        timer.start()
        try:
            yield self
        finally:
            self._stop.set()
            timer.join(2.0)
            self.clock.observer = None
            self._close()
            install(None)


class RichProgress(Silent):
    """One progress bar per pipeline step."""

    def __init__(self, console):
        super().__init__(console)
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

        self.progress = Progress(TextColumn("{task.description:<28}"), BarColumn(), MofNCompleteColumn(),
                                 TimeElapsedColumn(), console=console, transient=False)
        self.tasks = {}

    def say(self, text: str) -> None:
        self.console.print(text, highlight=False, markup=False, soft_wrap=True)

    def step(self, name: str, total: int) -> None:
        if name not in self.tasks:
            self.tasks[name] = self.progress.add_task(name, total=total)

    def advance(self, name: str, n: int = 1) -> None:
        if name in self.tasks:
            self.progress.advance(self.tasks[name], n)

    def compiling(self, event: str, kernel: str, seconds: float) -> None:
        super().compiling(event, kernel, seconds)
        if COMPILING not in self.tasks:
            self.tasks[COMPILING] = self.progress.add_task(COMPILING, total=None)
        self.tick()

    def tick(self) -> None:
        if COMPILING in self.tasks and self.clock is not None:
            self.progress.update(self.tasks[COMPILING], description=compile_text(self.kernels,
                                                                                 self.clock.busy_seconds()))

    def _open(self) -> None:
        self.progress.start()

    def _close(self) -> None:
        if COMPILING in self.tasks:
            self.tick()
            self.progress.update(self.tasks[COMPILING], total=1, completed=1)
        self.progress.stop()


class PlainProgress(Silent):
    """Timestamped lines (``07:12:03 render measurements 5/24``), flushed as written: a
    step's start and end, its count at most every ``every`` seconds, and a line for
    whatever is still running when nothing was said for ``quiet`` seconds."""

    every = 10.0
    quiet = 30.0

    def __init__(self, console):
        super().__init__(console)
        self.stream = console.file
        self._lock = threading.Lock()
        self.steps: dict[str, list] = {}  # name -> [total, done, start, last line]
        self._last = time.monotonic()
        self._doing = ("starting", self._last)  # the last status line and when it was said
        self._compile_said = None  # when the compile line was last written (None: not compiling)

    def _line(self, text: str) -> None:
        with self._lock:
            print(f"{time.strftime('%H:%M:%S')} {text}", file=self.stream, flush=True)
            self._last = time.monotonic()

    def say(self, text: str) -> None:
        self._doing = (text, time.monotonic())
        self._line(text)

    def step(self, name: str, total: int) -> None:
        if name in self.steps:
            return
        now = time.monotonic()
        self.steps[name] = [total, 0, now, now]
        self._line(f"{name} 0/{total}" if total else f"{name}: nothing to do")

    def advance(self, name: str, n: int = 1) -> None:
        s = self.steps.get(name)
        if s is None:
            return
        s[1] += n
        now = time.monotonic()
        if s[1] >= s[0]:
            self._line(f"{name} {s[1]}/{s[0]} done ({now - s[2]:.0f} s)")
        elif now - s[3] >= self.every:
            s[3] = now
            self._line(f"{name} {s[1]}/{s[0]}")

    def compiling(self, event: str, kernel: str, seconds: float) -> None:
        super().compiling(event, kernel, seconds)
        if event == "start" and self._compile_said is None:
            self._compile_said = time.monotonic()
            self._line(f"{COMPILING}: {kernel.rsplit('.', 1)[-1]} ...")

    def tick(self) -> None:
        now = time.monotonic()
        if self._compile_said is not None and self.clock is not None and now - self._compile_said >= self.every:
            self._compile_said = now if self.clock.compiling else None
            self._line(compile_text(self.kernels, self.clock.busy_seconds()))
        elif now - self._last >= self.quiet:
            running = [f"{n} {s[1]}/{s[0]} ({now - s[2]:.0f} s)" for n, s in self.steps.items() if s[1] < s[0]]
            doing, since = self._doing
            self._line("; ".join(running) if running else f"still {doing} ({now - since:.0f} s)")

    def _close(self) -> None:
        if self._compile_said is not None and self.clock is not None:
            self._line(compile_text(self.kernels, self.clock.busy_seconds()))
