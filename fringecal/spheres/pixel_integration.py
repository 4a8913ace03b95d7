"""Pixel-integration bias of the phases decoded on a sphere (thesis chapter 5).

A camera pixel integrates the light of a patch of surface, so the phase it decodes is
the irradiance-weighted mean of the projector phase over that patch, not the phase
where the pixel centre's ray meets the surface. On a sphere the two differ for two
reasons: the phase is not linear across the patch (curvature), and the patch is
brighter on the side that faces the projector (the intensity gradient of thesis
section 5.1, which weights the mean towards that side). Both grow with the square of
the footprint, so they matter for coarse cameras: at 320 px across a 1.5 m field the
decoded points of a 50 mm sphere lie 20-60 um behind the surface, more where the
projector light comes in obliquely, and the bundle adjustment turns that pattern into
a bias of the calibration.

Given a sphere (centre and radius in the scanner's frame) the bias is predicted here
and subtracted from the decoded phases of the control points. The model:

* the pixel's response is uniform over a square ``footprint_px`` wide (a sensor with
  100 % fill factor and no optical blur: ``footprint_px = 1``); it is integrated by a
  ``nodes`` x ``nodes`` Gauss-Legendre rule, each node a ray through the full camera
  model;
* the surface is Lambertian and lit by the projector pinhole as a point source:
  irradiance ``cos(i) / d^2``, ``i`` the angle between the sphere normal and the
  direction to the projector, ``d`` the distance to it; nodes that miss the sphere or
  face away from the projector weigh nothing;
* the mean is linear in the phase (the spread of the phase over one footprint is a few
  hundredths of a radian, so the circular mean of the phasors differs from it by far
  less than the phase noise).

A camera with a larger point spread (defocus, anti-aliasing filter) has a larger
effective footprint; the correction scales with its square, so ``footprint_px`` is a
setting (``control_points.pixel_integration_px``; 0 switches the correction off).
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from fringecal.pointcloud import triangulate_image_points
from fringecal.rig import Scanner
from fringecal.sensor import Sensor
from fringecal.triangulation import sphere_hits

__all__ = ["phase_integration_bias", "correct_control_points", "correct_sphere_points", "CORRECTION_COLUMNS"]

#: control-point columns holding the subtracted bias (rad)
CORRECTION_COLUMNS = ("pixel_integration_x_rad", "pixel_integration_y_rad")


def _phase_and_irradiance(camera: Sensor, projector: Sensor, uv, centres, radius):
    origin, d = camera.rays(camera.image_mm(uv))
    X = sphere_hits(origin, d, centres, radius)
    normal = (X - centres) / radius[..., None]
    to_prj = projector.pinhole - X
    dist = np.linalg.norm(to_prj, axis=-1)
    cos_i = np.einsum("...k,...k->...", normal, to_prj) / dist
    irradiance = np.where(cos_i > 0, cos_i, 0.0) / dist**2
    tau = projector.measured(projector.project(X))
    return tau, np.nan_to_num(irradiance)


def phase_integration_bias(camera: Sensor, projector: Sensor, uv, centres, radius, footprint_px: float = 1.0,
                           nodes: int = 3) -> np.ndarray:
    """Predicted decoded-minus-centre phase of pixels on spheres.

    Parameters
    ----------
    camera, projector : Sensor
        The scanner's sensors, in the frame of ``centres``.
    uv : (n, 2) float
        Camera pixels (column, row).
    centres : (n, 3) float
        Centre of the sphere each pixel sees (mm).
    radius : (n,) float
        Its radius (mm).
    footprint_px : float
        Side of the square, uniform pixel response (px); 0 gives zeros.
    nodes : int
        Gauss-Legendre nodes per side.

    Returns
    -------
    (n, 2) float
        ``(tau_x, tau_y)`` bias in rad: subtract it from the decoded phases. NaN where
        the pixel centre's ray misses its sphere or no node is lit.

    Examples
    --------
    A pixel looking at the middle of a sphere lit from the camera's own direction sees
    a symmetric patch: no bias to first order, but curvature still pushes the phase a
    little.

    >>> from fringecal.simulate.control_points import thesis_truth
    >>> scanner = thesis_truth()[0].scanners[0]
    >>> cam, prj = scanner.camera, scanner.projector
    >>> centre = cam.pinhole + 2500.0 * cam.R[2]
    >>> uv = cam.measured(cam.project(centre[None]))
    >>> bias = phase_integration_bias(cam, prj, uv, centre[None], np.array([25.0]))
    >>> bool(np.all(np.abs(bias) < 1e-4))
    True
    """
    uv = np.asarray(uv, float)
    centres = np.asarray(centres, float)
    radius = np.asarray(radius, float)
    if footprint_px <= 0 or len(uv) == 0:
        return np.zeros((len(uv), 2))
    x, w = np.polynomial.legendre.leggauss(int(nodes))
    x, w = x * footprint_px / 2, w / 2
    offsets = np.stack(np.meshgrid(x, x, indexing="ij"), axis=-1).reshape(-1, 2)
    weights = np.outer(w, w).ravel()
    tau_c, _ = _phase_and_irradiance(camera, projector, uv[:, None, :], centres[:, None, :], radius[:, None])
    tau_s, irr = _phase_and_irradiance(camera, projector, uv[:, None, :] + offsets, centres[:, None, :],
                                       radius[:, None])
    wp = weights * irr
    total = wp.sum(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.einsum("nm,nmk->nk", wp, np.nan_to_num(tau_s)) / total[:, None]
    out = mean - tau_c[:, 0, :]
    out[~(total > 0)] = np.nan
    return out


def correct_control_points(control_points: pd.DataFrame, spheres: pd.DataFrame, scanner: Scanner,
                           footprint_px: float = 1.0) -> pd.DataFrame:
    """Subtract the pixel-integration bias from the control points of one measurement.

    Parameters
    ----------
    control_points : DataFrame
        Rows of :class:`fringecal.schemas.ControlPointsTable` of one (measurement, scanner).
    spheres : DataFrame
        The measurement's sphere fits (``sphere_id, x_mm, y_mm, z_mm, radius_mm``) in
        the frame of ``scanner``'s sensors.
    footprint_px : float
        See :func:`phase_integration_bias`; 0 returns the table with zero corrections.

    Returns
    -------
    DataFrame
        ``tau_x_rad, tau_y_rad`` corrected, the subtracted bias in
        :data:`CORRECTION_COLUMNS`. Control points whose bias cannot be predicted (the
        pixel centre's ray misses the fitted sphere: the rim) are left out.
    """
    out = control_points.copy()
    if footprint_px <= 0 or len(out) == 0:
        for col in CORRECTION_COLUMNS:
            out[col] = 0.0
        return out
    fits = spheres.assign(sphere_id=spheres["sphere_id"].astype(str)).set_index("sphere_id")
    ids = out["sphere_id"].astype(str)
    centres = fits.loc[ids, ["x_mm", "y_mm", "z_mm"]].to_numpy(float)
    radius = fits.loc[ids, "radius_mm"].to_numpy(float)
    bias = phase_integration_bias(scanner.camera, scanner.projector, out[["u_px", "v_px"]].to_numpy(float),
                                  centres, radius, footprint_px)
    for k, (col, tau) in enumerate(zip(CORRECTION_COLUMNS, ("tau_x_rad", "tau_y_rad"))):
        out[col] = bias[:, k]
        out[tau] = out[tau] - bias[:, k]
    return out[np.isfinite(bias).all(axis=1)].reset_index(drop=True)


def correct_sphere_points(scanner: Scanner, uv, points, centre, radius: float, footprint_px: float = 1.0
                          ) -> tuple[np.ndarray, np.ndarray]:
    """Triangulated points of one sphere moved as if their phases had been corrected for
    the pixel integration: what a sphere fit (ball-bar, acceptance, measure) needs, as
    the control points get it from :func:`correct_control_points`.

    Each point's projector coordinates are taken where it projects (the triangulated
    point's own), the predicted bias (:func:`phase_integration_bias` against the sphere
    ``centre`` (3,), ``radius``) is subtracted, and the point moves by the difference of
    the two triangulations: the bias's effect, to first order in it, without the
    store's phases.

    Parameters
    ----------
    scanner : the scanner (camera at the measurement's resolution) in the points' frame
    uv : (n, 2) camera pixels (column, row) of the points
    points : (n, 3) the triangulated points, mm

    Returns
    -------
    points : (n, 3) corrected (the input where no bias can be predicted)
    ok : (n,) bool, False where the pixel centre's ray misses the sphere (the rim) or
        nothing is lit: a fit leaves those out, as the control points do
    """
    points = np.asarray(points, float)
    uv = np.asarray(uv, float)
    if footprint_px <= 0 or len(points) == 0:
        return points.copy(), np.ones(len(points), bool)
    cam, prj = scanner.camera, scanner.projector
    bias = phase_integration_bias(cam, prj, uv, np.broadcast_to(np.asarray(centre, float), points.shape),
                                  np.full(len(points), float(radius)), footprint_px)
    ok = np.isfinite(bias).all(axis=1)
    tau = prj.measured(prj.project(points))
    cam_mm = cam.image_mm(uv)
    moved = (triangulate_image_points(cam, prj, cam_mm, prj.image_mm(tau - np.where(ok[:, None], bias, 0.0)))
             - triangulate_image_points(cam, prj, cam_mm, prj.image_mm(tau)))
    ok &= np.isfinite(moved).all(axis=1)
    return np.where(ok[:, None], points + np.nan_to_num(moved), points), ok
