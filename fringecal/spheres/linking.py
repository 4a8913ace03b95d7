"""Scanner frames linked into the reference scanner's frame (thesis sections 6.2-6.3).

Every scanner measures the artefact in its own frame, giving per measurement ``m``
a pose ``T_scanner_artefact(m)`` (the poses table). A measurement seen by two
scanners A and B links their frames::

    T_A_B(m) = T_A_artefact(m) o T_B_artefact(m)^-1

which is the same rigid transform for every shared measurement up to noise. The
estimates are averaged robustly (chordal mean of the rotations, mean of the
translations, outliers beyond ``k`` robust standard deviations dropped) and their
spread is reported. Scanners that share no measurement with the reference are
chained through intermediate scanners: the scanners form a graph whose edges are
shared measurements, and each scanner is reached by the path with the fewest links
(ties: the most shared measurements).

:func:`fringecal.rig.rig_in_frame` then expresses a scanner's sensors in the reference
frame, so every scanner starts the bundle adjustment in one global frame.
"""

from __future__ import annotations

import heapq
from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from fringecal.frames import Frame
from fringecal.schemas import PosesTable, validate_table

__all__ = [
    "FrameLink", "LinkResult", "mean_frame", "robust_mean_frame", "link_scanners",
    "pose_contradictions", "LINK_COLUMNS",
]

LINK_COLUMNS = ["scanner", "reference", "tx_mm", "ty_mm", "tz_mm", "omega_rad", "phi_rad", "kappa_rad",
                "n_measurements", "n_rejected", "translation_spread_mm", "rotation_spread_rad",
                "u_translation_mm", "u_rotation_rad", "via"]


def _project_to_rotation(M: np.ndarray) -> np.ndarray:
    u, _, vt = np.linalg.svd(M)
    d = np.sign(np.linalg.det(u @ vt)) or 1.0
    return u @ np.diag([1.0, 1.0, d]) @ vt


def _rotation_angle(R: np.ndarray) -> np.ndarray:
    """Angle (...) of rotation matrices (..., 3, 3)."""
    c = (np.trace(R, axis1=-2, axis2=-1) - 1) / 2
    return np.arccos(np.clip(c, -1.0, 1.0))


def mean_frame(frames, near=None) -> tuple[Frame, np.ndarray, np.ndarray]:
    """Mean of rigid frames: chordal L2 mean rotation, arithmetic mean origin.

    Returns the mean frame and, per input frame, its translation deviation (mm) and
    rotation deviation (rad) from the mean.
    """
    frames = list(frames)
    R = np.stack([f.R for f in frames])
    t = np.stack([f.t for f in frames])
    R_mean = _project_to_rotation(R.sum(axis=0))
    t_mean = t.mean(axis=0)
    near = frames[0].angles if near is None else near
    mean = Frame.from_matrix(R_mean, t_mean, near=near)
    dt = np.linalg.norm(t - t_mean, axis=1)
    dr = _rotation_angle(R @ R_mean.T)
    return mean, dt, dr


def robust_mean_frame(frames, k: float = 4.0, floor_mm: float = 0.05, floor_rad: float = 2e-5,
                      lever_mm: float = 1000.0) -> tuple[Frame, np.ndarray]:
    """:func:`mean_frame` after dropping outliers.

    Deviations combine translation and rotation as ``dt + lever_mm * dr``. They are
    first measured from the medoid (the estimate closest to all others, robust while
    most estimates are good), an estimate beyond ``k`` robust standard deviations
    (1.4826 MAD, at least ``floor_mm + lever_mm * floor_rad``) is dropped, then the
    test is repeated about the mean of the rest. Needs three or more estimates to
    reject anything. Returns the mean and the kept mask.
    """
    frames = list(frames)
    keep = np.ones(len(frames), bool)
    if len(frames) >= 3:
        R = np.stack([f.R for f in frames])
        t = np.stack([f.t for f in frames])
        pair = (np.linalg.norm(t[:, None] - t[None, :], axis=2)
                + lever_mm * _rotation_angle(np.einsum("aij,bkj->abik", R, R)))
        dev = pair[int(np.argmin(pair.sum(axis=1)))]
        floor = floor_mm + lever_mm * floor_rad
        for _ in range(2):
            sigma = max(1.4826 * float(np.median(dev[keep] if keep.sum() > 2 else dev)), floor)
            keep = dev <= k * sigma
            _, dt, dr = _deviations(frames, mean_frame([f for f, k_ in zip(frames, keep) if k_])[0])
            dev = dt + lever_mm * dr
    mean, _, _ = mean_frame([f for f, k_ in zip(frames, keep) if k_])
    return mean, keep


def _deviations(frames, mean: Frame):
    R = np.stack([f.R for f in frames])
    t = np.stack([f.t for f in frames])
    return mean, np.linalg.norm(t - mean.t, axis=1), _rotation_angle(R @ mean.R.T)


