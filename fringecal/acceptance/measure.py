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
  and removes nothing a scanner measures on it. The points are then corrected for the
  pixel integration over the sphere (as the control points and the ball-bar's are,
  :func:`fringecal.spheres.pixel_integration.correct_sphere_points`).
- **Flat**: the largest plane of valid points (RANSAC with ``segment_mm`` inlier
  distance, seeded, 8-connected image region of the inliers); a plane whose region
  spans more than 1.2 times the flat's diagonal is a backdrop or a table and is set
  aside for the next largest. Edge pixels, pixels within ``FLAT_RIM_PX`` (2 px) of the
  region's border (a side face of the flat the camera sees joins the face there) and
  pixels seen at more than ``max_incidence_deg`` are left out as for the sphere.
- Then, for both: a least-squares fit (free radius; total least squares plane), the
  ``exclude_fraction`` of points with the largest residuals removed, half from each
  end (the 0.3 % of the guideline), the fit repeated on the points kept, and the
  range of its residuals is P_F or F.
- **P_S** is the fitted diameter minus the calibrated, the diameter of a free-radius
  sphere fitted to the same kept points **along the camera's lines of sight**
  (:func:`sphere_along_rays`) when the camera is known. A fringe-projection point is
  noisy along the camera ray through its pixel (the phase moves it along that ray,
  the pixel does not move), not across it. The guideline's orthogonal (Gaussian)
  fit of a partial cap treats that noise as if it were radial: near the rim it
  moves the points sideways, the fit's centre slides toward the camera and the
  radius shrinks. On the demo's far positions (3.6 m, 0.4 mm RMS along the rays)
  that bias is -0.11 mm of diameter, while the points themselves are unbiased; the
  fit along the rays, whose residual is each point's distance along its ray to the
  sphere, is the maximum-likelihood fit of that noise and has no such bias
  (docs/acceptance.md, *P_S at the far positions*). The orthogonal fit's diameter
  is kept beside it (``diameter_orthogonal_mm``).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, replace

import numpy as np
from scipy import ndimage
from scipy.optimize import least_squares

from fringecal.acceptance.standards import FlatStandard, SphereStandard
from fringecal.artefact import Artefact
from fringecal.rig import Scanner
from fringecal.spheres.fit import FitError, PlaneModel, SphereModel
from fringecal.spheres.pixel_integration import correct_sphere_points
from fringecal.spheres.regions import boundary_flags
from fringecal.verification.ballbar import SightingConfig, find_sightings
from fringecal.verification.measure import store_maps

