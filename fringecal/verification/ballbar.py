"""The ball-bar verification of a calibrated rig (thesis section 6.9.3, VDI/VDE 2634).

A ball-bar (two spheres, certified centre distance) is placed so that one sphere is
seen by one scanner and the other by the next: its measured length then tests the
link between the scanners' frames that the calibration made. This module places the
bar (:func:`thesis_positions`, :func:`vdi7_positions`), builds its scene for the
virtual scanner, and measures the sphere a scanner sees in its maps: from a plan that
says which sphere it sees and where the other one is (:func:`measure_sphere`), or from
the data alone (:func:`find_sightings`, :func:`cluster_centres`, :func:`name_clusters`,
:func:`refit_sighting`, put together by :func:`fringecal.verification.measure.measure_position`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from fringecal.artefact import Artefact
from fringecal.frames import Frame
from fringecal.pointcloud import PointMaps
from fringecal.rig import Scanner
from fringecal.spheres.candidates import find_sphere_candidates
from fringecal.spheres.fit import FitError, SphereModel
from fringecal.spheres.pixel_integration import correct_sphere_points
from fringecal.spheres.regions import RegionPoints, boundary_flags, fit_region
from fringecal.spheres.robust import RejectionConfig, fit_sphere_robust

__all__ = ["BallBarPosition", "frame_along", "thesis_positions", "vdi7_positions", "ballbar_rods",
           "measure_sphere", "SphereMeasurement", "SightingConfig", "Sighting", "find_sightings",
           "cluster_centres", "name_clusters", "refit_sighting", "disc_pixels"]


@dataclass(frozen=True)
class BallBarPosition:
    """One placement of the bar: ``T_world_ballbar`` (sphere A at the local origin,
    B on the local +x axis) and which scanner sees which sphere."""

    name: str
    T_world_ballbar: Frame
    scanner_of: dict  # sphere id -> scanner name


def frame_along(a, b) -> Frame:
    """``T_world_bar`` with its origin at ``a`` and local +x towards ``b``.

    >>> T = frame_along([0, 0, 0], [0, 10, 0])
    >>> T.to_world([[5.0, 0, 0]]).round(12).tolist()
    [[0.0, 5.0, 0.0]]
    """
    a = np.asarray(a, float)
    u = np.asarray(b, float) - a
    u /= np.linalg.norm(u)
    helper = np.array([0.0, 0.0, 1.0]) if abs(u[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    v = np.cross(helper, u)
    v /= np.linalg.norm(v)
    w = np.cross(u, v)
    R = np.stack([u, v, w])  # rows: local axes in world; x_local = R (x_world - a)
    return Frame.from_matrix(R, a)


def thesis_positions(table_6_9: pd.DataFrame, scanners=("scanner1", "scanner2")) -> list[BallBarPosition]:
    """The nine positions of thesis table 6-9 (centres of A and B per measurement).

    The thesis's measured centres fix where the bar was; its direction and midpoint
    are kept and the bar is placed with its certified length by the artefact itself.
    """
    out = []
    for meas, g in table_6_9.groupby("measurement", sort=False):
        a = g[g.sphere_id == "A"][["x_mm", "y_mm", "z_mm"]].to_numpy(float)[0]
        b = g[g.sphere_id == "B"][["x_mm", "y_mm", "z_mm"]].to_numpy(float)[0]
        out.append(BallBarPosition(f"bb{int(meas):02d}" if str(meas).isdigit() else f"bb{meas}",
                                   frame_along(a, b), {"A": scanners[0], "B": scanners[1]}))
    return out


def vdi7_positions(reference: list[BallBarPosition], length_mm: float) -> list[BallBarPosition]:
    """Seven positions after VDI/VDE 2634's scheme, spanning two volumes side by side.

    The guideline puts the bar along the four space diagonals and three directions
    parallel to the axes of the measurement volume. With two scanners side by side
    and a bar longer than one scanner's field, every position spans both volumes:
    four join opposite corners (in height and depth) of the regions where the
    ``reference`` positions put spheres A and B, and three run level across the
    middle and at the lowest and highest heights. Sphere B is then placed at the
    bar's length from A.
    """
    A = np.array([p.T_world_ballbar.t for p in reference])
    B = np.array([p.T_world_ballbar.to_world([[length_mm, 0, 0]])[0] for p in reference])
    lo_a, hi_a = A.min(0), A.max(0)
    lo_b, hi_b = B.min(0), B.max(0)
    mid_a, mid_b = (lo_a + hi_a) / 2, (lo_b + hi_b) / 2
    pick = lambda lo, hi, sy, sz, mid: np.array([mid[0], (lo if sy < 0 else hi)[1] if sy else mid[1],  # noqa: E731
                                                 (lo if sz < 0 else hi)[2] if sz else mid[2]])
    pairs = [(pick(lo_a, hi_a, -1, -1, mid_a), pick(lo_b, hi_b, 1, 1, mid_b)),
             (pick(lo_a, hi_a, 1, -1, mid_a), pick(lo_b, hi_b, -1, 1, mid_b)),
             (pick(lo_a, hi_a, -1, 1, mid_a), pick(lo_b, hi_b, 1, -1, mid_b)),
             (pick(lo_a, hi_a, 1, 1, mid_a), pick(lo_b, hi_b, -1, -1, mid_b)),
             (mid_a, mid_b),
             (pick(lo_a, hi_a, -1, 0, mid_a), pick(lo_b, hi_b, -1, 0, mid_b)),
             (pick(lo_a, hi_a, 1, 0, mid_a), pick(lo_b, hi_b, 1, 0, mid_b))]
    scanners = reference[0].scanner_of
    return [BallBarPosition(f"vdi{i + 1}", frame_along(a, b), dict(scanners)) for i, (a, b) in enumerate(pairs)]


def ballbar_rods(artefact: Artefact) -> pd.DataFrame:
    """The bar's tube as a rods table (one rod joining its two spheres)."""
    a, b = artefact.ids[:2]
    return pd.DataFrame({"rod_id": ["bar"], "sphere_a": [a], "sphere_b": [b], "length_mm": [0.0]})


