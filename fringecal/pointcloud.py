"""Point clouds from phase maps: every valid camera pixel triangulated (section 2.3.3).

For each camera pixel (u, v) with decoded projector phases (tau_x, tau_y) the camera
ray and the projector ray are intersected by closest approach, exactly as
:func:`fringecal.triangulation.triangulate` does, giving maps ``x, y, z`` (world mm)
and the signed ``eps1`` (mm) of the same shape as the camera image.

What is cached and why
----------------------
A measurement of a 2048 x 2048 camera has four million pixels, so the work per
pixel must be small. The camera's *ideal* image coordinates (undistorted, relative
to the principal point) depend only on the camera's format, principal point and
distortion, not on its pose nor on the measurement, so :class:`CameraRayCache`
computes them once per camera (Newton per pixel, once) and every measurement then
only rotates them into the world. Keeping them in the camera frame (16 bytes per
pixel) rather than as world directions (24 bytes) means the cache also survives
changes of the camera's exterior orientation and principal distance (a
bundle-adjustment iteration, a frame change) and costs less memory traffic.
The projector's ideal coordinates depend on the measured phases and are solved by
Newton per pixel inside the fused kernel, started from the first-order inverse
``m - d(m)``: two steps leave an error below 1e-14 mm on the image plane for the
thesis lenses (the last step is below 1e-7 mm; convergence is quadratic), pixels
that need more get them. The two pinholes, rotations and the baseline are per
measurement constants.

The fused kernel (numba, parallel over rows, compiled once and cached on disk)
reads tau_x, tau_y and the valid mask and writes the four outputs in one pass; its
pixel loop is branch-free so LLVM vectorises it (it is compute-bound: ~10x the time
of streaming the same bytes, and ~60x faster than the numpy reference).
Sensors with thin-prism terms or a correction field (:mod:`fringecal.sensor`) go
through the same kernels:
their image points are first replaced by the points the sensor without the terms maps
to the same rays (:meth:`fringecal.sensor.Sensor.brown_image_mm`, numpy, once per
camera and per projector block; the 14-parameter path is untouched).
Pixels that are invalid, NaN, on (near-)parallel rays (less than 1e-6 rad apart)
or where the projector's distortion model cannot be inverted come out as NaN, each
with its status code.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from dataclasses import dataclass

import numba as nb
import numpy as np

from fringecal.lens.inversion import first_order_inverse, newton_step
from fringecal.sensor import Sensor

__all__ = [
    "provenance",
    "triangulate_image_points",
    "CameraRayCache",
    "PointMaps",
    "camera_ray_cache",
    "triangulate_maps",
    "triangulate_rows",
]

_NEWTON_STEP_MM = 1e-7
# sin^2 of the angle between the rays below which they count as parallel (1e-6 rad):
# the depth of such a "point" is meaningless (thesis rig: ~25 deg, sin^2 ~ 0.18).
_PARALLEL_DEN = 1e-12
_UNDISTORT_MAX_ITER = 30
# Reassociation and reciprocal multiplication let LLVM vectorise the pixel loop;
# no "nnan"/"ninf", so NaN inputs still propagate and are detected.
_FASTMATH = {"contract", "arcp", "nsz", "reassoc"}

#: status codes written per pixel by the kernel
STATUS_OK, STATUS_INVALID, STATUS_UNDISTORT_FAILED, STATUS_PARALLEL = 0, 1, 2, 3
_STATUS_RETRY = 4


@nb.njit(cache=True, fastmath=_FASTMATH)
def _undistort_point(mx, my, k1, k2, k3, p1, p2):
    """Newton for u + d(u) = m to convergence. Returns (x, y, ok).

    Stops once a step is below ``_NEWTON_STEP_MM`` (1e-7 mm): convergence is
    quadratic, so the error left is about C * step^2 with C = |f''| / (2 |f'|),
    ~0.01 mm^-1 for the thesis lenses and < 1 mm^-1 for far worse ones, i.e. below
    1e-14 mm on the image plane. Refuses fold-overs as the reference does.
    """
    x, y = first_order_inverse(mx, my, k1, k2, k3, p1, p2)
    step, det, tr = np.inf, 1.0, 1.0
    for _ in range(_UNDISTORT_MAX_ITER):
        x, y, step, det, tr = newton_step(x, y, mx, my, k1, k2, k3, p1, p2)
        if step <= _NEWTON_STEP_MM:
            break
    return x, y, step <= _NEWTON_STEP_MM and det > 0 and tr > 0


@nb.njit(parallel=True, cache=True)
def _ideal_grid(width, height, sx, sy, xi_h, eta_h, k1, k2, k3, p1, p2, out):
    """Ideal coordinates of every pixel (eq. 2-21, then undistort), out (2, h, w)."""
    bad = 0
    for v in nb.prange(height):
        ym = (v / (height - 1) - 0.5) * sy - eta_h
        for u in range(width):
            xm = (u / (width - 1) - 0.5) * sx - xi_h
            x, y, ok = _undistort_point(xm, ym, k1, k2, k3, p1, p2)
            out[0, v, u] = x if ok else np.nan
            out[1, v, u] = y if ok else np.nan
            bad += 0 if ok else 1
    return bad


@nb.njit(parallel=True, cache=True)
def _ideal_points(xm, ym, k1, k2, k3, p1, p2, out):
    """:func:`_ideal_grid` of given image points relative to the principal point (h, w)."""
    bad = 0
    for v in nb.prange(xm.shape[0]):
        for u in range(xm.shape[1]):
            x, y, ok = _undistort_point(xm[v, u], ym[v, u], k1, k2, k3, p1, p2)
            ok = ok and xm[v, u] == xm[v, u]
            out[0, v, u] = x if ok else np.nan
            out[1, v, u] = y if ok else np.nan
            bad += 0 if ok else 1
    return bad


@nb.njit(cache=True, inline="always", fastmath=_FASTMATH)
def _ray_pair(ix, iy, px, py, Rc, c_cam, o1, Rp, c_prj, o2):
    """Camera ray from ideal (ix, iy), projector ray from ideal (px, py), both
    R^T (-x, -y, c) normalised; closest approach as
    fringecal.triangulation.closest_approach. Returns (X, Y, Z, eps1, ok)."""
    lx, ly, lz = -ix, -iy, c_cam
    d1x = Rc[0, 0] * lx + Rc[1, 0] * ly + Rc[2, 0] * lz
    d1y = Rc[0, 1] * lx + Rc[1, 1] * ly + Rc[2, 1] * lz
    d1z = Rc[0, 2] * lx + Rc[1, 2] * ly + Rc[2, 2] * lz
    n1 = 1.0 / np.sqrt(d1x * d1x + d1y * d1y + d1z * d1z)
    d1x *= n1
    d1y *= n1
    d1z *= n1
    lx, ly, lz = -px, -py, c_prj
    d2x = Rp[0, 0] * lx + Rp[1, 0] * ly + Rp[2, 0] * lz
    d2y = Rp[0, 1] * lx + Rp[1, 1] * ly + Rp[2, 1] * lz
    d2z = Rp[0, 2] * lx + Rp[1, 2] * ly + Rp[2, 2] * lz
    n2 = 1.0 / np.sqrt(d2x * d2x + d2y * d2y + d2z * d2z)
    d2x *= n2
    d2y *= n2
    d2z *= n2
    bx = o2[0] - o1[0]
    by = o2[1] - o1[1]
    bz = o2[2] - o1[2]
    a = d1x * d1x + d1y * d1y + d1z * d1z
    b = d1x * d2x + d1y * d2y + d1z * d2z
    c = d2x * d2x + d2y * d2y + d2z * d2z
    d = -(d1x * bx + d1y * by + d1z * bz)
    e = -(d2x * bx + d2y * by + d2z * bz)
    den = a * c - b * b
    nx = d1y * d2z - d1z * d2y
    ny = d1z * d2x - d1x * d2z
    nz = d1x * d2y - d1y * d2x
    nn = np.sqrt(nx * nx + ny * ny + nz * nz)
    iden = 1.0 / den
    s1 = (b * e - c * d) * iden
    s2 = (a * e - b * d) * iden
    X = 0.5 * ((o1[0] + s1 * d1x) + (o2[0] + s2 * d2x))
    Y = 0.5 * ((o1[1] + s1 * d1y) + (o2[1] + s2 * d2y))
    Z = 0.5 * ((o1[2] + s1 * d1z) + (o2[2] + s2 * d2z))
    E = (bx * nx + by * ny + bz * nz) / nn
    return X, Y, Z, E, den > _PARALLEL_DEN and nn > 0.0


@nb.njit(parallel=True, cache=True, fastmath=_FASTMATH)
def _triangulate_kernel(ideal_x, ideal_y, tau_x, tau_y, valid, Rc, c_cam, o1,
                        Rp, c_prj, xi_hp, eta_hp, kp, pp, phase_scale, o2,
                        out_x, out_y, out_z, out_e, status):
    """Fused per-pixel triangulation, parallel over rows.

    The first loop over a row is branch-free (two Newton steps for every pixel,
    results selected by flags) so LLVM vectorises it; the few pixels whose
    projector undistortion needs more steps are finished by the scalar loop after.
    """
    rows, cols = tau_x.shape
    k1, k2, k3 = kp[0], kp[1], kp[2]
    p1, p2 = pp[0], pp[1]
    sx, sy = phase_scale[0], phase_scale[1]
    nan = np.nan
    for r in nb.prange(rows):
        retry = 0
        for j in range(cols):
            tx = np.float64(tau_x[r, j])
            ty = np.float64(tau_y[r, j])
            ix = ideal_x[r, j]
            iy = ideal_y[r, j]
            mx = tx * sx - xi_hp
            my = ty * sy - eta_hp
            x, y = first_order_inverse(mx, my, k1, k2, k3, p1, p2)
            x, y, step, det, tr = newton_step(x, y, mx, my, k1, k2, k3, p1, p2)
            x, y, step, det, tr = newton_step(x, y, mx, my, k1, k2, k3, p1, p2)
            X, Y, Z, E, rays_ok = _ray_pair(ix, iy, x, y, Rc, c_cam, o1, Rp, c_prj, o2)
            inputs = valid[r, j] and tx == tx and ty == ty and ix == ix
            converged = step <= _NEWTON_STEP_MM and det > 0 and tr > 0
            good = inputs and converged and rays_ok
            out_x[r, j] = X if good else nan
            out_y[r, j] = Y if good else nan
            out_z[r, j] = Z if good else nan
            out_e[r, j] = E if good else nan
            status[r, j] = 0 if good else (1 if not inputs else (_STATUS_RETRY if not converged else 3))
            retry += 1 if inputs and not converged else 0
        if retry == 0:
            continue
        for j in range(cols):
            if status[r, j] != _STATUS_RETRY:
                continue
            mx = np.float64(tau_x[r, j]) * sx - xi_hp
            my = np.float64(tau_y[r, j]) * sy - eta_hp
            x, y, ok = _undistort_point(mx, my, k1, k2, k3, p1, p2)
            if not ok:
                status[r, j] = 2
                continue
            X, Y, Z, E, rays_ok = _ray_pair(ideal_x[r, j], ideal_y[r, j], x, y, Rc, c_cam, o1, Rp, c_prj, o2)
            if not rays_ok:
                status[r, j] = 3
                continue
            out_x[r, j] = X
            out_y[r, j] = Y
            out_z[r, j] = Z
            out_e[r, j] = E
            status[r, j] = 0


@dataclass(frozen=True)
class CameraRayCache:
    """Ideal image coordinates of every pixel of one camera, shape (2, rows, cols), mm.

    ``ideal[0]`` and ``ideal[1]`` are the undistorted x and y relative to the
    principal point (planar, so the kernel reads them with vector loads).

    Depends only on the camera's format, principal point and distortion (not on its
    pose nor its principal distance), so one cache serves every measurement of the
    camera and every exterior orientation tried for it. ``key`` identifies those
    parameters.
    """

    key: bytes
    ideal: np.ndarray
    n_unrayable: int = 0

    @classmethod
    def for_camera(cls, camera: Sensor) -> "CameraRayCache":
        if camera.role != "camera":
            raise ValueError(f"sensor {camera.name!r} is a {camera.role}, not a camera")
        f = camera.format
        ideal = np.empty((2, f.height_px, f.width_px))
        k, p = camera.k, camera.p
        if camera.beyond_brown:
            # thin-prism terms or a correction field: the pixel grid through the 14-parameter model's equivalent
            # image points (Sensor.brown_image_mm), then the same compiled Newton
            v, u = np.mgrid[0:f.height_px, 0:f.width_px]
            grid = camera.brown_image_mm(camera.format.pixel_to_mm(np.stack([u, v], axis=-1)))
            xm = np.ascontiguousarray(grid[..., 0] - camera.principal_point[0])
            ym = np.ascontiguousarray(grid[..., 1] - camera.principal_point[1])
            bad = _ideal_points(xm, ym, k[0], k[1], k[2], p[0], p[1], ideal)
        else:
            bad = _ideal_grid(f.width_px, f.height_px, f.width_mm, f.height_mm,
                              camera.principal_point[0], camera.principal_point[1],
                              k[0], k[1], k[2], p[0], p[1], ideal)
        # Pixels where the lens model folds over (none for real lenses) get no ray:
        # they stay NaN and every measurement reports them as invalid.
        ideal.setflags(write=False)
        return cls(_interior_key(camera), ideal, int(bad))

    def matches(self, camera: Sensor) -> bool:
        return self.key == _interior_key(camera)


def _interior_key(camera: Sensor) -> bytes:
    f = camera.format
    head = np.array([f.width_px, f.height_px, f.width_mm, f.height_mm], float)
    # principal point and distortion; not c, which only enters the kernel's (-x, -y, c)
    p = np.asarray(camera.params, float)
    key = head.tobytes() + np.r_[p[6:8], p[9:14]].tobytes()
    if camera.has_prism:
        key += camera.prism.tobytes()
    if camera.has_field:
        key += np.r_[camera.field.degree, camera.field.coefficients].tobytes()
    return key


_CACHE: "OrderedDict[bytes, CameraRayCache]" = OrderedDict()
_CACHE_LOCK = threading.Lock()
_CACHE_SIZE = 4  # a 2048 x 2048 camera takes 64 MiB


def camera_ray_cache(camera: Sensor) -> CameraRayCache:
    """The (process-wide, least-recently-used) ray cache of ``camera``'s interior."""
    key = _interior_key(camera)
    with _CACHE_LOCK:
        hit = _CACHE.get(key)
        if hit is not None:
            _CACHE.move_to_end(key)
            return hit
    cache = CameraRayCache.for_camera(camera)
    with _CACHE_LOCK:
        _CACHE[key] = cache
        while len(_CACHE) > _CACHE_SIZE:
            _CACHE.popitem(last=False)
    return cache


