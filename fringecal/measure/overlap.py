"""Where two scanners see the same surface, how far apart are their clouds?

For a pair (A, B) every point of A (or a random sample of ``max_points``) that has at
least ``MIN_NEIGHBOURS`` points of B within the search radius is compared with B's
surface there: the plane through those neighbours (least squares, the smallest
principal axis as normal, oriented towards B's camera), and the signed distance of
A's point from it. The radius is ``RADIUS_SPACINGS`` times B's median point spacing,
so it follows the resolution. A's points that find no such neighbourhood are outside
the overlap. Both directions are reported (A against B's surface and B against A's):
with a calibration error the two agree in size and have opposite signs; noise alone
gives a mean near zero and an RMS of about the two clouds' noise combined.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from scipy.spatial import cKDTree

from fringecal.measure.cloud import Cloud

__all__ = ["OverlapStats", "surface_distances", "overlap_report", "MIN_NEIGHBOURS", "RADIUS_SPACINGS"]

MIN_NEIGHBOURS = 6
RADIUS_SPACINGS = 4.0


@dataclass(frozen=True)
class OverlapStats:
    """Distances (mm) of ``of``'s points from ``to``'s surface in their overlap."""

    of: str
    to: str
    n_points: int
    mean_mm: float
    median_mm: float
    rms_mm: float
    p95_abs_mm: float

    def as_dict(self) -> dict:
        return asdict(self)


def _spacing(tree: cKDTree, points: np.ndarray, rng: np.random.Generator) -> float:
    sample = points[rng.choice(len(points), min(len(points), 2000), replace=False)]
    d, _ = tree.query(sample, k=2)
    return float(np.median(d[:, 1]))


def surface_distances(a: np.ndarray, b: np.ndarray, towards_b, max_points: int = 200_000,
                      seed: int = 0) -> np.ndarray:
    """Signed distances (m,) of points ``a`` (n, 3) from the surface of points ``b``
    (k, 3), positive on the side of ``towards_b`` (B's camera centre, (3,)); only
    points of ``a`` inside the overlap get one."""
    rng = np.random.default_rng(seed)
    if len(a) < 1 or len(b) < MIN_NEIGHBOURS:
        return np.zeros(0)
    if len(a) > max_points:
        a = a[rng.choice(len(a), max_points, replace=False)]
    tree = cKDTree(b)
    radius = RADIUS_SPACINGS * _spacing(tree, b, rng)
    k = 4 * MIN_NEIGHBOURS
    d, idx = tree.query(a, k=min(k, len(b)), distance_upper_bound=radius)
    ok = np.isfinite(d)
    inside = ok.sum(axis=1) >= MIN_NEIGHBOURS
    a, d, idx, ok = a[inside], d[inside], idx[inside], ok[inside]
    if len(a) == 0:
        return np.zeros(0)
    nb = b[np.where(ok, idx, 0)]                       # (m, k, 3); missing neighbours masked below
    w = ok[..., None].astype(float)
    centre = (nb * w).sum(axis=1) / w.sum(axis=1)
    q = (nb - centre[:, None, :]) * w
    _, vecs = np.linalg.eigh(np.einsum("mki,mkj->mij", q, q))
    normal = vecs[:, :, 0]
    flip = np.einsum("mi,mi->m", normal, np.asarray(towards_b, float)[None, :] - centre) < 0
    normal[flip] *= -1
    return np.einsum("mi,mi->m", a - centre, normal)


def overlap_report(cloud: Cloud, camera_centres: dict, min_points: int = 100, max_points: int = 200_000
                   ) -> list[OverlapStats]:
    """Every ordered pair of scanners whose overlap holds at least ``min_points`` points;
    ``camera_centres`` scanner -> (3,) world position of its camera."""
    out = []
    names = [s for s, n in cloud.counts().items() if n > 0]
    xyz = {s: cloud.xyz(s) for s in names}
    for a in names:
        for b in names:
            if a == b:
                continue
            d = surface_distances(xyz[a], xyz[b], camera_centres[b], max_points)
            if len(d) < min_points:
                continue
            out.append(OverlapStats(a, b, int(len(d)), float(np.mean(d)), float(np.median(d)),
                                    float(np.sqrt(np.mean(d**2))), float(np.percentile(np.abs(d), 95))))
    return out
