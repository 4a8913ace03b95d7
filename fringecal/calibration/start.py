"""Start values from the control points themselves (thesis sections 6.2.1, 6.3).

Object-space residuals of spheres have a limited basin: a pose wrong by 0.02 rad moves a
sphere a metre from the artefact's origin by 20 mm, close to its 25 mm radius, and a
sensor wrong by a few mrad relative to its partner reconstructs the spheres tens of
millimetres off in depth (4 mrad over a 900 mm baseline at 3 m: about 40 mm); the
adjustment can then settle in a separate minimum (F several mm instead of the noise
floor). The thesis avoided this by building its start from the data: poses from sphere
centres, every sensor from the DLT of the registered centres. :func:`reinitialise` does
the same from the control points, trusting only the reference camera:

1. per (measurement, scanner, sphere) image, the image of the sphere's centre in the
   camera and in the projector (:func:`sphere_centre_images`): the control points are
   triangulated with the given sensors, a sphere (free centre and radius) is fitted to
   the points on the *camera* rays and its centre projected into the camera, and
   likewise with the points on the *projector* rays for the projector. An error of the
   given sensors moves the triangulated cap mostly along the sensor's own rays, which
   does not move the centre's image: on the simulated three-scanner rig with start
   errors of 2-8 mm and 2-8 mrad the centre images are within 3-10 um (RMS) of the
   truth. The centroid of the control points' image coordinates (used before, and still
   where a fit fails) is 50 um off, because the lit and visible cap is not symmetric
   about the centre (it leans towards the projector): about 1 mrad, as large as the
   start errors it is meant to remove;
2. per measurement, the pose T_world_artefact by resection (PnP) of the CMM centres on
   the reference camera's centre images, started from the given pose and from the
   registration (SVD) of the CMM centres to the centres fitted in the reference
   scanner's own triangulation; the one that reprojects better is kept (three spheres or
   more);
3. every other sensor from the CMM centres moved by those poses against its centre
   images: by the DLT (:mod:`.dlt`; ``sensors="dlt"``, all nine undistorted parameters,
   distortion zero) or by resection of its six external parameters with its given
   internal parameters and distortion (``sensors="resection"``; better where the DLT is
   poor: few spheres, little depth). The reference camera keeps its start values (its
   external parameters fix the world frame);
4. measurements the reference camera did not see: resection on another camera, now
   initialised.

:func:`fringecal.calibration.bundle.bundle_adjust` adjusts from these starts when the
adjustment from the given one does not reach the noise floor (:mod:`.convergence`).
"""

from __future__ import annotations

import numpy as np
import scipy.optimize

from fringecal.calibration.dlt import DLTError, DLTEstimate
from fringecal.calibration.model import BundleProblem
from fringecal.frames import Frame
from fringecal.registration import kabsch
from fringecal.rotation import angles_from_matrix
from fringecal.sensor import Sensor, UndistortError
from fringecal.triangulation import closest_points

__all__ = ["reinitialise", "resect_pose", "resect_sensor", "sphere_centre_images", "sphere_image_centroids"]

#: a fitted sphere whose radius is outside this range times the CMM radius is not used
#: (the cap was too small or too distorted to fit); its image centroid is used instead
RADIUS_RANGE = (0.5, 2.0)


def _group_index(problem: BundleProblem):
    n_sph = len(problem.artefact)
    n_m = len(problem.measurements)
    key = (problem.scanner_idx * n_m + problem.meas_idx) * n_sph + problem.sphere_idx
    uniq, inv, counts = np.unique(key, return_inverse=True, return_counts=True)
    sm = uniq // n_sph
    return uniq, inv, counts, sm // n_m, sm % n_m, uniq % n_sph