@dataclass(frozen=True)
class PointMaps:
    """Triangulated maps, each shape (rows, cols): world x, y, z and signed eps1 (mm).

    ``status`` (uint8) per pixel: 0 triangulated, 1 invalid input (mask, NaN phase
    or no camera ray), 2 projector distortion not invertible, 3 parallel rays.
    """

    x: np.ndarray
    y: np.ndarray
    z: np.ndarray
    eps1: np.ndarray
    status: np.ndarray

    @property
    def valid(self) -> np.ndarray:
        return self.status == STATUS_OK

    @property
    def n_points(self) -> int:
        return int(np.count_nonzero(self.status == STATUS_OK))

    def counts(self) -> dict[str, int]:
        """Pixels per outcome: triangulated, invalid, undistort_failed, parallel_rays."""
        c = np.bincount(self.status.ravel(), minlength=4)
        return {"triangulated": int(c[0]), "invalid": int(c[1]),
                "undistort_failed": int(c[2]), "parallel_rays": int(c[3])}

    def points(self, mask=None) -> np.ndarray:
        """Points (n, 3) of the valid pixels (and ``mask``), row-major order."""
        keep = self.valid if mask is None else self.valid & mask
        return np.stack([self.x[keep], self.y[keep], self.z[keep]], axis=-1).astype(float)


