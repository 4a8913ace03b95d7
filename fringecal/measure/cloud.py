"""One registered point cloud from a measurement of several scanners.

Every valid camera pixel of every scanner's store (decoded phases ``tau_x``,
``tau_y``, ``valid``) is triangulated with that scanner's calibrated sensors in the
global frame (:func:`fringecal.pointcloud.triangulate_maps`, the compiled kernel the
pipeline uses). Per point the cloud keeps what a user filters and colours by:

=========== ===== =========================================================
field       dtype meaning
=========== ===== =========================================================
x, y, z     f4    world coordinates, mm (float32: 0.5 um steps at 4 m, far
                  below any scanner's noise)
scanner     u1    index into :attr:`Cloud.scanners`
measurement u2    index into :attr:`Cloud.measurements` (the folders measured)
u, v        u2    camera pixel (column, row) of the store
eps1        f4    signed closest-approach distance of the two rays, mm
modulation  f4    the weaker of the two orientations' fringe modulation (DN)
u_mm        f4    standard uncertainty of the point's position from the
                  calibration (3-D: sqrt of the trace of its covariance), mm;
                  NaN when the calibration carries no covariance
outside_    u1    1 where the point's camera pixel or its projector phases
observed_         lie outside the region of that sensor's image plane where
region            the calibration saw control points, else 0 (also where the
                  calibration file records no region, and for a black box's
                  points)
=========== ===== =========================================================

The last field is the calibration's observed region
(:class:`fringecal.lens.observed_region.ObservedRegion`, per sensor in
``calibration.json``): the model there is extrapolated, untested by any control point,
and a correction field may be far off. Such points are flagged, never dropped.

The uncertainty is the calibration's covariance (adjustment, artefact CMM and
artefact scale, :class:`fringecal.calibration.propagation.ParameterCovariances`) propagated
through the triangulation (:func:`fringecal.calibration.propagation.point_jacobian`).
``fringecal measure`` first moves it to the frame the sensors realise
(:func:`fringecal.calibration.propagation.frame_free_covariance`): the adjustment's
datum (one camera's exterior orientation held fixed) would otherwise add ~1 mm at
3.5 m that describes how the frame is defined, not the measurement. What is left is
the point's uncertainty relative to the rig (thesis rig, default run: 0.32-0.36 mm for
the ball-bar's centres at about 3 m, dominated by the orientation of the scanners,
1e-4 rad); distances between points, and thus lengths and shapes, are far better known
(the ball-bar's: 15-29 um over 1 m, :mod:`fringecal.measure.spheres`), because a common
orientation error cancels: a point's ``u_mm`` says nothing about them.
That costs 56 triangulations per point, so it is computed exactly on a grid of every
``UNCERTAINTY_STEP``-th pixel and interpolated bilinearly between the grid nodes that
lie on the same surface (within ``SAME_SURFACE_MM`` of the point); a pixel without
such a node (edges, small islands) gets its own exact value. The uncertainty changes
by well under 1 % over a few pixels of a surface (``tests/test_measure.py`` checks the
interpolation against the exact value everywhere). The phase noise of the pixel itself
is not in ``u_mm``: it is the measurement's own (its size shows in ``eps1``).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from fringecal.calibration.propagation import point_variances, scanner_block
from fringecal.lens.observed_region import ObservedRegion, outside
from fringecal.pointcloud import triangulate_maps
from fringecal.rig import Rig, Scanner
from fringecal.verification.measure import store_scanner

__all__ = ["POINT_DTYPE", "Cloud", "MeasureSettings", "scanner_points", "measure_cloud", "point_uncertainty",
           "UNCERTAINTY_STEP", "SAME_SURFACE_MM", "OUTSIDE", "outside_observed_region"]

POINT_DTYPE = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("scanner", "u1"), ("measurement", "<u2"),
                        ("u", "<u2"), ("v", "<u2"),
                        ("eps1", "<f4"), ("modulation", "<f4"), ("u_mm", "<f4"),
                        ("outside_observed_region", "u1")])
#: the field of :data:`POINT_DTYPE` that flags points outside the calibration's observed region
OUTSIDE = "outside_observed_region"

#: pixel spacing of the grid on which the uncertainty is computed exactly
UNCERTAINTY_STEP = 4
#: a grid node within this distance of a point lies on its surface (mm)
SAME_SURFACE_MM = 5.0


@dataclass(frozen=True)
class MeasureSettings:
    """``decimate``: keep every n-th pixel in rows and columns (1 keeps all);
    ``max_eps1_mm``: drop points whose rays pass farther apart (None keeps all);
    ``uncertainty``: compute ``u_mm`` (needs the calibration's covariance)."""

    decimate: int = 1
    max_eps1_mm: float | None = None
    uncertainty: bool = True

    def __post_init__(self):
        if int(self.decimate) != self.decimate or self.decimate < 1:
            raise ValueError(f"decimate must be a whole number >= 1, got {self.decimate}")
        if self.max_eps1_mm is not None and not (np.isfinite(self.max_eps1_mm) and self.max_eps1_mm > 0):
            raise ValueError(f"max_eps1_mm must be a finite length > 0, got {self.max_eps1_mm}")


@dataclass(frozen=True)
class Cloud:
    """Points (structured array of :data:`POINT_DTYPE`, shape (n,)), the scanner names
    their ``scanner`` field indexes and the measurement names of ``measurement``."""

    points: np.ndarray
    scanners: tuple[str, ...]
    measurements: tuple[str, ...] = ("",)

    def __len__(self) -> int:
        return len(self.points)

    def xyz(self, scanner: str | None = None) -> np.ndarray:
        """Coordinates (n, 3) in mm, float64; of one scanner if named."""
        p = self.points if scanner is None else self.points[self.points["scanner"] == self.scanners.index(scanner)]
        return np.stack([p["x"], p["y"], p["z"]], axis=-1).astype(float)

    def counts(self) -> dict[str, int]:
        n = np.bincount(self.points["scanner"], minlength=len(self.scanners))
        return {s: int(n[i]) for i, s in enumerate(self.scanners)}


def outside_observed_region(scanner: Scanner, regions: Mapping[str, ObservedRegion] | None, cam_mm,
                            prj_mm) -> np.ndarray:
    """Whether each point, seen at camera image-plane ``cam_mm`` (n, 2) and projector
    image-plane ``prj_mm`` (n, 2), lies outside the observed region of its camera or of
    its projector (``regions``: sensor name -> region) -> bool (n,). A sensor without a
    region (not known) flags nothing."""
    return outside(regions, ((scanner.camera.name, cam_mm), (scanner.projector.name, prj_mm)))


def point_uncertainty(scanner: Scanner, cov28: np.ndarray, tau_x, tau_y, rows, cols) -> np.ndarray:
    """Exact standard uncertainty (n,) in mm (sqrt of the covariance's trace) of the
    points at pixels (rows, cols) of a store with phases ``tau_x``, ``tau_y`` (maps);
    ``cov28`` (28, 28) the scanner's parameter covariance (camera 14, projector 14)."""
    return np.sqrt(point_variances(scanner, cov28, tau_x, tau_y, rows, cols).sum(axis=1))


def _interpolated_uncertainty(scanner, cov28, tau_x, tau_y, xyz, keep, step: int) -> np.ndarray:
    """``u_mm`` map (rows, cols), NaN outside ``keep``: exact on the grid nodes, bilinear
    between nodes on the same surface, exact where no node is."""
    h, w = keep.shape
    out = np.full((h, w), np.nan)
    node = np.zeros_like(keep)
    node[::step, ::step] = True
    node &= keep
    r, c = np.nonzero(node)
    out[r, c] = point_uncertainty(scanner, cov28, tau_x, tau_y, r, c)
    r, c = np.nonzero(keep & ~node)
    if r.size == 0:
        return out
    r0, c0 = (r // step) * step, (c // step) * step
    fr, fc = (r - r0) / step, (c - c0) / step
    num = np.zeros(r.size)
    den = np.zeros(r.size)
    p = xyz[:, r, c]
    for dr, dc, wgt in ((0, 0, (1 - fr) * (1 - fc)), (0, step, (1 - fr) * fc), (step, 0, fr * (1 - fc)),
                        (step, step, fr * fc)):
        rn, cn = r0 + dr, c0 + dc
        inside = (rn < h) & (cn < w)
        rn, cn = np.where(inside, rn, 0), np.where(inside, cn, 0)
        ok = inside & node[rn, cn] & (np.linalg.norm(xyz[:, rn, cn] - p, axis=0) <= SAME_SURFACE_MM) & (wgt > 0)
        num += np.where(ok, wgt * np.nan_to_num(out[rn, cn]), 0.0)
        den += np.where(ok, wgt, 0.0)
    has = den > 0
    out[r[has], c[has]] = num[has] / den[has]
    lone = ~has
    out[r[lone], c[lone]] = point_uncertainty(scanner, cov28, tau_x, tau_y, r[lone], c[lone])
    return out


def scanner_points(scanner: Scanner, index: int, store, settings: MeasureSettings = MeasureSettings(),
                   cov28: np.ndarray | None = None, measurement: int = 0,
                   regions: Mapping[str, ObservedRegion] | None = None) -> np.ndarray:
    """The points (structured array of :data:`POINT_DTYPE`) of one scanner's store.

    Parameters
    ----------
    scanner : the calibrated scanner, its camera at the store's image size
    index, measurement : the values of the ``scanner`` and ``measurement`` fields
    store : mapping with ``tau_x``, ``tau_y``, ``valid`` and ``modulation_x``,
        ``modulation_y`` maps, shape (rows, cols) (an opened store or an in-memory
        decoded measurement)
    cov28 : (28, 28) covariance of the scanner's parameters, or None (``u_mm`` NaN)
    regions : sensor name -> its observed region (``outside_observed_region``; None or
        a sensor missing: nothing flagged)
    """
    tau_x = np.asarray(store["tau_x"])
    tau_y = np.asarray(store["tau_y"])
    valid = np.asarray(store["valid"], bool)
    maps = triangulate_maps(scanner.camera, scanner.projector, tau_x, tau_y, valid)
    keep = maps.valid
    if settings.decimate > 1:
        grid = np.zeros_like(keep)
        grid[::settings.decimate, ::settings.decimate] = True
        keep &= grid
    if settings.max_eps1_mm is not None:
        keep &= np.abs(maps.eps1) <= settings.max_eps1_mm
    rows, cols = np.nonzero(keep)
    pts = np.empty(rows.size, POINT_DTYPE)
    pts["x"], pts["y"], pts["z"] = maps.x[rows, cols], maps.y[rows, cols], maps.z[rows, cols]
    pts["scanner"] = index
    pts["measurement"] = measurement
    pts["u"], pts["v"] = cols, rows
    pts["eps1"] = maps.eps1[rows, cols]
    mod = np.minimum(np.asarray(store["modulation_x"])[rows, cols], np.asarray(store["modulation_y"])[rows, cols])
    pts["modulation"] = mod
    if regions:  # a calibration without regions flags nothing: no image-plane coordinates needed
        cam_mm = scanner.camera.image_mm(np.stack([cols, rows], axis=-1))
        prj_mm = scanner.projector.image_mm(np.stack([tau_x[rows, cols], tau_y[rows, cols]], axis=-1))
        pts[OUTSIDE] = outside_observed_region(scanner, regions, cam_mm, prj_mm)
    else:
        pts[OUTSIDE] = 0
    if cov28 is None or not settings.uncertainty:
        pts["u_mm"] = np.nan
    else:
        xyz = np.stack([maps.x, maps.y, maps.z])
        step = max(1, UNCERTAINTY_STEP // settings.decimate) * settings.decimate
        pts["u_mm"] = _interpolated_uncertainty(scanner, cov28, tau_x, tau_y, xyz, keep, step)[rows, cols]
    return pts


def measure_cloud(rig: Rig, stores: Mapping[str, object], settings: MeasureSettings = MeasureSettings(),
                  covariance: np.ndarray | None = None, measurement: int = 0,
                  regions: Mapping[str, ObservedRegion] | None = None) -> Cloud:
    """One cloud of every scanner's store of one measurement.

    Parameters
    ----------
    rig : the calibration; each store's scanner must be in it, cameras are resampled
        to the store's image size when that differs (a binned camera)
    stores : scanner name -> store (see :func:`scanner_points`)
    covariance : (14 n_sensors, 14 n_sensors) covariance of every sensor parameter in
        rig order (``ParameterCovariances.total``), or None
    measurement : the value of the points' ``measurement`` field
    regions : sensor name -> its observed region
        (:attr:`fringecal.calibration.file.Calibration.observed_regions`), or None
    """

    names = tuple(s.name for s in rig.scanners)
    unknown = sorted(set(stores) - set(names))
    if unknown:
        raise KeyError(f"scanner(s) {unknown} are not in the calibration ({list(names)})")
    parts = []
    for i, name in enumerate(names):
        if name not in stores:
            continue
        ds = stores[name]
        scanner = store_scanner(ds, rig.scanner(name))
        cov28 = None if covariance is None else scanner_block(covariance, rig, name)
        parts.append(scanner_points(scanner, i, ds, settings, cov28, measurement, regions))
    return Cloud(np.concatenate(parts) if parts else np.empty(0, POINT_DTYPE), names)