def sphere_image_centroids(problem: BundleProblem, min_points: int = 10) -> dict:
    """(scanner, measurement) -> (sphere indices (k,), camera mm (k, 2), projector mm (k, 2)):
    the centroids of the control points' image coordinates per sphere image."""
    uniq, inv, counts, scan, meas, sph = _group_index(problem)
    cam = np.zeros((len(uniq), 2))
    prj = np.zeros((len(uniq), 2))
    np.add.at(cam, inv, problem.cam_mm)
    np.add.at(prj, inv, problem.prj_mm)
    cam /= counts[:, None]
    prj /= counts[:, None]
    out: dict = {}
    for k in np.flatnonzero(counts >= min_points):
        out.setdefault((int(scan[k]), int(meas[k])), []).append((int(sph[k]), cam[k], prj[k]))
    return {k: (np.array([a for a, _, _ in v]), np.array([b for _, b, _ in v]), np.array([c for _, _, c in v]))
            for k, v in out.items()}


def _fit_spheres(P, g, G, w):
    """Algebraic sphere (free centre and radius) per group of points P (n, 3); (centres (G, 3),
    radii (G,)), NaN where a group's system is singular."""
    cnt = np.bincount(g, w, G)
    mean = np.stack([np.bincount(g, w * P[:, k], G) for k in range(3)], 1) / np.maximum(cnt, 1)[:, None]
    Q = P - mean[g]
    q = np.sum(Q * Q, axis=1)
    A = np.concatenate([2 * Q, np.ones((len(Q), 1))], axis=1)
    AtA = np.zeros((G, 4, 4))
    Atq = np.zeros((G, 4))
    for a in range(4):
        Atq[:, a] = np.bincount(g, w * A[:, a] * q, G)
        for b in range(a, 4):
            AtA[:, a, b] = AtA[:, b, a] = np.bincount(g, w * A[:, a] * A[:, b], G)
    ok = cnt >= 4
    ok[ok] = np.linalg.cond(AtA[ok]) < 1e12
    sol = np.full((G, 4), np.nan)
    sol[ok] = np.linalg.solve(AtA[ok], Atq[ok][..., None])[..., 0]
    c = sol[:, :3]
    r = np.sqrt(np.maximum(sol[:, 3] + np.sum(c * c, axis=1), 0.0))
    return c + mean, r


def sphere_centre_images(problem: BundleProblem, min_points: int = 10) -> tuple[dict, dict]:
    """The image of every sphere's centre in the camera and the projector that saw it
    (module docstring, step 1), with the problem's start values.

    Returns ``(images, counts)``: ``images`` maps (scanner, measurement) to (sphere
    indices (k,), camera mm (k, 2), projector mm (k, 2), centres (k, 3) fitted to the
    scanner's own triangulation, NaN where no fit); ``counts`` says how many sphere
    images came from fits and how many from centroids.
    """
    uniq, inv, counts, scan, meas, sph = _group_index(problem)
    G = len(uniq)
    cent = sphere_image_centroids(problem, 1)
    cam = np.full((G, 2), np.nan)
    prj = np.full((G, 2), np.nan)
    world = np.full((G, 3), np.nan)
    for si, sc in enumerate(problem.rig.scanners):
        sel = problem.scanner_idx == si
        if not sel.any():
            continue
        try:
            o1, d1 = sc.camera.rays(problem.cam_mm[sel])
            o2, d2 = sc.projector.rays(problem.prj_mm[sel])
        except UndistortError:
            continue
        o1 = np.broadcast_to(o1, d1.shape)
        o2 = np.broadcast_to(o2, d2.shape)
        Xc, Xp = closest_points(o1, d1, o2, d2)
        g = inv[sel]
        finite = np.all(np.isfinite(Xc), 1) & np.all(np.isfinite(Xp), 1)
        w = finite.astype(float)
        Xc = np.where(finite[:, None], Xc, 0.0)
        Xp = np.where(finite[:, None], Xp, 0.0)
        cc, rc = _fit_spheres(Xc, g, G, w)
        cp, rp = _fit_spheres(Xp, g, G, w)
        cs, rs = _fit_spheres(0.5 * (Xc + Xp), g, G, w)
        mine = np.zeros(G, bool)
        mine[np.unique(g)] = True
        n_ok = np.bincount(g, w, G)
        r_cmm = problem.artefact.radii[sph]
        lo, hi = RADIUS_RANGE[0] * r_cmm, RADIUS_RANGE[1] * r_cmm
        good = mine & (n_ok >= min_points)
        for r in (rc, rp, rs):
            good &= np.isfinite(r) & (r >= lo) & (r <= hi)
        if not good.any():
            continue
        with np.errstate(invalid="ignore", divide="ignore"):
            ic = sc.camera.project(cc[good])
            ip = sc.projector.project(cp[good])
        fine = np.all(np.isfinite(ic), 1) & np.all(np.isfinite(ip), 1)
        idx = np.flatnonzero(good)[fine]
        cam[idx], prj[idx], world[idx] = ic[fine], ip[fine], cs[idx]
    out: dict = {}
    n_fit = n_centroid = 0
    for k in range(G):
        if counts[k] < min_points:
            continue
        s, m, j = int(scan[k]), int(meas[k]), int(sph[k])
        if np.isfinite(cam[k]).all():
            c, p = cam[k], prj[k]
            n_fit += 1
        else:
            sphs, cs_, ps_ = cent[(s, m)]
            pos = int(np.flatnonzero(sphs == j)[0])
            c, p = cs_[pos], ps_[pos]
            n_centroid += 1
        out.setdefault((s, m), []).append((j, c, p, world[k]))
    images = {k: (np.array([a[0] for a in v]), np.array([a[1] for a in v]), np.array([a[2] for a in v]),
                  np.array([a[3] for a in v])) for k, v in out.items()}
    return images, {"fitted": n_fit, "centroid": n_centroid}