def _as_map(a, name, shape=None):
    a = np.asarray(a)
    if a.ndim != 2:
        raise ValueError(f"{name} must be a (rows, cols) map, got shape {a.shape}")
    if shape is not None and a.shape != shape:
        raise ValueError(f"{name} has shape {a.shape}, expected {shape}")
    return a


def triangulate_rows(camera: Sensor, projector: Sensor, tau_x, tau_y, valid, row0: int = 0,
                     cache: CameraRayCache | None = None, dtype=np.float64, out: PointMaps | None = None) -> PointMaps:
    """Triangulate a block of full-width camera rows starting at row ``row0``.

    Parameters
    ----------
    camera, projector : Sensor
        The scanner's sensors (14 parameters each, same world frame).
    tau_x, tau_y : array_like, shape (rows, cols)
        Decoded projector phases in rad (float32 or float64, NaN allowed) for camera
        rows ``row0 .. row0 + rows - 1``; ``cols`` is the camera width.
    valid : array_like of bool, shape (rows, cols)
        Pixels to triangulate (the decoder's mask); the others come out NaN.
    row0 : int
        First camera row of the block (for chunked processing of a store).
    cache : CameraRayCache, optional
        The camera's ray cache; by default the process-wide one.
    dtype : float32 or float64
        Output dtype. Computation is float64 either way.
    out : PointMaps, optional
        Preallocated outputs of the block's shape and ``dtype`` (written in place).

    Returns
    -------
    PointMaps
    """
    tau_x = _as_map(tau_x, "tau_x")
    tau_y = _as_map(tau_y, "tau_y", tau_x.shape)
    valid = _as_map(valid, "valid", tau_x.shape).astype(bool, copy=False)
    rows, cols = tau_x.shape
    if cache is None:
        cache = camera_ray_cache(camera)
    elif not cache.matches(camera):
        raise ValueError(f"the ray cache was built for another interior orientation than camera {camera.name!r}")
    h, w = cache.ideal.shape[1:]
    if cols != w or row0 < 0 or row0 + rows > h:
        raise ValueError(f"rows {row0}..{row0 + rows - 1} x {cols} columns do not fit camera "
                         f"{camera.name!r} of {h} x {w} pixels")
    if tau_x.dtype not in (np.float32, np.float64):
        tau_x = tau_x.astype(np.float64)
    if tau_y.dtype != tau_x.dtype:
        tau_y = tau_y.astype(tau_x.dtype)
    if out is None:
        out = PointMaps(*(np.empty((rows, cols), dtype) for _ in range(4)), np.empty((rows, cols), np.uint8))
    f = projector.format
    phase_scale = np.array([f.width_mm, f.height_mm]) / (2 * np.pi)
    if projector.beyond_brown:  # the phases the projector without its extra terms would give
        tau = f.mm_to_phase(projector.brown_image_mm(f.phase_to_mm(np.stack([tau_x, tau_y], axis=-1))))
        tau_x, tau_y = tau[..., 0].astype(tau_x.dtype), tau[..., 1].astype(tau_x.dtype)
    # Each argument must be C-contiguous: a strided view compiles to a kernel that
    # LLVM does not vectorise (7x slower). Row blocks of the planar cache are.
    _triangulate_kernel(
        cache.ideal[0, row0:row0 + rows], cache.ideal[1, row0:row0 + rows],
        np.ascontiguousarray(tau_x), np.ascontiguousarray(tau_y),
        np.ascontiguousarray(valid), camera.R, camera.c, np.array(camera.pinhole),
        projector.R, projector.c, float(projector.principal_point[0]), float(projector.principal_point[1]),
        np.array(projector.k), np.array(projector.p), phase_scale, np.array(projector.pinhole),
        out.x, out.y, out.z, out.eps1, out.status,
    )
    return out


