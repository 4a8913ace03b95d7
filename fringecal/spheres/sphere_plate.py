"""The sphere-plate analysis of thesis chapter 5 (intensity-gradient errors).

A 20 mm chrome-steel sphere sits on a stalk 50.645 mm (CMM, table 5-1) in front of
a flat ground plate. The scanner measures it over a grid of plate tilts theta
(0, 30, 60, 70 deg) and rotations phi (-45, -20, 0, 20, 45 deg). The plate's
normal changes, the sphere always looks the same to the scanner, so a systematic
error in the measured sphere position (the intensity-gradient bias: a pixel
integrates brighter light on one side) shows up as a sphere-to-plane distance that
varies with the orientation. Tables 5-2..5-5 list, per tilt, the mean distance per
rotation and its spread; :func:`analyse_sphere_plate` produces the same tables
without the manual regions of interest: the plate is the dominant plane (or the
caller's labels), the sphere comes from the rejection pipeline with the stalk masked
as a rod along the plate normal.

Orientation convention (:func:`plate_normal`): the scanner looks along -z, camera
and projector are displaced along x (the plane of the optical axes is x-z). The
rotation phi turns the plate normal within that plane, the tilt theta out of it:
``n = (sin phi, -cos phi sin theta, cos phi cos theta)``, so at theta = 0 the normal
lies in the plane of the optical axes, as in section 5.5.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pandas as pd
from scipy import stats

from fringecal.spheres.fit import FitError
from fringecal.spheres.robust import RejectionConfig, fit_plane_robust, fit_sphere_robust

__all__ = [
    "CMM_SEPARATION_MM", "THESIS_TILTS_DEG", "THESIS_ROTATIONS_DEG", "THESIS_MEAN_SEPARATION_MM",
    "plate_normal", "SpherePlateResult", "measure_sphere_plate", "analyse_sphere_plate", "SpherePlateAnalysis",
]

#: Table 5-1: CMM distance from the plate's best-fit plane to the sphere centre.
CMM_SEPARATION_MM = 50.645
THESIS_TILTS_DEG = (0.0, 30.0, 60.0, 70.0)
THESIS_ROTATIONS_DEG = (-45.0, -20.0, 0.0, 20.0, 45.0)
#: Tables 5-2..5-5, mean separation (mm) by tilt (rows) and rotation (columns, as above).
THESIS_MEAN_SEPARATION_MM = {
    0.0: (50.689, 50.689, 50.639, 50.598, 50.589),
    30.0: (50.652, 50.646, 50.585, 50.599, 50.616),
    60.0: (50.614, 50.603, 50.613, 50.584, 50.606),
    70.0: (50.615, 50.587, 50.523, 50.591, 50.587),
}


def plate_normal(tilt_deg: float, rotation_deg: float) -> np.ndarray:
    """Unit plate normal (3,) for a tilt and rotation (degrees), facing the scanner (+z)."""
    t, r = np.radians(tilt_deg), np.radians(rotation_deg)
    return np.array([np.sin(r), -np.cos(r) * np.sin(t), np.cos(r) * np.cos(t)])


@dataclass(frozen=True)
class SpherePlateResult:
    """One pose: the sphere-centre-to-plane distance and what it came from."""

    distance_mm: float
    u_distance_mm: float
    sphere: object = field(repr=False)  # RobustSphereFit
    plane: object = field(repr=False)   # RobustPlaneFit

    def row(self) -> dict:
        s, p = self.sphere.model, self.plane.model
        return {
            "distance_mm": self.distance_mm, "u_distance_mm": self.u_distance_mm,
            "sphere_radius_mm": s.radius, "sphere_rms_mm": s.rms, "sphere_points": s.n_points,
            "plate_flatness_sd_mm": p.rms, "plate_flatness_pv_mm": p.flatness, "plate_points": p.n_points,
            **{f"sphere_rejected_{k}": v for k, v in self.sphere.rejected.items()},
        }


def measure_sphere_plate(points, labels=None, sphere_radius_mm: float = 10.0, stalk_radius_mm: float = 4.0,
                         noise_mm: float = 0.02, viewpoints=None, fixed_radius: bool = False) -> SpherePlateResult:
    """Sphere-centre-to-plane distance of one sphere-plate point cloud.

    Parameters
    ----------
    points : array_like, shape (n, 3)
    labels : array_like of str, shape (n,), optional
        ``"plate"`` / ``"sphere"`` per point (others ignored). Without labels the
        plate is the dominant plane and the sphere is searched among the rest.
    sphere_radius_mm : float
        Nominal radius (RANSAC plausibility; the fitted radius is free unless
        ``fixed_radius``).
    stalk_radius_mm : float
        The stalk is masked as a rod along the plate normal through the centre.
    viewpoints : array_like, shape (m, 3), optional
        Camera and projector pinholes for the silhouette test.
    """
    p = np.asarray(points, float)
    toward = None if viewpoints is None else np.asarray(viewpoints, float).reshape(-1, 3)[0]
    if labels is not None:
        labels = np.asarray(labels).astype(str)
        plane = fit_plane_robust(p[labels == "plate"], noise_mm=noise_mm, toward=toward)
        sphere_pts = p[labels == "sphere"]
    else:
        plane = fit_plane_robust(p, noise_mm=noise_mm, toward=toward)
        full = np.zeros(len(p), bool)
        full[np.flatnonzero(np.all(np.isfinite(p), axis=1))] = True
        off_plane = np.abs(plane.model.residuals(np.where(full[:, None], p, 0))) > 5 * plane.threshold_mm
        sphere_pts = p[full & off_plane & (plane.model.residuals(np.where(full[:, None], p, 0)) > 0)]
    if toward is None:
        # without viewpoints, orient the normal toward the sphere side
        probe = np.nanmedian(sphere_pts, axis=0)
        if plane.model.distance(probe) < 0:
            m = plane.model
            plane = type(plane)(type(m)(-m.normal, m.point, m.rms, m.flatness, m.n_points, m.spread, m.axes),
                                plane.kept, plane.threshold_mm, plane.sigma_mm)
    cfg = RejectionConfig(noise_mm=noise_mm, rod_radius_mm=stalk_radius_mm, detect_rods=False,
                          min_points=20)
    sphere = fit_sphere_robust(sphere_pts, sphere_radius_mm if fixed_radius else None,
                               expected_radius=sphere_radius_mm, viewpoints=viewpoints,
                               rod_axes=[-plane.model.normal], config=cfg)
    c = sphere.model.centre
    dist = plane.model.distance(c)
    n = plane.model.normal
    var = plane.model.distance_variance(c) + float(n @ sphere.model.covariance[:3, :3] @ n)
    return SpherePlateResult(dist, float(np.sqrt(var)), sphere, plane)


@dataclass(frozen=True)
class SpherePlateAnalysis:
    """Per-pose table and the per-tilt summaries (tables 5-2..5-5).

    ``poses``: tilt_deg, rotation_deg, repeat, distance_mm, deviation_mm (from the
    CMM), u_distance_mm, sphere and plate statistics, or ``error`` for poses that
    failed. ``by_rotation``: per (tilt, rotation) mean distance, SD over repeats
    (or the fit uncertainty for a single repeat) and plate flatness SD, as the
    thesis tables. ``by_tilt``: mean, deviation, SD across rotations, the RMS fit
    uncertainty, chi^2 per degree of freedom of the distances about their mean and
    its p-value: a small p-value says the distance depends on the orientation
    beyond noise (a systematic, intensity-gradient-like error).
    """

    poses: pd.DataFrame
    by_rotation: pd.DataFrame
    by_tilt: pd.DataFrame
    cmm_distance_mm: float

    @property
    def mean_deviation_mm(self) -> float:
        return float(self.poses["deviation_mm"].mean())


def analyse_sphere_plate(measurements, cmm_distance_mm: float = CMM_SEPARATION_MM, **kwargs) -> SpherePlateAnalysis:
    """Analyse a grid of sphere-plate measurements.

    Parameters
    ----------
    measurements : iterable of dict
        Each with ``tilt_deg``, ``rotation_deg``, ``points`` (n, 3) and optionally
        ``labels`` (n,) and ``repeat`` (int).
    cmm_distance_mm : float
        Reference separation (table 5-1).
    **kwargs
        Passed to :func:`measure_sphere_plate` (radius, stalk radius, noise, viewpoints).
    """
    rows = []
    for m in measurements:
        base = {"tilt_deg": float(m["tilt_deg"]), "rotation_deg": float(m["rotation_deg"]),
                "repeat": int(m.get("repeat", 0))}
        try:
            r = measure_sphere_plate(m["points"], m.get("labels"), **kwargs)
        except FitError as err:
            rows.append({**base, "error": str(err)})
            continue
        rows.append({**base, **r.row(), "deviation_mm": r.distance_mm - cmm_distance_mm, "error": ""})
    poses = pd.DataFrame(rows)
    ok = poses[poses["error"] == ""] if "distance_mm" in poses else poses.iloc[0:0]

    def rot_summary(g):
        sd = g["distance_mm"].std(ddof=1) if len(g) > 1 else g["u_distance_mm"].iloc[0]
        return pd.Series({"mean_distance_mm": g["distance_mm"].mean(), "sd_distance_mm": sd,
                          "plate_flatness_sd_mm": g["plate_flatness_sd_mm"].mean(), "n_repeats": len(g)})

    def tilt_summary(g):
        d = g["mean_distance_mm"].to_numpy()
        u = g["u_mean_mm"].to_numpy()
        mean = float(np.average(d, weights=1 / u**2))
        chi2 = float(np.sum(((d - mean) / u) ** 2))
        dof = max(len(d) - 1, 1)
        return pd.Series({"mean_distance_mm": d.mean(), "deviation_mm": d.mean() - cmm_distance_mm,
                          "sd_across_rotations_mm": d.std(ddof=1) if len(d) > 1 else np.nan,
                          "u_rms_mm": float(np.sqrt(np.mean(u**2))), "chi2_per_dof": chi2 / dof,
                          "p_value": float(stats.chi2.sf(chi2, dof)) if len(d) > 1 else np.nan,
                          "plate_flatness_sd_mm": g["plate_flatness_sd_mm"].mean(), "n_rotations": len(d)})

    if len(ok):
        by_rotation = ok.groupby(["tilt_deg", "rotation_deg"]).apply(rot_summary, include_groups=False).reset_index()
        u_mean = ok.groupby(["tilt_deg", "rotation_deg"]).apply(
            lambda g: (g["distance_mm"].std(ddof=1) / np.sqrt(len(g))) if len(g) > 2 else
            float(np.sqrt(np.mean(g["u_distance_mm"] ** 2)) / np.sqrt(len(g))), include_groups=False)
        by_rotation["u_mean_mm"] = u_mean.to_numpy()
        by_tilt = by_rotation.groupby("tilt_deg").apply(tilt_summary, include_groups=False).reset_index()
    else:
        by_rotation = pd.DataFrame()
        by_tilt = pd.DataFrame()
    return SpherePlateAnalysis(poses, by_rotation, by_tilt, cmm_distance_mm)
