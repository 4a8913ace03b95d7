"""Sphere candidates in a measurement's point maps, found without manual input.

The thesis drew a region of interest around every sphere by hand (section 6.2.1).
Here every triangulated pixel votes for the centre of the sphere it would lie on:
with the surface normal ``n`` (from the image-space gradients of the point maps,
oriented towards the camera) a point ``p`` on a sphere of radius ``r`` has its centre
at ``p - r n``. Points of one sphere all vote for the same place; points on rods and
end caps (cylinders of another radius) vote along lines, a background plane over a
plane, so dense clusters of votes are spheres of the artefact's radius. This is a
Hough transform with the radius known from the artefact definition, chosen over
connected components (spheres, caps and rods touch in the image) and over RANSAC on the
whole cloud (slower, and blind to which pixels belong together).

Each candidate's region is the set of pixels whose point lies within a shell around
the voted centre and whose vote lands near it; :func:`fringecal.spheres.regions.fit_region`
then fits it and rejects rods, end caps, edges and glints with reasons.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from fringecal.pointcloud import PointMaps

__all__ = ["CandidateConfig", "SphereCandidate", "surface_normals", "find_sphere_candidates"]


@dataclass(frozen=True)
class CandidateConfig:
    """Settings of :func:`find_sphere_candidates`.

    Attributes
    ----------
    normal_baseline_mm : float
        Length of the finite-difference stencil for normals; the pixel step is chosen
        so neighbours are about this far apart on the surface (noise averages out).
    cell_mm : float
        Size of the voting cells.
    vote_radius_mm : float
        Votes within this distance of a peak count for it.
    shell_mm : float
        Pixels whose point lies within this distance of the candidate's sphere surface
        belong to its region (the robust fit removes what does not fit) ...
    region_vote_mm : float
        ... if their own vote lands within this distance of the candidate's centre.
        End-cap points next to a sphere lie on its surface where the cap meets it, but
        their normals are square to the rod, so their votes land ~27 mm away.
    min_votes : int
        Fewest votes for a candidate.
    min_vote_fraction : float
        A candidate needs at least this fraction of the votes of the strongest one
        (suppresses clusters on rods and planes).
    min_separation_factor : float
        Candidates closer than this times the radius to a stronger one are the same sphere.
    max_incidence_deg : float
        Pixels seen more obliquely than this do not vote (silhouette points have
        unreliable normals).
    """

    normal_baseline_mm: float = 3.0
    cell_mm: float = 4.0
    vote_radius_mm: float = 4.0
    shell_mm: float = 4.0
    region_vote_mm: float = 8.0
    min_votes: int = 20
    min_vote_fraction: float = 0.08
    min_separation_factor: float = 1.5
    max_incidence_deg: float = 75.0


@dataclass(frozen=True)
class SphereCandidate:
    """A sphere candidate: voted centre, number of votes, and its image region."""

    centre: np.ndarray
    votes: int
    region: np.ndarray = field(repr=False)  # bool (rows, cols)

    @property
    def n_pixels(self) -> int:
        return int(self.region.sum())


def surface_normals(maps: PointMaps, step: int = 1, rows=None, cols=None) -> np.ndarray:
    """Unit normals from central differences of the point maps, ``step`` pixels apart.

    For every pixel, shape (rows, cols, 3), or with ``rows``, ``cols`` only for those
    pixels, shape (n, 3). NaN where a neighbour is missing. Orientation is arbitrary;
    :func:`find_sphere_candidates` turns them towards the viewpoint.
    """
    P = np.stack([maps.x, maps.y, maps.z], axis=-1)
    H, W = maps.valid.shape
    if rows is None:
        rows, cols = np.indices((H, W)).reshape(2, -1)
        shape = (H, W, 3)
    else:
        shape = (len(rows), 3)
    rows = np.asarray(rows)
    cols = np.asarray(cols)

    def at(r, c):
        inside = (r >= 0) & (r < H) & (c >= 0) & (c < W)
        r, c = np.clip(r, 0, H - 1), np.clip(c, 0, W - 1)
        out = P[r, c].astype(float)
        out[~(inside & maps.valid[r, c])] = np.nan
        return out

    du = at(rows, cols + step) - at(rows, cols - step)
    dv = at(rows + step, cols) - at(rows - step, cols)
    n = np.cross(du, dv)
    with np.errstate(invalid="ignore", divide="ignore"):
        n /= np.linalg.norm(n, axis=-1, keepdims=True)
    return n.reshape(shape)


def _pixel_step(maps: PointMaps, baseline_mm: float) -> int:
    """Pixel step whose surface distance is about ``baseline_mm`` (median over every
    8th row of the image)."""
    P = np.stack([maps.x[::8], maps.y[::8], maps.z[::8]], axis=-1)
    valid = maps.valid[::8]
    d = np.linalg.norm(P[:, 1:] - P[:, :-1], axis=-1)
    ok = valid[:, 1:] & valid[:, :-1] & np.isfinite(d)
    if not ok.any():
        return 1
    spacing = float(np.median(d[ok]))
    return int(np.clip(round(baseline_mm / max(spacing, 1e-9) / 2), 1, 8))


def find_sphere_candidates(maps: PointMaps, radius_mm: float, viewpoint,
                           config: CandidateConfig | None = None) -> list[SphereCandidate]:
    """Sphere candidates of radius ``radius_mm`` in one measurement.

    Parameters
    ----------
    maps : PointMaps
        Triangulated maps of the measurement (world mm).
    radius_mm : float
        Expected sphere radius (from the artefact definition).
    viewpoint : array_like, shape (3,)
        Camera pinhole in the same frame; normals are turned towards it.
    config : CandidateConfig, optional

    Returns
    -------
    list of SphereCandidate, strongest first.
    """
    cfg = config or CandidateConfig()
    step = _pixel_step(maps, cfg.normal_baseline_mm)
    rows, cols = np.nonzero(maps.valid)
    pts = np.stack([maps.x[rows, cols], maps.y[rows, cols], maps.z[rows, cols]], axis=-1).astype(float)
    n = surface_normals(maps, step, rows, cols)
    view = np.asarray(viewpoint, float) - pts
    view /= np.linalg.norm(view, axis=-1, keepdims=True)
    cos_inc = np.einsum("ij,ij->i", n, view)
    n[cos_inc < 0] *= -1
    voting = np.isfinite(cos_inc) & (np.abs(cos_inc) >= np.cos(np.radians(cfg.max_incidence_deg)))
    rows, cols, pts = rows[voting], cols[voting], pts[voting]
    if len(rows) < cfg.min_votes:
        return []
    votes = pts - radius_mm * n[voting]

    cells = np.floor(votes / cfg.cell_mm).astype(np.int64)
    uniq, counts = np.unique(cells, axis=0, return_counts=True)
    order = np.argsort(counts)[::-1]
    tree = cKDTree(votes)
    centres: list[np.ndarray] = []
    strengths: list[int] = []
    min_sep = cfg.min_separation_factor * radius_mm
    best = 0
    for ci in order:
        if counts[ci] * 8 < max(cfg.min_votes, cfg.min_vote_fraction * best):
            break  # no later cell (3x3x3 neighbourhood at most 27x) can still qualify
        seed = (uniq[ci] + 0.5) * cfg.cell_mm
        if any(np.linalg.norm(seed - c) < min_sep for c in centres):
            continue
        c = seed
        for _ in range(5):  # mean shift with a flat kernel
            idx = tree.query_ball_point(c, cfg.vote_radius_mm)
            if not idx:
                break
            c_new = votes[idx].mean(axis=0)
            if np.linalg.norm(c_new - c) < 0.01:
                c = c_new
                break
            c = c_new
        idx = tree.query_ball_point(c, cfg.vote_radius_mm)
        k = len(idx)
        if k < max(cfg.min_votes, cfg.min_vote_fraction * best):
            continue
        if any(np.linalg.norm(c - cc) < min_sep for cc in centres):
            continue
        centres.append(np.median(votes[idx], axis=0))
        strengths.append(k)
        best = max(best, k)
    keep = [i for i, k in enumerate(strengths) if k >= cfg.min_vote_fraction * best]
    # A candidate's region: the pixels whose own vote lands near its centre and whose
    # point lies near its surface. A pixel claimed twice (spheres touching in the image)
    # goes to the nearer surface.
    deviation = np.full(len(votes), np.inf)
    owner = np.full(len(votes), -1)
    for j, i in enumerate(keep):
        idx = np.asarray(tree.query_ball_point(centres[i], cfg.region_vote_mm), dtype=int)
        if not len(idx):
            continue
        dev = np.abs(np.linalg.norm(pts[idx] - centres[i], axis=1) - radius_mm)
        take = (dev <= cfg.shell_mm) & (dev < deviation[idx])
        deviation[idx[take]] = dev[take]
        owner[idx[take]] = j
    out = []
    for j, i in enumerate(keep):
        region = np.zeros(maps.valid.shape, bool)
        sel = owner == j
        region[rows[sel], cols[sel]] = True
        out.append(SphereCandidate(centres[i], strengths[i], region))
    return out