def triangulate_maps(camera: Sensor, projector: Sensor, tau_x, tau_y, valid=None,
                     cache: CameraRayCache | None = None, dtype=np.float64, row_chunk: int = 256) -> PointMaps:
    """Triangulate a whole measurement, block by block of ``row_chunk`` rows.

    ``tau_x``, ``tau_y`` and ``valid`` are (rows, cols) maps of the full camera image
    (numpy arrays or anything sliceable, such as zarr arrays: only one block is read
    at a time). ``valid`` defaults to "phases are finite".

    Examples
    --------
    >>> from fringecal.rig import load_rig
    >>> from fringecal.config import thesis_dir
    >>> from fringecal.triangulation import triangulate
    >>> s = load_rig(thesis_dir() / "sensors_refined_table6-8.csv").scanners[0]
    >>> X = np.array([[-100.0, 50.0, 0.0]])
    >>> uv = s.camera.measured(s.camera.project(X))[0]      # the pixel seeing X
    >>> tau = s.projector.measured(s.projector.project(X))[0]
    >>> tx = np.full((2048, 2048), np.nan); ty = tx.copy()
    >>> tx[1000, 1000], ty[1000, 1000] = tau                # phases at one pixel
    >>> m = triangulate_maps(s.camera, s.projector, tx, ty)
    >>> p, e = triangulate(s.camera, s.projector, [1000, 1000], tau)
    >>> bool(np.allclose([m.x[1000, 1000], m.y[1000, 1000], m.z[1000, 1000]], p, atol=1e-9, rtol=0))
    True
    >>> m.n_points
    1
    """
    h, w = tau_x.shape
    out = PointMaps(*(np.empty((h, w), dtype) for _ in range(4)), np.empty((h, w), np.uint8))
    if cache is None:
        cache = camera_ray_cache(camera)
    for r0 in range(0, h, row_chunk):
        r1 = min(h, r0 + row_chunk)
        tx = np.asarray(tau_x[r0:r1])
        ty = np.asarray(tau_y[r0:r1])
        ok = np.isfinite(tx) & np.isfinite(ty) if valid is None else np.asarray(valid[r0:r1])
        block = PointMaps(out.x[r0:r1], out.y[r0:r1], out.z[r0:r1], out.eps1[r0:r1], out.status[r0:r1])
        triangulate_rows(camera, projector, tx, ty, ok, row0=r0, cache=cache, dtype=dtype, out=block)
    return out


