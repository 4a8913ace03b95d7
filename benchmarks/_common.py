"""What every benchmark script shares: the record of the conditions it measured under, the
``--smoke`` and ``--out`` options, and writing its JSON.

A speed figure means little without the machine's load while it was taken, the commit
it measured and whether numba's kernels were already compiled, so every script's JSON
carries ``conditions`` (:func:`conditions`): date, commit (and whether the working tree
differed from it), cores, Python, the load average at the start and the end, and the
cache state (``numba_cache``: ``warm`` when the compiled decoder is in numba's cache,
as after any earlier run; ``cold`` on a machine or checkout that never ran fringecal).

``--smoke`` runs a script at a tiny size in seconds: the figures are meaningless, but
every code path runs, so an API change that breaks a benchmark fails the tests
(``tests/test_benchmarks.py`` runs every script this way, in the test process).
Scripts are imported by that test with this folder on ``sys.path``.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import platform
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

__all__ = ["ROOT", "add_options", "conditions", "finish", "commit"]


def add_options(ap: argparse.ArgumentParser, out_help: str = "also write the JSON here") -> argparse.ArgumentParser:
    """Add ``--smoke`` and ``--out`` to a script's parser."""
    ap.add_argument("--smoke", action="store_true",
                    help="a tiny size that runs in seconds (tests/test_benchmarks.py): checks, not figures")
    ap.add_argument("--out", type=Path, help=out_help)
    return ap


def commit() -> str:
    """Short hash of HEAD, with a note when the working tree's tracked files differ."""
    def git(*args):
        try:
            return subprocess.run(["git", *args], cwd=ROOT, capture_output=True, text=True, timeout=30).stdout.strip()
        except (OSError, subprocess.SubprocessError):
            return ""
    head = git("rev-parse", "--short", "HEAD") or "unknown"
    dirty = bool(git("status", "--porcelain", "--untracked-files=no"))
    return head + (" (working tree differs)" if dirty else "")


def _numba_cache() -> str:
    from fringecal.run.warmup import cache_is_cold

    return "cold" if cache_is_cold() else "warm"


def conditions(benchmark: str, argv: list[str] | None, smoke: bool = False) -> dict:
    """The conditions at the start of a benchmark (see the module notes)."""
    return {"benchmark": benchmark,
            "command": f"PYTHONPATH=. python benchmarks/{benchmark}.py " + " ".join(sys.argv[1:] if argv is None else argv),
            "smoke": bool(smoke),
            "conditions": {"date": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
                           "commit": commit(), "cores": len(os.sched_getaffinity(0)),
                           "python": platform.python_version(), "platform": platform.platform(),
                           "load_average_start": [round(v, 2) for v in os.getloadavg()],
                           "numba_cache": _numba_cache()}}


def finish(doc: dict, out: Path | None, stream=None) -> dict:
    """Add the end's load average to ``doc``, print it as JSON (``stream``, default
    stdout) and write it to ``out`` if given; return it."""
    doc.setdefault("conditions", {})["load_average_end"] = [round(v, 2) for v in os.getloadavg()]
    text = json.dumps(_finite(doc), indent=1, default=_plain, allow_nan=False)
    if out is not None:
        Path(out).parent.mkdir(parents=True, exist_ok=True)
        Path(out).write_text(text + "\n")
    print(text, file=stream or sys.stdout, flush=True)
    return doc


def _finite(value):
    """``value`` with every NaN or infinite float replaced by None (strict JSON)."""
    if isinstance(value, float):
        return value if value == value and abs(value) != float("inf") else None
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_finite(v) for v in value]
    try:
        import numpy as np

        if isinstance(value, np.floating):
            return _finite(float(value))
        if isinstance(value, np.ndarray):
            return _finite(value.tolist())
    except ImportError:  # pragma: no cover
        pass
    return value


def _plain(value):
    try:
        import numpy as np

        if isinstance(value, np.generic):
            return value.item()
        if isinstance(value, np.ndarray):
            return value.tolist()
    except ImportError:  # pragma: no cover
        pass
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"not JSON: {type(value).__name__}")
