"""Wild bootstrap of the bundle adjustment: the calibration's bias and spread beyond
linear propagation.

The adjustment's residuals are non-linear in the phase noise: a control point's noise
moves its triangulated point along the camera ray, and ``alpha2 = |S - S_t| - r``
bends that into the sphere's normal. With the noise of coarse cameras (some 0.25 mm
per point at 320 px) and a few dozen points per sphere, the estimate is biased by
about one standard uncertainty where a length's two spheres are seen by different
scanners (simulated ball-bar position bb04 of the coverage benchmark: -46 um on
average over ten seeds, linear u 47 um; with exact phases the bias vanishes). Linear
propagation of the covariance cannot see that; re-adjusting bootstrap replicas can.

Each replica keeps the camera pixels and replaces the projector observations by those
the calibrated model predicts (the pixel's ray meets its sphere, the hit is projected
into the projector) plus the control point's own residual times a random sign
(Rademacher weights: the wild bootstrap, which keeps every point's noise level). A
point's sign in each replica is keyed by its own camera and projector coordinates
(:mod:`fringecal.calibration.keyed`), not by its place in the problem, so that the
replicas, and the bias they give, do not depend on the measurements' names or order. The
replicas' sensor parameters give, for any derived quantity ``q``, the bias
``mean(q*) - q`` (to be subtracted) and its spread ``std(q*)``.

A replica differs from the calibrated problem only in its projector observations, so
its adjustment reuses everything else: the parameter layout, the groups and chunks of
control points the kernels work through, the rotation increments, and the solution as
the start. It is the adjustment's own minimisation (:func:`.bundle.minimise`: the same
solver, tolerances and robust loss), without what a replica does not need: the checks
of the start values and of the structure (the calibration passed them), the noise-floor
test, the uncertainty and the diagnoses. The signs are drawn before any replica runs, so
the replicas and their minima do not depend on how many run at once (``workers`` threads, each replica's kernels on one thread).
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np
import scipy.linalg

from fringecal.calibration.bundle import BundleResult, StartValueError, minimise
from fringecal.calibration.increments import RotationIncrements
from fringecal.calibration.keyed import keyed_signs, row_keys
from fringecal.calibration.model import Evaluator
from fringecal.rotation import rotation_matrix
from fringecal.threads import numba_threads
from fringecal.triangulation import sphere_hits

__all__ = ["predicted_projector_mm", "bootstrap_calibrations"]


def predicted_projector_mm(result: BundleResult) -> np.ndarray:
    """(n, 2) projector image-plane mm each control point would show without noise
    under the calibrated model, in problem order; NaN where the ray misses its sphere."""
    problem = result.problem
    poses = np.asarray(result.poses, float)
    R = rotation_matrix(poses[:, 3], poses[:, 4], poses[:, 5])
    centres, radii = problem.artefact.centres, problem.artefact.radii
    out = np.full_like(problem.prj_mm, np.nan)
    for k, scanner in enumerate(result.rig.scanners):
        sel = problem.scanner_idx == k
        m, s = problem.meas_idx[sel], problem.sphere_idx[sel]
        C = poses[m, :3] + np.einsum("nji,nj->ni", R[m], centres[s])  # S_t = R^T s + t
        origin, d = scanner.camera.rays(problem.cam_mm[sel])
        out[sel] = scanner.projector.project(sphere_hits(origin, d, C, radii[s]))
    return out


def bootstrap_calibrations(result: BundleResult, draws: int, seed: int = 0, workers: int = 1) -> np.ndarray:
    """Sensor parameters (draws, n_sensors, 14) of ``draws`` wild-bootstrap re-adjustments.

    Control points whose noise-free prediction does not exist (the ray misses the
    sphere) keep their observation unchanged. Every replica is adjusted with the
    result's own options, from the result's parameters, ``workers`` at a time.
    """
    if draws <= 0:
        return np.empty((0,) + result.rig.params.shape)
    problem = result.problem
    predicted = predicted_projector_mm(result)
    ok = np.isfinite(predicted).all(axis=1)
    residual = np.where(ok[:, None], problem.prj_mm - predicted, 0.0)
    base = np.where(ok[:, None], predicted, problem.prj_mm)
    keys = row_keys(problem.cam_mm, problem.prj_mm)
    flips = np.stack([keyed_signs(keys, seed, r) < 0 for r in range(draws)])
    evaluator = Evaluator(problem.with_start(result.rig, result.poses), result.layout, result.options.chunk_size)
    starts = _first_steps(result, evaluator, base + residual, base - residual, flips)
    sensors = result.rig.params

    def replica(r: int) -> np.ndarray:
        ev = evaluator.with_projector(np.where(flips[r][:, None], base - residual, base + residual))
        x, start = result.x, None
        if starts is not None:
            x, cost_at_solution = starts[0][r], starts[1][r]
            start = ev.evaluate(x, True)
            if not start.cost < cost_at_solution:  # the shared first step did not descend: start at the solution
                x, start = result.x, None
        if start is None:
            start = ev.evaluate(x, True)
        if not (start.ok.all() and np.isfinite(start.cost)):
            raise StartValueError(f"a bootstrap replica cannot form rays at {int(np.sum(~start.ok))} control "
                                  "points from the calibration")
        report, _, _ = minimise(ev, x, start, result.options, coarse=False, replica=True)
        return result.layout.sensor_rows(report.x, result.rig, result.poses)

    if workers <= 1:
        return np.stack([replica(r) for r in range(draws)])

    def on_one_thread(r: int) -> np.ndarray:  # each replica's kernels on one thread: the replicas run in parallel
        with numba_threads(1):
            return replica(r)

    with ThreadPoolExecutor(max_workers=workers) as pool:
        return np.stack(list(pool.map(on_one_thread, range(draws))))


def _first_steps(result: BundleResult, evaluator: Evaluator, plus: np.ndarray, minus: np.ndarray,
                 flips: np.ndarray):
    """Every replica's first Gauss-Newton step from the solution, from one pass over the
    control points and one factorisation; None with a robust loss or without the
    solution's normal equations.

    At the solution x^ a replica's gradient is the calibration's plus the change of each
    flipped control point's term, exact (:meth:`.model.Evaluator.replica_differences`);
    its normal matrix differs from the calibration's by a few parts in 10^4, so the
    calibration's N^ (factorised once, in the rotation increments' coordinates) gives
    the same first step as the replica's own N. Returns the start points (R, p) and each
    replica's F at x^ (the first step must lower it, else the replica starts at x^).
    """
    e = result.report.evaluation
    options = result.options
    if options.robust_loss not in ("none", "linear") or e is None or e.N1 is None:
        return None
    problem = evaluator.problem
    dcost, dgrad, ok = evaluator.replica_differences(result.x, plus, minus, flips)
    if not ok.all():
        return None
    rotations = RotationIncrements.of(result.layout)
    N, b = rotations.transform(result.x, e.normal(problem.gamma1, problem.gamma2), e.b[None, :] + dgrad)
    D = np.sqrt(np.diag(N))
    D[D == 0] = 1.0
    try:
        factor = scipy.linalg.cho_factor(N / np.outer(D, D), check_finite=False)
    except np.linalg.LinAlgError:
        return None
    steps = -scipy.linalg.cho_solve(factor, (b / D).T, check_finite=False).T / D
    if not np.all(np.isfinite(steps)):
        return None
    return np.stack([rotations.retract(result.x, d) for d in steps]), e.cost + dcost
