"""The scanner frame every measurement agrees on, given the artefact's pose in each.

Step 5 of :mod:`fringecal.spheres.label_scanners`: each possible labelling of measurement
m (a *hypothesis*) implies the scanner's frame in the frame of the poses,
``T_scanner_world = T_scanner_artefact o T_world_artefact(m)^-1``. The poses are the
hexapod's planned ones, or (the link step) the poses other scanners measured, carried
into the reference frame by their links. Frames are compared by where they put the
artefact's spheres (at the first pose): RMS distance, normalised by the standard
uncertainty of each implied frame, from the registration of the spheres seen
(:func:`frame_uncertainty`, centre uncertainty as stated) and from the pose
(``plan_u_mm`` / ``plan_u_rad``, or the measured pose's own registration). A
candidate frame's misfit is the sum over measurements of the squared normalised
distance of its nearest hypothesis, capped at ``k**2``; the best is refined by the
mean of its members, and refused when too few measurements agree with it or a frame
far from it misfits by less than ``consensus_margin`` more.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fringecal.artefact import Artefact
from fringecal.frames import Frame
from fringecal.registration import kabsch
from fringecal.spheres.labelling import Labelling, LabellingConfig, LabellingRefused
from fringecal.spheres.linking import mean_frame

__all__ = ["scanner_frame_from_plan", "frame_uncertainty", "alternatives"]


def alternatives(res, min_spheres: int = 3) -> list[tuple]:
    """The labellings a result leaves possible: an accepted one, or every alternative of
    an ambiguous refusal (with ``min_spheres`` or more spheres); none otherwise."""
    if isinstance(res, Labelling):
        alts = [res.sphere_ids]
    elif isinstance(res, LabellingRefused) and res.reason == "ambiguous":
        alts = res.alternatives
    else:
        return []
    return [a for a in dict.fromkeys(alts) if sum(s is not None for s in a) >= min_spheres]


def _split(alt, artefact: Artefact):
    idx = [i for i, s in enumerate(alt) if s is not None]
    return idx, artefact.centres_of([alt[i] for i in idx])


def frame_uncertainty(X: np.ndarray, probe: np.ndarray, u: float) -> float:
    """RMS over ``probe`` (scanner frame) of the 3-D standard uncertainty of points
    carried by a rigid registration of centres ``X`` with per-coordinate uncertainty
    ``u`` (linearised: small rotation and translation, independent errors)."""
    c = X.mean(axis=0)

    def jac(P):
        r = P - c
        J = np.zeros((len(P), 3, 6))
        J[:, :, :3] = np.eye(3)
        # d(p)/d(omega) = -[r]x : columns omega_x, omega_y, omega_z
        J[:, 0, 4], J[:, 0, 5] = r[:, 2], -r[:, 1]
        J[:, 1, 3], J[:, 1, 5] = -r[:, 2], r[:, 0]
        J[:, 2, 3], J[:, 2, 4] = r[:, 1], -r[:, 0]
        return J

    J = jac(X).reshape(-1, 6)
    N = J.T @ J
    Jp = jac(probe)
    cov = np.linalg.pinv(N)
    var = np.einsum("pij,jk,pik->p", Jp, cov, Jp)
    return float(u * np.sqrt(np.mean(var)))


def _plan_sigma(probe_art: np.ndarray, cfg: LabellingConfig) -> float:
    r2 = np.sum((probe_art - probe_art.mean(axis=0)) ** 2, axis=1)
    return float(np.sqrt(3 * cfg.plan_u_mm**2 + 2 * cfg.plan_u_rad**2 * np.mean(r2)))


@dataclass
class _Hyp:
    measurement: str
    alt: tuple
    R: np.ndarray  # T_scanner_world as x_scanner = R x_world + t
    t: np.ndarray
    points: np.ndarray  # the probe in the scanner frame, (q, 3)
    sigma: float

    @property
    def frame(self) -> Frame:
        return Frame.from_matrix(self.R.T, self.t)


def _hypothesis(m, X, alt, planned: Frame, probe_world, artefact, cfg, scale, plan_sigma=None) -> _Hyp:
    idx, Y = _split(alt, artefact)
    M, t = kabsch(Y, X[idx] / scale)  # x_scanner = M y + t
    R = M @ planned.R  # y = R_P (x_world - t_P)
    t = t - R @ planned.t
    pts = probe_world @ R.T + t
    sig_reg = frame_uncertainty(X[idx] / scale, pts, cfg.centre_u_mm)
    sig = float(np.hypot(sig_reg, _plan_sigma(artefact.centres, cfg) if plan_sigma is None else plan_sigma))
    return _Hyp(m, tuple(alt), R, t, pts, sig)


def _rms(a, b) -> np.ndarray:
    return np.sqrt(np.mean(np.sum((a - b) ** 2, axis=-1), axis=-1))


class _Consensus:
    """Misfit of candidate frames against one scanner's hypotheses (step 5)."""

    def __init__(self, hyps: list[_Hyp], probe: np.ndarray, cfg: LabellingConfig):
        hyps = sorted(hyps, key=lambda h: h.measurement)
        self.hyps, self.probe, self.cfg = hyps, probe, cfg
        self.P = np.stack([h.points for h in hyps])
        self.sig = np.array([h.sigma for h in hyps])
        ms = [h.measurement for h in hyps]
        self.starts = np.flatnonzero([i == 0 or ms[i] != ms[i - 1] for i in range(len(ms))])

    def z2(self, points, sigma) -> np.ndarray:
        return _rms(self.P, points[None]) ** 2 / (self.sig**2 + sigma**2)

    def _per_measurement(self, z2):
        """Capped z^2 of each measurement's nearest hypothesis (rows: candidates)."""
        return np.minimum.reduceat(np.minimum(z2, self.cfg.k**2), self.starts, axis=-1)

    def misfit(self, points, sigma) -> tuple[float, np.ndarray, np.ndarray]:
        """(misfit, z^2 per hypothesis, indices of the members: nearest per measurement within k)."""
        z2 = self.z2(points, sigma)
        best = np.array([s + int(np.argmin(z2[s:e])) for s, e in zip(self.starts, list(self.starts[1:]) + [len(z2)])])
        members = best[z2[best] <= self.cfg.k**2]
        return float(self._per_measurement(z2).sum()), z2, members

    def scores(self, chunk: int = 512) -> np.ndarray:
        """Misfit of every hypothesis's own frame."""
        q = self.P.shape[1]
        F = self.P.reshape(len(self.P), -1)
        F = F - F.mean(axis=0)
        n2 = np.sum(F**2, axis=1)
        out = np.empty(len(F))
        for a in range(0, len(F), chunk):
            d2 = np.maximum(n2[a:a + chunk, None] + n2[None] - 2 * F[a:a + chunk] @ F.T, 0) / q
            z2 = d2 / (self.sig[a:a + chunk, None] ** 2 + self.sig[None] ** 2)
            out[a:a + chunk] = self._per_measurement(z2).sum(axis=1)
        return out

    def refine(self, i0: int):
        """Mean frame of the members of hypothesis ``i0``'s cluster, its misfit and members."""

        points, sigma, frame = self.P[i0], self.sig[i0], self.hyps[i0].frame
        for _ in range(3):
            _, _, members = self.misfit(points, sigma)
            if not len(members):
                break
            frame = mean_frame([self.hyps[i].frame for i in members])[0]
            sigma = float(np.sqrt(1 / np.sum(1 / self.sig[members] ** 2)))
            points = frame.to_world(self.probe)
        score, _, members = self.misfit(points, sigma)
        return frame, points, sigma, score, [int(i) for i in members]


