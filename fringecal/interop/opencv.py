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
measured the same way.

**A sensor with a correction field** (:mod:`fringecal.lens.field`) has no exact OpenCV
model: of the field's 19 degree-2..4 directions, OpenCV's terms hold about two (s2, s4)
to first order. :func:`to_opencv` then fits OpenCV's 14-coefficient model (rational,
thin prism, tilt) and the camera matrix to the sensor's whole mapping by least squares
(:func:`_fit_field_model`): for every point m of a :data:`FIT_GRID` x :data:`FIT_GRID`
grid over the format, edges included, the direction of :meth:`Sensor.rays` (m) in the
sensor frame must project to m's pixel through ``cv2.projectPoints``. Fitted: fx, fy,
cx, cy, k1, k2, k3, p1, p2, s1..s4, tauX, tauY, from the exact model of the sensor
without its field. Held: the rotation and translation (the sensor's exterior is
exported exactly, so a stereo file's R, T are fringecal's), and k4..k6 at zero -- to
first order the rational denominator's terms are -k1..-k3's, so fitting them only
trades k1 against k4 (measured on the thesis camera C1 with a field of 8.7 um RMS: k1 =
k4 = -112, worst difference 2.662 px against 2.672 px without them). The difference is
then measured as for any sensor (:func:`model_difference`, through
:meth:`Sensor.project`, on other points than the fit's and on the rays of a finer
lattice that reaches the format's edges and corners, where a fitted model differs
most) and stated: the model *fits* where the worst
difference is at most :data:`FIT_TOLERANCE_PX`, else it *approximates* with that worst
difference (:attr:`OpenCVCamera.verdict`). A sensor without a field is exported
exactly as before. Only the pixel -> mm scale is not in OpenCV's model: the
format's width in mm is an argument of :func:`from_opencv` (any value gives the same
projection; ``c`` and the distortion coefficients scale with it).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.optimize import least_squares

from fringecal.rotation import angles_from_matrix
from fringecal.sensor import Role, Sensor, SensorFormat, UndistortError, distort

__all__ = [
    "DEPTHS_MM",
    "FIT_GRID",
    "FIT_TOLERANCE_PX",
    "GRID",
    "ImportedSensor",
    "OpenCVCamera",
    "from_opencv",
    "model_difference",
    "pixel_map",
    "points_mm",
    "points_px",
    "to_opencv",
]