def _reprojection_rms(sensor: Sensor, pose, cmm_centres, image_mm) -> float:
    with np.errstate(invalid="ignore", divide="ignore"):
        xy = sensor.project(Frame.from_params(pose).to_world(cmm_centres))
    r = np.sum((xy - image_mm) ** 2, axis=1)
    return float(np.sqrt(np.mean(r))) if np.all(np.isfinite(r)) else float("inf")


def resect_pose(sensor: Sensor, cmm_centres: np.ndarray, image_mm: np.ndarray, start) -> np.ndarray | None:
    """Pose (6,) T_world_artefact that projects ``cmm_centres`` (k, 3) onto ``image_mm``
    (k, 2) in ``sensor``, from ``start`` (6,); None if it fails or k < 3."""
    if len(cmm_centres) < 3:
        return None
    start = np.asarray(start, float)

    def fun(p):
        with np.errstate(invalid="ignore", divide="ignore"):
            xy = sensor.project(Frame.from_params(p).to_world(cmm_centres))
        r = (xy - image_mm).ravel()
        return np.where(np.isfinite(r), r, 1e3)

    sol = scipy.optimize.least_squares(fun, start, x_scale=np.r_[np.full(3, 100.0), np.full(3, 0.05)],
                                       method="lm" if 2 * len(cmm_centres) >= 6 else "trf")
    if not sol.success or not np.all(np.isfinite(sol.x)):
        return None
    f = Frame.from_params(sol.x)
    return np.concatenate([f.t, angles_from_matrix(f.R, near=start[3:])])


def resect_sensor(sensor: Sensor, points_world: np.ndarray, image_mm: np.ndarray, free=None,
                  starts=()) -> tuple[np.ndarray, float] | None:
    """The sensor's external parameters (among ``free`` (6,) bool, default all) that
    project ``points_world`` (k, 3) onto ``image_mm`` (k, 2), its internal parameters
    and distortion kept; from its own values and each of ``starts`` (6,) external
    parameter sets, the best reprojection kept. Returns (params (14,), reprojection RMS
    mm) or None (fewer than three points, or no solution)."""
    if len(points_world) < 3:
        return None
    p0 = np.array(sensor.params, float)
    free = np.ones(6, bool) if free is None else np.asarray(free, bool)[:6]
    if not free.any():
        return p0, _reprojection_rms(sensor, np.zeros(6), points_world, image_mm)

    def fun(z, base):
        p = base.copy()
        p[:6][free] = z
        with np.errstate(invalid="ignore", divide="ignore"):
            xy = sensor.with_params(p).project(points_world)
        r = (xy - image_mm).ravel()
        return np.where(np.isfinite(r), r, 1.0)

    best = None
    for ext in [p0[:6], *starts]:
        base = p0.copy()
        base[:6] = np.where(free, ext, p0[:6])
        scale = np.r_[np.full(3, 10.0), np.full(3, 0.003)][free]
        sol = scipy.optimize.least_squares(fun, base[:6][free], args=(base,), x_scale=scale,
                                           method="lm" if 2 * len(points_world) >= free.sum() else "trf")
        if not np.all(np.isfinite(sol.x)):
            continue
        p = base.copy()
        p[:6][free] = sol.x
        p[3:6] = angles_from_matrix(Frame(p[:3], p[3:6]).R, near=p0[3:6])
        rms = float(np.sqrt(np.mean(np.sum(fun(sol.x, base).reshape(-1, 2) ** 2, axis=1))))
        if best is None or rms < best[1]:
            best = (p, rms)
    return best