@dataclass(frozen=True)
class FrameLink:
    """``T_reference_scanner`` with its evidence.

    ``via`` lists the scanners from the reference to this one; spreads are the RMS
    deviations of the per-measurement estimates of the *last* link from its mean,
    accumulated in quadrature along the path; ``u_*`` are the standard
    uncertainties of the mean (spread / sqrt(n) per link, in quadrature).
    """

    scanner: str
    reference: str
    frame: Frame
    n_measurements: int
    n_rejected: int
    translation_spread_mm: float
    rotation_spread_rad: float
    u_translation_mm: float
    u_rotation_rad: float
    via: tuple[str, ...]
    measurements: tuple[str, ...] = field(default=(), repr=False)
    rejected: tuple[str, ...] = field(default=(), repr=False)


@dataclass(frozen=True)
class LinkResult:
    """Links of every reachable scanner and the reasons for the others."""

    reference: str
    links: dict
    unlinked: dict

    def table(self) -> pd.DataFrame:
        rows = []
        for s, lk in self.links.items():
            rows.append((s, lk.reference, *lk.frame.t, *lk.frame.angles, lk.n_measurements, lk.n_rejected,
                         lk.translation_spread_mm, lk.rotation_spread_rad, lk.u_translation_mm,
                         lk.u_rotation_rad, " > ".join(lk.via)))
        return pd.DataFrame(rows, columns=LINK_COLUMNS)


def _edge(poses_a: dict, poses_b: dict, k: float):
    shared = sorted(set(poses_a) & set(poses_b))
    estimates = [poses_a[m].compose(poses_b[m].inverse()) for m in shared]
    mean, keep = robust_mean_frame(estimates, k=k)
    used = [e for e, k_ in zip(estimates, keep) if k_]
    _, dt, dr = _deviations(used, mean)
    n = len(used)
    spread_t = float(np.sqrt(np.mean(dt**2))) if n > 1 else float("nan")
    spread_r = float(np.sqrt(np.mean(dr**2))) if n > 1 else float("nan")
    return (mean, n, int((~keep).sum()), spread_t, spread_r, tuple(m for m, k_ in zip(shared, keep) if k_),
            tuple(m for m, k_ in zip(shared, keep) if not k_))


def link_scanners(poses: pd.DataFrame, reference: str, k: float = 4.0, source: str = "<poses>") -> LinkResult:
    """Link every scanner of a poses table into ``reference``'s frame.

    Parameters
    ----------
    poses : DataFrame
        :class:`fringecal.schemas.PosesTable` rows: ``T_scanner_artefact`` per (measurement, scanner).
    reference : str
        The scanner whose frame becomes the global frame.
    k : float
        Outlier threshold in robust standard deviations.

    Returns
    -------
    LinkResult
        ``links[scanner].frame`` is ``T_reference_scanner``; ``unlinked`` names
        scanners sharing no measurement path with the reference.

    Examples
    --------
    >>> T_r_a = [Frame.from_params([0, 0, 1000 + 10 * m, 0.1 * m, 0, 0]) for m in range(3)]
    >>> T_r_s = Frame.from_params([500, 0, 0, 0, 0.2, 0])      # the truth
    >>> rows = []
    >>> for m, T in enumerate(T_r_a):
    ...     rows.append((str(m), "ref", *T.params, 0.0, 4))
    ...     rows.append((str(m), "s2", *T_r_s.inverse().compose(T).params, 0.0, 4))
    >>> cols = ["measurement", "scanner", "tx_mm", "ty_mm", "tz_mm", "omega_rad", "phi_rad",
    ...         "kappa_rad", "rms_mm", "n_spheres"]
    >>> res = link_scanners(pd.DataFrame(rows, columns=cols), "ref")
    >>> bool(np.allclose(res.links["s2"].frame.params, T_r_s.params))
    True
    """
    poses = validate_table(poses, PosesTable, source)
    by_scanner: dict[str, dict[str, Frame]] = {}
    for r in poses.itertuples(index=False):
        by_scanner.setdefault(r.scanner, {})[r.measurement] = Frame(
            [r.tx_mm, r.ty_mm, r.tz_mm], [r.omega_rad, r.phi_rad, r.kappa_rad])
    scanners = list(by_scanner)
    if reference not in by_scanner:
        raise ValueError(f"{source}: reference scanner {reference!r} has no poses "
                         f"(scanners with poses: {scanners})")
    identity = FrameLink(reference, reference, Frame(np.zeros(3), np.zeros(3)), len(by_scanner[reference]), 0,
                         0.0, 0.0, 0.0, 0.0, (reference,), tuple(sorted(by_scanner[reference])))
    links = {reference: identity}
    # Dijkstra on (links, -shared measurements)
    shared = {(a, b): len(set(by_scanner[a]) & set(by_scanner[b])) for a in scanners for b in scanners if a != b}
    best = {reference: (0, 0)}
    parent: dict[str, str] = {}
    heap = [(0, 0, reference)]
    while heap:
        hops, neg, s = heapq.heappop(heap)
        if best.get(s, (np.inf, 0)) < (hops, neg):
            continue
        for t in scanners:
            n_sh = shared.get((s, t), 0)
            if t == s or n_sh == 0:
                continue
            cand = (hops + 1, neg - n_sh)
            if cand < best.get(t, (np.inf, 0)):
                best[t] = cand
                parent[t] = s
                heapq.heappush(heap, (*cand, t))
    order = sorted((s for s in best if s != reference), key=lambda s: best[s][0])
    for s in order:
        p = parent[s]
        mean, n, n_rej, st, sr, used, rejected = _edge(by_scanner[p], by_scanner[s], k)
        prev = links[p]
        frame = mean if p == reference else prev.frame.compose(mean)
        links[s] = FrameLink(
            s, reference, frame, n, n_rej,
            float(np.hypot(prev.translation_spread_mm, st)), float(np.hypot(prev.rotation_spread_rad, sr)),
            float(np.hypot(prev.u_translation_mm, st / np.sqrt(n))), float(np.hypot(prev.u_rotation_rad, sr / np.sqrt(n))),
            prev.via + (s,), used, rejected)
    unlinked = {s: f"shares no measurement (directly or through other scanners) with {reference!r}"
                for s in scanners if s not in links}
    return LinkResult(reference, links, unlinked)


