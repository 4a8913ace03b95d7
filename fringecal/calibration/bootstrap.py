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
replicas, and the bias they give, do not depend on the measurements' names or order.
The adjustment of each replica starts from the calibration. The replicas' sensor
parameters give, for any derived quantity ``q``, the bias ``mean(q*) - q`` (to be
subtracted) and its spread ``std(q*)``.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from fringecal.calibration.bundle import BundleResult, bundle_adjust
from fringecal.calibration.keyed import keyed_signs, row_keys
from fringecal.rotation import rotation_matrix
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


def bootstrap_calibrations(result: BundleResult, draws: int, seed: int = 0) -> np.ndarray:
    """Sensor parameters (draws, n_sensors, 14) of ``draws`` wild-bootstrap re-adjustments.

    Control points whose noise-free prediction does not exist (the ray misses the
    sphere) keep their observation unchanged. Every replica is adjusted with the
    result's own options, from the result's parameters.
    """
    if draws <= 0:
        return np.empty((0,) + result.rig.params.shape)
    problem = result.problem
    predicted = predicted_projector_mm(result)
    ok = np.isfinite(predicted).all(axis=1)
    residual = np.where(ok[:, None], problem.prj_mm - predicted, 0.0)
    base = np.where(ok[:, None], predicted, problem.prj_mm)
    start = problem.with_start(result.rig, result.poses)
    options = result.options.model_copy(update={"start": "given"})
    keys = row_keys(problem.cam_mm, problem.prj_mm)
    out = np.empty((draws,) + result.rig.params.shape)
    for i in range(draws):
        signs = keyed_signs(keys, seed, i)[:, None]
        out[i] = bundle_adjust(replace(start, prj_mm=base + signs * residual), options).rig.params
    return out
