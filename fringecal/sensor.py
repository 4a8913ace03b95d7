"""The 14-parameter sensor model of thesis section 2.3.2 (eqs. 2-1..2-6, 2-21, 2-22).

A sensor is a camera or a projector. Its parameters, in this order, are

    x0, y0, z0          pinhole in world coordinates (mm)
    omega, phi, kappa   Euler angles of eq. 2-6 (rad), x' = R (x - x0)
    xi_H, eta_H         principal point on the image plane (mm)
    c                   principal distance (mm)
    k1, k2, k3          radial distortion (mm^-2, mm^-4, mm^-6)
    p1, p2              tangential distortion (mm^-1)

Projection (world -> image plane, mm)::

    x' = R (X - X0)
    x = -c x'/z',  y = -c y'/z'                  ideal, relative to (xi_H, eta_H)
    r^2 = x^2 + y^2,  q = k1 r^2 + k2 r^4 + k3 r^6
    dx = x q + p1 (r^2 + 2 x^2) + 2 p2 x y       (Brown-Conrady)
    dy = y q + p2 (r^2 + 2 y^2) + 2 p1 x y
    xi = xi_H + x + dx,  eta = eta_H + y + dy    eq. 2-4

Optional thin-prism terms (OpenCV's s1..s4, mm^-1 and mm^-3; ``Sensor.prism``, zero
unless the model chosen for a run frees them, :mod:`fringecal.calibration.models`)
add to the same distortion of the ideal coordinates::

    dx += s1 r^2 + s2 r^4,   dy += s3 r^2 + s4 r^4

Optional correction field (``Sensor.field``, :mod:`fringecal.lens.field`; None unless the
model chosen for a run has it): a smooth field ``f`` over the *measured* image plane, so
that a measured point ``m`` stands for the point ``m - f(m)`` of the model above.

Decision (the thesis leaves it open: eq. 2-2 evaluates the distortion at the measured
coordinate, which then appears on both sides of eq. 2-4): distortion is a function of
the *ideal* coordinates, as in Brown's model and OpenCV, so projecting a world point
is closed-form and back-projecting an image point (a pixel or a projector phase pair)
solves ``u + d(u) = m`` by Newton's method. Points in front of a sensor have z' > 0
(the thesis rig has omega ~ -pi, so its sensors look along world -z).

Image-plane coordinates: camera pixels by eq. 2-21 with 0-based column ``u`` and row
``v`` (``xi = (u/(M-1) - 1/2) N_x``, ``eta = (v/(N-1) - 1/2) N_y``); projector phases
by eq. 2-22 (``xi = tau_x N_x / 2 pi``, ``eta = tau_y N_y / 2 pi``).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Literal

import numpy as np

from fringecal.frames import Frame
from fringecal.lens.field import CorrectionField, field_names
from fringecal.rotation import angles_from_matrix, rotation_matrix

__all__ = [
    "sensor_in_frame",
    "scaled_format",
    "PARAM_NAMES",
    "PARAM_COLUMNS",
    "PRISM_NAMES",
    "PRISM_COLUMNS",
    "SensorFormat",
    "Sensor",
    "distort",
    "undistort",
    "UndistortError",
]

PARAM_NAMES = (
    "x0", "y0", "z0", "omega", "phi", "kappa",
    "xi_h", "eta_h", "c", "k1", "k2", "k3", "p1", "p2",
)
#: Table column for each parameter, with its unit (docs/conventions.md: units in column names).
PARAM_COLUMNS = (
    "x0_mm", "y0_mm", "z0_mm", "omega_rad", "phi_rad", "kappa_rad",
    "xi_h_mm", "eta_h_mm", "c_mm", "k1_per_mm2", "k2_per_mm4", "k3_per_mm6",
    "p1_per_mm", "p2_per_mm",
)

#: OpenCV's thin-prism coefficients, outside the thesis's 14 parameters (zero by default).
PRISM_NAMES = ("s1", "s2", "s3", "s4")
PRISM_COLUMNS = ("s1_per_mm", "s2_per_mm3", "s3_per_mm", "s4_per_mm3")
NO_PRISM = (0.0, 0.0, 0.0, 0.0)

Role = Literal["camera", "projector"]


class UndistortError(ArithmeticError):
    """Newton's method did not converge: the point lies where the model folds over."""


