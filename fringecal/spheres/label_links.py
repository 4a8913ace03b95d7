"""Scanner links without a plan: the one transform every shared measurement agrees on.

Without planned poses a scanner whose views are each ambiguous (parts of a near-regular
artefact) has several possible labellings per measurement, its *hypotheses*
(:class:`~fringecal.spheres.label_scanners.ScannerEstimate`). Two scanners A and B that
see the artefact in the same measurement m are linked by::

    T_A_B(m) = T_A_artefact(m, h_A) o T_B_artefact(m, h_B)^-1

for the true hypotheses h_A, h_B, and the scanners are rigidly mounted: T_A_B is the
same in every measurement. A wrong pair repeats the symmetry of the spheres seen, and
the artefact's moves between measurements make its T_A_B differ from measurement to
measurement. So, per pair of scanners (each scanner's centres divided by its estimated
scale, so a prior 0.2-0.6 % off in scale does not move the link):

1. every pair of hypotheses of every shared measurement is a *candidate link*, placed
   by where it carries B's view of the artefact into A's frame (an RMS distance over
   the artefact's spheres, computed from six points with the same mean and second
   moments), with the standard uncertainty of the two registrations there
   (:func:`~fringecal.spheres.label_consensus.frame_uncertainty`);
2. a candidate's *misfit* is the sum over the shared measurements of the squared
   normalised distance to that measurement's nearest candidate, each capped at ``k**2``
   (the same robust misfit as the planned-pose consensus); the candidates of the
   measurements with the fewest pairs are scored, the best is refined by the mean of
   its members (the nearest candidate of each measurement within ``k``);
3. it is accepted when at least two measurements and half of the shared ones agree,
   and every far rival (more than ``2 k`` away) misfits by ``consensus_margin`` more.
   Otherwise the pair is not linked, with the reason.

Scanners are linked to the reference where they share measurements with it, and
otherwise through a scanner already linked (the one giving the most agreeing
measurements). The measurements' labellings then follow from the links: a placement
of the artefact on which the linked scanners' hypotheses agree
(:mod:`fringecal.spheres.label_joint`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd
from scipy.spatial import cKDTree

from fringecal.artefact import Artefact
from fringecal.frames import Frame
from fringecal.spheres.labelling import LabellingConfig
from fringecal.spheres.linking import FrameLink, LinkResult, mean_frame

__all__ = ["PairLink", "links_from_hypotheses", "moment_probe", "pair_link", "scanner_views"]


@dataclass(frozen=True)
class PairLink:
    """``T_A_B`` of two scanners from their hypotheses, or why there is none.

    ``frame`` (None when refused): maps B's scale-corrected frame into A's;
    ``members``: the measurements that agree on it; ``n_shared``: the measurements both
    scanners have hypotheses for; ``misfit``, ``rival_misfit``: the robust misfits of the
    winner and of the best far rival (inf without one); ``sigma``: the standard
    uncertainty (mm, RMS over the artefact's spheres) of the mean link; ``note``: all
    this in words.
    """

    frame: Frame | None
    members: tuple
    n_shared: int
    misfit: float
    rival_misfit: float
    sigma: float
    note: str


def moment_probe(points: np.ndarray) -> np.ndarray:
    """Six points with the mean and the second moments of ``points`` (n, 3): the RMS
    distance between two rigid images of ``points`` equals that of the six."""
    c = points.mean(axis=0)
    w, v = np.linalg.eigh(np.cov((points - c).T, bias=True))
    axes = v * np.sqrt(3 * np.maximum(w, 0))
    return np.vstack([c + axes.T, c - axes.T])


@dataclass
class _Views:
    """One scanner's hypotheses in one measurement: x_scanner = M y_artefact + t per
    hypothesis, with the standard uncertainty of each registration."""

    M: np.ndarray  # (h, 3, 3)
    t: np.ndarray  # (h, 3)
    sigma: np.ndarray  # (h,)


def _views(X: np.ndarray, alts: list, artefact: Artefact, scale: float, u: float) -> _Views | None:
    """Every hypothesis's rigid registration and its uncertainty, in batches of the
    hypotheses that label the same candidates (the same :func:`kabsch` and
    :func:`~fringecal.spheres.label_consensus.frame_uncertainty`, vectorised)."""
    groups: dict = {}
    for alt in alts:
        idx = tuple(i for i, s in enumerate(alt) if s is not None)
        if len(idx) >= 3:
            groups.setdefault(idx, []).append(artefact.index([alt[i] for i in idx]))
    if not groups:
        return None
    Ms, ts, sg = [], [], []
    for idx, rows in groups.items():
        Xs = X[list(idx)] / scale  # (n, 3), the same for the batch
        Y = artefact.centres[np.array(rows)]  # (h, n, 3)
        a0, b0 = Y.mean(axis=1), Xs.mean(axis=0)
        H = np.einsum("ni,hnj->hij", Xs - b0, Y - a0[:, None])
        uu, _, vt = np.linalg.svd(H)
        d = np.sign(np.linalg.det(uu @ vt))
        d[d == 0] = 1.0
        M = uu @ (np.eye(3)[None] * np.stack([np.ones_like(d), np.ones_like(d), d], axis=1)[:, None]) @ vt
        t = b0 - np.einsum("hij,hj->hi", M, a0)
        Ms.append(M)
        ts.append(t)
        probes = np.einsum("hij,qj->hqi", M, artefact.centres) + t[:, None]
        sg.append(_sigmas(Xs, probes, u))
    return _Views(np.concatenate(Ms), np.concatenate(ts), np.concatenate(sg))


def _jacobian(P: np.ndarray, c: np.ndarray) -> np.ndarray:
    """d(point)/d(translation, small rotation) of points P (..., 3) about c: (..., 3, 6)."""
    r = P - c
    J = np.zeros((*P.shape[:-1], 3, 6))
    J[..., :3] = np.eye(3)
    J[..., 0, 4], J[..., 0, 5] = r[..., 2], -r[..., 1]
    J[..., 1, 3], J[..., 1, 5] = -r[..., 2], r[..., 0]
    J[..., 2, 3], J[..., 2, 4] = r[..., 1], -r[..., 0]
    return J


def _sigmas(Xs: np.ndarray, probes: np.ndarray, u: float) -> np.ndarray:
    """:func:`~fringecal.spheres.label_consensus.frame_uncertainty` of the registration
    of ``Xs`` at each of the probe sets ``probes`` (h, q, 3)."""
    c = Xs.mean(axis=0)
    J = _jacobian(Xs, c).reshape(-1, 6)
    cov = np.linalg.pinv(J.T @ J)
    Jp = _jacobian(probes, c)
    var = np.einsum("hpij,jk,hpik->hp", Jp, cov, Jp)
    return u * np.sqrt(np.mean(var, axis=1))


def _candidates(a: _Views, b: _Views, probe_b: np.ndarray):
    """Every pair's link x_a = L x_b + l, its image of ``probe_b`` (flattened) and sigma."""
    L = np.einsum("aij,bkj->abik", a.M, b.M)  # M_a M_b^T
    l = a.t[:, None] - np.einsum("abij,bj->abi", L, b.t)
    L, l = L.reshape(-1, 3, 3), l.reshape(-1, 3)
    P = np.einsum("nij,qj->nqi", L, probe_b) + l[:, None]
    sigma = np.hypot(a.sigma[:, None], b.sigma[None]).reshape(-1)
    return L, l, P.reshape(len(L), -1), sigma


class _PairConsensus:
    """The robust misfit of candidate links against every shared measurement.

    Candidates are found by where they carry the probe's centroid (a 3-D tree: a
    candidate within ``k`` of another in RMS is within as much at the centroid), then
    compared over the whole probe."""

    def __init__(self, per_m: dict, q: int, k: float):
        self.ms = sorted(per_m)
        self.per_m, self.q, self.k = per_m, q, k
        self.trees = {m: cKDTree(self._centroids(per_m[m][2])) for m in self.ms}

    def _centroids(self, P: np.ndarray) -> np.ndarray:
        return P.reshape(len(P), self.q, 3).mean(axis=1)

    def misfit(self, P: np.ndarray, sigma: np.ndarray):
        """(misfit per candidate, member index per measurement or -1) of candidate
        images ``P`` (c, 3q) with standard uncertainties ``sigma`` (c,)."""
        k2 = self.k**2
        total = np.zeros(len(P))
        members = np.full((len(P), len(self.ms)), -1)
        cent = self._centroids(P)
        for j, m in enumerate(self.ms):
            _, _, Pm, sm = self.per_m[m]
            near = self.trees[m].query_ball_point(cent, self.k * np.sqrt(sigma**2 + sm.max() ** 2))
            counts = np.fromiter(map(len, near), int, len(near))
            zb = np.full(len(P), np.inf)
            ib = np.full(len(P), -1)
            if counts.sum():
                cand = np.repeat(np.arange(len(P)), counts)
                idx = np.concatenate([np.asarray(x, int) for x in near if x])
                z2 = np.sum((P[cand] - Pm[idx]) ** 2, axis=1) / self.q / (sigma[cand] ** 2 + sm[idx] ** 2)
                order = np.lexsort((z2, cand))  # per candidate, its nearest first
                first = order[np.r_[True, cand[order][1:] != cand[order][:-1]]]
                zb[cand[first]], ib[cand[first]] = z2[first], idx[first]
            total += np.minimum(zb, k2)
            members[:, j] = np.where(zb <= k2, ib, -1)
        return total, members

    def refine(self, P0: np.ndarray, s0: float, frame0: Frame, probe_b: np.ndarray):
        """The mean link of the members of a candidate, iterated; (frame, image,
        sigma, misfit, member measurements)."""
        P, s, frame = P0, s0, frame0
        for _ in range(3):
            _, members = self.misfit(P[None], np.array([s]))
            rows = [(m, int(i)) for m, i in zip(self.ms, members[0]) if i >= 0]
            if not rows:
                break
            frames = [Frame.from_matrix(self.per_m[m][0][i].T, self.per_m[m][1][i]) for m, i in rows]
            frame = mean_frame(frames)[0]
            s = float(np.sqrt(1 / np.sum([1 / self.per_m[m][3][i] ** 2 for m, i in rows])))
            P = frame.to_world(probe_b).reshape(-1)
        score, members = self.misfit(P[None], np.array([s]))
        return frame, P, s, float(score[0]), tuple(m for m, i in zip(self.ms, members[0]) if i >= 0)


def pair_link(views_a: dict, views_b: dict, probe_b: np.ndarray, config: LabellingConfig, names=("A", "B"),
              n_seeds: int = 2) -> PairLink:
    """``T_A_B`` by consensus of the shared measurements (steps 1-3 of the module doc).

    ``views_a``, ``views_b``: measurement -> :class:`_Views` of each scanner;
    ``probe_b``: points in B's scale-corrected frame where it sees the artefact.
    """
    cfg = config
    shared = sorted(set(views_a) & set(views_b))
    a, b = names
    if not shared:
        return PairLink(None, (), 0, np.inf, np.inf, np.inf, f"{a} and {b} share no measurement")
    probe = moment_probe(probe_b)
    per_m = {m: _candidates(views_a[m], views_b[m], probe) for m in shared}
    cons = _PairConsensus(per_m, len(probe), cfg.k)
    need = max(2, int(np.ceil(len(shared) / 2)))
    seeds = sorted(shared, key=lambda m: len(per_m[m][2]))[:n_seeds]
    P = np.vstack([per_m[m][2] for m in seeds])
    S = np.concatenate([per_m[m][3] for m in seeds])
    src = [(m, i) for m in seeds for i in range(len(per_m[m][2]))]
    score, _ = cons.misfit(P, S)
    order = np.argsort(score, kind="stable")

    def refined(j):
        m, i = src[j]
        return cons.refine(P[j], float(S[j]), Frame.from_matrix(per_m[m][0][i].T, per_m[m][1][i]), probe)

    frame, Pb, sb, best, members = refined(int(order[0]))
    if len(members) < need:
        return PairLink(None, members, len(shared), best, np.inf, sb,
                        f"no link of {b} to {a} is shared by {need} or more of their {len(shared)} shared "
                        f"measurements (best: {len(members)}, {', '.join(members) or 'none'})")
    far = np.sqrt(np.sum((P - Pb) ** 2, axis=1) / len(probe)) > 2 * cfg.k * np.sqrt(S**2 + sb**2)
    rival = np.inf
    note = ""
    if far.any():
        _, r_P, r_s, rival, r_members = refined(int(order[np.flatnonzero(far[order])[0]]))
        dist = float(np.sqrt(np.sum((r_P - Pb) ** 2) / len(probe)))
        if rival - best < cfg.consensus_margin and dist > 2 * cfg.k * np.hypot(sb, r_s):
            return PairLink(None, (), len(shared), best, rival, sb,
                            f"two links of {b} to {a} {dist:.0f} mm apart fit nearly as well (misfit {best:.1f} "
                            f"with measurements {list(members)}, {rival:.1f} with {list(r_members)}; a margin "
                            f"of {cfg.consensus_margin:g} is required)")
        note = f"; the next link, {dist:.0f} mm away, misfits by {rival:.1f}"
    return PairLink(frame, members, len(shared), best, rival, sb,
                    f"{len(members)} of {len(shared)} shared measurements agree on the link of {b} to {a} "
                    f"(misfit {best:.1f}){note}")


def scanner_views(labelled: pd.DataFrame, estimates: dict, artefact: Artefact, config: LabellingConfig) -> dict:
    """scanner -> measurement -> :class:`_Views` of every hypothesis the labelling left
    (each scanner's centres divided by its scale)."""
    out: dict = {}
    for (m, s), g in labelled.groupby(["measurement", "scanner"], sort=False):
        est = estimates.get(s)
        if est is None or not est.hypotheses.get(m):
            continue
        X = g[["x_mm", "y_mm", "z_mm"]].to_numpy(float)
        v = _views(X, est.hypotheses[m], artefact, est.scale, max(est.centre_u_mm, config.centre_u_mm))
        if v is not None:
            out.setdefault(s, {})[str(m)] = v
    return out


def links_from_hypotheses(labelled: pd.DataFrame, estimates: dict, artefact: Artefact, reference: str,
                          config: LabellingConfig | None = None) -> LinkResult:
    """Link every scanner to ``reference`` from the hypotheses alone (module doc).

    ``labelled``: the sphere-fits table the labelling returned (each group's rows in
    the order of its hypotheses); ``estimates``: scanner -> ScannerEstimate. Returns
    a :class:`~fringecal.spheres.linking.LinkResult` whose ``unlinked`` says, per
    scanner, why no link was found (the reference is always linked to itself).
    """
    cfg = config or LabellingConfig()
    views = scanner_views(labelled, estimates, artefact, cfg)
    scanners = list(dict.fromkeys(map(str, labelled["scanner"])))
    identity = FrameLink(reference, reference, Frame(np.zeros(3), np.zeros(3)), len(views.get(reference, {})), 0,
                         0.0, 0.0, 0.0, 0.0, (reference,), tuple(sorted(views.get(reference, {}))))
    links = {reference: identity}
    why: dict[str, str] = {}
    probes = {}
    for s, per in views.items():
        v = per[min(per)]
        probes[s] = artefact.centres @ v.M[0].T + v.t[0]
    changed = True
    while changed:
        changed = False
        for s in scanners:
            if s in links:
                continue
            if s not in views:
                why[s] = "none of its measurements has a possible labelling of three or more spheres"
                continue
            tried = []
            for a in [x for x in links if x in views]:
                res = pair_link(views[a], views[s], probes[s], cfg, (a, s))
                tried.append((a, res))
            ok = [(a, r) for a, r in tried if r.frame is not None]
            if not ok:
                why[s] = "; ".join(r.note for _, r in tried) or "no linked scanner to link it to"
                continue
            a, r = max(ok, key=lambda ar: len(ar[1].members))
            frame = r.frame if a == reference else links[a].frame.compose(r.frame)
            links[s] = FrameLink(s, reference, frame, len(r.members), r.n_shared - len(r.members), np.nan, np.nan,
                                 r.sigma, np.nan, links[a].via + (s,), r.members)
            why.pop(s, None)
            changed = True
    return LinkResult(reference, links, {s: w for s, w in why.items() if s not in links})

