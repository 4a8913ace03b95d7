"""Progress of a run for the terminal (rich), kept out of the flow's parameters.

The CLI installs a :class:`RichProgress`; flows call :func:`step` and :func:`advance`,
which do nothing when no reporter is installed (tests, deployments, Dask workers).
"""

from __future__ import annotations

from contextlib import contextmanager

__all__ = ["install", "step", "advance", "RichProgress"]

_reporter = None
#: The progress line that appears while numba compiles kernels.
COMPILING = "compiling kernels (first run only)"


def install(reporter) -> None:
    global _reporter
    _reporter = reporter


def step(name: str, total: int = 1) -> None:
    if _reporter is not None:
        _reporter.step(name, total)


def advance(name: str, n: int = 1) -> None:
    if _reporter is not None:
        _reporter.advance(name, n)


class RichProgress:
    """One progress bar per pipeline step."""

    def __init__(self, console):
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

        self.progress = Progress(TextColumn("{task.description:<28}"), BarColumn(), MofNCompleteColumn(),
                                 TimeElapsedColumn(), console=console, transient=False)
        self.tasks = {}
        self.kernels_compiled = 0

    def step(self, name: str, total: int) -> None:
        if name not in self.tasks:
            self.tasks[name] = self.progress.add_task(name, total=total)

    def advance(self, name: str, n: int = 1) -> None:
        if name in self.tasks:
            self.progress.advance(self.tasks[name], n)

    def compiling(self, event: str, kernel: str, seconds: float) -> None:
        """Observer of :mod:`fringecal.compile_clock`: one line that appears when numba
        compiles (a first run on this machine) and shows the seconds spent so far."""
        if COMPILING not in self.tasks:
            self.tasks[COMPILING] = self.progress.add_task(COMPILING, total=None)
        if event == "end":
            self.kernels_compiled += 1
        self.progress.update(self.tasks[COMPILING],
                             description=f"{COMPILING}: {self.kernels_compiled} kernels, {seconds:.0f} s")

    @contextmanager
    def running(self):
        from fringecal import compile_clock  # lazy: numba loads when a run shows its progress

        clock = compile_clock.install()
        install(self)
        clock.observer = self.compiling
        with self.progress:
            try:
                yield self
            finally:
                clock.observer = None
                if COMPILING in self.tasks:
                    self.progress.update(self.tasks[COMPILING], total=1, completed=1)
                install(None)