@dataclass(frozen=True)
class SensorFormat:
    """Pixel count and physical size of the image plane (CCD or SLM).

    >>> cam = SensorFormat(2048, 2048, 15.1, 15.1)
    >>> cam.pixel_to_mm(np.array([[0.0, 0.0], [2047.0, 2047.0]]))
    array([[-7.55, -7.55],
           [ 7.55,  7.55]])
    >>> prj = SensorFormat(1400, 1050, 19.0, 14.3)
    >>> prj.phase_to_mm(np.array([np.pi, -np.pi / 2]))
    array([ 9.5  , -3.575])
    """

    width_px: int
    height_px: int
    width_mm: float
    height_mm: float

    @property
    def shape(self) -> tuple[int, int]:
        """(rows, columns)."""
        return (self.height_px, self.width_px)

    @property
    def size_mm(self) -> np.ndarray:
        return np.array([self.width_mm, self.height_mm])

    def pixel_to_mm(self, uv) -> np.ndarray:
        """Eq. 2-21: 0-based (column u, row v), shape (..., 2) -> image plane mm."""
        uv = np.asarray(uv, float)
        n = np.array([self.width_px - 1, self.height_px - 1], float)
        return (uv / n - 0.5) * self.size_mm

    def mm_to_pixel(self, xy) -> np.ndarray:
        """Inverse of :meth:`pixel_to_mm`."""
        xy = np.asarray(xy, float)
        n = np.array([self.width_px - 1, self.height_px - 1], float)
        return (xy / self.size_mm + 0.5) * n

    def phase_to_mm(self, tau) -> np.ndarray:
        """Eq. 2-22: (tau_x, tau_y) in rad, shape (..., 2) -> image plane mm."""
        return np.asarray(tau, float) / (2 * np.pi) * self.size_mm

    def mm_to_phase(self, xy) -> np.ndarray:
        """Inverse of :meth:`phase_to_mm`."""
        return np.asarray(xy, float) / self.size_mm * (2 * np.pi)

    def contains_mm(self, xy) -> np.ndarray:
        """True where an image-plane point (..., 2) lies on the sensor."""
        xy = np.asarray(xy, float)
        half = self.size_mm / 2
        return np.all(np.abs(xy) <= half, axis=-1)


def scaled_format(fmt: SensorFormat, width_px: int, height_px: int | None = None) -> SensorFormat:
    """``fmt`` with ``width_px`` x ``height_px`` pixels (height keeps the aspect ratio
    if omitted) over the same physical size.

    >>> scaled_format(SensorFormat(2048, 2048, 15.1, 15.1), 256)
    SensorFormat(width_px=256, height_px=256, width_mm=15.1, height_mm=15.1)
    """
    if height_px is None:
        height_px = max(2, round(width_px * fmt.height_px / fmt.width_px))
    if width_px < 2 or height_px < 2:
        raise ValueError(f"a camera needs at least 2 x 2 pixels, not {width_px} x {height_px}")
    return SensorFormat(int(width_px), int(height_px), fmt.width_mm, fmt.height_mm)


def _distortion_terms(x, y, k, p):
    r2 = x * x + y * y
    q = r2 * (k[0] + r2 * (k[1] + r2 * k[2]))
    dx = x * q + p[0] * (r2 + 2 * x * x) + 2 * p[1] * x * y
    dy = y * q + p[1] * (r2 + 2 * y * y) + 2 * p[0] * x * y
    return r2, q, dx, dy


def distort(xy, k, p, prism=None) -> np.ndarray:
    """Ideal -> distorted coordinates relative to the principal point, (..., 2) mm
    (``prism``: optional thin-prism s1..s4)."""
    xy = np.asarray(xy, float)
    x, y = xy[..., 0], xy[..., 1]
    r2, _, dx, dy = _distortion_terms(x, y, k, p)
    if prism is not None and any(prism):
        s1, s2, s3, s4 = prism
        dx = dx + r2 * (s1 + s2 * r2)
        dy = dy + r2 * (s3 + s4 * r2)
    return np.stack([x + dx, y + dy], axis=-1)