def provenance(camera: Sensor, projector: Sensor) -> dict:
    """JSON-native record of how maps were triangulated, for a store's attributes:
    both sensors' 14 parameters and formats, and the method."""

    def sensor(s: Sensor) -> dict:
        f = s.format
        return {"name": s.name, "role": s.role, "params": s.as_dict(),
                "format": {"width_px": f.width_px, "height_px": f.height_px,
                           "width_mm": f.width_mm, "height_mm": f.height_mm}}

    return {"camera": sensor(camera), "projector": sensor(projector),
            "method": "midpoint of closest approach; eps1 signed (o_p - o_c) . (d_c x d_p)/|d_c x d_p| "
                      "(fringecal.triangulation); projector undistorted by Newton to a step < 1e-7 mm",
            "units": {"x": "mm", "y": "mm", "z": "mm", "eps1": "mm"}}


@nb.njit(cache=True, fastmath=_FASTMATH)
def _triangulate_points_kernel(cam_mm, prj_mm, Rc, c_cam, o1, cam_int, Rp, c_prj, o2, prj_int, out):
    """Closest-approach midpoints of (n, 2) camera and projector image-plane mm;
    ``*_int`` = (xi_h, eta_h, k1, k2, k3, p1, p2). NaN where a point does not undistort
    or the rays are parallel."""
    for i in range(cam_mm.shape[0]):
        ix, iy, ok1 = _undistort_point(cam_mm[i, 0] - cam_int[0], cam_mm[i, 1] - cam_int[1], cam_int[2], cam_int[3],
                                       cam_int[4], cam_int[5], cam_int[6])
        px, py, ok2 = _undistort_point(prj_mm[i, 0] - prj_int[0], prj_mm[i, 1] - prj_int[1], prj_int[2], prj_int[3],
                                       prj_int[4], prj_int[5], prj_int[6])
        X, Y, Z, _, ok = _ray_pair(ix, iy, px, py, Rc, c_cam, o1, Rp, c_prj, o2)
        good = ok1 and ok2 and ok
        out[i, 0] = X if good else np.nan
        out[i, 1] = Y if good else np.nan
        out[i, 2] = Z if good else np.nan


def triangulate_image_points(camera: Sensor, projector: Sensor, cam_mm, prj_mm) -> np.ndarray:
    """Points (n, 3) world mm of camera and projector image-plane coordinates (n, 2) mm:
    :func:`fringecal.triangulation.triangulate` for a list of observations in one compiled
    loop (NaN where the model does not invert or the rays are parallel). Used where the
    same points are triangulated with many parameter sets (Monte Carlo, derivatives).
    """
    cam_mm = np.ascontiguousarray(camera.brown_image_mm(cam_mm), float).reshape(-1, 2)
    prj_mm = np.ascontiguousarray(projector.brown_image_mm(prj_mm), float).reshape(-1, 2)
    out = np.empty((len(cam_mm), 3))
    interior = lambda s: np.ascontiguousarray(np.r_[s.params[6:8], s.params[9:14]])  # noqa: E731
    _triangulate_points_kernel(cam_mm, prj_mm, np.ascontiguousarray(camera.R), camera.c,
                               np.ascontiguousarray(camera.pinhole), interior(camera),
                               np.ascontiguousarray(projector.R), projector.c,
                               np.ascontiguousarray(projector.pinhole), interior(projector), out)
    return out