@dataclass(frozen=True)
class SphereMeasurement:
    """The centre of the one bar sphere a scanner saw, with its fit statistics."""

    centre: np.ndarray
    radius_mm: float
    rms_mm: float
    n_points: int
    rejected: dict
    pixels: tuple | None = field(default=None, repr=False)  # (rows, cols) of the kept points


def measure_sphere(maps: PointMaps, valid, camera, projector, radius_mm: float, rod_axis=None,
                   rejection_config: RejectionConfig | None = None, fixed_radius: bool = True,
                   pixel_integration_px: float = 1.0) -> SphereMeasurement:
    """Find and fit the (single) bar sphere in a measurement's maps.

    The strongest sphere candidate of the bar's radius is fitted robustly; with
    ``rod_axis`` (unit direction from this sphere to the other, in the maps' frame)
    the tube and its end cap are masked by a cone, as for the artefact. The kept
    points are then corrected for pixel integration and fitted again, as
    :func:`refit_sighting` does.

    Raises
    ------
    FitError
        No sphere of that radius in the measurement, or too few clean points.
    """
    cands = find_sphere_candidates(maps, radius_mm, camera.pinhole)
    if not cands:
        raise FitError(f"no sphere of radius {radius_mm:.3f} mm found")
    best = max(cands, key=lambda c: c.votes)
    axes = None if rod_axis is None else np.asarray(rod_axis, float).reshape(1, 3)
    rf = fit_region(maps, best.region, radius_mm if fixed_radius else None, expected_radius=radius_mm,
                    flag_maps={"edge": boundary_flags(valid)}, viewpoints=[camera.pinhole, projector.pinhole],
                    rod_axes=axes, config=rejection_config)
    m = rf.fit.model
    if pixel_integration_px > 0:
        px, kept = rf.pixels, rf.fit.kept
        uv = np.stack([px.cols[kept], px.rows[kept]], axis=-1).astype(float)
        points, ok = correct_sphere_points(Scanner(camera.name, camera, projector), uv, px.points[kept], m.centre,
                                           float(m.radius), pixel_integration_px)
        m = SphereModel.from_estimate(points[ok], radius=radius_mm if fixed_radius else None)
    return SphereMeasurement(np.asarray(m.centre, float), float(m.radius), float(m.rms), int(m.n_points),
                             dict(rf.fit.rejected))


