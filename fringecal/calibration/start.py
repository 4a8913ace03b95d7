"""Start values from the control points themselves (thesis sections 6.2.1, 6.3).

Object-space residuals of spheres have a limited basin: a pose wrong by 0.02 rad moves a
sphere a metre from the artefact's origin by 20 mm, close to its 25 mm radius, and a
sensor wrong by 0.02 rad relative to its partner reconstructs the spheres as ellipsoids;
the adjustment can then settle in a separate minimum (F several mm instead of the noise
floor). The thesis avoided this by building its start from the data: poses from sphere
centres, every sensor from the DLT of the registered centres. :func:`reinitialise` does
the same from the control points, trusting only the reference camera:

1. per (measurement, scanner, sphere) group, the centroid of the control points' camera
   and projector image coordinates: the image of the sphere's centre, to a fraction of
   the sphere's image radius (the visible cap is not symmetric about it);
2. per measurement, the pose T_world_artefact by resection (PnP) of the CMM centres on
   the reference camera's centroids (Gauss-Newton from the given pose; three spheres or
   more);
3. every other sensor by the DLT (:mod:`.dlt`) of the CMM centres moved by those poses
   against its centroids; the reference camera keeps its start values (its external
   parameters fix the world frame);
4. measurements the reference camera did not see: resection on another camera, now
   initialised.

:func:`fringecal.calibration.bundle.bundle_adjust` adjusts from the given start and from
this one (``BundleOptions.start = "best"``) and keeps the lower minimum of F.
"""

from __future__ import annotations

import numpy as np
import scipy.optimize

from ..frames import Frame
from ..rotation import angles_from_matrix
from ..sensor import Sensor
from .dlt import DLTError, DLTEstimate
from .model import BundleProblem

__all__ = ["sphere_image_centroids", "resect_pose", "reinitialise"]


def sphere_image_centroids(problem: BundleProblem, min_points: int = 10) -> dict:
    """(scanner, measurement) -> (sphere indices (k,), camera mm (k, 2), projector mm (k, 2))."""
    n_sph = len(problem.artefact)
    n_m = len(problem.measurements)
    key = (problem.scanner_idx * n_m + problem.meas_idx) * n_sph + problem.sphere_idx
    uniq, inv, counts = np.unique(key, return_inverse=True, return_counts=True)
    cam = np.zeros((len(uniq), 2))
    prj = np.zeros((len(uniq), 2))
    np.add.at(cam, inv, problem.cam_mm)
    np.add.at(prj, inv, problem.prj_mm)
    cam /= counts[:, None]
    prj /= counts[:, None]
    out: dict = {}
    for u, c, p, n in zip(uniq, cam, prj, counts):
        if n < min_points:
            continue
        sm = int(u // n_sph)
        out.setdefault((sm // n_m, sm % n_m), []).append((int(u % n_sph), c, p))
    return {k: (np.array([a for a, _, _ in v]), np.array([b for _, b, _ in v]), np.array([c for _, _, c in v]))
            for k, v in out.items()}


def resect_pose(sensor: Sensor, cmm_centres: np.ndarray, image_mm: np.ndarray, start) -> np.ndarray | None:
    """Pose (6,) T_world_artefact that projects ``cmm_centres`` (k, 3) onto ``image_mm``
    (k, 2) in ``sensor``, from ``start`` (6,); None if it fails or k < 3."""
    if len(cmm_centres) < 3:
        return None
    start = np.asarray(start, float)

    def fun(p):
        xy = sensor.project(Frame.from_params(p).to_world(cmm_centres))
        r = (xy - image_mm).ravel()
        return np.where(np.isfinite(r), r, 1e3)

    sol = scipy.optimize.least_squares(fun, start, x_scale=np.r_[np.full(3, 100.0), np.full(3, 0.05)],
                                       method="lm" if 2 * len(cmm_centres) >= 6 else "trf")
    if not sol.success or not np.all(np.isfinite(sol.x)):
        return None
    f = Frame.from_params(sol.x)
    return np.concatenate([f.t, angles_from_matrix(f.R, near=start[3:])])


def reinitialise(problem: BundleProblem) -> tuple[BundleProblem, dict]:
    """The problem with start values computed from its control points (see module
    docstring); the report names the sensors and poses that were re-initialised."""
    rig = problem.rig
    names = [s.name for s in rig.scanners]
    ref = names.index(rig.reference)
    cents = sphere_image_centroids(problem)
    cmm = problem.artefact.centres
    poses = problem.poses.copy()
    known = set()
    ref_cam = rig.scanners[ref].camera
    for m in range(len(problem.measurements)):
        if (ref, m) in cents:
            sph, cam, _ = cents[(ref, m)]
            p = resect_pose(ref_cam, cmm[sph], cam, poses[m])
            if p is not None:
                poses[m] = p
                known.add(m)
    params = rig.params.copy()
    done = {2 * ref}
    report = {"poses": sorted(problem.measurements[m] for m in known), "sensors": [], "failed": {}}
    for _ in range(len(rig.scanners) + 1):
        progress = False
        for s, sc in enumerate(rig.scanners):
            groups = [(m, cents[(s, m)]) for m in sorted(known) if (s, m) in cents]
            if not groups:
                continue
            world = np.concatenate([Frame.from_params(poses[m]).to_world(cmm[g[0]]) for m, g in groups])
            for role, k in ((1, 2 * s), (2, 2 * s + 1)):
                if k in done:
                    continue
                image = np.concatenate([g[role] for _, g in groups])
                sensor = rig.sensors[k]
                try:
                    est = DLTEstimate.from_estimate(world, image, near_angles=sensor.angles)
                except DLTError as err:
                    report["failed"][sensor.name] = str(err)
                    continue
                new = est.params14
                new[~rig.free[k]] = params[k][~rig.free[k]]
                params[k] = new
                done.add(k)
                report["sensors"].append(sensor.name)
                progress = True
        new_rig = rig.with_params(params)
        for m in range(len(problem.measurements)):
            if m in known:
                continue
            for s, sc in enumerate(new_rig.scanners):
                if 2 * s in done and (s, m) in cents:
                    sph, cam, _ = cents[(s, m)]
                    p = resect_pose(sc.camera, cmm[sph], cam, poses[m])
                    if p is not None:
                        poses[m] = p
                        known.add(m)
                        report["poses"].append(problem.measurements[m])
                        progress = True
                        break
        if not progress:
            break
    poses = np.where(problem.pose_free, poses, problem.poses)
    return problem.with_start(rig.with_params(params), poses), report
