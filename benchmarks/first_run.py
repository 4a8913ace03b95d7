"""Benchmark of a newcomer's first contact: the README's demo command in a fresh clone.

    PYTHONPATH=. python benchmarks/first_run.py [--repeats 3] [--out benchmarks/results/first_run.json]

What is timed is what a new user waits for, with nothing cached:

1. ``git clone`` of this checkout's HEAD into a temporary folder, then the README's
   install (``python3 -m venv .venv && .venv/bin/pip install -q -e .``; pip's own
   download cache is the machine's, as on a machine that installed Python packages
   before), timed once;
2. ``.venv/bin/fringecal run`` in the clone, ``--repeats`` times *cold*: before each
   repeat every ``__pycache__`` folder of the clone is removed (byte code and numba's
   kernel cache, as in a fresh clone), Prefect gets a new empty home
   (``PREFECT_HOME``) and the run a new run directory;
3. the same command ``--repeats`` times *warm*, each into a new run directory, with
   kernels and byte code cached and the last cold repeat's Prefect home (its database
   already migrated), as a user's second and later runs.

Each repeat records its wall time, the flow's own total, the seconds numba spent
compiling kernels (``summary.json``: ``compile_seconds``), the bundle adjustment's
reported time, and the load average before and after. The JSON gives the medians (cold
and warm), the machine (cores, Python) and the commit measured.

``--smoke``: the same clone, cache clearing and command, but without the install (the
clone runs on this interpreter), with ``--until simulate-prepare`` on the tests' small
rig (no kernel needed, so no warm-up helper either), one cold repeat only and this
environment's Prefect home (its database set up once): the machinery runs in seconds,
the figures mean nothing.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import add_options, conditions, finish  # noqa: E402


def _sh(cmd: list[str], cwd: Path, env: dict | None = None, ok=(0,)) -> float:
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True)
    if proc.returncode not in ok:
        raise SystemExit(f"{' '.join(cmd)} failed ({proc.returncode}):\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}")
    return time.perf_counter() - t0


def _clear_caches(clone: Path) -> int:
    """Remove every __pycache__ folder of the clone (not of its venv); return how many."""
    n = 0
    for folder in list(clone.rglob("__pycache__")):
        if ".venv" not in folder.relative_to(clone).parts:
            shutil.rmtree(folder)
            n += 1
    return n


def _run(clone: Path, run_dir: str, prefect_home: Path | None, smoke: bool = False) -> dict:
    env = {**os.environ, **({"PREFECT_HOME": str(prefect_home)} if prefect_home is not None else {})}
    env = {k: v for k, v in env.items() if k not in ("PREFECT_API_URL", "PREFECT_PROFILE", "NUMBA_CACHE_DIR",
                                                     "PYTHONPATH")}
    command = [str(clone / ".venv" / "bin" / "fringecal"), "run", "--out", run_dir]
    if smoke:  # the clone's code on this interpreter, the small rig up to its first step
        from fringecal.simulate.small_thesis import write_small_thesis_config

        env["PYTHONPATH"] = str(clone)
        config = write_small_thesis_config(Path(tempfile.mkdtemp(dir=clone.parent)))
        command = [sys.executable, "-m", "fringecal.flows.cli", "run", "-c", str(config), "--out", run_dir,
                   "--until", "simulate-prepare"]
    load0 = os.getloadavg()[0]
    # 3: the run finished and its verdict is NOT ACCEPTED (a changed demo may be)
    wall = _sh(command, clone, env, ok=(0, 3))
    summary = json.loads((clone / run_dir / "summary.json").read_text())
    bundle = summary.get("bundle_seconds")  # absent from a run stopped early (--smoke)
    bundle_file = clone / run_dir / "bundle_summary.json"
    bootstrap = json.loads(bundle_file.read_text()).get("bootstrap_seconds") if bundle_file.is_file() else None
    verification = (summary.get("verification") or {}).get("max_abs_error_mm")
    return {"wall_s": round(wall, 1), "flow_s": round(summary["total_seconds"], 1),
            "compile_s": round(sum((summary.get("compile_seconds") or {}).values()), 1),
            "compile_by_step_s": {k: round(v, 1) for k, v in (summary.get("compile_seconds") or {}).items()},
            "bundle_s": None if bundle is None else round(bundle, 2),
            "bootstrap_s": None if bootstrap is None else round(bootstrap, 2),
            "bundle_compile_s": round(summary.get("bundle_compile_seconds", 0.0), 2),
            "ball_bar_max_error_um": None if verification is None else round(1000 * verification, 1),
            "verdict": (summary.get("verdict") or {}).get("word"),
            "threads": summary.get("threads"),
            "load_before": round(load0, 2), "load_after": round(os.getloadavg()[0], 2)}


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=3)
    args = add_options(ap).parse_args(argv)
    if args.smoke:
        args.repeats = 1
    head = conditions("first_run", argv, args.smoke)
    with tempfile.TemporaryDirectory(prefix="fringecal-first-run-") as tmp:
        tmp = Path(tmp)
        clone = tmp / "fringecal"
        _sh(["git", "clone", "--quiet", str(ROOT), str(clone)], tmp)
        install = None
        if not args.smoke:
            install = _sh(["sh", "-c", "python3 -m venv .venv && .venv/bin/pip install -q -e ."], clone)
        cold = []
        for i in range(args.repeats):
            cleared = _clear_caches(clone)
            home = None if args.smoke else tmp / f"prefect-cold-{i}"  # smoke: this environment's Prefect home
            cold.append({**_run(clone, f"runs/cold-{i}", home, args.smoke),
                         "pycache_folders_cleared": cleared})
            print(json.dumps({"cold": cold[-1]}), file=sys.stderr)
        warm = []
        for i in range(0 if args.smoke else args.repeats):
            warm.append(_run(clone, f"runs/warm-{i}", tmp / f"prefect-cold-{args.repeats - 1}", args.smoke))
            print(json.dumps({"warm": warm[-1]}), file=sys.stderr)
    result = {
        **head,
        "timed_command": "fringecal run (README's demo) in a fresh clone" if not args.smoke else
                         "fringecal run -c small --until simulate-prepare in a fresh clone (smoke: this interpreter)",
        "install_s": None if install is None else round(install, 1),
        "cold_median_wall_s": statistics.median(r["wall_s"] for r in cold),
        "cold_median_compile_s": statistics.median(r["compile_s"] for r in cold),
        "warm_median_wall_s": statistics.median(r["wall_s"] for r in warm) if warm else None,
        "cold": cold, "warm": warm,
    }
    return finish(result, args.out)


if __name__ == "__main__":
    main()