# -- measuring a position from the data alone ------------------------------------------


@dataclass(frozen=True)
class SightingConfig:
    """What counts as a sighting of a bar sphere, and how the two spheres are named.

    Attributes
    ----------
    radius_tolerance : float
        A candidate's free-radius fit must lie within this fraction of one of the bar's
        certified radii. 0.1 (2.5 mm for the thesis bar) is about three times the
        worst free-fit error of a whole sphere in the simulated thesis rig at 320 px
        (0.7-0.9 mm; RMS 0.27 mm, at 768 px 0.03 mm); end caps and tubes (10.9 mm)
        and planes fail it by far.
    min_disc_fraction : float
        The fit must keep at least this fraction of the pixels of the sphere's full
        disc in the camera (:func:`disc_pixels`). A whole sphere keeps 0.5-0.6 of them
        at 320 px and 0.7-0.8 at 768 px (edge pixels and the rim go), one cut in half
        by the image border about half that; a sliver at the border is no sighting.
        Unlike a point count this does not depend on the camera's resolution;
        ``RejectionConfig.min_points`` applies as well.
    distinct_diameter_mm : float
        Certified diameters that differ by more than this name the spheres by their
        fitted radii (mean free-fit radius of each sphere's sightings, paired with the
        certified radii the closer way). For 1 mm the pairing flips only if the two
        free-fit errors differ by 0.5 mm the wrong way: never seen at 768 px, possible
        at 320 px. Below it the spheres count as alike and are named by order
        (:func:`name_clusters`).
    pixel_integration_px : float
        The refit's points are corrected for the integration of each pixel over the
        sphere (:func:`fringecal.spheres.pixel_integration.correct_sphere_points`, the
        correction the control points get; the footprint in pixels, 0 switches it off):
        uncorrected, the points lie tens of um behind the surface at 512 px, more where
        the light comes in obliquely, which shifts the centre along the view.
    """

    radius_tolerance: float = 0.1
    min_disc_fraction: float = 0.25
    distinct_diameter_mm: float = 1.0
    pixel_integration_px: float = 1.0


@dataclass(frozen=True)
class Sighting:
    """One bar sphere in one scanner's measurement, found and fitted with a free radius.

    Attributes
    ----------
    scanner : str
    centre : ndarray, shape (3,)
        Free-radius fit, world mm.
    radius_mm, rms_mm : float
        Free-radius fit.
    n_points : int
        Points the free fit kept.
    column_px : float
        Mean camera column of the kept pixels (for naming, :func:`name_clusters`).
    pixels : RegionPoints
        The candidate region's points, refitted by :func:`refit_sighting`.
    viewpoints : ndarray, shape (2, 3)
        Camera and projector pinholes (silhouette test).
    sensors : Scanner or None
        The scanner that measured it, at the store's resolution (for the refit's
        pixel-integration correction; None: no correction).
    """

    scanner: str
    centre: np.ndarray
    radius_mm: float
    rms_mm: float
    n_points: int
    column_px: float
    pixels: RegionPoints = field(repr=False)
    viewpoints: np.ndarray = field(repr=False)
    sensors: Scanner | None = field(default=None, repr=False)


def disc_pixels(camera, centre, radius_mm: float) -> float:
    """Pixels of the full image disc of a sphere (``centre`` (3,), world mm) in ``camera``:
    ``pi rho^2`` with ``rho = c R / sqrt(d^2 - R^2)`` pixels at the centre's distance ``d``
    (the disc near the image centre; off-axis it grows slightly)."""
    d2 = float(np.sum((np.asarray(centre, float) - camera.pinhole) ** 2))
    fmt = camera.format
    pitch = np.sqrt(fmt.width_mm / fmt.width_px * fmt.height_mm / fmt.height_px)
    rho = camera.c * radius_mm / np.sqrt(max(d2 - radius_mm**2, 1e-9)) / pitch
    return float(np.pi * rho**2)


