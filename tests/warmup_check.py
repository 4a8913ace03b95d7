"""Run as ``python tests/warmup_check.py FOLDER``: build and evaluate a small bundle
problem as the pipeline does (control points read back from CSV) and print the seconds
numba spent compiling; 0.0 means every kernel came from the cache
(tests/test_kernel_warmup.py)."""

import sys

import pandas as pd

from fringecal import compile_clock
from fringecal.run import warmup as kernel_warmup

compile_clock.install()
assert not kernel_warmup.cache_is_cold()
from fringecal.calibration.model import POSE_COLUMNS, BundleProblem, Evaluator  # noqa: E402
from fringecal.simulate.control_points import simulate_control_points, thesis_truth  # noqa: E402

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
