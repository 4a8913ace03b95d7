"""One sensor to and from OpenCV's pinhole camera model, verified in pixels.

OpenCV projects a world point ``X`` as ``x_c = R X + t``, ``(x, y) = x_c[:2] / x_c[2]``,
distorts ``(x, y)`` with ``(k1, k2, p1, p2, k3)`` and maps to pixels by ``K``.
fringecal (:mod:`fringecal.sensor`) takes ``x' = R_s (X - X0)``, the ideal image point
``-c x'[:2] / x'[2]`` in mm, Brown distortion of the ideal point, the principal point
``(xi_h, eta_h)`` and a format that maps mm to pixels. The two are the same model:

* **Frame.** fringecal's image point is ``-c x'/z'``, so OpenCV's camera frame is the
  sensor frame turned by pi about its optical axis, ``x_c = F x'`` with
  ``F = diag(-1, -1, 1)``: ``R = F R_s``, ``t = -F R_s X0``, and OpenCV's normalised
  point is the ideal point divided by ``c``.
* **Pixels.** ``u = a_x xi + b_x``, ``v = a_y eta + b_y`` with ``b = ((W-1)/2, (H-1)/2)``
  (pixel centres at integers, as OpenCV) and, for a camera (eq. 2-21, pixel centres 0
  and W-1 at the format's edges) ``a = ((W-1)/N_x, (H-1)/N_y)``; for a projector
  (eq. 2-22, ``tau = +-pi`` at the outer edges of the W x H pixels of the SLM, one
  pixel ``2 pi / W``) ``a = (W/N_x, H/N_y)``, i.e. ``u = (tau_x/2pi + 1/2) W - 1/2``.
  Hence ``fx = a_x c``, ``fy = a_y c``, ``cx = a_x xi_h + b_x``, ``cy = a_y eta_h + b_y``.
* **Distortion.** Both are Brown's model of the ideal point; with ``x = c x_n`` the
  coefficients scale by powers of ``c`` and OpenCV's p1, p2 are fringecal's p2, p1:
  ``(k1 c^2, k2 c^4, p2 c, p1 c, k3 c^6)``. A sensor with thin-prism terms exports
  OpenCV's 12 coefficients, k4..k6 zero and ``(s1 c, s2 c^3, s3 c, s4 c^3)``, and such
  a model imports exactly.

The conversion is therefore exact; :func:`model_difference` checks it on a dense grid
over the whole format at several depths by projecting the same world points with
``cv2.projectPoints`` and :meth:`fringecal.sensor.Sensor.project`. OpenCV models with
terms fringecal lacks (rational k4..k6, tilt) are imported by a
least-squares fit of k1, k2, k3, p1, p2 over the image, and the remaining difference is
measured the same way. Only the pixel -> mm scale is not in OpenCV's model: the
format's width in mm is an argument of :func:`from_opencv` (any value gives the same
projection; ``c`` and the distortion coefficients scale with it).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from fringecal.rotation import angles_from_matrix
from fringecal.sensor import Role, Sensor, SensorFormat

__all__ = ["OpenCVCamera", "ImportedSensor", "to_opencv", "from_opencv", "model_difference", "pixel_map",
           "GRID", "DEPTHS_MM"]

#: sensor frame -> OpenCV camera frame (a half turn about the optical axis)
F = np.diag([-1.0, -1.0, 1.0])
#: grid points per image axis of the verification (over the format + 10 % on each side)
GRID = 81
#: depths z' (mm, along the optical axis) at which the verification grid is placed
DEPTHS_MM = (300.0, 1000.0, 3000.0, 10000.0)
_DIST_LENGTHS = (4, 5, 8, 12, 14)


@dataclass(frozen=True)
class OpenCVCamera:
    """One sensor in OpenCV's model.

    Attributes
    ----------
    name : str
    role : {"camera", "projector"}
    image_size : (int, int)
        (width, height) in pixels; a projector's is its SLM's pixel grid.
    K : ndarray, shape (3, 3)
        Camera matrix, pixels.
    dist : ndarray, shape (5,)
        (k1, k2, p1, p2, k3) of OpenCV's normalised coordinates.
    R : ndarray, shape (3, 3)
        Rotation world -> OpenCV camera frame.
    t : ndarray, shape (3,)
        ``x_c = R X + t`` (mm).
    size_mm : (float, float)
        fringecal's format in mm, which OpenCV does not carry.
    worst_px, rms_px : float
        Largest and RMS distance (pixels) between ``cv2.projectPoints`` with this model and
        fringecal's projection over the whole image at each of :data:`DEPTHS_MM`
        (:func:`model_difference`).
    """

    name: str
    role: Role
    image_size: tuple[int, int]
    K: np.ndarray
    dist: np.ndarray
    R: np.ndarray
    t: np.ndarray
    size_mm: tuple[float, float]
    worst_px: float
    rms_px: float

    @property
    def rvec(self) -> np.ndarray:
        """Rodrigues vector of :attr:`R`, shape (3,)."""
        return cv2.Rodrigues(self.R)[0].ravel()


@dataclass(frozen=True)
class ImportedSensor:
    """A sensor built from an OpenCV model and how well it reproduces it.

    ``fitted`` says whether the OpenCV model had distortion terms beyond
    (k1, k2, p1, p2, k3) so that fringecal's coefficients were fitted; ``worst_px`` and
    ``rms_px`` are measured as for :class:`OpenCVCamera`.
    """

    sensor: Sensor
    worst_px: float
    rms_px: float
    fitted: bool


def pixel_map(role: Role, fmt: SensorFormat) -> tuple[np.ndarray, np.ndarray]:
    """``(a, b)``, each shape (2,): OpenCV pixel = ``a * image_mm + b`` (see the module notes).

    >>> a, b = pixel_map("camera", SensorFormat(2048, 2048, 15.1, 15.1))
    >>> (a * np.array([-7.55, 7.55]) + b).round(9).tolist() == [0.0, 2047.0]
    True
    >>> a, b = pixel_map("projector", SensorFormat(1400, 1050, 19.0, 14.3))
    >>> (a * np.array([-9.5, 7.15]) + b).round(12).tolist()
    [-0.5, 1049.5]
    """
    n = np.array([fmt.width_px, fmt.height_px], float)
    a = ((n - 1) if role == "camera" else n) / fmt.size_mm
    return a, (n - 1) / 2


def to_opencv(sensor: Sensor, grid: int = GRID, depths=DEPTHS_MM) -> OpenCVCamera:
    """OpenCV's model of ``sensor`` (exact), with the measured model difference.

    Parameters
    ----------
    sensor : Sensor
        A camera or projector in any frame; that frame is OpenCV's world.
    grid : int
        Verification points per image axis.
    depths : sequence of float
        Depths (mm) of the verification points.
    """
    a, b = pixel_map(sensor.role, sensor.format)
    c = sensor.c
    K = np.array([[a[0] * c, 0.0, a[0] * sensor.principal_point[0] + b[0]],
                  [0.0, a[1] * c, a[1] * sensor.principal_point[1] + b[1]],
                  [0.0, 0.0, 1.0]])
    k1, k2, k3 = sensor.k
    p1, p2 = sensor.p
    dist = np.array([k1 * c**2, k2 * c**4, p2 * c, p1 * c, k3 * c**6])
    if sensor.has_prism:  # OpenCV's 12-coefficient model: k4..k6 zero, then s1..s4
        s1, s2, s3, s4 = sensor.prism
        dist = np.concatenate([dist, [0.0, 0.0, 0.0, s1 * c, s2 * c**3, s3 * c, s4 * c**3]])
    R = F @ sensor.R
    t = -R @ sensor.pinhole
    worst, rms = model_difference(sensor, K, dist, R, t, grid, depths)
    f = sensor.format
    return OpenCVCamera(sensor.name, sensor.role, (f.width_px, f.height_px), K, dist, R, t,
                        (f.width_mm, f.height_mm), worst, rms)


def from_opencv(K, dist, R, t, image_size, *, name: str, role: Role, width_mm: float | None = None,
                fmt: SensorFormat | None = None, near=None, grid: int = GRID, depths=DEPTHS_MM) -> ImportedSensor:
    """A fringecal sensor from OpenCV's model, with the measured model difference.

    Parameters
    ----------
    K : array_like, shape (3, 3)
        Camera matrix (pixels), zero skew.
    dist : array_like, shape (4,), (5,), (8,), (12,) or (14,)
        OpenCV's distortion coefficients (k1, k2, p1, p2[, k3[, k4, k5, k6[, s1..s4[, tx, ty]]]]).
    R : array_like, shape (3, 3)
        Rotation world -> camera (a Rodrigues vector, shape (3,), is accepted too).
    t : array_like, shape (3,)
        Translation (mm), ``x_c = R X + t``.
    image_size : (int, int)
        (width, height) in pixels.
    name, role : the sensor's name and ``"camera"`` or ``"projector"``.
    width_mm : float, optional
        Format width in mm (default: ``fmt.width_mm``); the height follows from ``fy``.
    fmt : SensorFormat, optional
        Where the width comes from when ``width_mm`` is not given; its height is kept
        when the one ``fy`` gives agrees with it to 1e-9 (relative).
    near : array_like, shape (3,), optional
        Euler-angle branch (:func:`fringecal.rotation.angles_from_matrix`).

    Raises
    ------
    ValueError
        A matrix of the wrong shape, non-finite values, skew, a non-positive focal
        length, a matrix that is not a rotation, or no width in mm.
    """
    K, dist, R, t, (w, h) = _checked(K, dist, R, t, image_size)
    if width_mm is None:
        if fmt is None:
            raise ValueError(f"sensor {name!r}: OpenCV's model has no size in mm; give width_mm or a format")
        width_mm = fmt.width_mm
    if not width_mm > 0:
        raise ValueError(f"sensor {name!r}: width_mm must be positive, not {width_mm}")
    # thin prism alone beyond Brown's terms is fringecal's model too (exact); rational
    # k4..k6 or tilt are fitted
    prism_only = dist.size >= 12 and not np.any(dist[5:8] != 0) and not np.any(dist[12:] != 0)
    fitted = bool(np.any(dist[5:] != 0)) and not prism_only
    if fitted:
        coeffs = _fit_distortion(K, dist, (w, h))
    else:
        coeffs = np.append(dist, 0.0) if dist.size == 4 else dist[:5]
    n = np.array([w, h], float) - (1 if role == "camera" else 0)
    ax = n[0] / width_mm
    c = K[0, 0] / ax
    ay = K[1, 1] / c
    height_mm = float(n[1] / ay)
    if fmt is not None and abs(height_mm - fmt.height_mm) <= 1e-9 * fmt.height_mm:
        height_mm = float(fmt.height_mm)  # the given format's value, not its rounding
    fmt_new = SensorFormat(int(w), int(h), float(width_mm), height_mm)
    b = (np.array([w, h], float) - 1) / 2
    k1, k2, p1, p2, k3 = coeffs
    Rs = F @ R
    params = np.concatenate([-R.T @ t, angles_from_matrix(Rs, near=near),
                             [(K[0, 2] - b[0]) / ax, (K[1, 2] - b[1]) / ay, c,
                              k1 / c**2, k2 / c**4, k3 / c**6, p2 / c, p1 / c]])
    prism = np.zeros(4)
    if prism_only:
        prism = dist[8:12] / np.array([c, c**3, c, c**3])
    sensor = Sensor(name, role, fmt_new, params, prism)
    worst, rms = model_difference(sensor, K, dist, R, t, grid, depths)
    return ImportedSensor(sensor, worst, rms, fitted)


def model_difference(sensor: Sensor, K, dist, R, t, grid: int = GRID, depths=DEPTHS_MM) -> tuple[float, float]:
    """Worst and RMS pixel distance between fringecal's and OpenCV's projection.

    World points: a ``grid`` x ``grid`` lattice of ideal image points over the format
    enlarged by 10 % on every side, each at every depth z' of ``depths``, kept where
    fringecal's (distorted) image lies on the format -- so the kept points cover the whole
    image, edges included, without inverting the lens model (a calibrated model may
    fold over beyond the measured field, where back-projection is refused).
    fringecal's image (:meth:`Sensor.project`, mm) goes to pixels by :func:`pixel_map`;
    OpenCV's by ``cv2.projectPoints(X, rvec(R), t, K, dist)``.

    Returns
    -------
    worst_px, rms_px : float
    """
    f = sensor.format
    g = np.linspace(-0.6, 0.6, grid)
    ideal = np.stack(np.meshgrid(g * f.width_mm, g * f.height_mm), axis=-1).reshape(-1, 2) - sensor.principal_point
    d = np.concatenate([-ideal, np.full((len(ideal), 1), sensor.c)], axis=1)
    local = np.concatenate([d * (z / sensor.c) for z in depths])
    world = local @ sensor.R + sensor.pinhole
    image = sensor.project(world)
    keep = f.contains_mm(image)
    if not keep.any():
        raise ValueError(f"sensor {sensor.name!r}: no point of the verification grid is imaged on the format")
    a, b = pixel_map(sensor.role, f)
    ours = image[keep] * a + b
    rvec = cv2.Rodrigues(np.asarray(R, float))[0]
    theirs = cv2.projectPoints(world[keep].reshape(-1, 1, 3), rvec, np.asarray(t, float).reshape(3, 1),
                               np.asarray(K, float), np.asarray(dist, float))[0].reshape(-1, 2)
    e = np.linalg.norm(ours - theirs, axis=1)
    return float(e.max()), float(np.sqrt(np.mean(e**2)))


def _checked(K, dist, R, t, image_size):
    K = np.asarray(K, float)
    dist = np.asarray(dist, float).ravel()
    R = np.asarray(R, float)
    t = np.asarray(t, float).ravel()
    if R.shape in ((3,), (3, 1), (1, 3)):
        R = cv2.Rodrigues(R.reshape(3, 1))[0]
    if K.shape != (3, 3) or R.shape != (3, 3) or t.shape != (3,):
        raise ValueError(f"expected K 3x3, R 3x3 and t of 3 values; got K {K.shape}, R {R.shape}, t {t.shape}")
    if dist.size not in _DIST_LENGTHS:
        raise ValueError(f"distortion coefficients: expected {', '.join(map(str, _DIST_LENGTHS))} values, "
                         f"got {dist.size}")
    for label, v in (("K", K), ("dist", dist), ("R", R), ("t", t)):
        if not np.all(np.isfinite(v)):
            raise ValueError(f"{label} has non-finite values")
    if not (K[0, 0] > 0 and K[1, 1] > 0) or np.any(K[2] != [0, 0, 1]) or K[1, 0] != 0:
        raise ValueError(f"K must be [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0; got {K.tolist()}")
    if abs(K[0, 1]) > 1e-12 * K[0, 0]:
        raise ValueError(f"K has skew {K[0, 1]}; fringecal's sensor model has none")
    if np.abs(R @ R.T - np.eye(3)).max() > 1e-6 or np.linalg.det(R) < 0:
        raise ValueError(f"R is not a rotation (R R^T - I up to {np.abs(R @ R.T - np.eye(3)).max():.1e}, "
                         f"det {np.linalg.det(R):.6f})")
    u, _, vt = np.linalg.svd(R)
    w, h = (int(v) for v in image_size)
    if w < 2 or h < 2:
        raise ValueError(f"image size must be at least 2 x 2 pixels, not {w} x {h}")
    return K, dist, u @ vt, t, (w, h)


def _fit_distortion(K, dist, image_size, grid: int = GRID) -> np.ndarray:
    """(k1, k2, p1, p2, k3) closest in pixels to OpenCV's full model ``dist``.

    Ideal points whose images form a ``grid`` x ``grid`` lattice over the image come from
    ``cv2.undistortPointsIter``; their exact images under ``dist`` are the targets, and
    the five-coefficient model is linear in its coefficients: one least-squares solve,
    residuals weighted to pixels by fx, fy.
    """
    w, h = image_size
    uv = np.stack(np.meshgrid(np.linspace(0, w - 1, grid), np.linspace(0, h - 1, grid)), axis=-1).reshape(-1, 1, 2)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14)
    xn = cv2.undistortPointsIter(uv, K, dist, None, None, crit).reshape(-1, 2)
    pts = np.concatenate([xn, np.ones((len(xn), 1))], axis=1).reshape(-1, 1, 3)
    zero = np.zeros((3, 1))
    target = cv2.projectPoints(pts, zero, zero, np.eye(3), dist)[0].reshape(-1, 2) - xn
    x, y = xn[:, 0], xn[:, 1]
    r2 = x * x + y * y
    # columns: k1, k2, p1, p2, k3 (OpenCV's order)
    ax = np.stack([x * r2, x * r2**2, 2 * x * y, r2 + 2 * x * x, x * r2**3], axis=1)
    ay = np.stack([y * r2, y * r2**2, r2 + 2 * y * y, 2 * x * y, y * r2**3], axis=1)
    A = np.concatenate([ax * K[0, 0], ay * K[1, 1]])
    rhs = np.concatenate([target[:, 0] * K[0, 0], target[:, 1] * K[1, 1]])
    scale = np.linalg.norm(A, axis=0)
    sol = np.linalg.lstsq(A / scale, rhs, rcond=None)[0] / scale
    return sol