__all__ = ["SphereMeasurement", "FlatMeasurement", "RaySphere", "trim_by_residual", "sphere_along_rays",
           "probe_sphere", "probe_flat", "largest_plane",
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
    """P_F and P_S of one sphere measurement (mm), with the fits they come from.

    ``centre``, ``diameter_mm`` and ``diameter_u_fit_mm`` are those of the fit that
    gives P_S (along the camera rays when the camera is known, else the orthogonal
    one); ``diameter_orthogonal_mm`` (and its ``diameter_u_orthogonal_mm``) is the
    guideline's orthogonal fit's, whose residuals give P_F and ``rms_mm``."""

    centre: np.ndarray
    diameter_mm: float
    form_mm: float  # P_F: range of the radial residuals after the exclusion
    size_mm: float  # P_S: fitted minus calibrated diameter
    diameter_u_fit_mm: float
    rms_mm: float
    n_points: int
    n_excluded: int
    diameter_orthogonal_mm: float = float("nan")
    diameter_u_orthogonal_mm: float = float("nan")
    fit: str = "orthogonal"  # the fit P_S comes from: "orthogonal" or "along camera rays"
    # (rows, cols) of the camera pixels of the points the fit kept (the exclusion applied);
    # None: measured without pixels (a cloud)
    pixels: tuple | None = field(default=None, repr=False, compare=False)

    def to_dict(self) -> dict:
        d = asdict(replace(self, pixels=None))
        del d["pixels"]
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
    # (rows, cols) of the camera pixels of the points the fit kept, as for a sphere
    pixels: tuple | None = field(default=None, repr=False, compare=False)

    def to_dict(self) -> dict:
        d = asdict(replace(self, pixels=None))
        del d["pixels"]
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


@dataclass(frozen=True)
class RaySphere:
    """A sphere fitted along lines of sight: centre (3,), radius and its standard
    uncertainty (heteroscedasticity-consistent: the noise along a ray differs from
    point to point), RMS of the residuals along the rays (mm)."""

    centre: np.ndarray
    radius: float
    radius_u: float
    rms_along_rays: float


def sphere_along_rays(points, origin, centre, radius: float) -> RaySphere:
    """The least-squares sphere of ``points`` (n, 3) whose residual is each point's
    distance along its line of sight from ``origin`` (the camera's projection centre)
    to the sphere's near surface: the maximum-likelihood sphere when the points are
    noisy along their rays only. ``centre`` and ``radius`` start it (the orthogonal fit).

    A ray that misses the sphere (never, near the optimum, for points seen at an
    incidence below 90 degrees) is measured to its closest approach.

    Raises
    ------
    FitError
        Fewer than 5 points, or the fit does not converge.

    Examples
    --------
    A cap of a 127 mm sphere seen from 3.6 m, its points exactly on the sphere, started
    from a sphere 2 mm off: the fit finds it (``tests/test_acceptance_values.py`` shows
    that, with noise along the rays, the orthogonal fit is biased and this one is not).

    >>> u = np.random.default_rng(3).normal(size=(3000, 3)); u /= np.linalg.norm(u, axis=1, keepdims=True)
    >>> u = u[u[:, 2] < -np.cos(np.radians(64))]                # the cap facing the camera
    >>> s = sphere_along_rays([0.0, 0.0, 3600.0] + 63.5 * u, np.zeros(3), [1.0, 1.0, 3601.0], 62.5)
    >>> (np.round(s.centre, 6) + 0.0).tolist(), round(s.radius, 6), s.rms_along_rays < 1e-9
    ([0.0, 0.0, 3600.0], 63.5, True)
    """
    p = np.asarray(points, float)
    if len(p) < 5:
        raise FitError(f"sphere along rays: {len(p)} points, need at least 5")
    o = np.asarray(origin, float)
    v = p - o
    t = np.linalg.norm(v, axis=1)
    d = v / t[:, None]

    def _parts(x):
        c, r = x[:3], x[3]
        b = d @ (c - o)
        s = np.sqrt(np.maximum(b * b - (float(np.sum((o - c) ** 2)) - r * r), 1e-12))
        return c, r, b, s

    def residuals(x):
        _, _, b, s = _parts(x)
        return t - (b - s)

    def jacobian(x):
        c, r, b, s = _parts(x)
        return np.column_stack([-(d - (b[:, None] * d - (c - o)) / s[:, None]), r / s])

    fit = least_squares(residuals, np.r_[np.asarray(centre, float), float(radius)], jac=jacobian, method="lm",
                        xtol=1e-12, ftol=1e-12)
    if not fit.success:
        raise FitError(f"sphere along rays: no convergence ({fit.message})")
    # the noise along a ray grows toward the rim (less light, oblique incidence), where the
    # radius also moves a point most: the heteroscedasticity-consistent covariance (HC1)
    J, r = fit.jac, fit.fun
    try:
        A = np.linalg.inv(J.T @ J)
    except np.linalg.LinAlgError:
        raise FitError("sphere along rays: singular normal equations") from None
    cov = A @ (J.T * r ** 2) @ J @ A * len(p) / max(len(p) - 4, 1)
    return RaySphere(fit.x[:3].copy(), float(fit.x[3]), float(np.sqrt(max(cov[3, 3], 0.0))),
                     float(np.sqrt(np.mean(fit.fun ** 2))))


def probe_sphere(points, standard: SphereStandard, exclude_fraction: float = 0.003,
                 origin=None, pixels=None) -> SphereMeasurement:
    """P_F and P_S of the points (n, 3) of one sphere measurement (mm); ``origin``: the
    projection centre of the camera that measured them (P_S then comes from the fit
    along its rays, :func:`sphere_along_rays`; None: from the orthogonal fit);
    ``pixels``: (rows, cols) of the points' camera pixels, of which the measurement
    keeps those of the points the fit kept (:attr:`SphereMeasurement.pixels`).

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
    orthogonal = 2 * float(fit.radius)
    centre, diameter, u = np.asarray(fit.centre, float), orthogonal, 2 * float(np.sqrt(fit.covariance[3, 3]))
    how = "orthogonal"
    if origin is not None:
        rays = sphere_along_rays(p[keep], origin, fit.centre, fit.radius)
        centre, diameter, u, how = rays.centre, 2 * rays.radius, 2 * rays.radius_u, "along camera rays"
    return SphereMeasurement(centre, diameter, float(r.max() - r.min()), diameter - standard.diameter_mm, u,
                             float(fit.rms), int(keep.sum()), int((~keep).sum()), orthogonal,
                             2 * float(np.sqrt(fit.covariance[3, 3])), how, _kept(pixels, keep))


def _kept(pixels, keep: np.ndarray) -> tuple | None:
    """(rows, cols) of ``pixels`` where ``keep``; None without pixels."""
    if pixels is None:
        return None
    rows, cols = (np.asarray(a, np.int64) for a in pixels)
    if len(rows) != len(keep) or len(cols) != len(keep):
        raise ValueError(f"{len(rows)} pixel rows and {len(cols)} columns for {len(keep)} points")
    return rows[keep], cols[keep]


def probe_flat(points, exclude_fraction: float = 0.003, toward=None, pixels=None) -> FlatMeasurement:
    """F of the points (n, 3) of one flat measurement (mm); ``pixels`` as for
    :func:`probe_sphere`.

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
                           float(fit.rms), int(keep.sum()), int((~keep).sum()), extent, _kept(pixels, keep))


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
                         segment_mm: float = SEGMENT_MM, pixel_integration_px: float = 1.0) -> SphereMeasurement:
    """P_F and P_S of the sphere in one store, measured with ``scanner`` (world frame).

    The points are corrected for each pixel's integration over the sphere against the
    located sphere (:func:`fringecal.spheres.pixel_integration.correct_sphere_points`,
    footprint ``pixel_integration_px``, 0: none; the rim, whose bias cannot be
    predicted, left out): uncorrected they lie behind the surface, which reads as a
    size error P_S.

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
    rows, cols = np.nonzero(inner)
    p = xyz[rows, cols]
    near = np.abs(np.linalg.norm(p - s.centre, axis=1) - s.radius_mm) <= segment_mm
    p, rows, cols = p[near], rows[near], cols[near]
    normals = (p - s.centre) / np.linalg.norm(p - s.centre, axis=1, keepdims=True)
    seen = _incidence_ok(p, normals, scanner, max_incidence_deg)
    p, rows, cols = p[seen], rows[seen], cols[seen]
    if pixel_integration_px > 0:
        p, ok = correct_sphere_points(scanner, np.stack([cols, rows], axis=-1), p, s.centre, s.radius_mm,
                                      pixel_integration_px)
        p, rows, cols = p[ok], rows[ok], cols[ok]
    try:
        return probe_sphere(p, standard, exclude_fraction, origin=scanner.camera.pinhole, pixels=(rows, cols))
    except (FitError, AcceptanceMeasurementError) as err:
        raise AcceptanceMeasurementError(f"{store}: sphere: {err}") from None


def largest_plane(p: np.ndarray, rng, segment_mm: float, trials: int = 300):
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
        inl = largest_plane(p, rng, segment_mm)
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
        rows, cols = np.nonzero(sel)  # the order of xyz[sel]
        q = xyz[rows, cols]
        seen = _incidence_ok(q, np.broadcast_to(plane.normal, q.shape), scanner, max_incidence_deg)
        try:
            return probe_flat(q[seen], exclude_fraction, toward=scanner.camera.pinhole,
                              pixels=(rows[seen], cols[seen]))
        except (FitError, AcceptanceMeasurementError) as err:
            raise AcceptanceMeasurementError(f"{store}: flat: {err}") from None
    raise AcceptanceMeasurementError(f"{store}: no plane region of the flat's size ({standard.length_mm:g} x "
                                     f"{standard.width_mm:g} mm) found")
