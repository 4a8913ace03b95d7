"""Which fitted sphere is which artefact sphere: labelling by inter-centre distances.

The thesis ordered the fitted centres by hand (section 6.2.1). Here the candidates
of one (measurement, scanner) -- fitted centres in the scanner frame, in any order,
possibly with false candidates, missing spheres and poor partial fits -- are matched
to the artefact definition by an interpretation tree (Grimson & Lozano-Perez): each
candidate is assigned an artefact sphere or "none", and a branch survives only if
every pair of assigned candidates is as far apart as their spheres on the CMM, up to
one common scale factor ``sigma`` and a tolerance built from the uncertainties::

    |d_ij - sigma D_ab| <= k sqrt(u_i^2 + u_j^2 + u_a^2 + u_b^2),   |sigma - 1| <= scale_tol

(u_i: standard uncertainty of a fitted centre coordinate, u_a: of a CMM centre). The
branch carries the interval of scales its pairs allow and dies when it is empty, so
all pairs of a labelling agree on one scale: a scanner whose own calibration is
0.6 % short measures every distance 0.6 % short, not some short and some long.
Complete branches with at least ``min_spheres`` spheres are verified by a similarity
registration (:func:`fringecal.registration.umeyama`, scale within ``scale_tol``):
every matched centre must lie within ``k sqrt(u_i^2 + u_a^2)`` of its registered CMM
centre, which also rejects mirror-image assignments that distances alone cannot tell
apart.

The labelling with the most verified spheres wins, and only if it is the only one:
when two different labellings explain the data equally well (e.g. subsets of the
artefact that are symmetric within the tolerance), the measurement is refused with
both alternatives named, never guessed. A prior pose (for example the hexapod's
planned pose) or the set of spheres a scanner can see removes such ambiguities.

The tolerances are the prior calibration's stated uncertainty (:class:`LabellingConfig`);
:func:`label_sphere_fits` (module :mod:`fringecal.spheres.label_scanners`) estimates each
scanner's scale and centre uncertainty from all its measurements, labels again with
them, finds each scanner's frame by consensus of its measurements and the planned
poses, and refuses any labelling the others contradict.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field

import numpy as np

from fringecal.artefact import Artefact
from fringecal.frames import Frame
from fringecal.registration import DegenerateGeometryError, RigidRegistration, kabsch, umeyama

__all__ = ["LabellingConfig", "Labelling", "LabellingRefused", "label_spheres", "ambiguous_subsets", "REFUSAL_REASONS"]

#: Codes of :class:`LabellingRefused`.
REFUSAL_REASONS = {
    "too_few_candidates": "fewer candidates than min_spheres can be artefact spheres",
    "inconsistent": "no assignment of min_spheres or more candidates matches the artefact's distances and shape, "
                    "or the scanner's other measurements contradict the labelling",
    "ambiguous": "two or more different assignments explain the data equally well",
    "search_limit": "the interpretation tree exceeded its node budget",
}


class LabellingRefused(ValueError):
    """The candidates cannot be labelled with certainty.

    Attributes
    ----------
    reason : str
        One of :data:`REFUSAL_REASONS`.
    alternatives : list of tuple
        For ``ambiguous``: the competing labellings (sphere id or None per candidate).
    """

    def __init__(self, reason: str, message: str, alternatives=()):
        super().__init__(f"{reason}: {message}")
        self.reason = reason
        self.alternatives = list(alternatives)


@dataclass(frozen=True)
class LabellingConfig:
    """Tolerances of the labelling: the prior calibration's stated uncertainty.

    The defaults are sized for scanners known only by their own (prior) calibration,
    as a customer's cell gives them: sphere centres up to 3 mm RMS off the CMM
    geometry (a scale error of up to 0.6 % about the scanner's origin, ~1 mm of
    smooth distortion-like warp, noise), planned hexapod poses good to ~1 mm / 1 mrad
    relative to each other, and each scanner's frame arbitrary. They are upper
    bounds: :func:`label_sphere_fits` estimates each scanner's scale and centre
    uncertainty from its measurements and labels again with those (never looser than
    stated here). For the simulated rig's true sensors (~0.01 mm) give
    ``centre_u_mm=0.01``.

    Attributes
    ----------
    k : float
        Tolerance in standard uncertainties.
    centre_u_mm : float
        The prior calibration's standard uncertainty of a sphere centre per
        coordinate once the scanner's scale is removed (warp and noise); also the
        floor of a fitted centre's own uncertainty (a fit's covariance says ~1 um).
        Default 0.75 mm: ~1 mm of warp plus noise.
    scale_tol : float
        The largest scale error of a prior calibration (relative): every distance of
        one scanner may be off by one common factor within ``1 +- scale_tol``.
        Default 0.008 (documented priors: up to 0.6 %).
    radius_tol_mm : float
        A candidate whose fitted radius differs more from every allowed sphere's
        CMM radius is not a sphere of the artefact (ignored when radii are not given).
    min_spheres : int
    prior_tol_mm : float
        With a prior pose, a candidate can only be a sphere predicted within this
        distance (an upper bound; spheres are ~600 mm apart).
    ambiguity_margin : float
        The winner is refused if a conflicting labelling with as many spheres passes
        with the tolerance widened by this factor: a clear winner is required, not
        one that won by a hair.
    max_nodes : int
        Budget of the tree search.
    plan_u_mm, plan_u_rad : float
        Standard uncertainty of the planned poses relative to each other (hexapod:
        ~1 mm, ~1 mrad); sizes how closely the scanner frames implied by different
        measurements must agree.
    consensus_margin : float
        The scanner frame found by consensus of the planned poses is refused when a
        different frame explains the measurements nearly as well: the rival's robust
        misfit (sum over measurements of the squared normalised distance, each
        capped at ``k**2``) must exceed the winner's by this much (default ``k**2``:
        at least one measurement flatly contradicts the rival and not the winner).
    refine : bool
        Refine the scale and centre uncertainty per scanner from its measurements
        (:func:`label_sphere_fits`).
    """

    k: float = 4.0
    centre_u_mm: float = 0.75
    scale_tol: float = 0.008
    radius_tol_mm: float = 1.0
    min_spheres: int = 3
    prior_tol_mm: float = 100.0
    ambiguity_margin: float = 2.0
    max_nodes: int = 2_000_000
    plan_u_mm: float = 1.0
    plan_u_rad: float = 0.001
    consensus_margin: float = 16.0
    refine: bool = True

    def __post_init__(self):
        rules = {"k": (self.k > 0, "> 0"), "centre_u_mm": (self.centre_u_mm > 0, "> 0"),
                 "scale_tol": (0 <= self.scale_tol < 0.5, "in [0, 0.5)"),
                 "radius_tol_mm": (self.radius_tol_mm >= 0, ">= 0"), "min_spheres": (self.min_spheres >= 3, ">= 3"),
                 "prior_tol_mm": (self.prior_tol_mm > 0, "> 0"),
                 "ambiguity_margin": (self.ambiguity_margin >= 1, ">= 1"), "max_nodes": (self.max_nodes > 0, "> 0"),
                 "plan_u_mm": (self.plan_u_mm >= 0, ">= 0"), "plan_u_rad": (self.plan_u_rad >= 0, ">= 0"),
                 "consensus_margin": (self.consensus_margin >= 0, ">= 0")}
        bad = [f"{name} = {getattr(self, name)!r} (must be {rule})" for name, (ok, rule) in rules.items() if not ok]
        if bad:
            raise ValueError(f"labelling settings: {'; '.join(bad)}")


@dataclass(frozen=True)
class Labelling:
    """An accepted labelling.

    Attributes
    ----------
    sphere_ids : tuple
        Artefact sphere id per candidate, None for candidates left unlabelled.
    residuals_mm : ndarray, shape (n,)
        Distance of each labelled candidate from its registered CMM centre (NaN if unlabelled).
    T_scanner_artefact : Frame
        The rigid registration of the labelled CMM centres onto the candidate centres
        divided by ``scale`` (artefact -> scale-corrected scanner frame).
    rms_mm : float
    unlabelled : dict
        Candidate index -> why it was left out.
    nodes : int
        Tree nodes visited.
    scale : float
        The scanner's scale this labelling implies: the ``scale`` given to
        :func:`label_spheres` times the fitted residual scale.
    """

    sphere_ids: tuple
    residuals_mm: np.ndarray = field(repr=False)
    T_scanner_artefact: Frame
    rms_mm: float
    unlabelled: dict
    nodes: int
    scale: float = 1.0

    @property
    def n_labelled(self) -> int:
        return sum(s is not None for s in self.sphere_ids)


def _conflict(a: dict, b: dict) -> bool:
    """Do two assignments (candidate -> sphere) disagree on any candidate or sphere?"""
    inv_b = {s: c for c, s in b.items()}
    return any((c in b and b[c] != s) or (s in inv_b and inv_b[s] != c) for c, s in a.items())


class _Search:
    """Interpretation tree over candidates; verified leaves with the most spheres.

    Each branch carries the interval of scales its pairs allow; a leaf is verified by
    a similarity registration with the scale inside ``scale_bounds``.
    """

    def __init__(self, X, d, D, Y, u, ua, order, options, scale_bounds, max_nodes):
        self.X, self.d, self.D, self.Y = X, d, D, Y
        self.u2, self.ua2 = u**2, ua**2
        self.order, self.options = order, options
        self.scale_bounds, self.max_nodes = scale_bounds, max_nodes
        self.nodes = 0

    def run(self, k: float, min_count: int) -> list[tuple[dict, np.ndarray, float, float]]:
        u2, ua2, d, D = self.u2, self.ua2, self.d, self.D
        # scale interval each (candidate pair, sphere pair) allows: sigma in [LO, HI]
        t = k * np.sqrt(u2[:, None, None, None] + u2[None, :, None, None] + ua2[None, None, :, None]
                        + ua2[None, None, None, :])
        with np.errstate(divide="ignore", invalid="ignore"):
            LO = (d[:, :, None, None] - t) / D[None, None]
            HI = (d[:, :, None, None] + t) / D[None, None]
        same = np.eye(len(D), dtype=bool)[None, None]
        LO, HI = np.where(same, np.inf, LO), np.where(same, -np.inf, HI)
        order = self.order
        order_arr = np.asarray(order, int)
        X, Y = self.X, self.Y
        # a 3-D position error that verification would still accept, per candidate
        eps = np.sqrt(3) * k * np.sqrt(u2 + ua2.max())
        cross_c, cross_s = {}, {}

        def cross(p, q):
            return np.array([p[1] * q[2] - p[2] * q[1], p[2] * q[0] - p[0] * q[2], p[0] * q[1] - p[1] * q[0]])

        def handed_c(j0, j1, j2, i):
            """Signed volume of candidates (j0, j1, j2, i) and its error bound."""
            if (j0, j1, j2) not in cross_c:
                n = cross(X[j1] - X[j0], X[j2] - X[j0])
                cross_c[j0, j1, j2] = n, float(np.sqrt(n @ n))
            n, nn = cross_c[j0, j1, j2]
            v = float(n @ (X[i] - X[j0]))
            return v, 2 * eps[i] * (nn + d[j0, i] * (d[j0, j1] + d[j0, j2]))

        def handed_s(b0, b1, b2, e):
            """Signed volumes of spheres (b0, b1, b2, every sphere) and their error bounds."""
            if (b0, b1, b2) not in cross_s:
                n = cross(Y[b1] - Y[b0], Y[b2] - Y[b0])
                cross_s[b0, b1, b2] = (Y - Y[b0]) @ n, float(np.sqrt(n @ n)) + D[b0] * (D[b0, b1] + D[b0, b2])
            v, bound = cross_s[b0, b1, b2]
            return v, 2 * e * bound
        allowed = np.zeros((len(d), len(D)), bool)
        for i, o in self.options.items():
            allowed[i, o] = True
        best = [min_count]
        found: list[tuple[dict, np.ndarray, float, float]] = []
        assign: dict[int, int] = {}
        used = np.zeros(len(D), bool)

        def leaf():
            if len(assign) < best[0]:
                return
            idx = sorted(assign)
            spheres = [assign[i] for i in idx]
            Ya, Xa = self.Y[spheres], self.X[idx]
            s, M, T = umeyama(Ya, Xa, self.scale_bounds)
            res = np.linalg.norm(s * Ya @ M.T + T - Xa, axis=1)
            if np.any(res > k * np.sqrt(u2[idx] + ua2[spheres])):
                return
            if len(assign) > best[0]:
                best[0] = len(assign)
                found.clear()
            found.append((dict(assign), res, float(np.sqrt(np.mean(res**2))), s))

        def search(pos, lo, hi):
            self.nodes += 1
            if self.nodes > self.max_nodes:
                raise LabellingRefused("search_limit", f"more than {self.max_nodes} tree nodes; "
                                       "give allowed_ids or a prior pose")
            if len(assign) + (len(order) - pos) < best[0]:
                return
            if pos == len(order):
                leaf()
                return
            i = order[pos]
            if assign and pos + 1 < len(order):
                # forward check: how many of the candidates still to come can be a sphere at all
                rest, js, bs = order_arr[pos:], list(assign), list(assign.values())
                lo_r = np.maximum(lo, LO[rest[:, None], js, :, bs].max(axis=1))
                hi_r = np.minimum(hi, HI[rest[:, None], js, :, bs].min(axis=1))
                alive = ((lo_r <= hi_r) & allowed[rest] & ~used).any(axis=1)
                if len(assign) + int(alive.sum()) < best[0]:
                    return
            if assign:
                js, bs = list(assign), list(assign.values())
                lo_a = np.maximum(lo, LO[i, js, :, bs].max(axis=0))
                hi_a = np.minimum(hi, HI[i, js, :, bs].min(axis=0))
                feasible = (lo_a <= hi_a) & allowed[i] & ~used
                if len(js) >= 3:
                    # handedness: the tetrahedron of the first three and this one must not be
                    # mirrored (where its volume is clearly not zero), as a rigid motion keeps it
                    vc, bc = handed_c(js[0], js[1], js[2], i)
                    if abs(vc) > bc:
                        vs, bs_ = handed_s(bs[0], bs[1], bs[2], eps[i])
                        feasible &= ~((np.sign(vs) != np.sign(vc)) & (np.abs(vs) > bs_))
            else:
                lo_a, hi_a = np.full(len(D), lo), np.full(len(D), hi)
                feasible = allowed[i] & ~used
            for a in np.flatnonzero(feasible).tolist():
                assign[i] = a
                used[a] = True
                search(pos + 1, lo_a[a], hi_a[a])
                del assign[i]
                used[a] = False
            search(pos + 1, lo, hi)  # candidate i is not an artefact sphere

        search(0, *self.scale_bounds)
        return found


def label_spheres(centres, artefact: Artefact, uncertainties=None, radii=None, allowed_ids=None,
                  prior: Frame | None = None, config: LabellingConfig | None = None,
                  scale: float = 1.0) -> Labelling:
    """Label candidate sphere centres against an artefact definition.

    Parameters
    ----------
    centres : array_like, shape (n, 3)
        Fitted candidate centres in the scanner frame, any order.
    artefact : Artefact
    uncertainties : array_like, shape (n,) or (n, 3), optional
        Standard uncertainty of each centre (per coordinate); floored at
        ``config.centre_u_mm``.
    radii : array_like, shape (n,), optional
        Fitted radii, checked against the CMM radii.
    allowed_ids : iterable of str, optional
        Spheres this scanner can see (default: all).
    prior : Frame, optional
        Approximate ``T_scanner_artefact`` (in the frame of the centres divided by
        ``scale``); restricts each candidate to spheres predicted within
        ``config.prior_tol_mm``.
    config : LabellingConfig
    scale : float
        The scanner's scale if known (estimated from its other measurements): the
        centres are divided by it, about the scanner's origin, and the remaining
        scale may be off by ``config.scale_tol``.

    Returns
    -------
    Labelling

    Raises
    ------
    LabellingRefused
        With ``reason`` in :data:`REFUSAL_REASONS`.

    Examples
    --------
    >>> art = Artefact(list("ABCDE"), [[0, 0, 0], [500, 0, 0], [0, 400, 0], [0, 0, 300], [200, 200, 200]],
    ...                [50] * 5)
    >>> T = Frame.from_params([10, 20, 2000, 0.3, -0.2, 1.0])
    >>> seen = 1.005 * T.to_world(art.centres_of(["D", "A", "E", "B"]))  # 0.5 % long
    >>> lab = label_spheres(np.vstack([seen, [[0.0, 0.0, 0.0]]]), art)  # plus a false candidate
    >>> lab.sphere_ids, round(lab.scale, 6)
    (('D', 'A', 'E', 'B', None), 1.005)
    """
    cfg = config or LabellingConfig()
    X = np.asarray(centres, float).reshape(-1, 3) / scale
    n = len(X)
    u = np.full(n, cfg.centre_u_mm) if uncertainties is None else np.asarray(uncertainties, float)
    if u.ndim == 2:
        u = np.sqrt(np.mean(u**2, axis=1))
    # unknown (NaN) uncertainty takes the floor: an infinite one would match anything
    u = np.maximum(np.nan_to_num(u, nan=cfg.centre_u_mm, posinf=cfg.centre_u_mm), cfg.centre_u_mm)
    ua = np.asarray(artefact.u, float)
    m = len(artefact)
    compat = np.ones((n, m), bool)
    why = {}
    if allowed_ids is not None:
        allowed = set(map(str, allowed_ids))
        compat &= np.array([sid in allowed for sid in artefact.ids])[None, :]
    if radii is not None:
        r = np.asarray(radii, float)
        ok = np.abs(r[:, None] - artefact.radii[None, :]) <= cfg.radius_tol_mm
        for i in np.flatnonzero(~ok.any(axis=1) & compat.any(axis=1)):
            why[int(i)] = f"radius {r[i]:.3f} mm matches no artefact sphere"
        compat &= ok
    if prior is not None:
        predicted = prior.to_world(artefact.centres)
        near = np.linalg.norm(X[:, None, :] - predicted[None, :, :], axis=2) <= cfg.prior_tol_mm
        for i in np.flatnonzero(~near.any(axis=1) & compat.any(axis=1)):
            why.setdefault(int(i), f"no sphere predicted within {cfg.prior_tol_mm:g} mm by the prior pose")
        compat &= near
    usable = np.flatnonzero(compat.any(axis=1))
    if len(usable) < cfg.min_spheres:
        raise LabellingRefused("too_few_candidates",
                               f"{len(usable)} of {n} candidate(s) can be artefact spheres; "
                               f"at least {cfg.min_spheres} are needed")

    D = artefact.distance_matrix()
    d = np.linalg.norm(X[:, None, :] - X[None, :, :], axis=2)
    # most constrained candidates first: fewer options, then fewer artefact distances like its
    # distances to the other candidates (a distinctive candidate near the root prunes more)
    tol = cfg.k * 2 * np.sqrt(2) * max(float(np.max(u)), float(np.max(ua))) + cfg.scale_tol * D.max()
    like = np.array([np.sum(np.abs(d[i][usable, None, None] - D[None]) <= tol) for i in range(n)])
    order = sorted(usable, key=lambda i: (compat[i].sum(), like[i]))
    options = {i: np.flatnonzero(compat[i]) for i in order}
    bounds = (1.0 - cfg.scale_tol, 1.0 + cfg.scale_tol)
    search = _Search(X, d, D, artefact.centres, u, ua, order, options, bounds, cfg.max_nodes)
    found = search.run(cfg.k, cfg.min_spheres)
    if not found:
        raise LabellingRefused("inconsistent",
                               f"no {cfg.min_spheres} or more of the {n} candidates match the artefact's "
                               "distances and shape within tolerance")

    def named(a):
        return tuple(artefact.ids[a[i]] if i in a else None for i in range(n))

    if len(found) > 1:
        alts = [named(a) for a, _, _, _ in found]
        shown = "; ".join(f"{list(alt)} (rms {f[2]:.3f} mm)" for alt, f in list(zip(alts, found))[:4])
        raise LabellingRefused("ambiguous", f"{len(found)} labellings of {len(found[0][0])} spheres fit equally "
                               f"well: {shown}", alts)
    # A labelling is trusted only if no conflicting one with as many spheres comes
    # even close: search again with the tolerance widened by ambiguity_margin.
    best = found[0][0]
    rivals = [a for a, _, _, _ in search.run(cfg.k * cfg.ambiguity_margin, len(best)) if _conflict(a, best)]
    if rivals:
        alts = [named(best)] + [named(a) for a in rivals]
        raise LabellingRefused("ambiguous", f"the best labelling {list(alts[0])} has {len(rivals)} rival(s) within "
                               f"{cfg.ambiguity_margin:g}x the tolerance, e.g. {list(alts[1])}", alts)
    assign_best, res, rms, s_fit = found[0]
    ids = named(assign_best)
    idx = sorted(assign_best)
    residuals = np.full(n, np.nan)
    residuals[idx] = res
    for i in range(n):
        if ids[i] is None:
            why.setdefault(i, "does not fit the labelled spheres' geometry")
    Y, Xs = artefact.centres[[assign_best[i] for i in idx]], X[idx] / s_fit
    try:
        T = RigidRegistration.from_estimate(Y, Xs).frame
    except DegenerateGeometryError:
        M, t = kabsch(Y, Xs)
        T = Frame.from_matrix(M.T, t)
    return Labelling(ids, residuals, T, rms, why, search.nodes, float(scale * s_fit))


def ambiguous_subsets(artefact: Artefact, subset_size: int, ids=None, config: LabellingConfig | None = None):
    """Subsets of ``ids`` (default all spheres) whose exact centres cannot be labelled
    unambiguously with ``config``: yields (subset, alternatives). For planning which
    spheres a scanner must see."""
    ids = list(artefact.ids if ids is None else map(str, ids))
    cfg = config or LabellingConfig()
    for sub in itertools.combinations(ids, subset_size):
        try:
            label_spheres(artefact.centres_of(sub), artefact, config=cfg)
        except LabellingRefused as err:
            if err.reason == "ambiguous":
                yield sub, err.alternatives
