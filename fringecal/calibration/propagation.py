"""Linear propagation of the calibration's covariance to triangulated points.

The bundle adjustment's covariance (:mod:`.uncertainty`) is over its free parameters,
sensors first, then poses. What a measurement needs is the block of the sensors: the
parameters of every sensor in rig order, 14 each, fixed ones with zero variance
(:func:`sensor_covariance`). A point triangulated by one scanner depends on that
scanner's 28 parameters (camera 14, projector 14); its Jacobian is taken by central
differences of the triangulation itself (:func:`point_jacobian`), so it follows the
full model, distortion included, with steps of a small fraction of each parameter's
standard uncertainty (the triangulation is smooth on that scale, and rounding stays
eight orders of magnitude below the effect).
"""

from __future__ import annotations

import numpy as np

from ..rig import Rig, Scanner
from ..pointcloud import triangulate_image_points

__all__ = ["sensor_covariance", "scanner_block", "point_jacobian", "point_covariance", "triangulate_mm",
           "point_uncertainty_map", "scanner_with", "STEP_FRACTION"]

#: central-difference step as a fraction of each parameter's standard uncertainty
STEP_FRACTION = 1e-3


def sensor_covariance(sensor_index: np.ndarray, covariance: np.ndarray) -> np.ndarray:
    """Covariance of every sensor parameter, shape (n_sensors * 14, n_sensors * 14).

    Parameters
    ----------
    sensor_index : (n_sensors, 14) int
        Position of each sensor parameter in the adjusted vector, -1 where fixed
        (:class:`~fringecal.calibration.model.ParameterLayout`).
    covariance : (p, p)
        Covariance of the adjusted vector.

    Row ``14 * i + j`` is parameter j of sensor i; fixed parameters have zero rows.
    """
    idx = np.asarray(sensor_index).reshape(-1)
    out = np.zeros((len(idx), len(idx)))
    free = idx >= 0
    out[np.ix_(free, free)] = np.asarray(covariance)[np.ix_(idx[free], idx[free])]
    return out


def scanner_block(cov_sensors: np.ndarray, rig: Rig, scanner: str) -> np.ndarray:
    """The (28, 28) block of one scanner (camera 14, then projector 14)."""
    i = [s.name for s in rig.scanners].index(scanner)
    sl = slice(28 * i, 28 * i + 28)
    return cov_sensors[sl, sl]


def triangulate_mm(scanner: Scanner, cam_mm, prj_mm) -> np.ndarray:
    """Points (n, 3) of camera and projector image-plane coordinates (n, 2) mm (NaN where
    the model does not invert; compiled, :func:`fringecal.pointcloud.triangulate_image_points`)."""
    return triangulate_image_points(scanner.camera, scanner.projector, cam_mm, prj_mm)


def scanner_with(scanner: Scanner, params28: np.ndarray) -> Scanner:
    """``scanner`` with other parameters (28,: camera 14, then projector 14)."""
    return Scanner(scanner.name, scanner.camera.with_params(params28[:14]), scanner.projector.with_params(params28[14:]))


def point_jacobian(scanner: Scanner, cam_mm, prj_mm, std28) -> np.ndarray:
    """d(point)/d(parameters) of triangulated points, shape (n, 3, 28).

    ``std28``: standard uncertainties of the scanner's 28 parameters (steps are
    ``STEP_FRACTION`` of them; parameters with zero uncertainty get a zero column).
    """
    cam_mm = np.asarray(cam_mm, float).reshape(-1, 2)
    prj_mm = np.asarray(prj_mm, float).reshape(-1, 2)
    p0 = np.concatenate([scanner.camera.params, scanner.projector.params])
    J = np.zeros((len(cam_mm), 3, 28))
    for j in np.flatnonzero(np.asarray(std28) > 0):
        h = STEP_FRACTION * float(std28[j])
        p = p0.copy()
        p[j] += h
        plus = triangulate_mm(scanner_with(scanner, p), cam_mm, prj_mm)
        p[j] -= 2 * h
        minus = triangulate_mm(scanner_with(scanner, p), cam_mm, prj_mm)
        J[:, :, j] = (plus - minus) / (2 * h)
    return J


def point_covariance(J: np.ndarray, cov28: np.ndarray) -> np.ndarray:
    """Covariance (n, 3, 3) of points with Jacobians J (n, 3, 28)."""
    return np.einsum("nij,jk,nlk->nil", J, cov28, J)


def point_uncertainty_map(scanner: Scanner, cov28: np.ndarray, tau_x, tau_y, valid, block: int = 20000):
    """Standard uncertainty of every point of a measurement from the calibration.

    Parameters
    ----------
    scanner : the calibrated scanner (camera at the measurement's resolution)
    cov28 : (28, 28) covariance of its parameters (:func:`scanner_block` of
        :func:`sensor_covariance`; add the artefact's share for a full statement)
    tau_x, tau_y, valid : (rows, cols) maps of the measurement

    Returns
    -------
    xarray.Dataset on dims ``(v, u)``: ``u_mm`` = sqrt(trace of the point's 3 x 3
    covariance), the 3-D standard uncertainty of its position in mm, and ``u_x_mm``,
    ``u_y_mm``, ``u_z_mm`` per world axis; NaN where no point was triangulated. The
    phase noise of the pixel itself is not in it (it is the measurement's own, seen in
    epsilon-1).
    """
    import xarray as xr

    valid = np.asarray(valid, bool) & np.isfinite(tau_x) & np.isfinite(tau_y)
    rows, cols = np.nonzero(valid)
    std = np.sqrt(np.clip(np.diag(cov28), 0, None))
    var = np.full((3,) + valid.shape, np.nan)
    for a in range(0, len(rows), block):
        r, c = rows[a:a + block], cols[a:a + block]
        cam = scanner.camera.image_mm(np.stack([c, r], axis=-1).astype(float))
        prj = scanner.projector.image_mm(np.stack([np.asarray(tau_x)[r, c], np.asarray(tau_y)[r, c]], axis=-1))
        C = point_covariance(point_jacobian(scanner, cam, prj, std), cov28)
        var[:, r, c] = np.clip(np.diagonal(C, axis1=1, axis2=2).T, 0, None)
    dims = ("v", "u")
    return xr.Dataset({"u_mm": (dims, np.sqrt(var.sum(axis=0))), "u_x_mm": (dims, np.sqrt(var[0])),
                       "u_y_mm": (dims, np.sqrt(var[1])), "u_z_mm": (dims, np.sqrt(var[2]))},
                      attrs={"units": "mm", "what": "standard uncertainty of each point from the calibration"})
