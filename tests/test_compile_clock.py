"""The compile clock counts numba's compilations (cache misses) per thread."""

import threading

from numba import njit

from fringecal import compile_clock


def _fresh_kernel():
    @njit(cache=False)
    def square_sum(x):
        s = 0.0
        for v in x:
            s += v * v
        return s

    return square_sum


def test_compilation_is_counted_once_in_the_thread_that_compiles():
    import numpy as np

    clock = compile_clock.install()
    kernel = _fresh_kernel()
    before, total_before = compile_clock.thread_seconds(), compile_clock.totals()["seconds"]
    assert kernel(np.arange(4.0)) == 14.0
    compiled = compile_clock.thread_seconds() - before
    assert compiled > 0.01 and compile_clock.totals()["seconds"] - total_before >= compiled
    assert any(name.endswith("square_sum") for name in clock.kernels)
    again = compile_clock.thread_seconds()
    kernel(np.arange(5.0))  # same signature: no compilation
    assert compile_clock.thread_seconds() == again
    kernel(np.arange(5, dtype=np.int32))  # a new signature compiles again
    assert compile_clock.thread_seconds() > again

    other = _fresh_kernel()
    mine = compile_clock.thread_seconds()
    t = threading.Thread(target=other, args=(np.arange(3.0),))
    t.start()
    t.join()
    assert compile_clock.thread_seconds() == mine  # another thread's compilation is its own


def test_observer_sees_outermost_compilations_only():
    import numpy as np

    clock = compile_clock.install()
    events = []
    clock.observer = lambda event, name, seconds: events.append((event, name.rsplit(".", 1)[-1]))

    @njit(cache=False)
    def inner(v):
        return v + 1.0

    @njit(cache=False)
    def outer(v):
        return inner(v) * 2.0

    try:
        assert outer(np.float64(1.0)) == 4.0
    finally:
        clock.observer = None
    assert events == [("start", "outer"), ("end", "outer")]


def test_busy_seconds_tick_while_a_kernel_compiles():
    """The wall time of compilation is readable while numba still compiles (what the
    progress line shows each second), and counts overlapping threads once."""
    import time

    clock = compile_clock.CompileClock()
    assert not clock.compiling and clock.busy_seconds() == 0.0
    clock.start("a")
    time.sleep(0.2)
    assert clock.compiling and clock.busy_seconds() >= 0.2  # before the compilation ends
    other = threading.Thread(target=lambda: (clock.start("b"), time.sleep(0.2), clock.end("b")))
    other.start()
    other.join()
    clock.end("a")
    busy = clock.busy_seconds()
    assert not clock.compiling and 0.4 <= busy < 0.55  # the two overlapping spells once, not 0.2 + 0.4 + 0.2
    assert clock.total_seconds >= 0.6  # the compile time of both threads
    time.sleep(0.05)
    assert clock.busy_seconds() == busy  # idle: no ticking
