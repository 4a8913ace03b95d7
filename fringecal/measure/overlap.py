"""Where two scanners see the same surface, how far apart are their clouds?

For a pair (A, B) every point of A (or a random sample of ``max_points``) that has at
least ``MIN_NEIGHBOURS`` points of B within the search radius is compared with B's
surface there: a quadric height field fitted to those neighbours by least squares,
``h = c0 + c1 x + c2 y + c3 x^2 + c4 x y + c5 y^2`` in the frame of their principal
axes (the smallest as height, oriented towards B's camera), and the signed distance of
A's point from it, its height over the quadric divided by ``sqrt(1 + |grad h|^2)``.
A plane would not do: it cuts the chord of a curved surface, so on a 25 mm sphere
sampled 3 mm apart (512 px at 3 m) two samplings of the same surface would lie
0.8 mm apart; the quadric follows the curvature, and what is
left is the surface's fourth-order term at the neighbourhood's centre (4 um there,
``tests/test_measure.py``). The quadric is fitted to the ``NEIGHBOURS`` nearest
points of B, at least ``MIN_NEIGHBOURS`` of them within the search radius,
``RADIUS_SPACINGS`` times B's median point spacing, so it follows the resolution. A's
points that find no such neighbourhood are outside the overlap. Both directions are reported (A against B's surface and B against A's):
with a calibration error the two agree in size and have opposite signs; noise alone
gives a mean near zero and an RMS of about the two clouds' noise combined.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from scipy.spatial import cKDTree

from fringecal.measure.cloud import Cloud

__all__ = ["OverlapStats", "surface_distances", "overlap_report", "MIN_NEIGHBOURS", "NEIGHBOURS", "RADIUS_SPACINGS"]

#: a quadric has 6 coefficients: a few more neighbours than that
MIN_NEIGHBOURS = 10
#: the quadric is fitted to at most this many nearest neighbours (on a camera grid: within ~2.5 spacings)
NEIGHBOURS = 16
RADIUS_SPACINGS = 5.0


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
    k = NEIGHBOURS
    d, idx = tree.query(a, k=min(k, len(b)), distance_upper_bound=radius)
    ok = np.isfinite(d)
    inside = ok.sum(axis=1) >= MIN_NEIGHBOURS
    a, d, idx, ok = a[inside], d[inside], idx[inside], ok[inside]
    if len(a) == 0:
        return np.zeros(0)
    nb = b[np.where(ok, idx, 0)]                       # (m, k, 3); missing neighbours masked below
    w = ok.astype(float)
    centre = (nb * w[..., None]).sum(axis=1) / w.sum(axis=1)[:, None]
    q = (nb - centre[:, None, :]) * w[..., None]
    _, axes = np.linalg.eigh(np.einsum("mki,mkj->mij", q, q))   # columns: smallest axis first
    flip = np.einsum("mi,mi->m", axes[:, :, 0], np.asarray(towards_b, float)[None, :] - centre) < 0
    axes[flip, :, 0] *= -1
    local = np.einsum("mki,mij->mkj", nb - centre[:, None, :], axes)  # (m, k, 3): height, across, across
    pa = np.einsum("mi,mij->mj", a - centre, axes)
    return _quadric_distance(local, w, pa)


def _quadric_distance(local: np.ndarray, w: np.ndarray, pa: np.ndarray) -> np.ndarray:
    """Signed distance (m,) of points ``pa`` (m, 3) from the quadric height field fitted
    to their neighbours ``local`` (m, k, 3), both in the neighbourhood's principal frame
    (column 0 the height, 1 and 2 across), ``w`` (m, k) 1 for a neighbour, 0 for none."""
    h, x, y = local[..., 0], local[..., 1], local[..., 2]
    scale = np.sqrt((w * (x**2 + y**2)).sum(axis=1) / w.sum(axis=1))[:, None]   # conditioning
    x, y = x / scale, y / scale
    V = np.stack([np.ones_like(x), x, y, x * x, x * y, y * y], axis=-1) * w[..., None]
    # pseudo-inverse: a neighbourhood along one line (a scan line's edge) fixes no quadric
    c = np.einsum("mij,mj->mi", np.linalg.pinv(np.einsum("mki,mkj->mij", V, V), rcond=1e-9),
                  np.einsum("mki,mk->mi", V, h * w))
    xa, ya = pa[:, 1] / scale[:, 0], pa[:, 2] / scale[:, 0]
    height = c[:, 0] + c[:, 1] * xa + c[:, 2] * ya + c[:, 3] * xa**2 + c[:, 4] * xa * ya + c[:, 5] * ya**2
    gx = (c[:, 1] + 2 * c[:, 3] * xa + c[:, 4] * ya) / scale[:, 0]
    gy = (c[:, 2] + c[:, 4] * xa + 2 * c[:, 5] * ya) / scale[:, 0]
    return (pa[:, 0] - height) / np.sqrt(1 + gx**2 + gy**2)


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
