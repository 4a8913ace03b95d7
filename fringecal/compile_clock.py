"""How long numba spends compiling kernels, so that step timings can leave it out.

The first run on a machine compiles every numba kernel the pipeline uses and
stores it in numba's cache (``__pycache__`` beside each module, or
``NUMBA_CACHE_DIR``); later runs load them in milliseconds. A step's time on the
first run therefore mixes its work with one-off compilation. :func:`install`
hooks numba's ``numba:compile`` event, which fires only on a cache miss (a cache
hit loads without it), and keeps, per thread, the seconds spent in outermost
compilations (a kernel compiling the helpers it calls counts once). A step reads
:func:`thread_seconds` before and after its work; the difference is its
compilation, reported next to its time rather than inside it.

Examples
--------
>>> clock = install()
>>> before = thread_seconds()
>>> thread_seconds() - before
0.0
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

__all__ = ["CompileClock", "install", "thread_seconds", "totals"]


class CompileClock:
    """Compile seconds per thread and in total, with an optional observer.

    ``observer(event, name, seconds)`` is called with ``"start"`` or ``"end"`` for each
    outermost compilation (``seconds`` is the total so far), e.g. to show a progress line.
    :meth:`busy_seconds` is the wall time during which some thread compiled, up to now
    (a compilation in progress included), for a display that ticks while numba works.
    """

    def __init__(self):
        self._local = threading.local()
        self._lock = threading.Lock()
        self.total_seconds = 0.0
        self.kernels: dict[str, float] = {}
        self.observer: Callable[[str, str, float], None] | None = None
        self._active = 0  # threads inside an outermost compilation
        self._busy_since = 0.0
        self._busy_before = 0.0  # wall seconds of earlier busy spells

    def _state(self):
        s = self._local
        if not hasattr(s, "depth"):
            s.depth, s.seconds, s.t0 = 0, 0.0, 0.0
        return s

    def start(self, name: str) -> None:
        s = self._state()
        s.depth += 1
        if s.depth == 1:
            s.t0 = time.perf_counter()
            with self._lock:
                if self._active == 0:
                    self._busy_since = s.t0
                self._active += 1
            if self.observer is not None:
                self.observer("start", name, self.total_seconds)

    def end(self, name: str) -> None:
        s = self._state()
        s.depth -= 1
        if s.depth == 0:
            dt = time.perf_counter() - s.t0
            s.seconds += dt
            with self._lock:
                self.total_seconds += dt
                self.kernels[name] = self.kernels.get(name, 0.0) + dt
                self._active -= 1
                if self._active == 0:
                    self._busy_before += time.perf_counter() - self._busy_since
            if self.observer is not None:
                self.observer("end", name, self.total_seconds)

    def thread_seconds(self) -> float:
        return self._state().seconds

    @property
    def compiling(self) -> bool:
        """Whether some thread is compiling now."""
        return self._active > 0

    def busy_seconds(self) -> float:
        """Wall seconds during which at least one thread compiled, up to now."""
        with self._lock:
            now = time.perf_counter() - self._busy_since if self._active else 0.0
            return self._busy_before + now


_clock: CompileClock | None = None


def install() -> CompileClock:
    """Listen to numba's compile events (once per process); return the clock."""
    global _clock
    if _clock is not None:
        return _clock
    from numba.core import event

    clock = CompileClock()

    class _Listener(event.Listener):
        def on_start(self, ev):
            clock.start(_kernel_name(ev))

        def on_end(self, ev):
            clock.end(_kernel_name(ev))

    event.register("numba:compile", _Listener())
    _clock = clock
    return clock


def _kernel_name(ev) -> str:
    dispatcher = (ev.data or {}).get("dispatcher")
    py_func = getattr(dispatcher, "py_func", None)
    return f"{py_func.__module__}.{py_func.__qualname__}" if py_func is not None else "?"


def thread_seconds() -> float:
    """Compile seconds of the calling thread so far (0 when the clock is not installed)."""
    return 0.0 if _clock is None else _clock.thread_seconds()


def totals() -> dict:
    """Seconds of compilation in this process and per kernel (empty when not installed)."""
    if _clock is None:
        return {"seconds": 0.0, "kernels": {}}
    return {"seconds": _clock.total_seconds, "kernels": dict(_clock.kernels)}
