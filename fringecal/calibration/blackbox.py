"""Black-box scanners in the adjustment: a scanner known only by the clouds it delivers.

A black-box scanner ``s`` measures sphere centres ``c`` in its own frame; it enters
with its exterior ``T_world_s`` (origin ``t_s``, angles ``omega, phi, kappa``: the
:class:`fringecal.frames.Frame` convention) and, by the setting ``scale``, a scale
factor ``k_s`` of its coordinates::

    x_world = R_s^T (k_s c) + t_s

Every labelled centre of measurement ``m`` and artefact sphere ``j`` observes the
sphere where the artefact's pose puts it::

    r = R_s^T (k_s c) + t_s - (R_m^T S_j + t_m)

weighted by the inverse of its covariance: the centre's, from the residuals of its
sphere fit (the fit's ``u_x_mm``, ``u_y_mm``, ``u_z_mm``) combined with the scanner's
measured scatter between spheres (:func:`scatter_between_spheres`: the scatter of its
centres about the artefact registered on each of its views, :func:`registration_noise`,
less what the fits and the CMM already state), carried into the world frame, plus the
CMM's ``u_mm`` of the sphere.
:func:`adjust_black_boxes` minimises the sum of the squared whitened residuals over
every black-box exterior and scale and every artefact pose at once:

* a rig of black boxes only: the reference scanner's frame is the world (its exterior
  fixed, its scale free with ``scale``), the poses are free;
* next to model-based scanners (:class:`ModelPrior`): the bundle adjustment's solution
  is a Gaussian prior; its pose block, cross-pose correlations included, enters as
  observations of the poses, and the modelled sensors follow the poses by Gaussian
  conditioning (:func:`_conditioned`): to first order the one adjustment of all of them.

Uncertainties: the covariance of every estimate is ``s0^2 (J^T J)^-1`` with ``J`` the
whitened Jacobian and ``s0^2 = sum r_w^2 / (n - p)`` the a-posteriori variance factor
when it exceeds 1 (the stated weights were too small for the scatter), else
``(J^T J)^-1`` (the stated weights alone).

:func:`pairwise_svd` is the baseline: each scanner registered on its own by its sphere
centres (the SVD pose of the artefact in each measurement, chained to the reference
scanner's pose of the same measurement, averaged over the measurements).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pandas as pd
import scipy.optimize

from fringecal.artefact import Artefact
from fringecal.frames import Frame
from fringecal.registration import kabsch, umeyama
from fringecal.rotation import rotation_derivatives, rotation_matrix

__all__ = ["BlackBoxResult", "BlackBoxScanner", "ModelPrior", "adjust_black_boxes", "pairwise_svd", "start_poses",
           "transform_points", "EXPORT_COLUMNS", "export_table", "inconsistent_views", "registration_noise",
           "scatter_between_spheres", "scanners_from_document", "point_uncertainty"]

#: columns of the simple export: one row per scanner, the 4x4 T_world_scanner row by row and the scale
EXPORT_COLUMNS = ("scanner", "scale", *(f"m{i}{j}" for i in range(4) for j in range(4)))


@dataclass(frozen=True)
class BlackBoxScanner:
    """One black-box scanner's calibration: ``x_world = R^T (scale c) + t``.

    ``params`` (tx, ty, tz, omega, phi, kappa, scale) and their covariance (7, 7), zero
    rows and columns for what was fixed (the reference's exterior; the scale without
    ``scale``). ``rms_mm``: RMS distance between its centres and the adjusted spheres;
    ``n_centres``: centres it contributed; ``scatter_mm``: its measured scatter between
    spheres per coordinate, net of its fits' own noise (:func:`scatter_between_spheres`;
    NaN in documents written before it was stored)."""

    name: str
    params: np.ndarray
    covariance: np.ndarray
    rms_mm: float
    n_centres: int
    scatter_mm: float = float("nan")

    @property
    def frame(self) -> Frame:
        return Frame.from_params(self.params[:6])

    @property
    def scale(self) -> float:
        return float(self.params[6])

    def matrix(self) -> np.ndarray:
        """4x4 homogeneous ``T_world_scanner`` (scale included): world = M @ [c, 1]."""
        M = np.eye(4)
        M[:3, :3] = self.scale * self.frame.R.T
        M[:3, 3] = self.params[:3]
        return M

    def to_dict(self) -> dict:
        names = ("tx_mm", "ty_mm", "tz_mm", "omega_rad", "phi_rad", "kappa_rad", "scale")
        return {"scanner": self.name, **{n: float(v) for n, v in zip(names, self.params)},
                "std": {n: float(np.sqrt(max(self.covariance[i, i], 0.0))) for i, n in enumerate(names)},
                "covariance": self.covariance.tolist(), "matrix": self.matrix().tolist(),
                "rms_mm": self.rms_mm, "n_centres": self.n_centres, "scatter_mm": self.scatter_mm}


@dataclass(frozen=True)
class BlackBoxResult:
    """What :func:`adjust_black_boxes` found: every black-box scanner, every pose
    (``poses``: PosePlanTable frame, ``pose_std``: their standard uncertainties), the
    a-posteriori variance factor ``s0`` and the redundancy ``dof``."""

    scanners: dict
    poses: pd.DataFrame
    pose_std: np.ndarray
    s0: float
    dof: int
    reference: str
    scale: bool
    residuals: pd.DataFrame = field(repr=False)
    joint: dict | None = field(default=None, repr=False)

    def to_dict(self) -> dict:
        out = {"reference": self.reference, "scale": self.scale, "s0": self.s0, "dof": self.dof,
               "scanners": [s.to_dict() for s in self.scanners.values()]}
        if self.joint is not None and self.joint["max_shift_sigma"] is not None:
            out["modelled_shift_max_sigma"] = self.joint["max_shift_sigma"]
        return out


def transform_points(scanner: BlackBoxScanner, points: np.ndarray) -> np.ndarray:
    """Points (n, 3) of ``scanner``'s frame in the world."""
    return np.asarray(points, float) @ scanner.matrix()[:3, :3].T + scanner.params[:3]