def _pose_from_centres(cmm_centres, world_centres, near) -> np.ndarray | None:
    ok = np.all(np.isfinite(world_centres), axis=1)
    if ok.sum() < 3:
        return None
    M, T = kabsch(cmm_centres[ok], world_centres[ok])  # world = M cmm + T = R^T cmm + t
    return np.concatenate([T, angles_from_matrix(M.T, near=near)])


def reinitialise(problem: BundleProblem, sensors: str = "dlt") -> tuple[BundleProblem, dict]:
    """The problem with start values computed from its control points (see module
    docstring; ``sensors``: ``"dlt"`` or ``"resection"``); the report names the sensors
    and poses that were re-initialised, how, and the sphere images used."""
    if sensors not in ("dlt", "resection"):
        raise ValueError(f"unknown sensor initialisation {sensors!r}; choose dlt or resection")
    rig = problem.rig
    names = [s.name for s in rig.scanners]
    ref = names.index(rig.reference)
    cents, used = sphere_centre_images(problem)
    cmm = problem.artefact.centres
    poses = problem.poses.copy()
    known = set()
    report = {"poses": [], "sensors": [], "method": {}, "failed": {}, "sphere_images": used}

    def place(m, sensor, sph, image, world):
        candidates = [poses[m]]
        reg = _pose_from_centres(cmm[sph], world, poses[m, 3:])
        if reg is not None:
            candidates.append(reg)
        best, best_rms = None, np.inf
        for c in candidates:
            p = resect_pose(sensor, cmm[sph], image, c)
            if p is not None:
                rms = _reprojection_rms(sensor, p, cmm[sph], image)
                if rms < best_rms:
                    best, best_rms = p, rms
        if best is None:
            return False
        poses[m] = best
        known.add(m)
        report["poses"].append(problem.measurements[m])
        return True

    ref_cam = rig.scanners[ref].camera
    for m in range(len(problem.measurements)):
        if (ref, m) in cents:
            sph, cam, _, world = cents[(ref, m)]
            place(m, ref_cam, sph, cam, world)
    params = rig.params.copy()
    done = {2 * ref}
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
                free = rig.free[k]
                new, how = None, sensors
                try:
                    est = DLTEstimate.from_estimate(world, image, near_angles=sensor.angles)
                except DLTError as err:
                    est = None
                    report["failed"][sensor.name] = f"DLT: {err}"
                if sensors == "dlt" and est is not None:
                    new = est.params14
                else:
                    fit = resect_sensor(sensor, world, image, free[:6], [est.params[:6]] if est is not None else [])
                    if fit is not None:
                        new, how = fit[0], "resection"
                if new is None:
                    report["failed"][sensor.name] = report["failed"].get(sensor.name, "") + " no resection"
                    continue
                new[~free] = params[k][~free]
                params[k] = new
                done.add(k)
                report["sensors"].append(sensor.name)
                report["method"][sensor.name] = how
                progress = True
        new_rig = rig.with_params(params)
        for m in range(len(problem.measurements)):
            if m in known:
                continue
            for s, sc in enumerate(new_rig.scanners):
                if 2 * s in done and (s, m) in cents:
                    sph, cam, _, world = cents[(s, m)]
                    if place(m, sc.camera, sph, cam, world):
                        progress = True
                        break
        if not progress:
            break
    poses = np.where(problem.pose_free, poses, problem.poses)
    return problem.with_start(rig.with_params(params), poses), report
