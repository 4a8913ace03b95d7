"""The bundle-adjustment problems of ``benchmarks/bundle.py`` and ``benchmarks/ceres.py``.

Each is simulated control points (``fringecal.simulate.control_points``: a truth rig, the
CMM artefact set 2, phase noise for a 45 um epsilon-1 RMS, a 75 degree rim limit) and the
DLT start values computed from them, as the thesis obtained its start (section 6.3):

=========  ====================================================================  ==========
case       rig and poses                                                         points
=========  ====================================================================  ==========
thesis     table 6-8's two scanners, the 12 poses of table 6-1, every 10 px       13,564
ring4      four copies of the thesis scanners on a ring (``ring_truth(4)``; two   134,237
           projectors at phi 84.6 and 95.4 deg, near gimbal lock), 50 random
           poses (``random_poses(50, rng=1)``), every 10 px
ring6      the six-scanner ring of ``configs/run_ring6.yaml`` (``configs/ring6``),   47,511
           the 12 poses of table 6-1, every 10 px
large      eight copies on a ring, 50 random poses, every 5 px                    ~1.09 M
=========  ====================================================================  ==========

``smoke=True`` keeps the rig and thins everything else (every 60 px, at most 6 poses)
so that a case builds and adjusts in about a second.
"""

from __future__ import annotations

import time

CASES = ("thesis", "ring4", "ring6", "large")


def bundle_problem(case: str, smoke: bool = False):
    """(problem from the DLT start, the same problem at the truth, seconds to simulate)."""
    from fringecal.calibration.model import BundleProblem
    from fringecal.config import configs_dir
    from fringecal.rig import load_rig
    from fringecal.simulate.control_points import (
        dlt_start,
        random_poses,
        ring_truth,
        simulate_control_points,
        thesis_truth,
    )

    t0 = time.perf_counter()
    spacing = {"thesis": 10, "ring4": 10, "ring6": 10, "large": 5}[case] if not smoke else 60
    rig, art, poses = thesis_truth()
    if case == "ring4":
        rig, _ = ring_truth(4)
        poses = random_poses(50, rng=1)
    elif case == "ring6":
        rig = load_rig(configs_dir() / "ring6" / "sensors.csv")
    elif case == "large":
        rig, _ = ring_truth(8)
        poses = random_poses(50, rng=1)
    elif case != "thesis":
        raise ValueError(f"unknown case {case!r}; the cases are {', '.join(CASES)}")
    if smoke:
        poses = poses.iloc[:6]
    sim = simulate_control_points(rig, art, poses, rng=2, spacing_px=spacing, max_incidence_deg=75)
    start_rig, start_poses = dlt_start(sim, rng=2)
    problem = BundleProblem.from_tables(start_rig, art, sim.control_points, start_poses)
    truth = problem.with_start(rig, poses.set_index("measurement").loc[list(problem.measurements)].to_numpy(float)[:, -6:])
    return problem, truth, time.perf_counter() - t0
