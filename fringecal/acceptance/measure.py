"""The values of one acceptance measurement: a sphere (P_F, P_S) or a flat (F) in one
scanner's store, from the data alone.

The dumbbell (SD) and the ball-bar (E) are lengths between two sphere centres and are
measured by the ball-bar code (:func:`fringecal.verification.measure.measure_positions`);
:mod:`fringecal.acceptance.evaluate` gathers all of them.

Decisions (VDI/VDE 2634 part 2 evaluates "the measured points" of the object; which
points belong to the object is the evaluator's segmentation, stated here):

- **Sphere**: the store is triangulated with the scanner's calibrated sensors (at the
  store's image size) and the sphere found like a ball-bar sphere
  (:func:`fringecal.verification.ballbar.find_sightings`, robust free-radius fit, which here only
  locates it: a far noisy sphere counts if it kept 5 % of its disc). Its points are
  every valid pixel whose point lies within ``segment_mm`` of that robust sphere,
  that is not an edge pixel (within 2 px of an invalid pixel, where a pixel mixes the
  surface with the background) and that the camera and the projector see at an
  incidence of at most ``max_incidence_deg`` (the grazing rim, where pixel
  integration biases the phase, thesis chapter 5). ``segment_mm`` (2 mm by default)
  is 40 times the thesis rig's noise: it separates the sphere from its surroundings
  and removes nothing a scanner measures on it.
- **Flat**: the largest plane of valid points (RANSAC with ``segment_mm`` inlier
  distance, seeded, 8-connected image region of the inliers); a plane whose region
  spans more than 1.2 times the flat's diagonal is a backdrop or a table and is set
  aside for the next largest. Edge pixels, pixels within ``FLAT_RIM_PX`` (2 px) of the
  region's border (a side face of the flat the camera sees joins the face there) and
  pixels seen at more than ``max_incidence_deg`` are left out as for the sphere.
- Then, for both: a least-squares fit (free radius; total least squares plane), the
  ``exclude_fraction`` of points with the largest residuals removed, half from each
  end (the 0.3 % of the guideline), the fit repeated on the points kept, and the
  range of its residuals is P_F or F. P_S is the fitted diameter minus the calibrated.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from scipy import ndimage

from fringecal.acceptance.standards import FlatStandard, SphereStandard
from fringecal.artefact import Artefact
from fringecal.rig import Scanner
from fringecal.spheres.fit import FitError, PlaneModel, SphereModel
from fringecal.spheres.regions import boundary_flags
from fringecal.verification.ballbar import SightingConfig, find_sightings
from fringecal.verification.measure import store_maps

__all__ = ["SphereMeasurement", "FlatMeasurement", "trim_by_residual", "probe_sphere", "probe_flat",
           "measure_sphere_store", "measure_flat_store", "AcceptanceMeasurementError"]

#: Distance (mm) from the robust object within which points belong to it.
SEGMENT_MM = 2.0
#: A plane region longer than this many flat diagonals is not the flat.
BACKDROP_FACTOR = 1.2
#: Pixels of the flat's image region this close to its border are left out: where the
#: face meets a side face the camera sees, points within ``segment_mm`` of the plane
#: belong to the side face (a strip narrower than a pixel at 768 px).
FLAT_RIM_PX = 2
#: The robust fit only locates the sphere (its points are then taken by distance): a
#: far, noisy sphere whose robust fit keeps few of its disc's pixels is still found.
LOCATE = SightingConfig(min_disc_fraction=0.05)


class AcceptanceMeasurementError(ValueError):
    """The object was not found in a store, or too few of its points remain."""


@dataclass(frozen=True)
class SphereMeasurement:
    """P_F and P_S of one sphere measurement (mm), with the fit they come from."""

    centre: np.ndarray
    diameter_mm: float
    form_mm: float  # P_F: range of the radial residuals after the exclusion
    size_mm: float  # P_S: fitted minus calibrated diameter
    diameter_u_fit_mm: float
    rms_mm: float
    n_points: int
    n_excluded: int

    def to_dict(self) -> dict:
        d = asdict(self)
        d["centre"] = [float(c) for c in self.centre]
        return d


@dataclass(frozen=True)
class FlatMeasurement:
    """F of one flat measurement (mm), with the plane it comes from."""

    normal: np.ndarray
    point: np.ndarray
    flatness_mm: float  # F: range of the signed residuals after the exclusion
    rms_mm: float
    n_points: int
    n_excluded: int
    extent_mm: tuple[float, float]

    def to_dict(self) -> dict:
        d = asdict(self)
        d["normal"] = [float(c) for c in self.normal]
        d["point"] = [float(c) for c in self.point]
        d["extent_mm"] = [float(e) for e in self.extent_mm]
        return d


def trim_by_residual(residuals, exclude_fraction: float) -> np.ndarray:
    """Boolean mask (n,) keeping all but the ``floor(f n / 2)`` lowest and as many
    highest residuals (the guideline's outlier exclusion, symmetric).

    >>> trim_by_residual([0.0, 5.0, -1.0, 0.5, -7.0, 0.1], 0.34).tolist()
    [True, False, True, True, False, True]
    """
    r = np.asarray(residuals, float)
    k = int(np.floor(exclude_fraction * len(r) / 2))
    keep = np.ones(len(r), bool)
    if k:
        order = np.argsort(r, kind="stable")
        keep[order[:k]] = False
        keep[order[len(r) - k:]] = False
    return keep


def probe_sphere(points, standard: SphereStandard, exclude_fraction: float = 0.003) -> SphereMeasurement:
    """P_F and P_S of the points (n, 3) of one sphere measurement (mm).

    Examples
    --------
    A sphere of diameter 50 mm with a +-10 um form (a 2-lobe wave), measured exactly:
    P_F is the wave's 20 um range, P_S the 0.02 mm of a 25.01 mm radius.

    >>> rng = np.random.default_rng(0)
    >>> u = rng.normal(size=(20000, 3)); u /= np.linalg.norm(u, axis=1, keepdims=True)
    >>> u = u[u[:, 2] > 0.2]
    >>> r = 25.01 + 0.010 * np.cos(2 * np.arctan2(u[:, 1], u[:, 0]))
    >>> m = probe_sphere([0, 0, 2000.0] + r[:, None] * u, SphereStandard(diameter_mm=50.0), 0.0)
    >>> round(m.form_mm, 3), round(m.size_mm, 3)
    (0.02, 0.02)
    """
    p = np.asarray(points, float)
    if len(p) < 10:
        raise AcceptanceMeasurementError(f"sphere: {len(p)} points, need at least 10")
    first = SphereModel.from_estimate(p)
    keep = trim_by_residual(np.linalg.norm(p - first.centre, axis=1) - first.radius, exclude_fraction)
    fit = SphereModel.from_estimate(p[keep]) if not keep.all() else first
    r = np.linalg.norm(p[keep] - fit.centre, axis=1) - fit.radius
    diameter = 2 * float(fit.radius)
    return SphereMeasurement(np.asarray(fit.centre, float), diameter, float(r.max() - r.min()),
                             diameter - standard.diameter_mm, 2 * float(np.sqrt(fit.covariance[3, 3])),
                             float(fit.rms), int(keep.sum()), int((~keep).sum()))


def probe_flat(points, exclude_fraction: float = 0.003, toward=None) -> FlatMeasurement:
    """F of the points (n, 3) of one flat measurement (mm).

    Examples
    --------
    A 400 x 60 mm flat with a 5 um bow, plus two outliers at +-50 um which the 0.3 %
    exclusion of 2000 points (3 from each end) removes:

    >>> rng = np.random.default_rng(1)
    >>> st = rng.uniform([-200, -30], [200, 30], (2000, 2))
    >>> z = 0.005 * (st[:, 0] / 200) ** 2
    >>> z[:2] = [0.05, -0.05]
    >>> round(probe_flat(np.c_[st, z] + [0, 0, 2500.0], 0.003).flatness_mm, 3)
    0.005
    >>> round(probe_flat(np.c_[st, z] + [0, 0, 2500.0], 0.0).flatness_mm, 3)
    0.1
    """
    p = np.asarray(points, float)
    if len(p) < 10:
        raise AcceptanceMeasurementError(f"flat: {len(p)} points, need at least 10")
    first = PlaneModel.from_estimate(p, toward=toward)
    keep = trim_by_residual((p - first.point) @ first.normal, exclude_fraction)
    fit = PlaneModel.from_estimate(p[keep], toward=toward) if not keep.all() else first
    r = (p[keep] - fit.point) @ fit.normal
    inplane = (p[keep] - fit.point) @ fit.axes.T
    extent = tuple(float(e) for e in inplane.max(axis=0) - inplane.min(axis=0))
    return FlatMeasurement(np.asarray(fit.normal, float), np.asarray(fit.point, float), float(r.max() - r.min()),
                           float(fit.rms), int(keep.sum()), int((~keep).sum()), extent)


# -- from a store -----------------------------------------------------------------------------


def _points(store, scanner: Scanner):
    """The store's scanner, maps, usable pixels, points (rows, cols, 3) and the usable
    pixels that are no edge pixels."""
    scanner, maps, valid = store_maps(store, scanner)
    ok = maps.valid & valid
    xyz = np.stack([maps.x, maps.y, maps.z], axis=-1)
    return scanner, maps, ok, xyz, ok & ~boundary_flags(ok)


def _incidence_ok(points, normals, scanner: Scanner, max_incidence_deg: float) -> np.ndarray:
    """Whether camera and projector both see each point (n, 3) with its unit normal
    (n, 3) at an incidence of at most ``max_incidence_deg``."""
    cos_max = np.cos(np.radians(max_incidence_deg))
    ok = np.ones(len(points), bool)
    for sensor in (scanner.camera, scanner.projector):
        v = sensor.pinhole - points
        ok &= np.abs(np.einsum("ij,ij->i", normals, v)) >= cos_max * np.linalg.norm(v, axis=1)
    return ok


def measure_sphere_store(store, scanner: Scanner, standard: SphereStandard, exclude_fraction: float = 0.003,
                         max_incidence_deg: float = 70.0, rejection_config=None,
                         segment_mm: float = SEGMENT_MM) -> SphereMeasurement:
    """P_F and P_S of the sphere in one store, measured with ``scanner`` (world frame).

    Raises
    ------
    AcceptanceMeasurementError
        No sphere of the standard's diameter in the store.
    """
    scanner, maps, ok, xyz, inner = _points(store, scanner)
    sphere = Artefact(("S",), np.zeros((1, 3)), [standard.diameter_mm])
    found, notes = find_sightings(maps, ok, scanner, sphere, rejection_config, LOCATE)
    if not found:
        raise AcceptanceMeasurementError(f"{store}: no sphere of diameter {standard.diameter_mm:g} mm found "
                                         f"({'; '.join(notes)})")
    s = found[0]
    p = xyz[inner]
    near = np.abs(np.linalg.norm(p - s.centre, axis=1) - s.radius_mm) <= segment_mm
    p = p[near]
    normals = (p - s.centre) / np.linalg.norm(p - s.centre, axis=1, keepdims=True)
    p = p[_incidence_ok(p, normals, scanner, max_incidence_deg)]
    try:
        return probe_sphere(p, standard, exclude_fraction)
    except (FitError, AcceptanceMeasurementError) as err:
        raise AcceptanceMeasurementError(f"{store}: sphere: {err}") from None


def _largest_plane(p: np.ndarray, rng, segment_mm: float, trials: int = 300):
    """Inlier mask (n,) of the plane through the most points of ``p`` (n, 3)."""
    best, best_n = None, -1
    n = len(p)
    for _ in range(trials):
        a, b, c = p[rng.choice(n, 3, replace=False)]
        normal = np.cross(b - a, c - a)
        norm = np.linalg.norm(normal)
        if norm < 1e-9:
            continue
        inl = np.abs((p - a) @ (normal / norm)) <= segment_mm
        k = int(inl.sum())
        if k > best_n:
            best, best_n = inl, k
    return best


def measure_flat_store(store, scanner: Scanner, standard: FlatStandard, exclude_fraction: float = 0.003,
                       max_incidence_deg: float = 70.0, segment_mm: float = SEGMENT_MM, seed: int = 0,
                       max_planes: int = 3) -> FlatMeasurement:
    """F of the flat in one store, measured with ``scanner`` (world frame).

    Raises
    ------
    AcceptanceMeasurementError
        No plane region of the flat's size in the store.
    """
    scanner, maps, ok, xyz, inner = _points(store, scanner)
    rng = np.random.default_rng(seed)
    candidates = ok.copy()
    diagonal = float(np.hypot(standard.length_mm, standard.width_mm))
    for _ in range(max_planes):
        rows, cols = np.nonzero(candidates)
        if len(rows) < 10:
            break
        p = xyz[rows, cols]
        inl = _largest_plane(p, rng, segment_mm)
        if inl is None:
            break
        mask = np.zeros_like(ok)
        mask[rows[inl], cols[inl]] = True
        labels, count = ndimage.label(mask, structure=np.ones((3, 3), bool))
        if count == 0:
            break
        region = labels == (1 + int(np.argmax(ndimage.sum(mask, labels, range(1, count + 1)))))
        pts = xyz[region]
        plane = PlaneModel.from_estimate(pts, toward=scanner.camera.pinhole)
        span = (pts - plane.point) @ plane.axes.T
        if float(np.linalg.norm(span.max(axis=0) - span.min(axis=0))) > BACKDROP_FACTOR * diagonal:
            candidates &= ~region
            continue
        sel = ndimage.binary_erosion(region, np.ones((3, 3), bool), iterations=FLAT_RIM_PX) & inner
        q = xyz[sel]
        q = q[_incidence_ok(q, np.broadcast_to(plane.normal, q.shape), scanner, max_incidence_deg)]
        try:
            return probe_flat(q, exclude_fraction, toward=scanner.camera.pinhole)
        except (FitError, AcceptanceMeasurementError) as err:
            raise AcceptanceMeasurementError(f"{store}: flat: {err}") from None
    raise AcceptanceMeasurementError(f"{store}: no plane region of the flat's size ({standard.length_mm:g} x "
                                     f"{standard.width_mm:g} mm) found")