def scanners_from_document(doc: dict) -> dict[str, BlackBoxScanner]:
    """The black-box scanners of ``black_boxes.json`` (or calibration.json's ``black_boxes``)."""
    names = ("tx_mm", "ty_mm", "tz_mm", "omega_rad", "phi_rad", "kappa_rad", "scale")
    return {d["scanner"]: BlackBoxScanner(d["scanner"], np.array([d[n] for n in names], float),
                                          np.array(d["covariance"], float), float(d["rms_mm"]), int(d["n_centres"]),
                                          float(d.get("scatter_mm", float("nan"))))
            for d in doc["scanners"]}


def point_uncertainty(scanner: BlackBoxScanner, points: np.ndarray) -> np.ndarray:
    """Standard uncertainty (n,) in mm (sqrt of the covariance's trace) of points of
    ``scanner``'s frame carried into the world, from its transform's covariance alone."""
    p = np.asarray(points, float)
    k = scanner.scale
    om, ph, ka = scanner.params[3:6]
    dR = rotation_derivatives(om, ph, ka)  # (3, 3, 3): d R / d angle
    R = scanner.frame.R
    J = np.empty((len(p), 3, 7))
    J[:, :, :3] = np.eye(3)
    for a in range(3):
        J[:, :, 3 + a] = k * p @ dR[a]  # d(R^T k c)/d angle = k (dR^T) c
    J[:, :, 6] = p @ R
    JC = np.einsum("nij,jk->nik", J, scanner.covariance)
    return np.sqrt(np.clip(np.einsum("nik,nik->n", JC, J), 0, None))


def export_table(scanners) -> pd.DataFrame:
    """The simple export: one row per scanner, scale and the 4x4 ``T_world_scanner``
    (``m00`` ... ``m33``, row by row; the scale is inside the upper 3x3)."""
    rows = []
    for s in scanners:
        M = s.matrix()
        rows.append({"scanner": s.name, "scale": s.scale, **{f"m{i}{j}": float(M[i, j]) for i in range(4)
                                                             for j in range(4)}})
    return pd.DataFrame(rows, columns=list(EXPORT_COLUMNS))


def _centres(centres: pd.DataFrame, artefact: Artefact) -> dict:
    c = centres[centres["sphere_id"].astype(str) != ""]
    u = np.column_stack([c[k].to_numpy(float) if k in c else np.full(len(c), np.nan)
                         for k in ("u_x_mm", "u_y_mm", "u_z_mm")])
    return {"measurement": c["measurement"].astype(str).to_numpy(), "scanner": c["scanner"].astype(str).to_numpy(),
            "sphere": c["sphere_id"].astype(str).map({s: i for i, s in enumerate(artefact.ids)}).to_numpy(),
            "xyz": c[["x_mm", "y_mm", "z_mm"]].to_numpy(float), "u": u}


