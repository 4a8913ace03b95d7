"""Sphere candidates in an unorganised point cloud (a black-box scanner's), fitted with
the same robust fit as the candidates of a point map.

A point map's candidates come from its pixel neighbourhoods; a cloud has none, so they
come from normal voting in space: the cloud is thinned to one point per cube of edge
``radius / 4`` (the mean of its points), each thinned point's normal is the smallest
principal direction of its 12 nearest neighbours, turned toward the scanner (the
origin of the cloud's frame: the scanner sees the outside of a sphere), and the point
votes for a centre one radius behind it. A sphere's votes pile up in the cube of its
centre, a plane's or a rod's spread over a surface; every cube holding at least
``min_votes`` votes and the most of its neighbourhood (within one radius) is a
candidate. Each candidate's points -- every point of the full cloud within 1.25 radii
of the voted centre -- are fitted by :func:`fringecal.spheres.robust.fit_sphere_robust`
(rod and residual rejection, free radius), and the fit becomes a
:class:`fringecal.schemas.SphereFitsTable` row with its centre's standard uncertainties
from the fit's residuals (the black-box scanner's measured noise).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from fringecal.schemas import SphereFitsTable
from fringecal.spheres.fit import FitError
from fringecal.spheres.poses_and_links import sphere_fit_row
from fringecal.spheres.robust import RejectionConfig, fit_sphere_robust

__all__ = ["CloudCandidateConfig", "cloud_sphere_fits", "vote_centres", "refit_cloud_sphere"]


@dataclass(frozen=True)
class CloudCandidateConfig:
    """Normal voting in a cloud (see the module notes).

    ``cell_fraction``: thinning cube and vote cube edge in radii; ``neighbours``: points
    of each normal's local plane; ``min_votes``: votes a candidate needs;
    ``min_radius_ratio``, ``max_radius_ratio``: a fit's radius against the expected one;
    ``search_radii``: the points of a candidate lie within this many radii of its vote.
    """

    cell_fraction: float = 0.25
    neighbours: int = 12
    min_votes: int = 12
    min_radius_ratio: float = 0.8
    max_radius_ratio: float = 1.2
    search_radii: float = 1.25
    max_candidates: int = 400


def _cube_keys(points: np.ndarray, cell: float) -> np.ndarray:
    """One int64 per cube of edge ``cell`` (21 bits an axis: 2 million cubes across)."""
    q = np.floor(points / cell).astype(np.int64)
    q -= q.min(axis=0)
    return (q[:, 0] << 42) | (q[:, 1] << 21) | q[:, 2]


def _cube_means(points: np.ndarray, cell: float) -> tuple[np.ndarray, np.ndarray]:
    """The mean point and the point count of every occupied cube of edge ``cell``."""
    _, inverse, counts = np.unique(_cube_keys(points, cell), return_inverse=True, return_counts=True)
    sums = np.column_stack([np.bincount(inverse, points[:, i], len(counts)) for i in range(3)])
    return sums / counts[:, None], counts


def _thin(points: np.ndarray, cell: float) -> np.ndarray:
    """One point per occupied cube of edge ``cell``: the mean of its points."""
    return _cube_means(points, cell)[0]


def _normals(points: np.ndarray, k: int) -> np.ndarray:
    """Unit normals (n, 3) from the k nearest neighbours, turned toward the origin."""
    from scipy.spatial import cKDTree

    k = min(k, len(points))
    _, idx = cKDTree(points).query(points, k=k)
    nb = points[idx] - points[idx].mean(axis=1, keepdims=True)
    cov = np.einsum("nki,nkj->nij", nb, nb)
    _, vec = np.linalg.eigh(cov)
    n = vec[:, :, 0]
    flip = np.einsum("ni,ni->n", n, -points) < 0
    n[flip] *= -1
    return n


def vote_centres(points: np.ndarray, radius: float, config: CloudCandidateConfig = CloudCandidateConfig(),
                 normals: np.ndarray | None = None) -> np.ndarray:
    """Candidate sphere centres (m, 3) of a cloud, most votes first."""
    cell = config.cell_fraction * radius
    thin = _thin(points, cell)
    if len(thin) < config.neighbours:
        return np.zeros((0, 3))
    n = _normals(thin, config.neighbours)
    votes = thin - radius * n
    centres, counts = _cube_means(votes, cell)
    # a cube and its 26 neighbours: a centre's votes straddle cube borders
    from scipy.spatial import cKDTree

    strong = np.flatnonzero(counts >= max(2, config.min_votes // 4))
    if not len(strong):
        return np.zeros((0, 3))
    tree = cKDTree(centres[strong])
    pooled_counts = np.array([counts[strong[j]].sum() for j in tree.query_ball_point(centres[strong], r=1.5 * cell)])
    order = np.argsort(-pooled_counts, kind="stable")
    chosen: list[int] = []
    for i in order:
        if pooled_counts[i] < config.min_votes or len(chosen) >= config.max_candidates:
            break
        c = centres[strong[i]]
        if all(np.linalg.norm(c - centres[strong[j]]) > radius for j in chosen):
            chosen.append(int(i))
    return np.array([centres[strong[i]] for i in chosen]).reshape(-1, 3)


def cloud_sphere_fits(points: np.ndarray, measurement: str, scanner: str, radius: float,
                      config: CloudCandidateConfig = CloudCandidateConfig(),
                      rejection: RejectionConfig | None = None,
                      normals: np.ndarray | None = None) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Fitted sphere candidates of one cloud.

    Returns
    -------
    fits : DataFrame
        :class:`fringecal.schemas.SphereFitsTable` rows, ``sphere_id`` empty.
    failures : DataFrame
        ``candidate``, ``reason`` of the candidates that could not be fitted or whose
        radius is implausible.
    """
    rows, failures = [], []
    reach = config.search_radii * radius
    for k, centre in enumerate(vote_centres(points, radius, config, normals)):
        near = np.all(np.abs(points - centre) <= reach, axis=1)
        sel = points[near]
        sel = sel[np.linalg.norm(sel - centre, axis=1) <= reach]
        name = f"c{k + 1}"
        try:
            fit = fit_sphere_robust(sel, expected_radius=radius, viewpoints=np.zeros((1, 3)), config=rejection)
        except (FitError, ValueError) as err:
            failures.append({"candidate": name, "reason": str(err)})
            continue
        ratio = fit.model.radius / radius
        if not config.min_radius_ratio <= ratio <= config.max_radius_ratio:
            failures.append({"candidate": name, "reason": f"radius {fit.model.radius:.2f} mm, expected "
                                                          f"{radius:.2f} mm"})
            continue
        rows.append(sphere_fit_row(measurement, scanner, name, fit))
    rows = _distinct(rows, radius)
    columns = list(SphereFitsTable.to_schema().columns)
    fits = pd.DataFrame(rows) if rows else pd.DataFrame(columns=columns)
    return fits, pd.DataFrame(failures, columns=["candidate", "reason"])