def _undistort_prism(m, k, p, prism, tol, max_iter, strict=True) -> np.ndarray:
    """Newton for ``u + d(u) = m`` with thin-prism terms (non-symmetric Jacobian)."""
    mx, my = m[..., 0], m[..., 1]
    x, y = mx.copy(), my.copy()
    k1, k2, k3 = k
    s1, s2, s3, s4 = prism
    for _ in range(max_iter):
        r2, q, dx, dy = _distortion_terms(x, y, k, p)
        dx = dx + r2 * (s1 + s2 * r2)
        dy = dy + r2 * (s3 + s4 * r2)
        fx = x + dx - mx
        fy = y + dy - my
        g = k1 + r2 * (2 * k2 + 3 * k3 * r2)
        t1 = 2 * (s1 + 2 * s2 * r2)
        t3 = 2 * (s3 + 2 * s4 * r2)
        j12 = 2 * x * y * g + 2 * p[0] * y + 2 * p[1] * x
        a11 = 1 + q + 2 * x * x * g + 6 * p[0] * x + 2 * p[1] * y + x * t1
        a22 = 1 + q + 2 * y * y * g + 6 * p[1] * y + 2 * p[0] * x + y * t3
        a12 = j12 + y * t1
        a21 = j12 + x * t3
        det = a11 * a22 - a12 * a21
        sx = (a22 * fx - a12 * fy) / det
        sy = (a11 * fy - a21 * fx) / det
        x = x - sx
        y = y - sy
        if np.all((np.abs(sx) + np.abs(sy) <= tol * (1 + np.abs(x) + np.abs(y))) | np.isnan(m).any(axis=-1)):
            break
    bad = ~(np.abs(sx) + np.abs(sy) <= 1e3 * tol * (1 + np.abs(x) + np.abs(y))) | ~((det > 0) & (a11 + a22 > 0))
    if not strict:
        return np.where(bad[..., None], np.nan, np.stack([x, y], axis=-1))
    if np.any(bad):
        raise UndistortError(
            f"undistortion did not converge for {int(np.sum(bad))} point(s), e.g. "
            f"{m[bad][:1].tolist()} mm: the distortion model folds over there"
        )
    return np.stack([x, y], axis=-1)


def undistort(xy, k, p, tol: float = 1e-13, max_iter: int = 30, prism=None) -> np.ndarray:
    """Distorted -> ideal coordinates relative to the principal point, by Newton.

    Solves ``u + d(u) = m`` per point; converges quadratically (3-4 iterations for
    the thesis lenses). Raises :class:`UndistortError` if any point fails to converge.

    >>> k, p = (-2.74e-5, 1.11e-7, -1.04e-9), (-3.04e-5, 1.46e-5)
    >>> u = np.array([[5.0, -6.0]])
    >>> bool(np.allclose(undistort(distort(u, k, p), k, p), u, atol=1e-12))
    True
    """
    m = np.asarray(xy, float)
    if prism is not None and any(prism):
        return _undistort_prism(m, k, p, tuple(float(v) for v in prism), tol, max_iter)
    if not any(k) and not any(p):
        return m.copy()
    mx, my = m[..., 0], m[..., 1]
    x, y = mx.copy(), my.copy()
    k1, k2, k3 = k
    for _ in range(max_iter):
        r2, q, dx, dy = _distortion_terms(x, y, k, p)
        fx = x + dx - mx
        fy = y + dy - my
        g = k1 + r2 * (2 * k2 + 3 * k3 * r2)  # d q / d(r^2)
        j11 = 1 + q + 2 * x * x * g + 6 * p[0] * x + 2 * p[1] * y
        j22 = 1 + q + 2 * y * y * g + 6 * p[1] * y + 2 * p[0] * x
        j12 = 2 * x * y * g + 2 * p[0] * y + 2 * p[1] * x
        det = j11 * j22 - j12 * j12
        sx = (j22 * fx - j12 * fy) / det
        sy = (j11 * fy - j12 * fx) / det
        x -= sx
        y -= sy
        if np.all(np.abs(sx) + np.abs(sy) <= tol * (1 + np.abs(x) + np.abs(y))):
            break
    # Not converged, or converged onto a branch beyond a fold of the model (the
    # Jacobian of u -> u + d(u) no longer positive): both are points the lens model
    # cannot invert, so refuse rather than return a wrong ray.
    bad = ~(np.abs(sx) + np.abs(sy) <= 1e3 * tol * (1 + np.abs(x) + np.abs(y))) | ~((det > 0) & (j11 + j22 > 0))
    if np.any(bad):
        raise UndistortError(
            f"undistortion did not converge for {int(np.sum(bad))} point(s), e.g. "
            f"{m[bad][:1].tolist()} mm: the distortion model folds over there"
        )
    return np.stack([x, y], axis=-1)