#: sensor frame -> OpenCV camera frame (a half turn about the optical axis)
F = np.diag([-1.0, -1.0, 1.0])
#: grid points per image axis of the verification (over the format + 10 % on each side)
GRID = 81
#: depths z' (mm, along the optical axis) at which the verification grid is placed
DEPTHS_MM = (300.0, 1000.0, 3000.0, 10000.0)
_DIST_LENGTHS = (4, 5, 8, 12, 14)
#: grid points per image axis of the least-squares fit of a sensor with a correction field
FIT_GRID = 49
#: worst difference (px) up to which a fitted OpenCV model is said to fit the sensor
FIT_TOLERANCE_PX = 0.01
#: OpenCV's coefficients (indices of the 14) fitted for a sensor with a correction field:
#: k1, k2, p1, p2, k3, s1..s4, tauX, tauY (k4..k6 held at zero, module notes)
_FIELD_FITTED = (0, 1, 2, 3, 4, 8, 9, 10, 11, 12, 13)


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
    fitted : bool
        Whether ``K`` and ``dist`` (then OpenCV's 14 coefficients) were fitted by least
        squares because the sensor has a correction field (module notes); False: the
        exact conversion.
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
    fitted: bool = False

    @property
    def verdict(self) -> str:
        """``"exact"`` (not fitted), ``"fits"`` (fitted, worst difference at most
        :data:`FIT_TOLERANCE_PX`) or ``"approximates"``."""
        if not self.fitted:
            return "exact"
        return "fits" if self.worst_px <= FIT_TOLERANCE_PX else "approximates"

    @property
    def statement(self) -> str:
        """One line on how the exported model stands for the sensor, with its worst and
        RMS difference in pixels over the format."""
        diff = f"worst {self.worst_px:.3g} px, RMS {self.rms_px:.3g} px over the format"
        if not self.fitted:
            return f"{self.name}: exact conversion ({diff})"
        if self.verdict == "fits":
            how = f"fits it ({diff}; tolerance {FIT_TOLERANCE_PX:g} px)"
        else:
            how = f"approximates it with {diff} (it would fit below {FIT_TOLERANCE_PX:g} px)"
        return (f"{self.name} has a correction field, which OpenCV's model cannot hold exactly: OpenCV's "
                f"14-coefficient model (k4..k6 zero), fitted by least squares over the format, {how}")

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


def points_px(role: Role, fmt: SensorFormat, image_mm) -> np.ndarray:
    """Image-plane points (m, 2) mm (e.g. an observed region's hull vertices) as OpenCV
    pixels (m, 2) of that sensor (:func:`pixel_map`; a projector's over its SLM).

    >>> px = points_px("camera", SensorFormat(2048, 2048, 15.1, 15.1), [[-7.55, 0.0], [7.55, 7.55]])
    >>> (px.round(9) + 0.0).tolist()
    [[0.0, 1023.5], [2047.0, 2047.0]]
    """
    a, b = pixel_map(role, fmt)
    return np.asarray(image_mm, float).reshape(-1, 2) * a + b


def points_mm(role: Role, fmt: SensorFormat, pixels) -> np.ndarray:
    """Inverse of :func:`points_px`: OpenCV pixels (m, 2) -> image-plane mm (m, 2)."""
    a, b = pixel_map(role, fmt)
    return (np.asarray(pixels, float).reshape(-1, 2) - b) / a


def to_opencv(sensor: Sensor, grid: int = GRID, depths=DEPTHS_MM) -> OpenCVCamera:
    """OpenCV's model of ``sensor`` (exact; fitted for a sensor with a correction
    field, module notes), with the measured model difference.

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
    if sensor.has_field:  # no exact model: OpenCV's 14 coefficients fitted, from the exact one without the field
        K, dist = _fit_field_model(sensor, K, dist)
    worst, rms = model_difference(sensor, K, dist, R, t, grid, depths, edges=sensor.has_field)
    f = sensor.format
    return OpenCVCamera(sensor.name, sensor.role, (f.width_px, f.height_px), K, dist, R, t,
                        (f.width_mm, f.height_mm), worst, rms, sensor.has_field)


def _fit_points(sensor: Sensor, grid: int) -> tuple[np.ndarray, np.ndarray]:
    """Measured image points (n, 2) mm over the whole format and OpenCV's normalised
    point (n, 2) of each one's ray: a ``grid`` x ``grid`` lattice, edges included,
    through :meth:`Sensor.directions_local` (OpenCV's camera frame is the sensor frame
    turned by pi about the axis, so the normalised point is ``-d[:2] / d[2]``). Where the
    lens model folds over inside the format and refuses back-projection, the lattice is
    one of ideal points instead (over the format + 10 %), kept where their measured
    image lies on the format."""
    f = sensor.format
    g = np.linspace(-0.5, 0.5, grid)
    m = np.stack(np.meshgrid(g * f.width_mm, g * f.height_mm), axis=-1).reshape(-1, 2)
    try:
        d = sensor.directions_local(m)
        return m, -d[:, :2] / d[:, 2:]
    except UndistortError:
        pass
    g = np.linspace(-0.55, 0.55, grid)
    ideal = np.stack(np.meshgrid(g * f.width_mm, g * f.height_mm), axis=-1).reshape(-1, 2) - sensor.principal_point
    m = sensor.field.measured(distort(ideal, sensor.k, sensor.p, sensor.prism) + sensor.principal_point)
    keep = f.contains_mm(m)
    return m[keep], ideal[keep] / sensor.c


def _fit_field_model(sensor: Sensor, K0: np.ndarray, dist0: np.ndarray,
                     grid: int = FIT_GRID) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV's camera matrix and 14 coefficients closest in pixels to ``sensor``'s
    whole mapping, a sensor with a correction field (module notes).

    Levenberg-Marquardt over fx, fy, cx, cy and :data:`_FIELD_FITTED` from the exact
    model ``K0``, ``dist0`` of the sensor without its field; residuals are pixels
    (``cv2.projectPoints`` of each fit point's normalised ray against the pixel of the
    measured point, :func:`pixel_map`), derivatives ``cv2.projectPoints``'.
    """
    a, b = pixel_map(sensor.role, sensor.format)
    m, xn = _fit_points(sensor, grid)
    pts = np.concatenate([xn, np.ones((len(xn), 1))], axis=1).reshape(-1, 1, 3)
    target = (m * a + b).ravel()
    start = np.concatenate([[K0[0, 0], K0[1, 1], K0[0, 2], K0[1, 2]], dist0, np.zeros(14 - dist0.size)])
    free = np.array([0, 1, 2, 3, *(4 + j for j in _FIELD_FITTED)])
    zero = np.zeros(3)

    def model(p):
        x = start.copy()
        x[free] = p
        return np.array([[x[0], 0.0, x[2]], [0.0, x[1], x[3]], [0.0, 0.0, 1.0]]), x[4:]

    def residuals(p):
        return cv2.projectPoints(pts, zero, zero, *model(p))[0].ravel() - target

    def jacobian(p):  # columns: rvec 3, tvec 3, fx fy, cx cy, the 14 coefficients
        return cv2.projectPoints(pts, zero, zero, *model(p))[1][:, 6:][:, free]

    fit = least_squares(residuals, start[free], jac=jacobian, method="lm", x_scale="jac",
                        xtol=1e-15, ftol=1e-15, gtol=1e-15)
    return model(fit.x)


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


def model_difference(sensor: Sensor, K, dist, R, t, grid: int = GRID, depths=DEPTHS_MM,
                     edges: bool = False) -> tuple[float, float]:
    """Worst and RMS pixel distance between fringecal's and OpenCV's projection.

    World points: a ``grid`` x ``grid`` lattice of ideal image points over the format
    enlarged by 10 % on every side, each at every depth z' of ``depths``, kept where
    fringecal's (distorted) image lies on the format -- so the kept points cover the whole
    image, edges included, without inverting the lens model (a calibrated model may
    fold over beyond the measured field, where back-projection is refused).
    fringecal's image (:meth:`Sensor.project`, mm) goes to pixels by :func:`pixel_map`;
    OpenCV's by ``cv2.projectPoints(X, rvec(R), t, K, dist)``.

    With ``edges`` (a fitted model, whose difference is largest in the corners): also the
    rays of a ``grid`` x ``grid`` lattice of measured points over the format, its edges
    and corners exactly (which the kept ideal points approach only to a grid step), at
    every depth, where back-projection does not refuse them.

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
    world, image = world[keep], image[keep]
    if edges:
        g = np.linspace(-0.5, 0.5, grid)
        m = np.stack(np.meshgrid(g * f.width_mm, g * f.height_mm), axis=-1).reshape(-1, 2)
        try:
            d = sensor.directions_local(m)
        except UndistortError:
            pass
        else:
            on = np.concatenate([d * (z / sensor.c) for z in depths]) @ sensor.R + sensor.pinhole
            world, image = np.concatenate([world, on]), np.concatenate([image, sensor.project(on)])
    a, b = pixel_map(sensor.role, f)
    ours = image * a + b
    rvec = cv2.Rodrigues(np.asarray(R, float))[0]
    theirs = cv2.projectPoints(world.reshape(-1, 1, 3), rvec, np.asarray(t, float).reshape(3, 1),
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