def start_poses(centres: pd.DataFrame, artefact: Artefact, frames: dict) -> dict:
    """``T_world_artefact`` per measurement from the first scanner of ``frames`` (name ->
    (Frame, scale)) that saw at least three spheres of it, by SVD."""
    obs = _centres(centres, artefact)
    out = {}
    for m in dict.fromkeys(obs["measurement"]):
        for s, (frame, k) in frames.items():
            sel = (obs["measurement"] == m) & (obs["scanner"] == s)
            if sel.sum() >= 3:
                world = frame.to_world(k * obs["xyz"][sel])
                R, t = kabsch(artefact.centres[obs["sphere"][sel]], world)
                out[m] = Frame.from_matrix(R.T, t)
                break
    return out


def pairwise_svd(centres: pd.DataFrame, artefact: Artefact, reference: str) -> dict:
    """Each scanner registered on its own by its sphere centres: per measurement it shares
    with the reference, ``T_world_s = T_world_artefact(ref) o T_s_artefact^-1`` (both by
    SVD of the centres), averaged over the measurements (chordal mean rotation, mean
    origin). Returns scanner -> :class:`BlackBoxScanner` (scale 1, no covariance)."""
    obs = _centres(centres, artefact)
    poses = {}
    for (m, s) in dict.fromkeys(zip(obs["measurement"], obs["scanner"])):
        sel = (obs["measurement"] == m) & (obs["scanner"] == s)
        if sel.sum() >= 3:
            R, t = kabsch(artefact.centres[obs["sphere"][sel]], obs["xyz"][sel])
            poses[(m, s)] = Frame.from_matrix(R.T, t)
    out = {reference: BlackBoxScanner(reference, np.r_[np.zeros(6), 1.0], np.zeros((7, 7)), float("nan"), 0)}
    for s in dict.fromkeys(obs["scanner"]):
        if s == reference:
            continue
        links = [poses[(m, reference)].compose(poses[(m, s)].inverse()) for (m, ss) in poses
                 if ss == s and (m, reference) in poses]
        if links:
            mean = _mean_frame(links)
            out[s] = BlackBoxScanner(s, np.r_[mean.params, 1.0], np.zeros((7, 7)), float("nan"), 0)
    return out


def registration_noise(obs: dict, artefact: Artefact, similarity: bool = False) -> dict:
    """Each scanner's measured centre noise: the RMS per coordinate of its centres about
    the artefact registered onto each of its views by SVD (redundancy 3 n - 6 per view
    of n >= 3 spheres). Unlike a sphere fit's own uncertainty it holds what differs
    from sphere to sphere in one view (a rod's shadow, a partly seen cap), which repeats
    from pose to pose when the artefact only translates. With ``similarity`` each view
    is registered with a scale too (what a scanner's adjusted scale factor absorbs)."""
    out = {}
    for s in dict.fromkeys(obs["scanner"]):
        ss, dof = 0.0, 0
        for m in dict.fromkeys(obs["measurement"][obs["scanner"] == s]):
            sel = (obs["scanner"] == s) & (obs["measurement"] == m)
            n = int(sel.sum())
            if n < 3:
                continue
            src = artefact.centres[obs["sphere"][sel]]
            if similarity and n >= 4:
                k, R, t = umeyama(src, obs["xyz"][sel])
                ss += float(np.sum((k * src @ R.T + t - obs["xyz"][sel]) ** 2))
                dof += 3 * n - 7
            else:
                R, t = kabsch(src, obs["xyz"][sel])
                ss += float(np.sum((src @ R.T + t - obs["xyz"][sel]) ** 2))
                dof += 3 * n - 6
        if dof > 0:
            out[s] = float(np.sqrt(ss / dof))
    return out


def scatter_between_spheres(obs: dict, artefact: Artefact, similarity: bool = False) -> dict:
    """Each scanner's scatter of centres between spheres per coordinate (mm), net of what
    its sphere fits and the CMM already state: ``sqrt(max(0, n^2 - mean u_fit^2 -
    mean u_CMM^2))`` with ``n`` the :func:`registration_noise` and the means over the
    scanner's centres and coordinates. Only this part is added to a centre's weight and
    to a sighting's U: the registration's residuals hold each fit's noise too, which its
    own covariance already carries (counted twice it made the mixed rig's ball-bar U 25 %
    too large: coverage 0.98, RMS error / u 0.79 over 20 seeds)."""
    noise = registration_noise(obs, artefact, similarity)
    u_cmm = np.asarray(artefact.u, float)[obs["sphere"]]
    out = {}
    for s, n in noise.items():
        sel = obs["scanner"] == s
        u = obs["u"][sel]
        fit_var = float(np.mean(u[np.isfinite(u)] ** 2)) if np.isfinite(u).any() else 0.0
        out[s] = float(np.sqrt(max(0.0, n**2 - fit_var - float(np.mean(u_cmm[sel] ** 2)))))
    return out


