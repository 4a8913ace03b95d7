"""The first-run warm-up compiles the later kernels with the signatures the pipeline uses.

In a fresh checkout the test session's own start is such a first run: the controller
runs the warm-up on the cold cache before any test worker starts, and checks it at once
(``pytest_sessionstart`` in tests/conftest.py, with :func:`check`), before any test could compile a kernel
into the same cache. The test reads that check. When the session started warm, the
test repeats the whole sequence in a cache folder of its own (about 27 s of one core)."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow  # whole runs: the fast tier (-m "not slow") leaves this module out

#: run as ``python -c CHECK FOLDER``: build and evaluate a small bundle problem as the pipeline
#: does (control points read back from CSV) and print the seconds numba spent compiling
CHECK = """
import sys

import pandas as pd

from fringecal import compile_clock
from fringecal.run import warmup as kernel_warmup

compile_clock.install()
assert not kernel_warmup.cache_is_cold()
from fringecal.calibration.model import POSE_COLUMNS, BundleProblem, Evaluator
from fringecal.simulate.control_points import simulate_control_points, thesis_truth

rig, artefact, poses = thesis_truth()
sim = simulate_control_points(rig, artefact, poses.iloc[3:5], spacing_px=150, rng=1)
path = sys.argv[1] + "/cp.csv"
sim.control_points.to_csv(path, index=False)  # the pipeline reads its control points from CSV
cp = pd.read_csv(path, dtype={"measurement": str, "scanner": str, "sphere_id": str})
ev = Evaluator(BundleProblem.from_tables(rig, artefact, cp, poses.iloc[3:5]))
x = ev.layout.pack(rig.params, poses.iloc[3:5][list(POSE_COLUMNS)].to_numpy(float))
ev.evaluate(x, True)
ev.jacobian_rows(x)
print(compile_clock.totals()["seconds"])
"""
#: where the session's start records its check (tests/conftest.py)
SESSION_CHECK = "FRINGECAL_TEST_WARMUP_CHECK"


def warm_up_and_check(env: dict, folder: Path) -> dict:
    """Run the warm-up as a first run does, then the check: its exit status, the compile
    seconds it printed and the end of its error output."""
    warm = subprocess.run([sys.executable, "-m", "fringecal.run.warmup"], env=env, capture_output=True, text=True)
    if warm.returncode != 0:
        return {"step": "warm-up", "returncode": warm.returncode, "stderr": warm.stderr[-2000:]}
    return check(env, folder)


def check(env: dict, folder: Path) -> dict:
    res = subprocess.run([sys.executable, "-c", CHECK, str(folder)], env=env, capture_output=True, text=True)
    lines = res.stdout.strip().splitlines()
    return {"step": "check", "returncode": res.returncode, "stderr": res.stderr[-3000:],
            "compile_seconds": float(lines[-1]) if res.returncode == 0 and lines else None}


def test_warm_up_leaves_nothing_for_the_bundle_to_compile(tmp_path):
    recorded = os.environ.get(SESSION_CHECK)
    if recorded:
        result = json.loads(recorded)
    else:
        env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "numba")}
        cold = subprocess.run([sys.executable, "-c", "from fringecal.run import warmup as k; print(k.cache_is_cold())"],
                              env=env, capture_output=True, text=True)
        assert cold.stdout.strip() == "True", cold.stderr[-2000:]
        result = warm_up_and_check(env, tmp_path)
    assert result["returncode"] == 0, (result["step"], result["stderr"])
    assert result["compile_seconds"] == 0.0  # every kernel came from the cache
