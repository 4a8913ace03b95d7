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

from dataclasses import dataclass

import numpy as np

from fringecal.frames import Frame
from fringecal.pointcloud import triangulate_image_points
from fringecal.rig import Rig, Scanner
from fringecal.rotation import angles_from_matrix

__all__ = ["ParameterCovariances", "FieldCovariances", "parameter_covariances", "sensor_covariance", "scanner_block", "point_jacobian", "point_covariance", "triangulate_mm",
           "point_variances", "point_uncertainty_map", "uncertainty_at_depth", "DepthUncertainty", "scanner_with", "STEP_FRACTION",
           "rigid_motion_basis", "frame_free_covariance", "ATTITUDE_WEIGHT_MM", "attitude_jacobian",
           "frame_motion_operator", "to_rig_frame"]

#: central-difference step as a fraction of each parameter's standard uncertainty
STEP_FRACTION = 1e-3
#: in the frame-free datum, a sensor attitude change of 1 rad counts as this many mm
ATTITUDE_WEIGHT_MM = 1000.0


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
    """The (28, 28) block of one scanner (camera 14, then projector 14); of an extended
    covariance (:class:`FieldCovariances`), its (28 + 2 K) block (:func:`extended_indices`)."""
    i = [s.name for s in rig.scanners].index(scanner)
    n14 = 14 * len(rig.sensors)
    if cov_sensors.shape[0] > n14:
        idx = extended_indices(len(rig.sensors), i, (cov_sensors.shape[0] - n14) // len(rig.sensors))
        return cov_sensors[np.ix_(idx, idx)]
    sl = slice(28 * i, 28 * i + 28)
    return cov_sensors[sl, sl]


def triangulate_mm(scanner: Scanner, cam_mm, prj_mm) -> np.ndarray:
    """Points (n, 3) of camera and projector image-plane coordinates (n, 2) mm (NaN where
    the model does not invert; compiled, :func:`fringecal.pointcloud.triangulate_image_points`)."""
    return triangulate_image_points(scanner.camera, scanner.projector, cam_mm, prj_mm)


def scanner_with(scanner: Scanner, params28: np.ndarray) -> Scanner:
    """``scanner`` with other parameters (28,: camera 14, then projector 14; or 28 + 2 K:
    then the camera's and the projector's K correction-field coefficients,
    :func:`fringecal.verification.budget.block_params`)."""
    p = np.asarray(params28, float)
    cam, prj = scanner.camera.with_params(p[:14]), scanner.projector.with_params(p[14:28])
    if len(p) > 28:
        K = (len(p) - 28) // 2
        cam, prj = (_with_coefficients(s, c) for s, c in ((cam, p[28:28 + K]), (prj, p[28 + K:])))
    return Scanner(scanner.name, cam, prj)


def _with_coefficients(sensor, coefficients):
    if sensor.field is None:
        if np.any(coefficients != 0.0):
            raise ValueError(f"sensor {sensor.name!r} has no correction field to take coefficients")
        return sensor
    return sensor.with_field(sensor.field.with_coefficients(coefficients))


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


#: the principal points' slots among a scanner's 28 parameters (camera xi_h, eta_h; projector)
PRINCIPAL_POINTS = (slice(6, 8), slice(20, 22))


def with_principal_point_steps(std28) -> np.ndarray:
    """``std28`` with a 1 um step where a principal point is fixed: a correction field's
    derivative is made of the principal point's (:func:`field_jacobian`)."""
    std = np.array(std28, float, copy=True)
    for sl in PRINCIPAL_POINTS:
        std[sl] = np.where(std[sl] > 0, std[sl], 1e-3 / STEP_FRACTION)
    return std


def field_jacobian(scanner: Scanner, cam_mm, prj_mm, J: np.ndarray, n_terms: int) -> np.ndarray:
    """d(point)/d(correction-field coefficients), (n, 3, 2 K): camera's K, then
    projector's, from the points' Jacobian ``J`` (n, 3, 28) by the principal points: a
    coefficient moves a point as the principal point does, weighted by its basis function
    at the observation (zero for a sensor without a field)."""
    cols = []
    for sensor, obs, sl in zip(scanner.sensors, (cam_mm, prj_mm), PRINCIPAL_POINTS):
        obs = np.asarray(obs, float).reshape(-1, 2)
        f = sensor.field
        phi = f.basis(obs) if f is not None and len(f.coefficients) == n_terms else np.zeros((len(obs), 2, n_terms))
        cols.append(np.einsum("ndk,nid->nik", phi, J[:, :, sl]))
    return np.concatenate(cols, axis=2)


def extended_indices(n_sensors: int, block: int, n_terms: int) -> np.ndarray:
    """Positions of scanner ``block``'s 28 parameters, then its camera's and projector's
    K correction-field coefficients, in the extended vector of :class:`FieldCovariances`."""
    return np.concatenate([np.arange(28 * block, 28 * block + 28),
                           14 * n_sensors + 2 * n_terms * block + np.arange(2 * n_terms)])


def point_covariance(J: np.ndarray, cov28: np.ndarray) -> np.ndarray:
    """Covariance (n, 3, 3) of points with Jacobians J (n, 3, 28)."""
    return np.einsum("nij,jk,nlk->nil", J, cov28, J)


def point_variances(scanner: Scanner, cov28: np.ndarray, tau_x, tau_y, rows, cols, block: int = 20000) -> np.ndarray:
    """Variances (n, 3) along the world axes of the points at pixels (rows, cols) of a
    measurement with phase maps ``tau_x``, ``tau_y``, from the parameter covariance
    ``cov28`` (28, 28) of ``scanner`` (camera at the measurement's resolution), or (28 +
    2 K) square with its correction fields' coefficients (:func:`extended_indices`)."""
    rows, cols = np.asarray(rows, int), np.asarray(cols, int)
    tau_x, tau_y = np.asarray(tau_x), np.asarray(tau_y)
    std = np.sqrt(np.clip(np.diag(cov28), 0, None))
    n_terms = (len(std) - 28) // 2
    out = np.zeros((len(rows), 3))
    for a in range(0, len(rows), block):
        r, c = rows[a:a + block], cols[a:a + block]
        cam = scanner.camera.image_mm(np.stack([c, r], axis=-1).astype(float))
        prj = scanner.projector.image_mm(np.stack([tau_x[r, c], tau_y[r, c]], axis=-1).astype(float))
        if n_terms:
            J = point_jacobian(scanner, cam, prj, with_principal_point_steps(std[:28]))
            J = np.concatenate([J, field_jacobian(scanner, cam, prj, J, n_terms)], axis=2)
        else:
            J = point_jacobian(scanner, cam, prj, std)
        C = point_covariance(J, cov28)
        out[a:a + block] = np.clip(np.diagonal(C, axis1=1, axis2=2), 0, None)
    return out


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
    var = np.full((3,) + valid.shape, np.nan)
    var[:, rows, cols] = point_variances(scanner, cov28, tau_x, tau_y, rows, cols, block).T
    dims = ("v", "u")
    return xr.Dataset({"u_mm": (dims, np.sqrt(var.sum(axis=0))), "u_x_mm": (dims, np.sqrt(var[0])),
                       "u_y_mm": (dims, np.sqrt(var[1])), "u_z_mm": (dims, np.sqrt(var[2]))},
                      attrs={"units": "mm", "what": "standard uncertainty of each point from the calibration"})


@dataclass(frozen=True)
class DepthUncertainty:
    """The calibration's uncertainty of the points a scanner measures on a plane of
    constant camera depth: ``u_mm`` (ny, nx), the 3-D standard uncertainty (square
    root of the covariance's trace) of the point seen at the centre of each cell of
    an ``nx`` x ``ny`` grid over the camera's image (NaN where the projector does not
    see the point); ``u_px``, ``v_px`` the cells' centres (camera pixels)."""

    depth_mm: float
    u_mm: np.ndarray
    u_px: np.ndarray
    v_px: np.ndarray


def uncertainty_at_depth(scanner: Scanner, cov28: np.ndarray, depth_mm: float, nx: int = 24) -> DepthUncertainty:
    """The map of :class:`DepthUncertainty` at camera depth ``depth_mm``: for each cell,
    the point on the camera ray through its centre at that depth, the projector
    coordinates that see it, and the covariance (28, 28) of the scanner's parameters
    propagated through the triangulation (:func:`point_jacobian`). What a measured
    point inherits from the calibration alone (the pixel's own phase noise is not in it).
    """
    cam = scanner.camera
    fmt = cam.format
    ny = max(1, int(round(nx * fmt.height_px / fmt.width_px)))
    u_px = (np.arange(nx) + 0.5) * fmt.width_px / nx - 0.5
    v_px = (np.arange(ny) + 0.5) * fmt.height_px / ny - 0.5
    uv = np.stack(np.meshgrid(u_px, v_px), axis=-1).reshape(-1, 2)
    cam_mm = fmt.pixel_to_mm(uv)
    origin, direction = cam.rays(cam_mm)
    X = origin + direction * (depth_mm / (direction @ cam.R[2]))[:, None]
    seen = scanner.projector.in_view(X)
    u = np.full(len(X), np.nan)
    if seen.any():
        prj_mm = scanner.projector.project(X[seen])
        std = np.sqrt(np.clip(np.diag(cov28), 0, None))
        C = point_covariance(point_jacobian(scanner, cam_mm[seen], prj_mm, std), cov28)
        u[seen] = np.sqrt(np.clip(np.trace(C, axis1=1, axis2=2), 0, None))
    return DepthUncertainty(float(depth_mm), u.reshape(ny, nx), u_px, v_px)


def rigid_motion_basis(rig: Rig, eps: float = 1e-6) -> np.ndarray:
    """How every sensor parameter changes when the whole rig moves rigidly: shape
    (n_sensors * 14, 6), columns per unit translation along world x, y, z (mm) and
    rotation about them (rad, about the centroid of the projection centres)."""

    sensors = rig.sensors
    pivot = np.mean([s.pinhole for s in sensors], axis=0)

    def moved(xi):
        T = Frame.from_params(xi)
        out = []
        for s in sensors:
            p = np.array(s.params, float)
            p[:3] = T.to_world((s.pinhole - pivot)[None])[0] + pivot
            p[3:6] = angles_from_matrix(s.R @ T.R, near=s.angles)
            out.append(p)
        return np.concatenate(out)

    G = np.zeros((14 * len(sensors), 6))
    for k in range(6):
        xi = np.zeros(6)
        xi[k] = eps
        G[:, k] = (moved(xi) - moved(-xi)) / (2 * eps)
    return G


def attitude_jacobian(sensor, std14, grid: int = 3) -> np.ndarray:
    """How the sensor's bundle of rays turns with its parameters: (3, 14), the rotation
    vector (rad, world axes) that best explains (least squares) the change of the
    world directions of the rays through a ``grid`` x ``grid`` of image points spanning
    its format, per unit of each parameter.

    This, not the three angles alone, is the sensor's attitude: turning the angles by
    ``d`` while moving the principal point by ``c d`` leaves every ray almost where it
    was. The reference camera, whose angles the adjustment holds fixed, turns with
    the rest of the rig through its principal point. Steps are ``STEP_FRACTION`` of
    ``std14``; parameters with zero uncertainty get a zero column.
    """
    fmt = sensor.format
    a = (np.arange(grid) + 0.5) / grid - 0.5
    uv = np.stack(np.meshgrid(a * fmt.width_mm, a * fmt.height_mm), axis=-1).reshape(-1, 2)
    _, d0 = sensor.rays(uv)
    # d(d_j) = w x d_j = -[d_j]x w: stack the cross-product matrices, solve for w
    A = np.zeros((len(d0), 3, 3))
    A[:, 0, 1], A[:, 0, 2], A[:, 1, 2] = d0[:, 2], -d0[:, 1], d0[:, 0]
    A[:, 1, 0], A[:, 2, 0], A[:, 2, 1] = -d0[:, 2], d0[:, 1], -d0[:, 0]
    A_pinv = np.linalg.pinv(A.reshape(-1, 3))
    out = np.zeros((3, 14))
    for j in np.flatnonzero(np.asarray(std14) > 0):
        h = STEP_FRACTION * float(std14[j])
        p = np.array(sensor.params, float)
        p[j] += h
        plus = sensor.with_params(p).rays(uv)[1]
        p[j] -= 2 * h
        minus = sensor.with_params(p).rays(uv)[1]
        out[:, j] = A_pinv @ ((plus - minus) / (2 * h)).reshape(-1)
    return out


def frame_motion_operator(rig: Rig, std: np.ndarray) -> np.ndarray:
    """K (6, n_sensors * 14): the rigid motion of the whole rig (as the columns of
    :func:`rigid_motion_basis`) that best explains a change ``delta`` of the sensor
    parameters, ``xi = K delta``: least squares over the sensors' projection centres
    (mm) and attitudes (:func:`attitude_jacobian`, 1 rad weighted as
    ``ATTITUDE_WEIGHT_MM`` mm). ``std`` (n_sensors * 14,) sets the differentiation steps.
    """
    G = rigid_motion_basis(rig)
    n = G.shape[0]
    M = np.zeros((n, n))
    for i, sensor in enumerate(rig.sensors):
        sl = slice(14 * i, 14 * i + 14)
        A = attitude_jacobian(sensor, np.asarray(std)[sl])
        M[sl, sl] = ATTITUDE_WEIGHT_MM ** 2 * A.T @ A
        M[14 * i:14 * i + 3, 14 * i:14 * i + 3] += np.eye(3)
    MG = M @ G
    return np.linalg.solve(G.T @ MG, MG.T)


def to_rig_frame(rig: Rig, xi: np.ndarray, points) -> np.ndarray:
    """Points (..., 3) measured by a rig that moved rigidly by ``xi`` (6,: as
    :func:`rigid_motion_basis`, e.g. ``frame_motion_operator(...) @ delta``) moved
    back: where the rig without that motion puts them."""
    pivot = np.mean([s.pinhole for s in rig.sensors], axis=0)
    return Frame.from_params(xi).to_local(np.asarray(points, float) - pivot) + pivot


def frame_free_covariance(rig: Rig, covariance: np.ndarray) -> np.ndarray:
    """The sensor covariance (n_sensors * 14 square) moved to the frame realised by the
    sensors themselves (an S-transformation to inner constraints).

    The adjustment's datum holds one camera's exterior orientation fixed, so the
    uncertainty of that camera's principal point (a few um, i.e. ~0.5 mrad of its
    axis) turns every point's position in the world frame by that much: 1.6 mm at
    3.5 m for the thesis rig, an uncertainty of how the frame is defined, not of what
    is measured. Here the rigid motions of the whole rig (:func:`rigid_motion_basis`,
    which no observation can see) are projected out so that the sensors' projection
    centres and attitudes do not move on average (:func:`frame_motion_operator`):
    ``P C P^T`` with ``P = I - G K``. A sensor's attitude is that of its bundle of
    rays (:func:`attitude_jacobian`), not its three angles: the reference camera's
    angles are fixed, and the frame turns through its principal point. Lengths,
    shapes and the registration between scanners keep their uncertainty exactly (a
    rigid motion changes none of them); a point's uncertainty becomes that relative
    to the rig. An extended covariance (:class:`FieldCovariances`) keeps its correction
    fields' coefficients: a rigid motion does not change them, and they hold no field of
    degree below 2, so none turns a bundle of rays (``P`` is the identity on them).
    """
    covariance = np.asarray(covariance, float)
    G = rigid_motion_basis(rig)
    n14 = G.shape[0]
    K = frame_motion_operator(rig, np.sqrt(np.clip(np.diag(covariance)[:n14], 0, None)))
    P = np.eye(len(covariance))
    P[:n14, :n14] -= G @ K
    return P @ covariance @ P.T


@dataclass(frozen=True)
class ParameterCovariances:
    """The sensor-parameter covariances (n_sensors * 14 square) and the scale response.

    calibration, cmm : covariance from the adjustment and from the artefact table;
    scale : (n_sensors * 14,) parameter change per unit relative scale of the artefact;
    u_scale : relative standard uncertainty of the artefact's scale (temperature).
    field : with free correction fields (:mod:`fringecal.lens.field`, K coefficients per
        sensor), the same three over the extended vector: the n_sensors * 14 parameters,
        then sensor i's coefficients at ``n_sensors * 14 + K i`` (:class:`FieldCovariances`);
        the 14 parameters' blocks above are then marginal over the coefficients.
    """

    calibration: np.ndarray
    cmm: np.ndarray
    scale: np.ndarray
    u_scale: float
    field: "FieldCovariances | None" = None

    @property
    def total(self) -> np.ndarray:
        return self.calibration + self.cmm + self.u_scale**2 * np.outer(self.scale, self.scale)

    @property
    def field_total(self) -> np.ndarray | None:
        """:attr:`total` over the extended vector with the correction fields (None without)."""
        f = self.field
        return None if f is None else f.calibration + f.cmm + self.u_scale**2 * np.outer(f.scale, f.scale)


@dataclass(frozen=True)
class FieldCovariances:
    """:class:`ParameterCovariances`' three over the extended vector (sensor parameters,
    then correction-field coefficients): ``n_terms`` K coefficients per sensor."""

    calibration: np.ndarray
    cmm: np.ndarray
    scale: np.ndarray
    n_terms: int


def parameter_covariances(arrays: dict, u_scale: float, u_factor: float = 1.0) -> ParameterCovariances:
    """The sensor-parameter covariances of a run's ``calibration_covariance.npz``
    (``u_factor`` on the artefact table's uncertainties, ``u_scale`` the relative
    standard uncertainty of the artefact's scale), with the correction fields' where the
    adjustment freed them (``field_index``)."""
    S = arrays["artefact_sensitivity"] * (u_factor * arrays["artefact_u"])[None, :]

    def three(idx):
        flat = np.asarray(idx).reshape(-1)
        scale = np.zeros(flat.size)
        scale[flat >= 0] = arrays["scale_sensitivity"][flat[flat >= 0]]
        return sensor_covariance(flat, arrays["covariance"]), sensor_covariance(flat, S @ S.T), scale

    idx = arrays["sensor_index"]
    field_index = np.asarray(arrays.get("field_index", np.zeros((len(idx), 0))), np.int64)
    field = None
    if field_index.size and np.any(field_index >= 0):
        field = FieldCovariances(*three(np.concatenate([np.ravel(idx), field_index.ravel()])),
                                 int(field_index.shape[1]))
    return ParameterCovariances(*three(idx), float(u_scale), field)