@dataclass(frozen=True)
class Sensor:
    """A camera or projector: format plus the 14 parameters, and optional thin-prism
    terms ``prism`` = (s1, s2, s3, s4) (zero: the thesis's model).

    Examples
    --------
    >>> cam = Sensor("C1", "camera", SensorFormat(2048, 2048, 15.1, 15.1),
    ...              [694.018, -211.648, 2585.78, -3.037, -0.264, 3.139,
    ...               -0.060, 0.291, 52.701, -2.74e-5, 1.11e-7, -1.04e-9, -3.04e-5, 1.46e-5])
    >>> X = np.array([[-300.0, 100.0, -200.0]])
    >>> o, d = cam.rays(cam.project(X))
    >>> float(np.linalg.norm(np.cross(X - o, d))) < 1e-9
    True
    """

    name: str
    role: Role
    format: SensorFormat
    params: np.ndarray = field(repr=False)
    prism: np.ndarray = field(default=NO_PRISM, repr=False)
    field: CorrectionField | None = field(default=None, repr=False)

    def __post_init__(self):
        p = np.asarray(self.params, float).reshape(14)
        p.setflags(write=False)
        object.__setattr__(self, "params", p)
        s = np.asarray(self.prism, float).reshape(4)
        s.setflags(write=False)
        object.__setattr__(self, "prism", s)
        if self.role not in ("camera", "projector"):
            raise ValueError(f"sensor {self.name!r}: role must be camera or projector, not {self.role!r}")

    # -- parameter views -------------------------------------------------
    @property
    def pinhole(self) -> np.ndarray:
        return self.params[0:3]

    @property
    def angles(self) -> np.ndarray:
        return self.params[3:6]

    @property
    def principal_point(self) -> np.ndarray:
        return self.params[6:8]

    @property
    def c(self) -> float:
        return float(self.params[8])

    @property
    def k(self) -> np.ndarray:
        return self.params[9:12]

    @property
    def p(self) -> np.ndarray:
        return self.params[12:14]

    @property
    def R(self) -> np.ndarray:
        """Rotation sensor <- world (eq. 2-5)."""
        return rotation_matrix(*self.angles)

    @property
    def frame(self) -> Frame:
        """T_world_sensor."""
        return Frame(self.pinhole, self.angles)

    def with_params(self, params, prism=None) -> "Sensor":
        """The sensor with other 14 parameters (and thin-prism terms, if given)."""
        if prism is None:
            return replace(self, params=np.asarray(params, float))
        return replace(self, params=np.asarray(params, float), prism=np.asarray(prism, float))

    def with_field(self, correction: CorrectionField | None) -> "Sensor":
        """The sensor with another correction field (None: without one)."""
        return replace(self, field=correction)

    @property
    def has_prism(self) -> bool:
        return bool(np.any(self.prism != 0.0))

    @property
    def has_field(self) -> bool:
        return self.field is not None and not self.field.is_zero

    @property
    def beyond_brown(self) -> bool:
        """Whether the sensor has terms the compiled 14-parameter kernels do not evaluate
        (thin-prism terms or a correction field): then :meth:`brown_image_mm` maps its
        observations first."""
        return self.has_prism or self.has_field

    def as_dict(self) -> dict[str, float]:
        """Parameter name -> value; the thin-prism terms and the correction field's
        coefficients (``field.f01``, ...) only where they are not zero."""
        out = dict(zip(PARAM_NAMES, map(float, self.params)))
        if self.has_prism:
            out.update(zip(PRISM_NAMES, map(float, self.prism)))
        if self.has_field:
            out.update((f"field.{n}", float(a)) for n, a in zip(field_names(self.field.degree), self.field.coefficients))
        return out

    def brown_image_mm(self, image_mm) -> np.ndarray:
        """Image-plane mm (..., 2) -> the image point that the same sensor *without* its
        correction field and thin-prism terms maps to the same ray.

        The compiled 14-parameter kernels (point clouds) then serve such a sensor
        unchanged: they invert ``u + d_brown(u) = m'`` and get the ``u`` that solves
        ``u + d_brown(u) + d_prism(u) = m - f(m)``. Identity for a 14-parameter sensor.
        """
        m = np.asarray(image_mm, float)
        if self.has_field:
            m = self.field.corrected(m)
        if not self.has_prism:
            return m
        h = self.principal_point
        # NaN where the phases are NaN or the model folds over: the kernels mark those invalid
        ideal = _undistort_prism(m - h, self.k, self.p, tuple(map(float, self.prism)), 1e-13, 30, strict=False)
        return distort(ideal, self.k, self.p) + h

    # -- geometry -----------------------------------------------------------
    def to_sensor(self, points_world) -> np.ndarray:
        """World points (..., 3) -> sensor frame x' (..., 3)."""
        return (np.asarray(points_world, float) - self.pinhole) @ self.R.T

    def project(self, points_world) -> np.ndarray:
        """World points (..., 3) -> distorted image-plane coordinates (..., 2) in mm.

        Points behind the sensor (z' <= 0) come out as NaN.
        """
        xs = self.to_sensor(points_world)
        z = xs[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            ideal = -self.c * xs[..., :2] / z[..., None]
        ideal = np.where((z > 0)[..., None], ideal, np.nan)
        return self._measured(distort(ideal, self.k, self.p, self.prism) + self.principal_point)

    def _measured(self, model_mm) -> np.ndarray:
        """The measured point whose correction is ``model_mm`` (identity without a field)."""
        return self.field.measured(model_mm) if self.has_field else model_mm

    def in_view(self, points_world, margin_mm=0.0) -> np.ndarray:
        """Whether each point (..., 3) is imaged inside the format, ``margin_mm`` (scalar
        or per point) from its edges: in front of the sensor, its distorted image inside,
        and its undistorted image too, so that a point far outside the field that the
        distortion polynomial folds back into the image does not count.
        """
        xs = self.to_sensor(points_world)
        z = xs[..., 2]
        front = z > 0
        with np.errstate(divide="ignore", invalid="ignore"):
            ideal = -self.c * xs[..., :2] / np.where(front, z, 1.0)[..., None]
        image = self._measured(distort(ideal, self.k, self.p, self.prism) + self.principal_point)
        half = np.array([self.format.width_mm, self.format.height_mm]) / 2 - np.asarray(margin_mm, float)[..., None]
        inside = np.all(np.abs(image) <= half, axis=-1) & np.all(np.abs(ideal + self.principal_point) <= 1.1 * half,
                                                                  axis=-1)
        return front & inside

    def directions_local(self, image_mm) -> np.ndarray:
        """Image-plane mm (..., 2) -> unnormalised ray directions (-x, -y, c) in the sensor frame."""
        m = np.asarray(image_mm, float)
        if self.has_field:
            m = self.field.corrected(m)
        ideal = undistort(m - self.principal_point, self.k, self.p, prism=self.prism)
        d = np.empty(ideal.shape[:-1] + (3,))
        d[..., :2] = -ideal
        d[..., 2] = self.c
        return d

    def rays(self, image_mm) -> tuple[np.ndarray, np.ndarray]:
        """Image-plane mm (..., 2) -> (origin (3,), unit directions (..., 3)) in world."""
        d = self.directions_local(image_mm) @ self.R  # R^T d for row vectors
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        return self.pinhole.copy(), d

    def image_mm(self, measured) -> np.ndarray:
        """Camera pixels (u, v) or projector phases (tau_x, tau_y) -> image-plane mm."""
        if self.role == "camera":
            return self.format.pixel_to_mm(measured)
        return self.format.phase_to_mm(measured)

    def measured(self, image_mm) -> np.ndarray:
        """Image-plane mm -> camera pixels or projector phases (inverse of :meth:`image_mm`)."""
        if self.role == "camera":
            return self.format.mm_to_pixel(image_mm)
        return self.format.mm_to_phase(image_mm)


def sensor_in_frame(sensor: Sensor, T_reference_scanner: Frame, near=None) -> Sensor:
    """A sensor expressed in the reference frame.

    A sensor frame maps ``x_sensor = R_s (x_scanner - x0)`` and the link maps
    ``x_scanner = R_T (x_ref - t)``, so in the reference frame the pinhole is
    ``T(x0)`` and the rotation ``R_s R_T``; the angles are taken on the branch
    nearest ``near`` (default: the sensor's own angles). Interior and distortion
    parameters are unchanged.
    """
    T = T_reference_scanner
    R_new = sensor.R @ T.R
    near = sensor.angles if near is None else near
    params = np.array(sensor.params, float)
    params[0:3] = T.to_world(sensor.pinhole)
    params[3:6] = angles_from_matrix(R_new, near=near)
    return sensor.with_params(params)
