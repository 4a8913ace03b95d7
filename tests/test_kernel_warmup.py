"""The first-run warm-up compiles the later kernels with the signatures the pipeline uses."""

import os
import subprocess
import sys

import pytest

pytestmark = pytest.mark.slow  # whole runs: the fast tier (-m "not slow") leaves this module out

CHECK = """
import numpy as np, pandas as pd, sys
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


def test_warm_up_leaves_nothing_for_the_bundle_to_compile(tmp_path):
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "numba")}
    cold = subprocess.run([sys.executable, "-c", "from fringecal.run import warmup as k; print(k.cache_is_cold())"],
                          env=env, capture_output=True, text=True)
    assert cold.stdout.strip() == "True", cold.stderr[-2000:]
    warm = subprocess.run([sys.executable, "-m", "fringecal.run.warmup"], env=env, capture_output=True, text=True)
    assert warm.returncode == 0, warm.stderr[-2000:]
    check = subprocess.run([sys.executable, "-c", CHECK, str(tmp_path)], env=env, capture_output=True, text=True)
    assert check.returncode == 0, check.stderr[-3000:]
    assert float(check.stdout.strip().splitlines()[-1]) == 0.0  # every kernel came from the cache