def scanner_frame_from_plan(results: dict, planned: dict, artefact: Artefact, config: LabellingConfig | None = None,
                            scale: float = 1.0, plan_sigma: dict | None = None) -> tuple[Frame | None, str, tuple]:
    """``T_scanner_world`` of one scanner by consensus of its measurements and the plan.

    ``results``: measurement -> (candidate centres (n, 3), Labelling or
    LabellingRefused, or a list of alternative labellings); ``planned``: measurement
    -> planned ``T_world_artefact``; ``scale``: the scanner's scale (centres are
    divided by it); ``plan_sigma``: measurement -> 3-D standard uncertainty (RMS over
    the artefact's spheres) of its planned pose, default from ``plan_u_mm`` and
    ``plan_u_rad``. Step 5 of the module doc. Returns (frame or None, a sentence
    saying how it was found or why not, the member measurements).
    """
    cfg = config or LabellingConfig()
    ms = [m for m in results if m in planned]
    if not ms:
        return None, "no measurement of this scanner has a planned pose", ()
    probe_world = planned[ms[0]].to_world(artefact.centres)
    hyps = []
    for m in ms:
        X, res = results[m]
        alts = res if isinstance(res, list) else alternatives(res, cfg.min_spheres)
        for alt in alts:
            hyps.append(_hypothesis(m, X, alt, planned[m], probe_world, artefact, cfg, scale,
                                    None if plan_sigma is None else plan_sigma.get(m)))
    n_meas = len({h.measurement for h in hyps})
    if n_meas < 2:
        return None, (f"{n_meas} measurement(s) with a possible labelling; the plan needs two or more to find the "
                      "scanner's frame"), ()
    cons = _Consensus(hyps, probe_world, cfg)
    hyps = cons.hyps
    order = np.argsort(cons.scores(), kind="stable")
    frame, points, sigma, score, members = cons.refine(int(order[0]))
    need = max(2, int(np.ceil(n_meas / 2)))
    if len(members) < need:
        return None, (f"no scanner frame is shared by {need} or more of the {n_meas} measurements "
                      f"(best: {len(members)})"), ()
    # the best far rival, refined the same way
    far = _rms(cons.P, points[None]) > 2 * cfg.k * np.sqrt(cons.sig**2 + sigma**2)
    rival_note = ""
    if far.any():
        j = int(order[np.flatnonzero(far[order])[0]])
        _, r_points, r_sigma, r_score, r_members = cons.refine(j)
        dist = float(_rms(points, r_points))
        if r_score - score < cfg.consensus_margin and dist > 2 * cfg.k * np.hypot(sigma, r_sigma):
            ms_a = sorted({hyps[i].measurement for i in members})
            ms_b = sorted({hyps[i].measurement for i in r_members})
            return None, (f"the planned poses do not single out one scanner frame: two frames {dist:.0f} mm "
                          f"apart fit nearly as well (misfit {score:.1f} with measurements {ms_a}, "
                          f"{r_score:.1f} with {ms_b}; a margin of {cfg.consensus_margin:g} is required), "
                          "e.g. the hexapod moved only along a symmetry axis of the spheres seen"), ()
        rival_note = f"; the next frame, {dist:.0f} mm away, misfits by {r_score:.1f}"
    ms_in = tuple(sorted({hyps[i].measurement for i in members}))
    return frame, (f"scanner frame from the plan: {len(ms_in)} of {n_meas} measurements agree "
                   f"(misfit {score:.1f}){rival_note}"), ms_in
