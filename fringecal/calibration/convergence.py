"""Has an adjustment reached its noise floor? A test that needs no truth.

Object-space sphere residuals have separate minima (see :mod:`.start`): the adjustment
can stop with F millimetres above the noise, or a few per cent above it, with every
convergence criterion of the solver met. Whether a minimum is the floor cannot be read
from F alone (the noise level is unknown), but the control points carry their own noise
estimate: within one sphere image (one sphere seen by one scanner in one measurement)
the residuals of a correctly calibrated scanner are noise, and a wrong calibration
shows as a smooth pattern over the image. So per sphere image

* epsilon-2 (distance to the CMM sphere moved by the pose) is compared with the
  distance of the same triangulated points to a sphere of **free centre and radius**
  fitted to them alone (algebraic fit, 4 parameters): a wrong minimum puts the caps
  millimetres off the spheres the poses put there, or deforms them, and the free fit
  absorbs the offset but not the noise;
* epsilon-1 (closest approach of the rays) is compared with its residual from a
  **plane in the camera image coordinates** (eps1 ~ a + b u + c v, 3 parameters): a
  wrong relative orientation of camera and projector makes epsilon-1 vary smoothly
  over a sphere's small image, noise does not.

The local estimates are corrected for their degrees of freedom (``n - 4 G`` and ``n - 3 G``
over G sphere images with at least ``MIN_POINTS`` points), the adjustment's by its
own (``nu_t`` of :mod:`.uncertainty`, i.e. ``sum alpha_t^2 * n / nu_t``). Their ratios

    ratio_t = sqrt(adjusted variance of term t / local variance of term t)

are 1.00 at the noise floor and 2.7 to 12 at the separate minima of rough starts; a
minimum 5 % above the floor in epsilon-2 shows as a ratio of about 1.05. At the truth
(simulated rigs, 8 noise realisations) they scatter by +-0.04-0.06 at 600-800 control
points, +-0.01 at 1,600-2,000 and +-0.002 at 7,000-9,000, about their expected spread
1 / sqrt(2 nu) or less (the two estimates share the noise). The floor counts as reached
when both ratios, over all control points, are at most ``FLOOR_RATIO`` plus the sampling
allowance ``ALLOWANCE_K / sqrt(2 nu)`` (nu: the local estimates' degrees of freedom; the
limit is 1.07 at 6,000 control points, 1.09 at 1,600), and every scanner's at most
``SCANNER_FLOOR_RATIO`` plus its allowance (one scanner stuck in a separate minimum of a
large rig hardly moves the overall figure).

Real data hold errors the model cannot absorb (the artefact's CMM values and form,
lens errors beyond the 14 parameters); the local fits absorb part of them, so a real
calibration at its true minimum may show ratios a little above 1. That is why a ratio
above the limit only makes :func:`fringecal.calibration.bundle.bundle_adjust` try
other starts, and the verdict (``BundleResult.extra["convergence"]``) distinguishes:

* ``noise_floor``: some start reached ratios within the limit (the lowest such minimum
  is the result);
* ``lowest_minimum``: none did, but at least two different starts ended in the same
  lowest minimum (F equal to 1e-6, every parameter within 0.1 of its standard
  uncertainty) with ratios at most ``SEPARATE_MINIMUM_RATIO``: the residuals exceed the
  per-point noise through systematic errors of data or model, not a separate minimum
  (warning ``above_noise_floor``);
* ``unconfirmed``: ``start="given"`` (one start only) with ratios between the limit and
  ``SEPARATE_MINIMUM_RATIO`` (warning ``above_noise_floor``);
* ``not_reached``: neither (error ``floor_not_reached``): the result is the lowest
  minimum found and must not be used as a calibration.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from fringecal.calibration.model import triangulated_points
from fringecal.sensor import UndistortError

__all__ = ["FLOOR_RATIO", "MIN_POINTS", "SCANNER_FLOOR_RATIO", "SEPARATE_MINIMUM_RATIO", "FloorCheck",
           "local_residuals", "noise_floor_check", "same_minimum"]

#: largest ratio of the adjusted to the local noise estimate (both terms, all control
#: points) accepted as the noise floor, before the sampling allowance
FLOOR_RATIO = 1.05
#: the same for the control points of one scanner
SCANNER_FLOOR_RATIO = 1.10
#: above this ratio a minimum is a separate one whatever other starts found (a real
#: calibration's systematic errors do not double the residuals the local fits leave)
SEPARATE_MINIMUM_RATIO = 2.0
#: sphere images with fewer control points do not enter the local estimates
MIN_POINTS = 8
#: sampling allowance: k / sqrt(2 nu) added to the limits (nu: local degrees of freedom;
#: twice the spread of one variance estimate's square root, measured spread smaller)
ALLOWANCE_K = 2.0


@dataclass(frozen=True)
class FloorCheck:
    """The noise-floor test of one minimum (see module docstring).

    ratio_eps1, ratio_eps2 : over all control points (inf where the rays could not be formed)
    local_eps1_mm, local_eps2_mm : the local (per sphere image) noise estimates
    limit : the overall limit with its sampling allowance
    per_scanner : scanner -> {"ratio_eps1", "ratio_eps2", "limit", "n_points"}
    shape_ratio : epsilon-2 RMS over the RMS distance to the free sphere fits, both without
        degrees-of-freedom corrections (the figure earlier versions reported)
    reached : every ratio within its limit
    """

    ratio_eps1: float
    ratio_eps2: float
    local_eps1_mm: float
    local_eps2_mm: float
    limit: float
    per_scanner: dict = field(default_factory=dict)
    shape_ratio: float = float("nan")

    @property
    def ratio(self) -> float:
        """The larger of the two overall ratios."""
        return max(self.ratio_eps1, self.ratio_eps2)

    @property
    def failing_scanners(self) -> list:
        return [s for s, d in self.per_scanner.items()
                if not max(d["ratio_eps1"], d["ratio_eps2"]) <= d["limit"]]

    @property
    def reached(self) -> bool:
        return bool(self.ratio <= self.limit) and not self.failing_scanners

    def to_dict(self) -> dict:
        return {"reached": self.reached, "ratio_eps1": self.ratio_eps1, "ratio_eps2": self.ratio_eps2,
                "limit": self.limit, "local_eps1_mm": self.local_eps1_mm, "local_eps2_mm": self.local_eps2_mm,
                "shape_ratio": self.shape_ratio, "per_scanner": self.per_scanner}


def _unreachable(problem) -> FloorCheck:
    inf = float("inf")
    return FloorCheck(inf, inf, float("nan"), float("nan"), FLOOR_RATIO,
                      {s.name: {"ratio_eps1": inf, "ratio_eps2": inf, "limit": SCANNER_FLOOR_RATIO, "n_points": 0}
                       for s in problem.rig.scanners}, inf)


def _group_sums(g, G, w, cols):
    return np.stack([np.bincount(g, w * c, G) for c in cols], axis=-1)


def local_residuals(problem, rig, eps1: np.ndarray):
    """Per control point: distance to the free sphere fitted to its sphere image, residual
    of epsilon-1 from the plane fitted over its sphere image, and whether its image
    entered the fits (at least ``MIN_POINTS`` points with finite rays); plus the number
    of sphere images used. Raises :class:`fringecal.sensor.UndistortError` (or returns
    NaN rows) where rays cannot be formed."""

    S = triangulated_points(problem, rig)
    n_sph, n_m = len(problem.artefact), len(problem.measurements)
    key = (problem.scanner_idx * n_m + problem.meas_idx) * n_sph + problem.sphere_idx
    _, g, _ = np.unique(key, return_inverse=True, return_counts=True)
    G = int(g.max()) + 1 if len(g) else 0
    good = np.all(np.isfinite(S), axis=1) & np.isfinite(eps1)
    w = good.astype(float)
    S = np.where(good[:, None], S, 0.0)
    e1 = np.where(good, eps1, 0.0)
    cnt = np.bincount(g, w, G)
    ok = cnt >= MIN_POINTS
    safe = np.maximum(cnt, 1)[:, None]
    # sphere: |p|^2 = 2 c.p + k about each image's centroid
    P = S - (_group_sums(g, G, w, S.T) / safe)[g]
    q = np.sum(P * P, axis=1)
    A = np.concatenate([2 * P, np.ones((len(P), 1))], axis=1)
    # plane: eps1 = a + b u + c v about each image's centroid
    uv = problem.cam_mm - (_group_sums(g, G, w, problem.cam_mm.T) / safe)[g]
    B = np.concatenate([np.ones((len(P), 1)), uv], axis=1)
    AtA = np.zeros((G, 4, 4))
    Atq = np.zeros((G, 4))
    BtB = np.zeros((G, 3, 3))
    Bte = np.zeros((G, 3))
    for a in range(4):
        Atq[:, a] = np.bincount(g, w * A[:, a] * q, G)
        for b in range(a, 4):
            AtA[:, a, b] = AtA[:, b, a] = np.bincount(g, w * A[:, a] * A[:, b], G)
    for a in range(3):
        Bte[:, a] = np.bincount(g, w * B[:, a] * e1, G)
        for b in range(a, 3):
            BtB[:, a, b] = BtB[:, b, a] = np.bincount(g, w * B[:, a] * B[:, b], G)
    # a sphere image whose points are (nearly) collinear gives singular systems: leave it out
    ok &= np.linalg.cond(np.where(ok[:, None, None], AtA, np.eye(4))) < 1e12
    ok &= np.linalg.cond(np.where(ok[:, None, None], BtB, np.eye(3))) < 1e12
    sol = np.zeros((G, 4))
    sol[ok] = np.linalg.solve(AtA[ok], Atq[ok][..., None])[..., 0]
    pl = np.zeros((G, 3))
    pl[ok] = np.linalg.solve(BtB[ok], Bte[ok][..., None])[..., 0]
    c = sol[:, :3]
    r = np.sqrt(np.maximum(sol[:, 3] + np.sum(c * c, axis=1), 0.0))
    d2 = np.linalg.norm(P - c[g], axis=1) - r[g]
    d1 = e1 - np.sum(B * pl[g], axis=1)
    keep = ok[g] & good
    return d1, d2, keep, g, ok


def noise_floor_check(problem, rig, residuals: np.ndarray, dof: tuple | None = None) -> FloorCheck:
    """The noise-floor test of an adjusted ``rig`` with its ``residuals`` (n, 2) on
    ``problem``'s control points; ``dof`` = (nu_1, nu_2) of the adjustment (None: n
    each, i.e. no correction for the adjusted parameters)."""

    n = problem.n_points
    try:
        d1, d2, keep, g, ok = local_residuals(problem, rig, residuals[:, 0])
    except (UndistortError, FloatingPointError, np.linalg.LinAlgError):
        return _unreachable(problem)
    if not keep.any():
        return _unreachable(problem)
    nu = (float(n), float(n)) if dof is None else tuple(max(float(v), 1.0) for v in dof)
    inflate = np.array([n / nu[0], n / nu[1]])

    def ratios(sel):
        m = int(np.sum(keep & sel))
        images = int(np.sum(ok & (np.bincount(g, (keep & sel).astype(float), len(ok)) > 0)))
        nu2, nu1 = m - 4 * images, m - 3 * images
        if m == 0 or nu1 <= 0 or nu2 <= 0:
            return float("inf"), float("inf"), float("nan"), float("nan"), 0, 1.0
        loc1 = np.sum(d1[keep & sel] ** 2) / nu1
        loc2 = np.sum(d2[keep & sel] ** 2) / nu2
        adj = np.sum(residuals[keep & sel] ** 2, axis=0) / m * inflate
        r1 = float(np.sqrt(adj[0] / loc1)) if loc1 > 0 else float("inf")
        r2 = float(np.sqrt(adj[1] / loc2)) if loc2 > 0 else float("inf")
        return r1, r2, float(np.sqrt(loc1)), float(np.sqrt(loc2)), m, ALLOWANCE_K / np.sqrt(2.0 * min(nu1, nu2))

    r1, r2, l1, l2, _, allow = ratios(np.ones(n, bool))
    per = {}
    for si, sc in enumerate(problem.rig.scanners):
        s1, s2, _, _, m, a = ratios(problem.scanner_idx == si)
        per[sc.name] = {"ratio_eps1": s1, "ratio_eps2": s2, "limit": SCANNER_FLOOR_RATIO + a, "n_points": m}
    shape = float(np.sqrt(np.mean(residuals[keep, 1] ** 2) / np.mean(d2[keep] ** 2)))
    return FloorCheck(r1, r2, l1, l2, FLOOR_RATIO + allow, per, shape)


def same_minimum(a, b, rel_cost: float = 1e-6, sigma: float = 0.1) -> bool:
    """Whether two adjustments (:class:`~fringecal.calibration.bundle.BundleResult` of one
    problem) ended in the same minimum: F equal to ``rel_cost`` and every free parameter
    within ``sigma`` of its standard uncertainty."""
    fa, fb = a.extra["cost"], b.extra["cost"]
    if not abs(fa - fb) <= rel_cost * max(fa, fb):
        return False
    u = np.maximum(np.maximum(a.uncertainty.std, b.uncertainty.std), 1e-300)
    return bool(np.all(np.abs(a.x - b.x) <= sigma * u))