def pose_contradictions(poses: pd.DataFrame, result: LinkResult, probe_local, tol_mm: float,
                        source: str = "<poses>") -> pd.DataFrame:
    """Poses that the other scanners' poses of the same measurement contradict.

    Each linked scanner's pose of measurement m, carried into the reference frame
    (``T_reference_scanner o T_scanner_artefact(m)``), puts the artefact somewhere;
    all of them should put it in the same place. Two poses *disagree* when some point
    of ``probe_local`` (artefact frame, e.g. the sphere centres) lands more than
    ``tol_mm`` apart. A mislabelled measurement moves a sphere onto another's place,
    so half the artefact's smallest sphere spacing separates a wrong labelling from
    pose noise. A pose that disagrees with every other scanner's while those agree
    with each other is *contradicted*; when the scanners of a measurement disagree
    without a majority (two scanners, say), every one of them is.

    Returns
    -------
    DataFrame
        ``measurement, scanner, deviation_mm`` (largest distance to the agreeing
        scanners' placement, or to the nearest other one), ``n_scanners``,
        ``message``; one row per contradicted pose.
    """
    poses = validate_table(poses, PosesTable, source)
    probe = np.asarray(probe_local, float)
    placed: dict[str, dict[str, np.ndarray]] = {}
    for r in poses.itertuples(index=False):
        if r.scanner not in result.links:
            continue
        T = result.links[r.scanner].frame.compose(
            Frame([r.tx_mm, r.ty_mm, r.tz_mm], [r.omega_rad, r.phi_rad, r.kappa_rad]))
        placed.setdefault(str(r.measurement), {})[r.scanner] = T.to_world(probe)
    rows = []
    for m, by in placed.items():
        names = list(by)
        if len(names) < 2:
            continue
        P = np.stack([by[s] for s in names])
        dev = np.linalg.norm(P[:, None] - P[None, :], axis=3).max(axis=2)
        if dev.max() <= tol_mm:
            continue
        # the placement most scanners share: around the scanner agreeing with the most others
        agree = (dev <= tol_mm).sum(axis=1)
        centre = min(range(len(names)), key=lambda i: (-agree[i], dev[i].sum()))
        cluster = [j for j in range(len(names)) if dev[centre, j] <= tol_mm]
        majority = len(cluster) > len(names) / 2
        for i, s in enumerate(names):
            if majority and i in cluster:
                continue
            if majority:
                d = float(dev[i, cluster].max())
                why = (f"measurement {m}: scanner {s}'s pose, carried into the reference frame by its link, puts the "
                       f"artefact {d:.0f} mm from where scanner(s) {', '.join(names[j] for j in cluster)} put it "
                       f"(they agree within {tol_mm:.0f} mm): its labelling is wrong")
            else:
                d = float(np.delete(dev[i], i).min())
                why = (f"measurement {m}: the poses of scanners {', '.join(names)} put the artefact up to "
                       f"{float(dev.max()):.0f} mm apart through their links, and no majority agrees within "
                       f"{tol_mm:.0f} mm: one of their labellings is wrong, which one cannot be told")
            rows.append((m, s, d, len(names), why))
    return pd.DataFrame(rows, columns=["measurement", "scanner", "deviation_mm", "n_scanners", "message"])
