"""Labelling one measurement with all linked scanners' views at once (no plan).

Once the scanners are linked (:mod:`fringecal.spheres.label_links`), each scanner's
possible labellings of a measurement put the artefact somewhere in the reference frame.
The true ones of different scanners agree; wrong ones repeat each view's symmetry and
scatter. A symmetry of everything the scanners see together (a column of near-regular
octahedra turned about its axis, say) leaves every scanner's labelling wrong in the same
way; such a measurement is labelled only where the placement the scanners agree on fits
clearly better than every other (the artefact's CMM shape is not exactly regular), never
guessed (:func:`joint_placement`).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np
import pandas as pd

from fringecal.artefact import Artefact
from fringecal.frames import Frame
from fringecal.registration import kabsch
from fringecal.spheres.label_consensus import _split, frame_uncertainty
from fringecal.spheres.labelling import LabellingConfig
from fringecal.spheres.linking import LinkResult

__all__ = ["JointPlacement", "joint_placement", "joint_placements"]


@dataclass(frozen=True)
class JointPlacement:
    """The artefact's pose in one measurement from every linked scanner's view at once.

    ``frame``: ``T_reference_artefact`` (None when refused); ``sigma``: its standard
    uncertainty (mm, RMS over the artefact's spheres); ``scanners``: the scanners whose
    labellings agree on it; ``labels``: scanner -> the labelling (sphere id or None per
    candidate); ``rms_mm``, ``rival_rms_mm``: RMS residual of the joint registration of
    the winner and of the best conflicting placement with as many scanners; ``note``:
    this in words, or why the measurement is refused.
    """

    frame: Frame | None
    sigma: float
    scanners: tuple
    labels: dict
    rms_mm: float
    rival_rms_mm: float
    note: str


def joint_placement(views: dict, links: dict, artefact: Artefact, tol: float, config: LabellingConfig | None = None,
                    free: dict | None = None, max_combinations: int = 20_000) -> JointPlacement:
    """Label one measurement with all its linked scanners' views together.

    ``views``: scanner -> (scale-corrected centres (n, 3) in its frame, hypotheses);
    ``links``: scanner -> ``T_reference_scanner``; ``tol``: two scanners' placements of
    the artefact agree when their RMS distance is within it (half the artefact's
    smallest sphere spacing: a wrong labelling moves spheres onto other spheres' places).

    Each scanner's hypotheses put the artefact somewhere in the reference frame; a
    *combination* takes one hypothesis per scanner among those that agree with the
    first scanner's (the one with the fewest hypotheses). The combination with the most
    scanners wins if the rigid registration of all its spheres at once, in the
    reference frame, leaves a residual sum of squares ``RSS`` that every conflicting
    combination with as many scanners exceeds by the factor ``1 + consensus_margin /
    dof`` (dof = 3 n - 6, n spheres): the winner's own residual sizes the test, so link
    errors that blur every placement alike refuse rather than decide. A symmetry of
    everything the scanners see together passes this test only where the artefact's
    CMM shape departs from it by more than the links' and centres' errors.

    ``free``: scanner -> scale-corrected centres of a linked scanner that sees too few
    spheres to be labelled on its own (one or two): each joins a combination at the
    sphere the placement puts nearest (within ``tol``), adding its residual and, if it
    lands on a sphere, its support; its labels are in ``labels`` too.
    """
    cfg = config or LabellingConfig()
    free_r = {s: links[s].to_world(X) for s, X in (free or {}).items() if s in links and len(X)}
    per = {}
    for s, (X, alts) in views.items():
        if s not in links:
            continue
        Xr = links[s].to_world(X)
        hyps = []
        for alt in alts:
            idx, Y = _split(alt, artefact)
            if len(idx) < 3:
                continue
            M, t = kabsch(Y, Xr[idx])
            hyps.append((tuple(alt), idx, artefact.centres @ M.T + t))
        if hyps:
            per[s] = (Xr, hyps)
    if not per or len(per) + len(free_r) < 2:
        return JointPlacement(None, np.inf, tuple(per), {}, np.nan, np.nan,
                              f"{len(per)} linked scanner(s) with a possible labelling and {len(free_r)} with one "
                              "or two spheres; two or more scanners are needed")
    names = sorted(per, key=lambda s: (len(per[s][1]), s))
    first, others = names[0], names[1:]
    placed = {s: np.stack([h[2] for h in per[s][1]]) for s in others}
    combos: dict = {}
    for h0 in per[first][1]:
        options = []
        for s in others:
            close = np.sqrt(np.mean(np.sum((placed[s] - h0[2]) ** 2, axis=2), axis=1)) <= tol
            options.append([per[s][1][i] for i in np.flatnonzero(close)] or [None])
        if np.prod([len(o) for o in options]) > max_combinations:
            return JointPlacement(None, np.inf, (), {}, np.nan, np.nan,
                                  f"more than {max_combinations} combinations of the scanners' labellings agree")
        for rest in itertools.product(*options):
            chosen = {first: h0, **{s: h for s, h in zip(others, rest) if h is not None}}
            key = tuple(sorted((s, h[0]) for s, h in chosen.items()))
            if key not in combos:
                fit = _joint_fit(chosen, per, artefact, free_r, tol)
                combos[key + tuple(sorted(fit[4].items()))] = fit
    def n_support(key):
        return sum(1 for _, lab in key if any(x is not None for x in lab))

    support = max(n_support(k) for k in combos)
    top = sorted(((c[0], k, c) for k, c in combos.items() if n_support(k) == support), key=lambda x: x[0])
    rss, key, (_, n, frame, Xall, _) = top[0]
    dof = max(3 * n - 6, 1)
    labels = dict(key)
    rivals = [r for r in top[1:] if any(dict(r[1]).get(s, lab) != lab for s, lab in labels.items())]
    rms = float(np.sqrt(rss / n))
    rival_rms = float(np.sqrt(rivals[0][0] / rivals[0][2][1])) if rivals else np.inf
    if support < 2:
        return JointPlacement(None, np.inf, (), {}, rms, rival_rms,
                              "no two scanners' labellings put the artefact in the same place")
    if rivals and rivals[0][0] < rss * (1 + cfg.consensus_margin / dof):
        r_lab = dict(rivals[0][1])
        return JointPlacement(None, np.inf, tuple(sorted(labels)), labels, rms, rival_rms,
                              f"the scanners' views together fit two placements nearly as well (RMS {rms:.2f} mm "
                              f"with {_describe(labels)}, {rival_rms:.2f} mm with {_describe(r_lab)}): what all "
                              "scanners see together is symmetric within the links' and centres' errors")
    u = float(np.sqrt(rss / dof)) if n > 2 else cfg.centre_u_mm
    sigma = frame_uncertainty(Xall, frame.to_world(artefact.centres), max(u, 1e-3))
    note = f"{len(labels)} scanners' views together: RMS {rms:.2f} mm"
    note += f", the next placement {rival_rms:.2f} mm" if rivals else ", no other placement"
    return JointPlacement(frame, sigma, tuple(sorted(labels)), labels, rms, rival_rms, note)


def _describe(labels: dict) -> str:
    return ", ".join(f"{s} {[x for x in lab if x]}" for s, lab in sorted(labels.items()))


def _joint_fit(chosen: dict, per: dict, artefact: Artefact, free: dict, tol: float):
    """(RSS, n, T_reference_artefact, points, free scanners' labels) of the rigid
    registration of every chosen scanner's labelled centres (reference frame) at once,
    with each free scanner's centres at the sphere the first registration puts nearest
    (within ``tol``)."""
    X = np.vstack([per[s][0][h[1]] for s, h in chosen.items()])
    ids = [sid for h in chosen.values() for sid in h[0] if sid is not None]
    M, t = kabsch(artefact.centres_of(ids), X)
    free_labels = {}
    if free:
        placed = artefact.centres @ M.T + t
        for s, P in free.items():
            d = np.linalg.norm(P[:, None] - placed[None], axis=2)
            near = np.argmin(d, axis=1)
            lab = tuple(artefact.ids[j] if d[i, j] <= tol else None for i, j in enumerate(near))
            free_labels[s] = lab
            X = np.vstack([X, P[[i for i, x in enumerate(lab) if x is not None]]])
            ids += [x for x in lab if x is not None]
        M, t = kabsch(artefact.centres_of(ids), X)
    Y = artefact.centres_of(ids)
    rss = float(np.sum((Y @ M.T + t - X) ** 2))
    return rss, len(X), Frame.from_matrix(M.T, t), X, free_labels


def joint_placements(labelled: pd.DataFrame, outcomes: pd.DataFrame, links: LinkResult, estimates: dict,
                      artefact: Artefact, config: LabellingConfig, skip: set, tol: float) -> dict:
    """measurement -> :class:`~fringecal.spheres.label_links.JointPlacement` of every
    measurement still ambiguous that no linked scanner has posed; linked scanners with
    one or two spheres there join as free points."""
    refused = outcomes[(outcomes["status"] == "refused") & outcomes["scanner"].isin(list(links.links))
                       & ~outcomes["measurement"].isin(list(skip))]
    out = {}
    for m, g in refused.groupby("measurement", sort=False):
        if not (g["reason"] == "ambiguous").any():
            continue
        views, free = {}, {}
        for s, reason in zip(g["scanner"], g["reason"]):
            est = estimates.get(s)
            if est is None:
                continue
            rows = (labelled["measurement"] == m) & (labelled["scanner"] == s)
            X = labelled.loc[rows, ["x_mm", "y_mm", "z_mm"]].to_numpy(float) / est.scale
            if reason == "ambiguous" and est.hypotheses.get(m):
                views[s] = (X, est.hypotheses[m])
            elif reason == "too_few_candidates" and len(X):
                free[s] = X
        frames = {s: links.links[s].frame for s in [*views, *free]}
        out[m] = joint_placement(views, frames, artefact, tol, config, free)
    return out