def _distinct(rows: list[dict], radius: float) -> list[dict]:
    """One fit per sphere: of fits whose centres lie within half a radius, the one with
    the most points."""
    kept: list[dict] = []
    for row in sorted(rows, key=lambda r: -r["n_points"]):
        c = np.array([row["x_mm"], row["y_mm"], row["z_mm"]])
        if all(np.linalg.norm(c - [k["x_mm"], k["y_mm"], k["z_mm"]]) > radius / 2 for k in kept):
            kept.append(row)
    return sorted(kept, key=lambda r: int(r["candidate"][1:]))


#: a second-pass fit whose points cover less of the sphere (:func:`fringecal.spheres.fit.angular_coverage`'s
#: occupied fraction; a whole cap to 60 degrees covers about 0.19-0.28) is a sliver at the edge of the
#: field or behind a rod, whose centre errs sideways by several times its fit's uncertainty: left out
MIN_COVERAGE = 0.15


def refit_cloud_sphere(points: np.ndarray, centre: np.ndarray, radius: float, rod_axes: np.ndarray | None = None,
                       rejection: RejectionConfig | None = None, max_incidence_deg: float | None = 60.0,
                       search_radii: float = 1.25):
    """Second pass of one labelled sphere in a cloud, as the point maps' second pass
    and control points treat it: the points within ``search_radii`` radii of the first
    fit's ``centre``, the rim left out (the surface seen at more than
    ``max_incidence_deg`` from the scanner's line of sight, where a fringe scanner's
    pixel integrates across the edge), cones about ``rod_axes`` (unit directions from
    the centre, the scanner's frame) masked, and the ``radius`` (the CMM's) fixed.
    Returns the :class:`fringecal.spheres.robust.RobustSphereFit`; a fit covering less
    than :data:`MIN_COVERAGE` of the sphere raises :class:`FitError`."""
    reach = search_radii * radius
    near = np.all(np.abs(points - centre) <= reach, axis=1)
    sel = points[near]
    sel = sel[np.linalg.norm(sel - centre, axis=1) <= reach]
    flags = {}
    if max_incidence_deg is not None:
        normal = (sel - centre) / np.linalg.norm(sel - centre, axis=1, keepdims=True)
        sight = -sel / np.linalg.norm(sel, axis=1, keepdims=True)
        flags["edge"] = np.einsum("ij,ij->i", normal, sight) < np.cos(np.radians(max_incidence_deg))
    fit = fit_sphere_robust(sel, radius, expected_radius=radius, flags=flags, viewpoints=np.zeros((1, 3)),
                            rod_axes=rod_axes, config=rejection)
    if fit.model.coverage < MIN_COVERAGE:
        raise FitError(f"sphere: its points cover {fit.model.coverage:.2f} of it, less than {MIN_COVERAGE} (a "
                       "sliver at the edge of the field or behind a rod)")
    return fit