def _xyz(p) -> str:
    return "(" + ", ".join(f"{v:.1f}" for v in p) + ") mm"


def _implausible(model, radii, camera, cfg: SightingConfig) -> str | None:
    """Why a free fit is no bar sphere, or None."""
    off = np.abs(model.radius - radii) / radii
    if off.min() > cfg.radius_tolerance:
        return (f"fitted radius {model.radius:.3f} mm is not within {cfg.radius_tolerance:.0%} of the "
                f"certified {' or '.join(f'{r:.3f}' for r in np.unique(radii))} mm")
    disc = disc_pixels(camera, model.centre, float(radii[np.argmin(off)]))
    if model.n_points < cfg.min_disc_fraction * disc:
        return (f"{model.n_points} points kept, fewer than {cfg.min_disc_fraction:.0%} of the sphere's "
                f"{disc:.0f}-pixel disc (a sliver at the image border?)")
    return None


def find_sightings(maps: PointMaps, valid, scanner, ballbar: Artefact, rejection_config: RejectionConfig | None = None,
                   config: SightingConfig | None = None) -> tuple[list[Sighting], list[str]]:
    """The bar spheres one scanner sees in its maps, with no plan: 0, 1 or 2 sightings.

    Candidates of the bar's (median certified) radius are fitted robustly with a free
    radius; a fit is a sighting when its radius and point count are plausible
    (:class:`SightingConfig`).

    Parameters
    ----------
    maps : PointMaps
        The measurement triangulated with ``scanner`` (world mm), shape (rows, cols).
    valid : bool array, shape (rows, cols)
    scanner : Scanner
        Its camera format must match the maps.
    ballbar : Artefact
        The bar; its first two spheres are the bar's.

    Returns
    -------
    sightings : list of Sighting, strongest candidate first
    notes : list of str
        Why candidates were no sightings (or that none was found).
    """
    cfg = config or SightingConfig()
    radii = ballbar.radii[:2]
    search = float(np.median(radii))
    cam, proj = scanner.camera, scanner.projector
    cands = find_sphere_candidates(maps, search, cam.pinhole)
    if not cands:
        return [], [f"no sphere of radius {search:.3f} mm found"]
    flags = {"edge": boundary_flags(valid)}
    viewpoints = np.array([cam.pinhole, proj.pinhole])
    out, notes = [], []
    for c in cands:
        try:
            rf = fit_region(maps, c.region, None, expected_radius=search, flag_maps=flags, viewpoints=viewpoints,
                            config=rejection_config)
        except FitError as err:
            notes.append(f"candidate at {_xyz(c.centre)}: {err}")
            continue
        m = rf.fit.model
        why = _implausible(m, radii, cam, cfg)
        if why is not None:
            notes.append(f"candidate at {_xyz(m.centre)}: {why}")
            continue
        out.append(Sighting(scanner.name, np.asarray(m.centre, float), float(m.radius), float(m.rms),
                            int(m.n_points), float(rf.kept_pixels[1].mean()), rf.pixels, viewpoints, scanner))
    return out, notes


def cluster_centres(centres, link_mm: float) -> np.ndarray:
    """Single-linkage clusters of points: two closer than ``link_mm`` are one sphere.

    Parameters
    ----------
    centres : array_like, shape (n, 3)
    link_mm : float

    Returns
    -------
    ndarray of int, shape (n,)
        Cluster labels 0, 1, ... in order of first appearance.

    >>> cluster_centres([[0, 0, 0], [1000, 0, 0], [3, 0, 0], [1010, 0, 0]], 25.4).tolist()
    [0, 1, 0, 1]
    """
    c = np.asarray(centres, float).reshape(-1, 3)
    parent = list(range(len(c)))

    def root(i):
        while parent[i] != i:
            i = parent[i]
        return i

    close = np.linalg.norm(c[:, None] - c[None], axis=-1) < link_mm
    for i, j in zip(*np.nonzero(np.triu(close, 1))):
        parent[root(j)] = root(i)
    roots = [root(i) for i in range(len(c))]
    first = {r: k for k, r in enumerate(dict.fromkeys(roots))}
    return np.array([first[r] for r in roots], dtype=int)


