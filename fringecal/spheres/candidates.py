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

from ..pointcloud import PointMaps

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


def surface_normals(maps: PointMaps, step: int = 1) -> np.ndarray:
    """Unit normals (rows, cols, 3) from central differences of the point maps.

    NaN where a neighbour ``step`` pixels away is missing. Orientation is arbitrary;
    :func:`find_sphere_candidates` turns them towards the viewpoint.
    """
    P = np.stack([maps.x, maps.y, maps.z], axis=-1).astype(float)
    P[~maps.valid] = np.nan
    du = np.full_like(P, np.nan)
    dv = np.full_like(P, np.nan)
    du[:, step:-step] = P[:, 2 * step:] - P[:, :-2 * step]
    dv[step:-step, :] = P[2 * step:, :] - P[:-2 * step, :]
    n = np.cross(du, dv)
    norm = np.linalg.norm(n, axis=-1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        return n / norm


def _pixel_step(maps: PointMaps, baseline_mm: float) -> int:
    """Pixel step whose surface distance is about ``baseline_mm`` (median over the image)."""
    P = np.stack([maps.x, maps.y, maps.z], axis=-1)
    d = np.linalg.norm(P[:, 1:] - P[:, :-1], axis=-1)
    ok = maps.valid[:, 1:] & maps.valid[:, :-1] & np.isfinite(d)
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
    n = surface_normals(maps, step)
    P = np.stack([maps.x, maps.y, maps.z], axis=-1).astype(float)
    view = np.asarray(viewpoint, float) - P
    view /= np.linalg.norm(view, axis=-1, keepdims=True)
    cos_inc = np.einsum("ijk,ijk->ij", n, view)
    n = np.where((cos_inc < 0)[..., None], -n, n)
    cos_inc = np.abs(cos_inc)
    voting = maps.valid & np.isfinite(cos_inc) & (cos_inc >= np.cos(np.radians(cfg.max_incidence_deg)))
    rows, cols = np.nonzero(voting)
    if len(rows) < cfg.min_votes:
        return []
    pts = P[rows, cols]
    votes = pts - radius_mm * n[rows, cols]

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
    vote_map = np.full(P.shape, np.nan)
    vote_map[rows, cols] = votes
    out = []
    for i in keep:
        c = centres[i]
        d = np.linalg.norm(P - c, axis=-1)
        with np.errstate(invalid="ignore"):
            near_vote = np.linalg.norm(vote_map - c, axis=-1) <= cfg.region_vote_mm
            shell = maps.valid & (np.abs(d - radius_mm) <= cfg.shell_mm) & near_vote
        out.append(SphereCandidate(c, strengths[i], shell))
    # A pixel in two shells (spheres touching in the image) goes to the nearer surface.
    if len(out) > 1:
        dev = np.stack([np.abs(np.linalg.norm(P - c.centre, axis=-1) - radius_mm) for c in out])
        owner = np.argmin(np.where(np.stack([c.region for c in out]), dev, np.inf), axis=0)
        out = [SphereCandidate(c.centre, c.votes, c.region & (owner == i)) for i, c in enumerate(out)]
    return out
