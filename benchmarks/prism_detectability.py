"""How large must a thin-prism lens term be before the data can tell it from noise?

For each corner displacement of a thin-prism term (OpenCV's s1 and s3, the simulator's
``thin_prism_corner_px``, a random direction per sensor), simulated control points of the
thesis rig are adjusted with the 14-parameter model and with the thin-prism model, and
the script records:

* ``z_max``: the residual-pattern statistic of the 14-parameter fit
  (:mod:`fringecal.calibration.adequacy`, flagged above 5);
* ``term_over_u``: each sensor's true term ``hypot(s1, s3)`` over the larger stated u of
  its fitted s1, s3 (what a Wald test of the term could see at best; below about 3 no
  statistic can flag it without also flagging noise);
* ``error_over_u``: the fitted terms' errors over their stated u (does the richer model
  recover the term within its u?).

Prints one JSON object::

    PYTHONPATH=. python benchmarks/prism_detectability.py \\
        --out benchmarks/results/prism_detectability.json

Simulation profile: ideal otherwise (thesis rig, 12 poses, control points every 20 px at
2048 px with the thesis's epsilon-1 noise, ``simulate_control_points``), as in
``tests/test_sensor_models.py``. ``--smoke``: the 3 px term on control points every 60 px.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from _common import add_options, conditions, finish  # noqa: E402

CORNERS_PX = (0.2, 0.5, 1.0, 2.0, 3.0)


def prism_world(corner_px: float, spacing_px: int):
    """The thesis rig's control points with a thin-prism term of ``corner_px`` at every
    sensor's corner, and the true terms (n_sensors, 4) in OpenCV's order."""
    from fringecal.calibration.model import BundleProblem
    from fringecal.simulate.control_points import simulate_control_points, thesis_truth
    from fringecal.simulate.unmodelled import thin_prism

    rig, art, poses = thesis_truth()
    angles = np.random.default_rng(0).uniform(0, 2 * np.pi, len(rig.sensors))
    truth = np.zeros((len(rig.sensors), 4))
    truth[:, [0, 2]] = [[*thin_prism(s.format, corner_px, a)] for s, a in zip(rig.sensors, angles)]
    sim = simulate_control_points(rig.with_params(rig.params, prism=truth), art, poses, spacing_px=spacing_px, rng=1)
    return BundleProblem.from_tables(rig, art, sim.control_points, poses), truth


def measure(corner_px: float, spacing_px: int) -> dict:
    from fringecal.calibration.adequacy import residual_pattern
    from fringecal.calibration.bundle import BundleOptions
    from fringecal.calibration.models import fit_model

    options = BundleOptions(bootstrap_draws=0, start="given")
    problem, truth = prism_world(corner_px, spacing_px)
    first = fit_model(problem, options, "brown14")
    richer = fit_model(problem.with_start(first.rig, first.poses), options, "thin_prism")
    u = richer.rig.prism_uncertainty[:, [0, 2]]
    return {"corner_px": corner_px, "n_control_points": int(problem.n_points),
            "z_max": float(residual_pattern(first.problem, first.residuals).z_max),
            "term_over_u": (np.hypot(truth[:, 0], truth[:, 2]) / u.max(axis=1)).tolist(),
            "error_over_u": ((richer.rig.prism[:, [0, 2]] - truth[:, [0, 2]]) / u).ravel().tolist()}


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    args = add_options(ap).parse_args(argv)
    doc = conditions("prism_detectability", argv, args.smoke)
    t0 = time.perf_counter()
    corners, spacing = ((3.0,), 60) if args.smoke else (CORNERS_PX, 20)
    rows = [measure(c, spacing) for c in corners]
    doc.update({"what": "thin-prism terms of growing size on the thesis rig's simulated control points (ideal "
                        "profile otherwise): the 14-parameter fit's residual-pattern Z (flag above 5), each "
                        "sensor's true term over its stated u, and the thin-prism fit's errors over their u",
                "spacing_px": spacing, "sizes": rows, "wall_seconds": time.perf_counter() - t0})
    return finish(doc, args.out)


if __name__ == "__main__":
    main()