def name_clusters(sightings: list[Sighting], labels, ballbar: Artefact, scanner_order,
                  config: SightingConfig | None = None) -> dict[int, str]:
    """Sphere ids of the two clusters of a position's sightings.

    If the bar's certified diameters differ by more than
    ``config.distinct_diameter_mm``, each cluster takes the id whose certified radius
    its mean free-fit radius matches (the closer pairing). Otherwise the spheres are
    alike and the names follow the data's order: the bar's first id goes to the
    sphere seen by the first scanner in ``scanner_order`` that sees any, and if that
    scanner sees both, to the one further left in its image (smaller mean camera
    column). A length (centre distance) does not depend on these names; with alike
    spheres a swap fixes a radius wrong by at most half the diameter difference.

    Parameters
    ----------
    sightings : list of Sighting
    labels : array_like of int, shape (len(sightings),)
        Exactly two distinct clusters (:func:`cluster_centres`).
    scanner_order : sequence of str
        The rig's scanners in order.

    Returns
    -------
    dict cluster label -> sphere id
    """
    cfg = config or SightingConfig()
    labels = np.asarray(labels)
    ids, radii = ballbar.ids[:2], ballbar.radii[:2]
    k0, k1 = sorted(set(labels.tolist()))
    if abs(ballbar.diameters[0] - ballbar.diameters[1]) > cfg.distinct_diameter_mm:
        fitted = [np.mean([s.radius_mm for s, lab in zip(sightings, labels) if lab == k]) for k in (k0, k1)]
        straight = abs(fitted[0] - radii[0]) + abs(fitted[1] - radii[1])
        swapped = abs(fitted[0] - radii[1]) + abs(fitted[1] - radii[0])
        first = k0 if straight <= swapped else k1
    else:
        rank = {name: i for i, name in enumerate(scanner_order)}
        order = sorted(range(len(sightings)),
                       key=lambda i: (rank.get(sightings[i].scanner, len(rank)), sightings[i].column_px))
        first = int(labels[order[0]])
    return {first: ids[0], (k1 if first == k0 else k0): ids[1]}


def refit_sighting(sighting: Sighting, radius_mm: float, rod_axis, rejection_config: RejectionConfig | None = None,
                   pixel_integration_px: float = 1.0) -> SphereMeasurement:
    """Refit a sighting's points with the certified radius fixed and the rod masked.

    ``rod_axis`` (3,) is the unit direction from this sphere towards the other one
    (world); a cone about it masks the tube and its end cap, as in
    :func:`measure_sphere`, which fits the same points the same way. With the
    sighting's ``sensors`` the kept points are then corrected for pixel integration
    against that fit (footprint ``pixel_integration_px``; the rim, whose bias cannot
    be predicted, left out) and fitted again.

    Raises
    ------
    FitError
        Too few clean points.
    """
    px = sighting.pixels
    fit = fit_sphere_robust(px.points, radius_mm, expected_radius=radius_mm, flags=px.flags,
                            viewpoints=sighting.viewpoints, rod_axes=np.asarray(rod_axis, float).reshape(1, 3),
                            config=rejection_config)
    m = fit.model
    rows, cols = px.rows[fit.kept], px.cols[fit.kept]
    if sighting.sensors is not None and pixel_integration_px > 0:
        uv = np.stack([cols, rows], axis=-1).astype(float)
        points, ok = correct_sphere_points(sighting.sensors, uv, px.points[fit.kept], m.centre, radius_mm,
                                           pixel_integration_px)
        m = SphereModel.from_estimate(points[ok], radius=radius_mm)
        rows, cols = rows[ok], cols[ok]
    return SphereMeasurement(np.asarray(m.centre, float), float(m.radius), float(m.rms), int(m.n_points),
                             dict(fit.rejected), (rows, cols))
