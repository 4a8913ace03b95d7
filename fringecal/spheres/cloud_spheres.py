"""Sphere candidates in an unorganised point cloud (a black-box scanner's), fitted with
the same robust fit as the candidates of a point map.

A point map's candidates come from its pixel neighbourhoods; a cloud has none, so they
come from normal voting in space: the cloud is sorted into cubes of edge ``radius / 4``,
each cube's normal is the smallest principal direction of the points of it and its 26
neighbours, turned toward the scanner (the origin of the cloud's frame: the scanner
sees the outside of a sphere), and the cube's mean point votes for a centre one radius
behind it. A sphere's votes pile up in the cube of its
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

from fringecal.scancloud import bounding_box
from fringecal.schemas import SphereFitsTable
from fringecal.spheres.cloud_kernels import cube_keys, cube_sums, neighbourhood_sums, within_reach, within_reach_of_any
from fringecal.spheres.fit import FitError
from fringecal.spheres.poses_and_links import sphere_fit_row
from fringecal.spheres.robust import RejectionConfig, fit_sphere_robust

__all__ = ["CloudCandidateConfig", "cloud_sphere_fits", "near_any", "refit_cloud_sphere", "vote_centres"]


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


_PAIRS = ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))
#: the 26 neighbours of a cube as differences of keys (:func:`_Cubes._keys`; the cubes
#: have a margin of one, so no index borrows from the next axis)
_NEIGHBOUR_OFFSETS = np.array([(int(a) << 42) + (int(b) << 21) + int(c)
                               for a, b, c in np.array(np.meshgrid([-1, 0, 1], [-1, 0, 1], [-1, 0, 1])).reshape(3, -1).T
                               if a or b or c], np.int64)


class _Cubes:
    """A cloud sorted into cubes of edge ``cell``: each occupied cube's points (a slice
    of the cloud's cube order), their mean, and sums for local planes; one compiled pass
    each (:mod:`fringecal.spheres.cloud_kernels`)."""

    def __init__(self, points: np.ndarray, cell: float):
        self.cell = cell
        self.cloud = np.ascontiguousarray(points, float)
        self.origin = np.floor(bounding_box(self.cloud)[0] / cell) - 1  # a margin of one cube for neighbours
        keys = cube_keys(self.cloud, cell, self.origin)
        self.order = np.argsort(keys)
        sorted_keys = keys[self.order]
        self.start = np.flatnonzero(np.r_[True, sorted_keys[1:] != sorted_keys[:-1]])
        self.keys = sorted_keys[self.start]
        self.count = np.diff(np.r_[self.start, len(keys)])
        self.shift = np.array([self.cloud[:, i].mean() for i in range(3)])
        self.s1, self.s2 = cube_sums(self.cloud, self.order, self.start, self.shift)

    @staticmethod
    def _keys(q: np.ndarray) -> np.ndarray:
        q = q.astype(np.int64)
        return (q[..., 0] << 42) | (q[..., 1] << 21) | q[..., 2]

    def lookup(self, keys: np.ndarray) -> np.ndarray:
        """Cube index of each key, -1 where no point lies."""
        i = np.minimum(np.searchsorted(self.keys, keys), len(self.keys) - 1)
        return np.where(self.keys[i] == keys, i, -1)

    def means(self) -> np.ndarray:
        return self.s1 / self.count[:, None] + self.shift

    def normals(self) -> np.ndarray:
        """Each cube's normal: the smallest principal direction of the points of it and
        its 26 neighbours, turned toward the origin (the scanner)."""
        n, s1, s2 = neighbourhood_sums(self.keys, self.count, self.s1, self.s2, _NEIGHBOUR_OFFSETS)
        mean = s1 / n[:, None]
        cov = np.empty((len(n), 3, 3))
        for k, (a, b) in enumerate(_PAIRS):
            cov[:, a, b] = cov[:, b, a] = s2[:, k] / n - mean[:, a] * mean[:, b]
        normal = np.linalg.eigh(cov)[1][:, :, 0]
        flip = np.einsum("ni,ni->n", normal, -self.means()) < 0
        normal[flip] *= -1
        return normal

    def near(self, centre: np.ndarray, reach: float) -> np.ndarray:
        """The points within ``reach`` of ``centre``."""
        lo = np.floor((centre - reach) / self.cell) - self.origin
        hi = np.floor((centre + reach) / self.cell) - self.origin
        grid = np.stack(np.meshgrid(*[np.arange(a, b + 1) for a, b in zip(lo, hi)], indexing="ij"), axis=-1)
        j = self.lookup(self._keys(grid.reshape(-1, 3)))
        j = j[j >= 0]
        if not len(j):
            return np.zeros((0, 3))
        p = self.cloud[np.concatenate([self.order[a:a + c] for a, c in zip(self.start[j], self.count[j])])]
        return p[np.linalg.norm(p - centre, axis=1) <= reach]


def vote_centres(points: np.ndarray, radius: float, config: CloudCandidateConfig = CloudCandidateConfig(),
                 cubes: _Cubes | None = None) -> np.ndarray:
    """Candidate sphere centres (m, 3) of a cloud, most votes first."""
    cell = config.cell_fraction * radius
    cubes = cubes or _Cubes(points, cell)
    if len(cubes.keys) < config.neighbours:
        return np.zeros((0, 3))
    votes = cubes.means() - radius * cubes.normals()
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
    cubes = _Cubes(np.asarray(points, float), config.cell_fraction * radius)
    for k, centre in enumerate(vote_centres(points, radius, config, cubes)):
        sel = cubes.near(centre, reach)
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


def near_any(points: np.ndarray, centres: np.ndarray, radius: float, search_radii: float = 1.25) -> np.ndarray:
    """The points of a cloud within ``search_radii`` radii of any of ``centres`` (k, 3), in
    the cloud's order: what :func:`refit_cloud_sphere` of each of them needs (the same
    points, in the same order, as from the whole cloud), found in one pass."""
    points = np.ascontiguousarray(points, float)
    centres = np.ascontiguousarray(np.reshape(centres, (-1, 3)), float)
    return points[within_reach_of_any(points, centres, float(search_radii * radius))]


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
    points = np.ascontiguousarray(points, float)
    sel = points[within_reach(points, np.ascontiguousarray(centre, float), float(reach))]
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