def inconsistent_views(labels: pd.DataFrame, scanners) -> pd.DataFrame:
    """The black boxes' views whose labelling the other scanners' poses contradicted
    (``refused``, reason ``inconsistent`` in a LabelOutcomesTable): a cloud of another
    scanner's frame (a swapped file) is one. A modelled scanner's such view is left out
    and the run goes on; a black box's stops it, since only its file can be wrong."""
    if labels is None or not len(labels):
        return pd.DataFrame(columns=["measurement", "scanner", "message"])
    bad = (labels["status"] == "refused") & (labels["reason"].astype(str) == "inconsistent") & \
        labels["scanner"].astype(str).isin(list(scanners))
    return labels.loc[bad, ["measurement", "scanner", "message"]].reset_index(drop=True)


def _mean_frame(frames) -> Frame:
    """Chordal mean rotation (the nearest rotation to the mean matrix) and mean origin."""
    u, _, vt = np.linalg.svd(np.mean([f.R for f in frames], axis=0))
    R = u @ np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt)) or 1.0]) @ vt
    return Frame.from_matrix(R, np.mean([f.t for f in frames], axis=0), near=frames[0].angles)


@dataclass(frozen=True)
class ModelPrior:
    """The bundle adjustment's solution as a Gaussian prior on its free parameters:
    ``x`` (p,) and their ``covariance`` (p, p) in the bundle's layout (``names``),
    ``pose_index`` (n_meas, 6) the place of each pose parameter in ``x`` (-1: fixed at
    ``poses``), ``poses`` (n_meas, 6) and their ``measurements``. With it the black
    boxes are adjusted together with every modelled parameter: to first order the one
    adjustment of all of them (the bundle's F is quadratic about its minimum with this
    covariance)."""

    x: np.ndarray
    covariance: np.ndarray
    pose_index: np.ndarray
    poses: np.ndarray
    measurements: tuple
    names: tuple


class _Layout:
    """Where each free parameter sits: black-box scanners (6 exterior + scale), then the
    poses (6 each)."""

    def __init__(self, scanners, reference, measurements, scale, prior: ModelPrior | None):
        self.scanners, self.measurements = list(scanners), list(measurements)
        self.free = {}
        k = 0
        for s in self.scanners:
            ext = [] if (s == reference and prior is None) else list(range(6))
            idx = ext + ([6] if scale else [])
            self.free[s] = (np.array(idx, int), np.arange(k, k + len(idx)))
            k += len(idx)
        self.n_boxes = k
        self.n = k + 6 * len(self.measurements)

    def unpack(self, x, base):
        params = {}
        for s in self.scanners:
            p = base[s].copy()
            idx, pos = self.free[s]
            p[idx] = x[pos]
            params[s] = p
        return params, x[self.n_boxes:].reshape(-1, 6)

    def pack(self, base, poses):
        x = np.empty(self.n)
        for s in self.scanners:
            idx, pos = self.free[s]
            x[pos] = base[s][idx]
        x[self.n_boxes:] = np.asarray(poses, float).ravel()
        return x


def _whitener(C: np.ndarray) -> np.ndarray:
    """W with W C W^T = I on C's range: C scaled to a unit diagonal first (parameters of
    mm, rad and mm^-6 differ by 20 orders), its eigenvalues below 1e-12 of the largest
    dropped."""
    d = np.sqrt(np.clip(np.diag(C), 1e-300, None))
    w, V = np.linalg.eigh((C + C.T) / 2 / np.outer(d, d))
    keep = w > 1e-12 * w.max()
    return (V[:, keep] / np.sqrt(w[keep])).T / d[None, :]


