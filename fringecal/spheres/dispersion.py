"""How far a scanner's sphere centres scatter between spheres, against what their fits state.

A sphere fit's covariance (:func:`~fringecal.spheres.fit.centre_sandwich_covariance`)
holds the noise of its own points, taken as independent. What moves a whole sighting
(a phase error smooth over the sphere, a projector's non-linearity, the sphere's form,
a lens term the model lacks) leaves its residuals nearly unchanged and is not in it.
The calibration's own data show it: in each view (one scanner, one measurement) the
centres fitted with the calibrated scanner should lie where the artefact's table puts
them, up to a rigid motion of the artefact, within their fits' covariance plus the
table's ``u_mm`` per coordinate. With ``W_i`` the inverse square root of sighting i's
covariance and the rigid motion ``(R, t)`` fitted by weighted least squares per view,

    kappa^2 = sum_views sum_i |W_i (c_i - R s_i - t)|^2 / sum_views (3 n_view - 6)

per scanner (views of at least 3 spheres). kappa is about 1 when the fits' covariance
says all there is, below 1 by what the adjustment itself absorbs (0.68-1.01 per scanner
for the simulated thesis rig's ideal profile at 320 px over 12 seeds), and above 1 when
sightings move as a whole (0.88-1.71 over 16 seeds of its realistic profile, whose
per-measurement phase field the fits do not see; 2.5 at 512 px, where the fits' own u is
smaller; ``benchmarks/coverage_split.py``). A ball-bar sighting of the same scanner carries the same kind of error, so
the verification scales its sphere fits' covariance by ``max(1, kappa)^2``
(:mod:`fringecal.verification.uncertainty`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fringecal.calibration.increments import rotation_exp
from fringecal.calibration.model import BundleProblem
from fringecal.calibration.propagation import triangulate_mm
from fringecal.registration import kabsch
from fringecal.rig import Rig
from fringecal.spheres.fit import FitError, SphereModel, centre_sandwich_covariance

__all__ = ["ScannerDispersion", "sighting_dispersion", "MIN_SIGHTING_POINTS"]

#: a sighting enters with at least this many control points
MIN_SIGHTING_POINTS = 30


@dataclass(frozen=True)
class ScannerDispersion:
    """One scanner's ``kappa`` (see the module), its degrees of freedom, the views and
    sightings it came from."""

    kappa: float
    dof: int
    views: int
    sightings: int

    def to_dict(self) -> dict:
        return {"kappa": self.kappa, "dof": self.dof, "views": self.views, "sightings": self.sightings}


def _weighted_chi2(centres: np.ndarray, table: np.ndarray, W: np.ndarray, iterations: int = 5) -> float:
    """sum |W_i (c_i - R s_i - t)|^2 at the weighted least-squares rigid motion:
    Gauss-Newton from the unweighted (Kabsch) one. centres, table (n, 3); W (n, 3, 3)."""
    R, t = kabsch(table, centres)
    for _ in range(iterations):
        moved = table @ R.T + t
        r = np.einsum("nij,nj->ni", W, centres - moved).reshape(-1)
        # d(moved)/d(dt) = I, d(moved)/d(w) = -[moved - t]x for a small rotation w applied after R
        q = moved - t
        skew = np.zeros((len(q), 3, 3))
        skew[:, 0, 1], skew[:, 0, 2], skew[:, 1, 2] = -q[:, 2], q[:, 1], -q[:, 0]
        skew[:, 1, 0], skew[:, 2, 0], skew[:, 2, 1] = q[:, 2], -q[:, 1], q[:, 0]
        J = -np.einsum("nij,njk->nik", W, np.concatenate([np.broadcast_to(np.eye(3), (len(q), 3, 3)), -skew], axis=2))
        J = J.reshape(-1, 6)
        step = np.linalg.lstsq(J, -r, rcond=None)[0]
        R = rotation_exp(step[3:]) @ R
        t = t + step[:3]
        if np.linalg.norm(step) < 1e-12:
            break
    r = np.einsum("nij,nj->ni", W, centres - (table @ R.T + t))
    return float(np.sum(r**2))


def sighting_dispersion(problem: BundleProblem, rig: Rig) -> dict[str, ScannerDispersion]:
    """Per scanner of ``rig`` (the calibrated rig, in the world of ``problem``'s control
    points), the scatter of its sphere centres between spheres against their fits'
    covariance and the artefact table's ``u_mm`` (see the module); scanners without a
    view of 3 spheres are left out.

    Each sighting (scanner, measurement, sphere) of at least ``MIN_SIGHTING_POINTS``
    control points is triangulated with the calibrated scanner and fitted with the
    table's radius fixed.
    """
    art = problem.artefact
    u_table = np.zeros(len(art.ids)) if art.u is None else np.nan_to_num(np.asarray(art.u, float))
    start, stop, scanner_of, meas_of = problem.groups()
    per_scanner: dict[int, list] = {}
    for a, b, s, m in zip(start, stop, scanner_of, meas_of):
        centres, table, W = [], [], []
        spheres = problem.sphere_idx[a:b]
        for j in np.unique(spheres):
            idx = a + np.flatnonzero(spheres == j)
            if len(idx) < MIN_SIGHTING_POINTS:
                continue
            X = triangulate_mm(rig.scanners[s], problem.cam_mm[idx], problem.prj_mm[idx])
            radius = float(art.radii[j])
            try:
                fit = SphereModel.from_estimate(X, radius=radius)
            except FitError:
                continue
            C = centre_sandwich_covariance(X, fit.centre, radius) + u_table[j] ** 2 * np.eye(3)
            w, V = np.linalg.eigh(C)
            if not np.all(w > 0):
                continue
            centres.append(fit.centre)
            table.append(art.centres[j])
            W.append((V / np.sqrt(w)) @ V.T)
        if len(centres) >= 3:
            chi2 = _weighted_chi2(np.array(centres), np.array(table), np.array(W))
            per_scanner.setdefault(int(s), []).append((chi2, 3 * len(centres) - 6, len(centres)))
    out = {}
    for s, views in sorted(per_scanner.items()):
        chi2 = sum(v[0] for v in views)
        dof = sum(v[1] for v in views)
        out[rig.scanners[s].name] = ScannerDispersion(float(np.sqrt(chi2 / dof)), int(dof), len(views),
                                                      int(sum(v[2] for v in views)))
    return out
