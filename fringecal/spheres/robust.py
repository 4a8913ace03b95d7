"""Sphere fits that never let rods, end caps, edges or glints in, with the reasons.

The thesis masked every sphere by hand because points of the rods' end caps spoil
both the sphere fits and the bundle adjustment (section 6.1). Here a candidate point
set (the points of one image region) goes through, in this order:

``invalid``
    non-finite coordinates;
caller flags (e.g. ``edge``, ``glint``, ``saturated``)
    per-point masks the image-space step supplies: pixels on the boundary of the
    valid mask, saturated or low-modulation pixels, large phase errors;
``rod``
    points inside a cone about a rod axis through the sphere centre. The cone's
    half-angle ``asin((r_rod + margin) / R)`` covers the rod, its end cap, the end
    cap's face (which touches the sphere, so its points have residuals near zero
    and no residual test can catch them) and a margin of sphere surface next to
    the joint. Axes come from the artefact definition and the pose (second pass,
    :func:`rod_directions`) and/or are detected in the current outliers: rod
    points satisfy ``v . a = sqrt(|v|^2 - r_rod^2)`` (v from the centre), linear
    in the unit axis ``a``;
``silhouette``
    points whose sphere normal is more than ``max_incidence_deg`` from the line of
    sight of any given viewpoint (camera and projector pinholes): the far side and
    the grazing rim, where pixels mix sphere and background;
``residual``
    orthogonal residual beyond ``threshold_sigma`` times the noise (the larger of the
    expected noise and a robust estimate from the current inliers).

The initial sphere comes from RANSAC (4-point algebraic spheres, MSAC score,
hypotheses with an implausible radius skipped), so a candidate with more rod than
sphere points still starts on the sphere. Then the fit and the classification are
repeated until the kept set no longer changes. Every point gets exactly one reason
(the first that applies, in the order above) and the summary counts them.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Mapping

import numpy as np

from fringecal.spheres.fit import FitError, PlaneModel, SphereModel

__all__ = ["RejectionConfig", "RobustSphereFit", "SphereRejectionError", "fit_sphere_robust",
           "rod_directions", "detect_rods", "RobustPlaneFit", "fit_plane_robust"]


class SphereRejectionError(FitError):
    """Too few points survive; ``counts`` says where they went."""

    def __init__(self, message: str, counts: Mapping[str, int]):
        super().__init__(f"{message} (rejected: {dict(counts)})")
        self.counts = dict(counts)


@dataclass(frozen=True)
class RejectionConfig:
    """Settings of :func:`fit_sphere_robust`.

    Attributes
    ----------
    noise_mm : float
        Expected standard deviation of sphere points along the normal (thesis
        scanners: about 0.02 mm). The residual threshold never falls below
        ``threshold_sigma * noise_mm``.
    threshold_sigma : float
        Residual threshold in units of the noise.
    ransac_threshold_mm : float or None
        Inlier band of the RANSAC start; default ``max(5 noise_mm, 0.05)``.
    radius_tolerance : float
        RANSAC hypotheses whose radius differs from the expected one by more than
        this fraction are skipped.
    max_incidence_deg : float
        Silhouette test against the viewpoints.
    rod_radius_mm : float
        Rod (and end-cap) outer radius, 10.9 mm for the thesis artefact.
    rod_margin_mm : float
        Extra radius of the rod cone, covering joint glue, shadows and interreflections.
    detect_rods : bool
        Look for rods among the outliers (first pass, when no axes are known).
    min_rod_points : int
        Outliers needed to accept a detected rod.
    min_points : int
        Fewer surviving points is an error.
    """

    noise_mm: float = 0.02
    threshold_sigma: float = 4.0
    ransac_threshold_mm: float | None = None
    ransac_max_iterations: int = 2000
    ransac_score_points: int = 2000
    radius_tolerance: float = 0.2
    max_incidence_deg: float = 80.0
    rod_radius_mm: float = 10.9
    rod_margin_mm: float = 2.0
    detect_rods: bool = True
    min_rod_points: int = 30
    min_points: int = 50
    max_rounds: int = 10
    seed: int = 0


@dataclass(frozen=True)
class RobustSphereFit:
    """Result of :func:`fit_sphere_robust`.

    Attributes
    ----------
    model : SphereModel
        The least-squares sphere of the kept points.
    kept : ndarray of bool, shape (n,)
    reason : ndarray of int, shape (n,)
        Index into ``reasons`` for rejected points, -1 for kept ones.
    reasons : tuple of str
        Reason names in precedence order.
    rejected : dict
        ``{reason: count}`` for every reason (zeros included).
    rod_axes : ndarray, shape (k, 3)
        Unit rod directions used for the cone test (known ones first).
    rods_detected : int
        How many of ``rod_axes`` were found in the outliers.
    threshold_mm, sigma_mm : float
        Final residual threshold and robust noise estimate.
    rounds : int
    """

    model: SphereModel
    kept: np.ndarray = field(repr=False)
    reason: np.ndarray = field(repr=False)
    reasons: tuple[str, ...]
    rejected: dict
    rod_axes: np.ndarray = field(repr=False)
    rods_detected: int
    threshold_mm: float
    sigma_mm: float
    rounds: int

    @property
    def n_rejected(self) -> int:
        return int(np.count_nonzero(~self.kept))

    def summary(self) -> dict:
        """Fit and rejection counts as one flat, JSON-ready dict."""
        out = self.model.to_dict()
        out.update({f"rejected_{k}": int(v) for k, v in self.rejected.items()})
        out.update(n_rejected=self.n_rejected, threshold_mm=self.threshold_mm, sigma_mm=self.sigma_mm,
                   rods_detected=self.rods_detected, rounds=self.rounds)
        return out


def rod_directions(artefact, rods, sphere_id: str, T_world_artefact=None) -> np.ndarray:
    """Unit directions (k, 3) from sphere ``sphere_id`` to its rod neighbours.

    ``rods`` is a rods table (``sphere_a, sphere_b``). With ``T_world_artefact``
    (a :class:`fringecal.frames.Frame`, e.g. the pose from the first pass) the
    directions are rotated into that frame (the scanner's), else they are in the
    artefact (CMM) frame.
    """
    sid = str(sphere_id)
    others = [str(b) if str(a) == sid else str(a) for a, b in zip(rods["sphere_a"], rods["sphere_b"])
              if sid in (str(a), str(b))]
    if not others:
        return np.zeros((0, 3))
    d = artefact.centres_of(others) - artefact.centres_of([sid])[0]
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    if T_world_artefact is not None:
        d = d @ T_world_artefact.R  # R^T d, as row vectors
    return d


def _ransac(p: np.ndarray, expected_radius, thr: float, cfg: RejectionConfig, rng) -> tuple[np.ndarray, float]:
    m = len(p)
    shift = p.mean(axis=0)
    q = p - shift
    score_pts = q if m <= cfg.ransac_score_points else q[rng.integers(0, m, cfg.ransac_score_points)]
    best_loss, best = np.inf, None
    needed, done, batch = cfg.ransac_max_iterations, 0, 100
    while done < min(needed, cfg.ransac_max_iterations):
        idx = rng.integers(0, m, (batch, 4))
        P = q[idx]
        A = np.concatenate([2 * P, np.ones((batch, 4, 1))], axis=2)
        b = np.einsum("kij,kij->ki", P, P)
        det = np.linalg.det(A)
        ok = np.abs(det) > 1e-9 * np.maximum(1.0, np.abs(P).max(axis=(1, 2))) ** 3
        done += batch
        if not np.any(ok):
            continue
        sol = np.linalg.solve(A[ok], b[ok][..., None])[..., 0]
        centres = sol[:, :3]
        r2 = sol[:, 3] + np.einsum("ki,ki->k", centres, centres)
        good = r2 > 0
        radii = np.sqrt(np.where(good, r2, 0))
        if expected_radius is not None:
            good &= np.abs(radii - expected_radius) <= cfg.radius_tolerance * expected_radius
        if not np.any(good):
            continue
        centres, radii = centres[good], radii[good]
        score_r = expected_radius if expected_radius is not None else radii[:, None]
        d = np.linalg.norm(score_pts[None, :, :] - centres[:, None, :], axis=2)
        loss = np.minimum((d - score_r) ** 2, thr * thr).sum(axis=1)
        k = int(np.argmin(loss))
        if loss[k] < best_loss:
            best_loss, best = loss[k], (centres[k], float(radii[k]))
            # adaptive number of hypotheses for 99.99 % confidence
            inl = np.mean(np.abs(d[k] - (expected_radius if expected_radius is not None else radii[k])) < thr)
            w4 = max(inl, 1e-3) ** 4
            needed = int(np.ceil(np.log(1e-4) / np.log1p(-min(w4, 1 - 1e-12)))) if w4 < 1 else batch
    if best is None:
        raise FitError("sphere: RANSAC found no sphere of plausible radius in the candidate points")
    return best[0] + shift, best[1]


def detect_rods(points: np.ndarray, centre: np.ndarray, radius: float, candidates: np.ndarray,
                cfg: RejectionConfig) -> np.ndarray:
    """Rod axes (k, 3) among ``points[candidates]`` (outliers outside the sphere).

    Seeds on the densest direction, fits the axis through the centre by the linear
    relation ``v . a = sqrt(|v|^2 - r^2)`` with trimming, accepts it if enough
    points lie on the cylinder (within 1 mm), removes the cone and repeats.
    """
    r_rod = cfg.rod_radius_mm
    v = points[candidates] - centre
    dist = np.linalg.norm(v, axis=1)
    keep = (dist > r_rod + 1e-9) & (dist < radius + 4 * r_rod + 60.0)
    v, dist = v[keep], dist[keep]
    axes = []
    cone = np.arcsin(min(1.0, (r_rod + cfg.rod_margin_mm) / radius))
    spread = 2 * np.arcsin(min(1.0, r_rod / radius))
    rng = np.random.default_rng(cfg.seed)
    for _ in range(12):
        if len(v) < cfg.min_rod_points:
            break
        u = v / dist[:, None]
        seeds = u if len(u) <= 200 else u[rng.integers(0, len(u), 200)]
        sample = u if len(u) <= 2000 else u[rng.integers(0, len(u), 2000)]
        # einsum, not @: a multithreaded BLAS gemm stalls for milliseconds on a busy machine
        counts = (np.einsum("ik,jk->ij", seeds, sample) > np.cos(spread / 2)).sum(axis=1)
        member = u @ seeds[int(np.argmax(counts))] > np.cos(spread)
        a = None
        for _trim in range(4):
            if np.count_nonzero(member) < cfg.min_rod_points:
                a = None
                break
            h = np.sqrt(dist[member] ** 2 - r_rod**2)
            a, *_ = np.linalg.lstsq(v[member], h, rcond=None)
            a /= np.linalg.norm(a)
            radial = np.linalg.norm(v - np.outer(v @ a, a), axis=1)
            member = (np.abs(radial - r_rod) < 1.0) & (v @ a > 0)
        if a is None or np.count_nonzero(member) < cfg.min_rod_points:
            break
        axes.append(a)
        inside = v @ a > dist * np.cos(cone)
        v, dist = v[~inside], dist[~inside]
    return np.array(axes).reshape(-1, 3)


def fit_sphere_robust(points, radius: float | None = None, *, expected_radius: float | None = None,
                      flags: Mapping[str, np.ndarray] | None = None, viewpoints=None, rod_axes=None,
                      config: RejectionConfig | None = None) -> RobustSphereFit:
    """Fit one sphere to a candidate point set, rejecting everything that is not sphere.

    Parameters
    ----------
    points : array_like, shape (n, 3)
        Candidate points (one image region), NaN allowed.
    radius : float, optional
        Fix the radius of the final fit (e.g. the CMM radius); free otherwise.
    expected_radius : float, optional
        Plausible radius for RANSAC (defaults to ``radius``).
    flags : mapping of str to bool arrays (n,), optional
        Caller's per-point rejections, applied in the mapping's order, e.g.
        ``{"edge": ..., "glint": ...}``.
    viewpoints : array_like, shape (m, 3), optional
        Camera and projector pinholes for the silhouette test.
    rod_axes : array_like, shape (k, 3), optional
        Known rod directions from the sphere centre (:func:`rod_directions`).
    config : RejectionConfig

    Returns
    -------
    RobustSphereFit

    Raises
    ------
    SphereRejectionError
        Fewer than ``config.min_points`` points survive.
    FitError
        No plausible sphere in the points.
    """
    cfg = config or RejectionConfig()
    p = np.asarray(points, float)
    if p.ndim != 2 or p.shape[1] != 3:
        raise FitError(f"sphere: points must have shape (n, 3), got {p.shape}")
    n = len(p)
    flags = dict(flags or {})
    reasons = ("invalid", *flags.keys(), "rod", "silhouette", "residual")
    for name in flags:
        if name in ("invalid", "rod", "silhouette", "residual"):
            raise ValueError(f"flag name {name!r} is reserved")
    code = {name: i for i, name in enumerate(reasons)}
    reason = np.full(n, -1, np.int8)
    finite = np.all(np.isfinite(p), axis=1)
    reason[~finite] = code["invalid"]
    for name, mask in flags.items():
        mask = np.asarray(mask, bool)
        if mask.shape != (n,):
            raise ValueError(f"flag {name!r} has shape {mask.shape}, expected ({n},)")
        reason[(reason < 0) & mask] = code[name]
    base = reason < 0

    def counts(r):
        c = np.bincount(r[r >= 0], minlength=len(reasons))
        return {name: int(c[i]) for i, name in enumerate(reasons)}

    if np.count_nonzero(base) < cfg.min_points:
        raise SphereRejectionError(f"sphere: {np.count_nonzero(base)} usable point(s), fewer than "
                                   f"{cfg.min_points}", counts(reason))
    exp_r = expected_radius if expected_radius is not None else radius
    rng = np.random.default_rng(cfg.seed)
    thr0 = cfg.ransac_threshold_mm or max(5 * cfg.noise_mm, 0.05)
    c0, r0 = _ransac(p[base], exp_r, thr0, cfg, rng)
    r_start = radius if radius is not None else r0
    kept = base & (np.abs(np.linalg.norm(np.where(base[:, None], p, 0) - c0, axis=1) - r_start) <= thr0)
    known = np.zeros((0, 3)) if rod_axes is None else np.asarray(rod_axes, float).reshape(-1, 3)
    if len(known):
        known = known / np.linalg.norm(known, axis=1, keepdims=True)
    views = None if viewpoints is None else np.asarray(viewpoints, float).reshape(-1, 3)
    cos_max = np.cos(np.radians(cfg.max_incidence_deg))
    axes, n_detected, sigma, thr, rounds = known, 0, cfg.noise_mm, thr0, 0
    model = None
    for rounds in range(1, cfg.max_rounds + 1):
        if np.count_nonzero(kept) < cfg.min_points:
            break
        model = SphereModel.from_estimate(p[kept], radius)
        res = np.where(base, model.residuals(np.where(base[:, None], p, 0)), np.inf)
        sigma = 1.4826 * float(np.median(np.abs(res[kept])))
        thr = cfg.threshold_sigma * max(cfg.noise_mm, sigma)
        v = np.where(base[:, None], p - model.centre, 0)
        dist = np.maximum(np.linalg.norm(v, axis=1), 1e-300)
        axes = known
        if cfg.detect_rods:
            found = detect_rods(p, model.centre, model.radius, base & (res > thr), cfg)
            axes, n_detected = np.vstack([known, found]), len(found)
        new_reason = np.full(n, -1, np.int8)
        if len(axes):
            cone = np.arcsin(min(1.0, (cfg.rod_radius_mm + cfg.rod_margin_mm) / model.radius))
            # also everything on the rods far out (their angle shrinks with distance)
            in_cone = (np.einsum("ij,kj->ik", v, axes) / dist[:, None] > np.cos(cone)).any(axis=1)
            new_reason[base & in_cone] = code["rod"]
        if views is not None:
            normal = v / dist[:, None]
            sil = np.zeros(n, bool)
            for o in views:
                sight = o - p
                cos_inc = np.einsum("ij,ij->i", normal, sight) / np.linalg.norm(sight, axis=1)
                sil |= cos_inc < cos_max
            new_reason[base & (new_reason < 0) & sil] = code["silhouette"]
        new_reason[base & (new_reason < 0) & (np.abs(res) > thr)] = code["residual"]
        new_kept = base & (new_reason < 0)
        if np.array_equal(new_kept, kept):
            reason[base] = new_reason[base]
            break
        kept = new_kept
        reason[base] = new_reason[base]
    if np.count_nonzero(kept) < cfg.min_points or model is None:
        raise SphereRejectionError(f"sphere: {np.count_nonzero(kept)} point(s) survive rejection, fewer "
                                   f"than {cfg.min_points}", counts(reason))
    model = SphereModel.from_estimate(p[kept], radius)
    return RobustSphereFit(model, kept, reason, reasons, counts(reason), axes, n_detected, float(thr),
                           float(sigma), rounds)


@dataclass(frozen=True)
class RobustPlaneFit:
    """Result of :func:`fit_plane_robust`: the plane of the kept points, the kept
    mask (n,) and the residual threshold used."""

    model: PlaneModel
    kept: np.ndarray = field(repr=False)
    threshold_mm: float
    sigma_mm: float


def fit_plane_robust(points, noise_mm: float = 0.02, threshold_sigma: float = 4.0, toward=None,
                     ransac_threshold_mm: float | None = None, iterations: int = 300,
                     seed: int = 0) -> RobustPlaneFit:
    """Total-least-squares plane of the dominant flat surface in ``points`` (n, 3).

    RANSAC on 3-point planes (inlier band ``ransac_threshold_mm``, default
    ``max(5 noise_mm, 0.05)``), then iterative trimming at ``threshold_sigma`` times
    the larger of ``noise_mm`` and the robust residual scale.
    """
    p = np.asarray(points, float)
    finite = np.all(np.isfinite(p), axis=1)
    q_all = p[finite]
    if len(q_all) < 3:
        raise FitError(f"plane: {len(q_all)} finite point(s); at least 3 are needed")
    rng = np.random.default_rng(seed)
    thr0 = ransac_threshold_mm or max(5 * noise_mm, 0.05)
    shift = q_all.mean(axis=0)
    q = q_all - shift
    score = q if len(q) <= 3000 else q[rng.integers(0, len(q), 3000)]
    idx = rng.integers(0, len(q), (iterations, 3))
    normals = np.cross(q[idx[:, 1]] - q[idx[:, 0]], q[idx[:, 2]] - q[idx[:, 0]])
    norm = np.linalg.norm(normals, axis=1)
    ok = norm > 1e-9
    normals = normals[ok] / norm[ok, None]
    offsets = np.einsum("ij,ij->i", normals, q[idx[ok, 0]])
    loss = np.minimum((np.einsum("kj,ij->ki", normals, score) - offsets[:, None]) ** 2, thr0**2).sum(axis=1)
    k = int(np.argmin(loss))
    kept = np.zeros(len(p), bool)
    kept[finite] = np.abs(q @ normals[k] - offsets[k]) <= thr0
    thr, sigma = thr0, noise_mm
    for _ in range(10):
        if kept.sum() < 3:
            raise FitError("plane: too few points on the dominant plane")
        model = PlaneModel.from_estimate(p[kept], toward=toward)
        res = np.where(finite, np.abs(model.residuals(np.where(finite[:, None], p, 0))), np.inf)
        sigma = 1.4826 * float(np.median(res[kept]))
        thr = threshold_sigma * max(noise_mm, sigma)
        new = res <= thr
        if np.array_equal(new, kept):
            break
        kept = new
    return RobustPlaneFit(PlaneModel.from_estimate(p[kept], toward=toward), kept, float(thr), float(sigma))