def adjust_black_boxes(centres: pd.DataFrame, artefact: Artefact, reference: str, start: dict,
                       scale: bool = False, prior: ModelPrior | None = None) -> BlackBoxResult:
    """Adjust every black-box scanner's exterior (and scale) and every artefact pose at once.

    Parameters
    ----------
    centres : DataFrame
        Labelled sphere fits of the black-box scanners (SphereFitsTable columns:
        ``measurement``, ``scanner``, ``sphere_id``, ``x_mm``..``z_mm``, ``u_x_mm``..``u_z_mm``).
    artefact : Artefact
    reference : str
        The world's scanner: a black box (its exterior fixed; black boxes only) or a
        modelled scanner (then ``prior`` is required and every black box is free).
    start : dict
        scanner -> (Frame T_world_scanner, scale) start values, one per black box.
    scale : bool
        Adjust a scale factor per black-box scanner.
    prior : ModelPrior, optional
        The bundle adjustment's solution (rigs with modelled scanners).
    """
    obs = _centres(centres, artefact)
    if not len(obs["xyz"]):
        raise ValueError("no labelled sphere centre of a black-box scanner")
    if reference not in start and prior is None:
        raise ValueError(f"reference scanner {reference!r} is not a black box: the bundle's solution is needed")
    scanners = list(start)
    if prior is not None:
        meas = [str(m) for m in prior.measurements]
    else:
        meas = list(dict.fromkeys(obs["measurement"]))
    keep = np.isin(obs["measurement"], meas) & np.isin(obs["scanner"], scanners)
    obs = {k: v[keep] for k, v in obs.items()}
    lay = _Layout(scanners, reference, meas, scale, prior)
    base = {s: np.r_[f.params, k] for s, (f, k) in start.items()}
    if prior is None:
        poses0 = start_poses(centres[np.isin(centres["scanner"].astype(str), scanners)], artefact, start)
        missing = [m for m in meas if m not in poses0]
        if missing:
            raise ValueError(f"measurement(s) {missing}: no pose (fewer than three labelled spheres in every "
                             "scanner)")
        p0 = np.array([poses0[m].params for m in meas])
    else:
        p0 = np.asarray(prior.poses, float)
        pose_free = (prior.pose_index >= 0).ravel()
        pose_at = prior.pose_index.ravel()[pose_free]
        pose_hat = prior.x[pose_at]
    x0 = lay.pack(base, p0)
    s_idx = np.array([scanners.index(s) for s in obs["scanner"]])
    m_idx = np.array([meas.index(m) for m in obs["measurement"]])
    u = obs["u"]
    good = np.isfinite(u) & (u > 0)
    u = np.where(good, u, np.median(u[good]) if good.any() else 0.01)
    floor = scatter_between_spheres(obs, artefact, similarity=scale)
    u = np.sqrt(u**2 + np.array([floor.get(s, 0.0) for s in obs["scanner"]])[:, None] ** 2)
    u_cmm = np.asarray(artefact.u, float)[obs["sphere"]]
    # whitening of each centre: its covariance in the world at the start rotation (fixed)
    W = np.empty((len(s_idx), 3, 3))
    for i, s in enumerate(obs["scanner"]):
        R, k = start[s][0].R, start[s][1]
        C = k**2 * R.T @ np.diag(u[i] ** 2) @ R + u_cmm[i] ** 2 * np.eye(3)
        W[i] = np.linalg.inv(np.linalg.cholesky(C))
    # the bundle's knowledge of the poses: the pose block of its covariance, cross-pose
    # correlations included (the sensors follow by conditioning, :func:`joint_covariance`)
    prior_W = _whitener(prior.covariance[np.ix_(pose_at, pose_at)]) if prior is not None else None

    def geometry(x):
        params, poses = lay.unpack(x, base)
        P = np.array([params[s] for s in scanners])
        Rs = rotation_matrix(P[:, 3], P[:, 4], P[:, 5])
        Rm = rotation_matrix(poses[:, 3], poses[:, 4], poses[:, 5])
        world = np.einsum("nji,nj->ni", Rs[s_idx], P[s_idx, 6][:, None] * obs["xyz"]) + P[s_idx, :3]
        target = np.einsum("nji,nj->ni", Rm[m_idx], artefact.centres[obs["sphere"]]) + poses[m_idx, :3]
        return params, poses, world - target

    def residuals(x):
        r = np.einsum("nij,nj->ni", W, geometry(x)[2]).ravel()
        if prior_W is not None:
            r = np.concatenate([r, prior_W @ (x[lay.n_boxes:][pose_free] - pose_hat)])
        return r

    sol = scipy.optimize.least_squares(residuals, x0, method="lm", x_scale="jac", xtol=1e-12, ftol=1e-12,
                                       max_nfev=200 * (lay.n + 1))
    x = sol.x
    J = _jacobian(residuals, x)
    r = residuals(x)
    dof = len(r) - lay.n
    s0 = float(np.sqrt(r @ r / dof)) if dof > 0 else float("nan")
    cov = _scaled_inverse(J.T @ J) * (max(s0, 1.0) ** 2 if dof > 0 else 1.0)
    params, poses, d = geometry(x)
    out = {}
    for s in scanners:
        idx, pos = lay.free[s]
        C = np.zeros((7, 7))
        C[np.ix_(idx, idx)] = cov[np.ix_(pos, pos)]
        sel = obs["scanner"] == s
        out[s] = BlackBoxScanner(s, params[s], C, float(np.sqrt(np.mean(np.sum(d[sel] ** 2, axis=1)))),
                                 int(sel.sum()), floor.get(s, 0.0))
    pose_df = pd.DataFrame(poses, columns=list(Frame_COLUMNS))
    pose_df.insert(0, "measurement", meas)
    pose_std = np.sqrt(np.clip(np.diag(cov)[lay.n_boxes:], 0, None)).reshape(-1, 6)
    res = pd.DataFrame({"measurement": obs["measurement"], "scanner": obs["scanner"],
                        "sphere_id": np.asarray(artefact.ids)[obs["sphere"]],
                        "dx_mm": d[:, 0], "dy_mm": d[:, 1], "dz_mm": d[:, 2]})
    if prior is not None:
        joint = _conditioned(prior, cov, x, lay, pose_free, pose_at)
    else:  # black boxes only: their transforms' covariance, cross-covariances included
        joint = {"covariance": cov[:lay.n_boxes, :lay.n_boxes], "n_model": 0, "x": np.zeros(0),
                 "max_shift_sigma": None}
    joint["free"] = {s: lay.free[s] for s in scanners}
    return BlackBoxResult(out, pose_df, pose_std, s0, int(dof), reference, bool(scale), res, joint)


