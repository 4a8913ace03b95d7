"""Which fitted sphere is which artefact sphere: labelling by inter-centre distances.

The thesis ordered the fitted centres by hand (section 6.2.1). Here the candidates
of one (measurement, scanner) -- fitted centres in the scanner frame, in any order,
possibly with false candidates, missing spheres and poor partial fits -- are matched
to the artefact definition by an interpretation tree (Grimson & Lozano-Perez): each
candidate is assigned an artefact sphere or "none", and a branch survives only if
every pair of assigned candidates is as far apart as their spheres on the CMM,
within a tolerance built from the uncertainties::

    |d_ij - D_ab| <= k sqrt(u_i^2 + u_j^2 + u_a^2 + u_b^2) + scale_tol D_ab

(u_i: standard uncertainty of a fitted centre coordinate, u_a: of a CMM centre).
Complete branches with at least ``min_spheres`` spheres are verified by SVD
registration (:func:`fringecal.registration.kabsch`): every matched centre must lie
within ``k sqrt(u_i^2 + u_a^2)`` (+ the scale term) of its registered CMM centre,
which also rejects mirror-image assignments that distances alone cannot tell apart.

The labelling with the most verified spheres wins, and only if it is the only one:
when two different labellings explain the data equally well (e.g. subsets of the
artefact that are symmetric within the tolerance), the measurement is refused with
both alternatives named, never guessed. A prior pose (for example the hexapod's
planned pose) or the set of spheres a scanner can see removes such ambiguities.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from ..artefact import Artefact
from ..frames import Frame
from ..registration import DegenerateGeometryError, RigidRegistration, kabsch

__all__ = ["LabellingConfig", "Labelling", "LabellingRefused", "label_spheres", "label_sphere_fits",
           "scanner_frame_from_plan", "ambiguous_subsets", "REFUSAL_REASONS"]

#: Codes of :class:`LabellingRefused`.
REFUSAL_REASONS = {
    "too_few_candidates": "fewer candidates than min_spheres can be artefact spheres",
    "inconsistent": "no assignment of min_spheres or more candidates matches the artefact's distances and shape",
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
    """Tolerances of :func:`label_spheres`.

    Attributes
    ----------
    k : float
        Tolerance in standard uncertainties.
    centre_u_mm : float
        Floor of a fitted centre's standard uncertainty per coordinate. A fit's own
        covariance says ~1 um; what limits agreement with the CMM is the scanner's
        calibration (simulated rig: ~0.01 mm; uncalibrated real scanners, like the
        thesis's before bundle adjustment: ~0.2 mm, so use ~0.15 there).
    scale_tol : float
        Relative length error allowed on top (scanner scale, temperature).
    radius_tol_mm : float
        A candidate whose fitted radius differs more from every allowed sphere's
        CMM radius is not a sphere of the artefact (ignored when radii are not given).
    min_spheres : int
    prior_tol_mm : float
        With a prior pose, a candidate can only be a sphere predicted within this
        distance.
    ambiguity_margin : float
        The winner is refused if a conflicting labelling with as many spheres passes
        with the tolerance widened by this factor: a clear winner is required, not
        one that won by a hair.
    max_nodes : int
        Budget of the tree search.
    """

    k: float = 4.0
    centre_u_mm: float = 0.02
    scale_tol: float = 1e-4
    radius_tol_mm: float = 1.0
    min_spheres: int = 3
    prior_tol_mm: float = 100.0
    ambiguity_margin: float = 2.0
    max_nodes: int = 2_000_000


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
        The SVD registration of the labelled centres (artefact -> scanner frame).
    rms_mm : float
    unlabelled : dict
        Candidate index -> why it was left out.
    nodes : int
        Tree nodes visited.
    """

    sphere_ids: tuple
    residuals_mm: np.ndarray = field(repr=False)
    T_scanner_artefact: Frame
    rms_mm: float
    unlabelled: dict
    nodes: int

    @property
    def n_labelled(self) -> int:
        return sum(s is not None for s in self.sphere_ids)


def _verify(X, Y, tol_pts):
    """Rigid fit of CMM centres Y onto candidates X; residuals and whether all pass."""
    M, T = kabsch(Y, X)
    res = np.linalg.norm(Y @ M.T + T - X, axis=1)
    return res, bool(np.all(res <= tol_pts))


def _conflict(a: dict, b: dict) -> bool:
    """Do two assignments (candidate -> sphere) disagree on any candidate or sphere?"""
    inv_b = {s: c for c, s in b.items()}
    return any((c in b and b[c] != s) or (s in inv_b and inv_b[s] != c) for c, s in a.items())


class _Search:
    """Interpretation tree over candidates; verified leaves with the most spheres."""

    def __init__(self, X, d, D, Y, u, ua, order, options, cfg):
        self.X, self.d, self.D, self.Y, self.u, self.ua = X, d, D, Y, u, ua
        self.order, self.options, self.cfg = order, options, cfg
        self.nodes = 0

    def run(self, k: float, min_count: int) -> list[tuple[dict, np.ndarray, float]]:
        cfg, u, ua, d, D = self.cfg, self.u, self.ua, self.d, self.D
        order, options = self.order, self.options
        best = [min_count]
        found: list[tuple[dict, np.ndarray, float]] = []
        assign: dict[int, int] = {}
        used: set[int] = set()

        def pair_ok(i, a, j, b):
            tol = k * np.sqrt(u[i] ** 2 + u[j] ** 2 + ua[a] ** 2 + ua[b] ** 2) + cfg.scale_tol * D[a, b]
            return abs(d[i, j] - D[a, b]) <= tol

        def leaf():
            if len(assign) < best[0]:
                return
            idx = sorted(assign)
            spheres = [assign[i] for i in idx]
            Ya = self.Y[spheres]
            spread = np.linalg.norm(Ya - Ya.mean(axis=0), axis=1)
            tol = k * np.sqrt(u[idx] ** 2 + ua[spheres] ** 2) + cfg.scale_tol * spread
            res, ok = _verify(self.X[idx], Ya, tol)
            if not ok:
                return
            if len(assign) > best[0]:
                best[0] = len(assign)
                found.clear()
            found.append((dict(assign), res, float(np.sqrt(np.mean(res**2)))))

        def search(pos):
            self.nodes += 1
            if self.nodes > cfg.max_nodes:
                raise LabellingRefused("search_limit", f"more than {cfg.max_nodes} tree nodes; "
                                       "give allowed_ids or a prior pose")
            if len(assign) + (len(order) - pos) < best[0]:
                return
            if pos == len(order):
                leaf()
                return
            i = order[pos]
            for a in options[i]:
                if a in used or not all(pair_ok(i, a, j, b) for j, b in assign.items()):
                    continue
                assign[i] = a
                used.add(a)
                search(pos + 1)
                del assign[i]
                used.discard(a)
            search(pos + 1)  # candidate i is not an artefact sphere

        search(0)
        return found


def label_spheres(centres, artefact: Artefact, uncertainties=None, radii=None, allowed_ids=None,
                  prior: Frame | None = None, config: LabellingConfig | None = None) -> Labelling:
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
        Approximate ``T_scanner_artefact``; restricts each candidate to spheres
        predicted within ``config.prior_tol_mm``.
    config : LabellingConfig

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
    >>> seen = T.to_world(art.centres_of(["D", "A", "E", "B"]))
    >>> lab = label_spheres(np.vstack([seen, [[0.0, 0.0, 0.0]]]), art)  # plus a false candidate
    >>> lab.sphere_ids
    ('D', 'A', 'E', 'B', None)
    """
    cfg = config or LabellingConfig()
    X = np.asarray(centres, float).reshape(-1, 3)
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
    # most constrained candidates first: fewer options near the root prunes more
    order = sorted(usable, key=lambda i: compat[i].sum())
    options = {i: np.flatnonzero(compat[i]) for i in order}
    search = _Search(X, d, D, artefact.centres, u, ua, order, options, cfg)
    found = search.run(cfg.k, cfg.min_spheres)
    if not found:
        raise LabellingRefused("inconsistent",
                               f"no {cfg.min_spheres} or more of the {n} candidates match the artefact's "
                               "distances and shape within tolerance")

    def named(a):
        return tuple(artefact.ids[a[i]] if i in a else None for i in range(n))

    if len(found) > 1:
        alts = [named(a) for a, _, _ in found]
        shown = "; ".join(f"{list(alt)} (rms {r:.3f} mm)" for alt, (_, _, r) in list(zip(alts, found))[:4])
        raise LabellingRefused("ambiguous", f"{len(found)} labellings of {len(found[0][0])} spheres fit equally "
                               f"well: {shown}", alts)
    # A labelling is trusted only if no conflicting one with as many spheres comes
    # even close: search again with the tolerance widened by ambiguity_margin.
    best = found[0][0]
    rivals = [a for a, _, _ in search.run(cfg.k * cfg.ambiguity_margin, len(best)) if _conflict(a, best)]
    if rivals:
        alts = [named(best)] + [named(a) for a in rivals]
        raise LabellingRefused("ambiguous", f"the best labelling {list(alts[0])} has {len(rivals)} rival(s) within "
                               f"{cfg.ambiguity_margin:g}x the tolerance, e.g. {list(alts[1])}", alts)
    assign_best, res, rms = found[0]
    ids = tuple(artefact.ids[assign_best[i]] if i in assign_best else None for i in range(n))
    idx = sorted(assign_best)
    residuals = np.full(n, np.nan)
    residuals[idx] = res
    for i in range(n):
        if ids[i] is None:
            why.setdefault(i, "does not fit the labelled spheres' geometry")
    try:
        reg = RigidRegistration.from_estimate(artefact.centres[[assign_best[i] for i in idx]], X[idx])
        T = reg.frame
    except DegenerateGeometryError:
        M, t = kabsch(artefact.centres[[assign_best[i] for i in idx]], X[idx])
        T = Frame.from_matrix(M.T, t)
    return Labelling(ids, residuals, T, rms, why, search.nodes)


def _frame_of(X, Y) -> Frame:
    M, t = kabsch(Y, X)
    return Frame.from_matrix(M.T, t)


def scanner_frame_from_plan(results: dict, planned: dict, artefact: Artefact,
                            tol_mm: float) -> tuple[Frame | None, str]:
    """``T_scanner_world`` of one scanner from its labelled and ambiguous measurements.

    ``results``: measurement -> (candidate centres (n, 3), Labelling or LabellingRefused);
    ``planned``: measurement -> planned ``T_world_artefact``. Every accepted labelling
    and every alternative of an ambiguous one proposes ``T_scanner_artefact o
    T_world_artefact^-1``; a proposal is supported by each measurement with a
    proposal that maps the planned artefact within ``tol_mm`` of it. The best-
    supported proposal wins if no far-away proposal has as much support (a wrong
    alternative repeats the same symmetry, but the hexapod's moves between
    measurements make its proposals disagree). Returns (frame or None, reason).
    """
    probe = next(iter(planned.values())).to_world(artefact.centres)
    hyps = []
    for m, (X, res) in results.items():
        if m not in planned:
            continue
        if isinstance(res, Labelling):
            idx = [i for i, sid in enumerate(res.sphere_ids) if sid is not None]
            alts = [res.sphere_ids]
        elif isinstance(res, LabellingRefused) and res.reason == "ambiguous":
            alts = res.alternatives
        else:
            continue
        for alt in alts:
            idx = [i for i, sid in enumerate(alt) if sid is not None]
            if len(idx) < 3:
                continue
            T = _frame_of(X[idx], artefact.centres_of([alt[i] for i in idx]))
            hyps.append((m, T.compose(planned[m].inverse())))
    if not hyps:
        return None, "no labelled or ambiguous measurement with a planned pose"
    mapped = np.stack([T.to_world(probe) for _, T in hyps])
    close = np.linalg.norm(mapped[:, None] - mapped[None, :], axis=3).max(axis=2) <= tol_mm
    meas = np.array([m for m, _ in hyps])
    support = np.array([len(set(meas[close[i]])) for i in range(len(hyps))])
    best = int(np.argmax(support))
    rivals = [i for i in range(len(hyps)) if support[i] == support[best] and not close[best, i]]
    if rivals:
        return None, (f"the planned poses do not single out one scanner frame: {len(rivals) + 1} frames "
                      f"are each supported by {support[best]} measurement(s)")
    members = [hyps[i][1] for i in np.flatnonzero(close[best])]
    from ..linking import robust_mean_frame

    frame, _ = robust_mean_frame(members)
    return frame, f"supported by {support[best]} of {len(set(meas))} measurement(s)"


def label_sphere_fits(fits: pd.DataFrame, artefact: Artefact, config: LabellingConfig | None = None,
                      allowed_ids: dict | None = None, planned: dict | None = None) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Label every (measurement, scanner) group of a sphere-fits table.

    Parameters
    ----------
    fits : DataFrame
        Rows of :class:`schemas.SphereFitsTable` (``measurement, scanner, candidate,
        x_mm, y_mm, z_mm`` and optionally ``radius_mm``, ``u_x_mm, u_y_mm, u_z_mm``).
    artefact : Artefact
    config : LabellingConfig
    allowed_ids : dict, optional
        scanner -> sphere ids that scanner can see.
    planned : dict, optional
        measurement -> planned ``T_world_artefact`` (Frame) from the pose plan, in
        any fixed frame. Measurements that distances alone leave ambiguous are then
        labelled with the prior ``T_scanner_world o T_world_artefact``, where each
        scanner's ``T_scanner_world`` comes from :func:`scanner_frame_from_plan`;
        an accepted labelling that contradicts the plan is refused as inconsistent.

    Returns
    -------
    labelled : DataFrame
        ``fits`` with ``sphere_id`` filled ("" where unlabelled) and ``label_residual_mm``.
    outcomes : DataFrame
        :class:`schemas.LabelOutcomesTable`: one row per group with ``status``
        (labelled / refused), ``reason``, ``method`` (distances / planned pose),
        ``n_candidates, n_labelled, rms_mm, message``.
    """
    cfg = config or LabellingConfig()
    out = fits.copy().reset_index(drop=True)
    out["sphere_id"] = ""
    out["label_residual_mm"] = np.nan
    groups = {}
    for (meas, scanner), g in out.groupby(["measurement", "scanner"], sort=False):
        X = g[["x_mm", "y_mm", "z_mm"]].to_numpy(float)
        u = g[["u_x_mm", "u_y_mm", "u_z_mm"]].to_numpy(float) if {"u_x_mm", "u_y_mm", "u_z_mm"} <= set(g) else None
        radii = g["radius_mm"].to_numpy(float) if "radius_mm" in g else None
        kwargs = dict(uncertainties=u, radii=radii, allowed_ids=(allowed_ids or {}).get(scanner), config=cfg)
        try:
            res = label_spheres(X, artefact, **kwargs)
        except LabellingRefused as err:
            res = err
        groups[(meas, scanner)] = dict(index=g.index, X=X, kwargs=kwargs, result=res, method="distances",
                                       candidates=list(g["candidate"]) if "candidate" in g else list(range(len(g))))
    if planned:
        for scanner in dict.fromkeys(s for _, s in groups):
            mine = {m: (v["X"], v["result"]) for (m, s), v in groups.items() if s == scanner}
            T_sw, why = scanner_frame_from_plan(mine, planned, artefact, cfg.prior_tol_mm / 2)
            for (m, s), v in groups.items():
                if s != scanner or m not in planned:
                    continue
                if T_sw is None:
                    if isinstance(v["result"], LabellingRefused):
                        v["result"] = LabellingRefused(v["result"].reason, f"{v['result'].args[0]}; plan: {why}",
                                                       v["result"].alternatives)
                    continue
                try:
                    res = label_spheres(v["X"], artefact, prior=T_sw.compose(planned[m]), **v["kwargs"])
                except LabellingRefused as err:
                    res = err
                before = v["result"]
                if isinstance(before, Labelling) and isinstance(res, Labelling) and before.sphere_ids != res.sphere_ids:
                    res = LabellingRefused("inconsistent", f"distances give {list(before.sphere_ids)} but the planned "
                                           f"pose gives {list(res.sphere_ids)}", [before.sphere_ids, res.sphere_ids])
                elif isinstance(before, Labelling) and isinstance(res, LabellingRefused):
                    continue  # the plan adds nothing
                v["result"] = res
                v["method"] = "planned pose" if isinstance(before, LabellingRefused) else "distances"
    rows = []
    for (meas, scanner), v in groups.items():
        res, n = v["result"], len(v["X"])
        if isinstance(res, LabellingRefused):
            rows.append((meas, scanner, "refused", res.reason, v["method"], n, 0, np.nan, str(res)))
            continue
        out.loc[v["index"], "sphere_id"] = [sid or "" for sid in res.sphere_ids]
        out.loc[v["index"], "label_residual_mm"] = res.residuals_mm
        rows.append((meas, scanner, "labelled", "", v["method"], n, res.n_labelled, res.rms_mm,
                     "; ".join(f"candidate {v['candidates'][i]}: {w}" for i, w in res.unlabelled.items())))
    outcomes = pd.DataFrame(rows, columns=["measurement", "scanner", "status", "reason", "method", "n_candidates",
                                           "n_labelled", "rms_mm", "message"])
    return out, outcomes


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