def _scaled_inverse(N: np.ndarray) -> np.ndarray:
    """N^-1 through its unit-diagonal scaling (parameters of very different units)."""
    d = np.sqrt(np.clip(np.diag(N), 1e-300, None))
    return np.linalg.pinv(N / np.outer(d, d), rcond=1e-13, hermitian=True) / np.outer(d, d)


def _conditioned(prior: ModelPrior, cov: np.ndarray, x: np.ndarray, lay: "_Layout", pose_free, pose_at) -> dict:
    """The bundle's parameters given what the black boxes added to its poses (Gaussian
    conditioning, exact for the linearised problem): with P the prior pose covariance,
    K = C_(all, poses) P^-1, the update is K (p - p_hat), the covariance
    C - K (P - P') K^T, and the cross-covariance with the black boxes K C'_(poses, boxes).
    Returns the covariance of [the bundle's free parameters, the black boxes' free
    parameters], the updated bundle parameters and their largest shift in standard
    uncertainties."""
    C = prior.covariance
    P = C[np.ix_(pose_at, pose_at)]
    K = C[:, pose_at] @ _scaled_inverse(P)
    nb = lay.n_boxes
    pose_cols = nb + np.flatnonzero(pose_free)
    P_post = cov[np.ix_(pose_cols, pose_cols)]
    cross = K @ cov[np.ix_(pose_cols, np.arange(nb))]
    C_mb = C - K @ (P - P_post) @ K.T
    out = np.block([[C_mb, cross], [cross.T, cov[:nb, :nb]]])
    update = K @ (x[pose_cols] - prior.x[pose_at])
    shift = update / np.sqrt(np.clip(np.diag(C), 1e-300, None))
    return {"covariance": out, "n_model": len(prior.x), "x": prior.x + update,
            "max_shift_sigma": float(np.max(np.abs(shift))) if len(shift) else 0.0}


Frame_COLUMNS = ("tx_mm", "ty_mm", "tz_mm", "omega_rad", "phi_rad", "kappa_rad")


def _jacobian(fun, x, step: float = 1e-6) -> np.ndarray:
    """Central-difference Jacobian (angles in rad and lengths in mm take the same step)."""
    r0 = fun(x)
    J = np.empty((len(r0), len(x)))
    for i in range(len(x)):
        h = step * max(1.0, abs(x[i]))
        e = np.zeros_like(x)
        e[i] = h
        J[:, i] = (fun(x + e) - fun(x - e)) / (2 * h)
    return J
