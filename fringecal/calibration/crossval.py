"""Cross-validation of a calibration: two halves of the measurements, compared in mm.

The measurements (artefact poses) are split into two halves (:func:`split_measurements`),
each half is calibrated on its own (:func:`subproblem`, :func:`.bundle.bundle_adjust`)
and both half-calibrations triangulate the *same* observations: a sample of each
scanner's control points of the full problem (camera pixel and projector phases as
image-plane mm). The halves share no measurement, so their parameter errors are
independent; if the model is right the difference ``d = P_1 - P_2`` of the two points
has the covariance ``C_d = C_1 + C_2`` the adjustments state (:mod:`.propagation`).
A difference beyond it is model error: something the 14-parameter sensors, rigid poses
and the artefact table do not describe and that differs between the halves (mrcal's
cross-validation, in object space and millimetres instead of pixels).

Decisions
---------
* Same observations in both halves: the observation noise of a sampled point is common
  to ``P_1`` and ``P_2`` and cancels to first order, so ``d`` holds the parameter errors
  only (``d = J_1 dtheta_1 - J_2 dtheta_2``); that half of the sampled points took part
  in one of the adjustments does not matter.
* Three frames (``FRAMES``). ``"world"``: the points as triangulated, in the reference
  scanner's frame. Its orientation is weakly determined even though the reference
  camera's exterior is fixed: that camera's free principal point trades against a
  rotation of everything else about its pinhole (0.06 mm at c = 53 mm is ~1 mrad, ~3 mm
  at the thesis's 3 m), so in the simulated thesis rig the world comparison is dominated
  by this rigid motion (mm where the other frames see 0.1 mm), which changes no
  measurement. As mrcal fits the "implied transformation" between two solutions before
  comparing projections, ``"reference"`` first removes the rigid motion that aligns the
  halves' points of the reference scanner (Kabsch over its sampled points) from every
  scanner's differences: whether a scanner's points land where the reference scanner's
  do (what merging the clouds depends on). ``"scanner"`` removes each scanner's own
  best-fit rigid motion: what a measurement of that scanner alone (lengths, forms)
  depends on. The covariances follow the same linear operation (Jacobian columns minus
  their least-squares small rigid motion, :func:`rigid_residual`, with each half's full
  sensor covariance, since an alignment on the reference scanner mixes scanners). The
  verdict uses ``VERDICT_FRAMES`` = scanner and reference; world is reported. An error of
  the reference scanner itself shows in its scanner frame and, through the alignment,
  in the other scanners' reference frame; an error of another scanner leaves the
  reference scanner's figures alone.
* Statistic: ``z^2 = d^T C_d^-1 d`` per point; with the stated uncertainty right its mean
  is exactly 3 (``E z^2 = tr(C_d^-1 C_d)``), so ``mean z^2 / 3`` is 1 on average.
* Model error: let each half-calibration carry, besides its stated random error, an
  unmodelled error ``b_k`` of each point, independent between the halves and with mean
  square length ``E|b_k|^2 = s^2`` (summed over the three coordinates). Then
  ``E|d|^2 = tr C_1 + tr C_2 + E|b_1|^2 + E|b_2|^2 - 2 E(b_1 . b_2) = tr C_d + 2 s^2``,
  so ``s = sqrt(max(0, mean|d|^2 - mean tr C_d) / 2)``: the RMS length of one
  half-calibration's unmodelled 3-D point error (``model_error_mm``; in the reference
  and scanner frames its part that no rigid motion absorbs). An error in one half only
  (``b_2 = 0``) gives ``|b_1| / sqrt(2)``; an error common to both halves (the same wrong
  artefact length in every measurement) cancels in ``d``: cross-validation cannot see
  it (the ball-bar check can).
* Verdict: the sampled points share the parameters of the two half-calibrations, so
  they are far from independent: with n independent points ``mean z^2 / 3`` would be
  ``chi^2_{3n} / 3n`` (99 % bound 1.04 for n = 2000), but it is a quadratic form in the
  parameter errors, ``Q = dtheta^T A dtheta`` with ``A = mean_i G_i^T C_d,i^-1 G_i``,
  ``G_i = [J_1,i, -J_2,i]``. Its effective number of degrees of freedom (Satterthwaite)
  is ``nu = tr(A S)^2 / tr((A S)^2)`` (``S`` = block-diag of the halves' covariances;
  ``tr(A S) = 3``), a few to a few tens (3 in the world frame, 6-10 in the others in the
  simulated thesis rig), and ``mean z^2 / 3 ~ chi^2_nu / nu``. The
  verdict is ``"consistent"`` when
  ``mean z^2 / 3 <= max(CONSISTENT_MAX, chi^2_nu quantile (1 - FALSE_ALARM) / nu)``:
  ``CONSISTENT_MAX = 4`` accepts differences up to twice the predicted RMS (2 sigma in RMS
  terms), so an uncertainty statement off by less than a factor two is not called model
  error; the chi-square bound raises it where ``nu`` is so small that chance alone
  exceeds 4 more often than ``FALSE_ALARM``. Checked on the simulated thesis rig (exact
  model, 60 noise realisations, 300 points per scanner): the average of ``mean z^2 / 3``
  was 0.92-1.13 per scanner and frame, its scatter as chi^2_nu / nu predicts, and one
  of the 240 verdicts was "model error" (4.9 against 4, reference frame, nu = 6).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
import scipy.stats

from fringecal.calibration.bundle import BundleOptions, BundleResult, bundle_adjust
from fringecal.calibration.keyed import keyed_uniform, row_keys
from fringecal.calibration.model import BundleProblem
from fringecal.calibration.propagation import (
    point_covariance,
    point_jacobian,
    sensor_covariance,
    triangulate_mm,
)
from fringecal.registration import kabsch
from fringecal.rotation import rotation_matrix
from fringecal.sensor import PARAM_NAMES

__all__ = [
    "CONSISTENT_MAX",
    "FALSE_ALARM",
    "FRAMES",
    "MIN_MEASUREMENTS_PER_SCANNER",
    "VERDICT_FRAMES",
    "CrossValidation",
    "PointComparison",
    "cross_validate",
    "rigid_residual",
    "split_measurements",
    "subproblem",
]

#: measurements with control points of a scanner that each half must keep
MIN_MEASUREMENTS_PER_SCANNER = 3
#: largest mean z^2 / 3 called consistent (differences twice the predicted RMS)
CONSISTENT_MAX = 4.0
#: probability of calling a correct calibration "model error" that the chi-square bound allows
FALSE_ALARM = 0.01
FRAMES = ("scanner", "reference", "world")
VERDICT_FRAMES = ("scanner", "reference")


def split_measurements(problem: BundleProblem, seed: int | None = None) -> tuple[tuple, tuple]:
    """Two halves of the measurements, each in table order.

    Parameters
    ----------
    problem : BundleProblem
    seed : int or None
        None (default): alternate measurements in the order of their stand-off (1st,
        3rd, ... and 2nd, 4th, ... nearest first, :func:`standoff_order`), which gives
        both halves the same spread over the depth of the volume; a split into near and
        far halves would give each half half the depth. The stand-off, not the table
        order, so that the halves do not depend on the measurements' names. An int: a
        random split of that order into halves of the same sizes (for repeated
        cross-validation).

    Returns
    -------
    (tuple of str, tuple of str)

    Raises
    ------
    ValueError
        If in either half some scanner has control points in fewer than
        ``MIN_MEASUREMENTS_PER_SCANNER`` measurements: its 28 parameters would rest on a
        single placement or two of the artefact (``single_pose``/``single_standoff``
        degeneracies of :mod:`.diagnostics`), and the comparison would measure that
        weakness instead of model error.
    """
    meas = problem.measurements
    order = standoff_order(problem)
    if seed is not None:
        order = order[np.random.default_rng(seed).permutation(len(meas))]
    halves = tuple(tuple(meas[i] for i in sorted(order[k::2])) for k in (0, 1))
    seen = _measurements_per_scanner(problem)
    missing = []
    for label, half in zip("AB", halves):
        for name, have in seen.items():
            kept = [m for m in half if m in have]
            if len(kept) < MIN_MEASUREMENTS_PER_SCANNER:
                missing.append(f"scanner {name} has control points in {len(kept)} measurement(s) of half {label} "
                               f"({', '.join(kept) or 'none'}; {len(have)} in all)")
    if missing:
        raise ValueError(f"cross-validation needs at least {MIN_MEASUREMENTS_PER_SCANNER} measurements with control "
                         f"points of every scanner in each half of the {len(meas)} measurements: "
                         + "; ".join(missing) + ". Add measurements in which these scanners see the artefact")
    return halves


def standoff_order(problem: BundleProblem) -> np.ndarray:
    """Measurement indices by the distance of the artefact's centroid (at the start
    poses) from the reference camera's projection centre, nearest first: an order of
    the data, not of the measurements' names."""
    poses = np.asarray(problem.poses, float)
    R = rotation_matrix(poses[:, 3], poses[:, 4], poses[:, 5])
    centroid = problem.artefact.centres.mean(axis=0)
    world = poses[:, :3] + np.einsum("nji,j->ni", R, centroid)  # x_world = R^T x_local + t
    camera = problem.rig.scanner(problem.rig.reference).camera.params[:3]
    distance = np.linalg.norm(world - camera, axis=1)
    return np.lexsort((row_keys(poses), distance))


def _measurements_per_scanner(problem: BundleProblem) -> dict:
    """Scanner name -> set of measurement names with control points of that scanner."""
    out = {}
    for si, sc in enumerate(problem.rig.scanners):
        idx = np.unique(problem.meas_idx[problem.scanner_idx == si])
        out[sc.name] = {problem.measurements[i] for i in idx}
    return out


def subproblem(problem: BundleProblem, measurements) -> BundleProblem:
    """The problem restricted to ``measurements``: their control points and poses only.

    Measurements keep the problem's (table) order whatever the order given; start values,
    free flags (``pose_free``), gammas, ``row`` (rows of the original table) and
    ``dropped`` are kept. Raises ValueError for names that are not measurements of the
    problem.
    """
    wanted = [str(m) for m in measurements]
    unknown = sorted(set(wanted) - set(problem.measurements))
    if unknown:
        raise ValueError(f"measurements {unknown} are not in the problem ({len(problem.measurements)} measurements)")
    keep_m = np.array([m in set(wanted) for m in problem.measurements], bool)
    new_index = np.cumsum(keep_m) - 1
    keep = keep_m[problem.meas_idx]
    return replace(problem, measurements=tuple(np.asarray(problem.measurements, object)[keep_m]),
                   poses=problem.poses[keep_m], pose_free=problem.pose_free[keep_m],
                   scanner_idx=problem.scanner_idx[keep], meas_idx=new_index[problem.meas_idx[keep]],
                   sphere_idx=problem.sphere_idx[keep], cam_mm=problem.cam_mm[keep], prj_mm=problem.prj_mm[keep],
                   row=problem.row[keep])


# -- points, Jacobians and the rigid motion --------------------------------------

def rigid_residual(points: np.ndarray, v: np.ndarray, fit=None) -> np.ndarray:
    """The part of displacements ``v`` that no small rigid motion of ``points`` explains.

    Parameters
    ----------
    points : (n, 3)
    v : (n, 3) or (n, 3, k)
        Displacements of the points (k columns, e.g. a Jacobian's).
    fit : index array or boolean mask, optional
        The points whose displacements define the motion (default all); it is removed
        from every point.

    Returns
    -------
    ndarray, shape of ``v``: v minus the least-squares fit ``t + w x (points - centroid)``
    to ``v[fit]`` (a linear projector; :func:`.registration.kabsch` is its exact counterpart).
    """
    points = np.asarray(points, float)
    fit = np.arange(len(points)) if fit is None else fit
    x = points - np.mean(points[fit], axis=0)
    n = len(x)
    H = np.zeros((n, 3, 6))
    H[:, :, :3] = np.eye(3)
    # w x x = -[x]_x w
    H[:, 0, 4], H[:, 0, 5] = x[:, 2], -x[:, 1]
    H[:, 1, 3], H[:, 1, 5] = -x[:, 2], x[:, 0]
    H[:, 2, 3], H[:, 2, 4] = x[:, 1], -x[:, 0]
    flat = np.asarray(v, float).reshape(n, 3, -1)
    Hf = H[fit]
    coef = np.linalg.solve(np.einsum("nki,nkj->ij", Hf, Hf), np.einsum("nki,nkp->ip", Hf, flat[fit]))
    return (flat - np.einsum("nki,ip->nkp", H, coef)).reshape(np.shape(v))


def _half_points(half: BundleResult, problem: BundleProblem, index: np.ndarray, scanner_of: np.ndarray):
    """World points (N, 3), their Jacobians (N, 3, 14 n_sensors) over all sensor
    parameters and the sensor covariance of one half-calibration."""
    S = sensor_covariance(half.layout.sensor_index, half.uncertainty.covariance)
    std = np.sqrt(np.clip(np.diag(S), 0, None))
    P = np.empty((len(index), 3))
    J = np.zeros((len(index), 3, len(S)))
    for si, sc in enumerate(half.rig.scanners):
        m = scanner_of == si
        cam, prj = problem.cam_mm[index[m]], problem.prj_mm[index[m]]
        cols = slice(28 * si, 28 * si + 28)  # camera then projector (rig order)
        P[m] = triangulate_mm(sc, cam, prj)
        J[m, :, cols] = point_jacobian(sc, cam, prj, std[cols])
    return P, J, S


def _in_frame(P1, P2, J1, J2, groups):
    """d (N, 3) and both Jacobians with best-fit rigid motions removed. ``groups``: pairs
    (fit rows, rows) -- the motion that aligns half 1's points of the fit rows on half
    2's is removed from the rows; None: nothing removed. d by Kabsch (exact), the
    Jacobians by the linear projector (first order)."""
    if groups is None:
        return P1 - P2, J1, J2
    d, R1, R2 = np.empty_like(P1), np.empty_like(J1), np.empty_like(J2)
    for fit, rows in groups:
        M, T = kabsch(P1[fit], P2[fit])
        d[rows] = P1[rows] @ M.T + T - P2[rows]
        mid = 0.5 * (P1[rows] + P2[rows])
        inner = np.flatnonzero(np.isin(rows, fit))
        R1[rows], R2[rows] = rigid_residual(mid, J1[rows], inner), rigid_residual(mid, J2[rows], inner)
    return d, R1, R2


@dataclass(frozen=True)
class PointComparison:
    """Two half-calibrations' points of the same observations of one scanner, in one frame.

    Attributes
    ----------
    scanner, frame : str
        Scanner name; one of ``FRAMES``.
    index : ndarray of int, shape (n,)
        The sampled control points (indices into the full problem's arrays).
    d : ndarray, shape (n, 3)
        P_1 - P_2 (mm), after the frame's rigid alignment.
    cov_d : ndarray, shape (n, 3, 3)
        C_1 + C_2 (mm^2).
    z2 : ndarray, shape (n,)
        d^T C_d^-1 d.
    effective_dof : float
        nu of mean z^2 / 3 ~ chi^2_nu / nu (module docstring).
    """

    scanner: str
    frame: str
    index: np.ndarray = field(repr=False)
    d: np.ndarray = field(repr=False)
    cov_d: np.ndarray = field(repr=False)
    z2: np.ndarray = field(repr=False)
    effective_dof: float

    @classmethod
    def of(cls, scanner, frame, index, d, J1, J2, S1, S2) -> PointComparison:
        """From differences d (n, 3), Jacobians J1, J2 (n, 3, p) and covariances S1, S2 (p, p)."""
        cols = np.flatnonzero(np.any(J1 != 0, axis=(0, 1)) | np.any(J2 != 0, axis=(0, 1)))
        J1, J2 = J1[:, :, cols], J2[:, :, cols]
        S1, S2 = S1[np.ix_(cols, cols)], S2[np.ix_(cols, cols)]
        cov = point_covariance(J1, S1) + point_covariance(J2, S2)
        z2 = np.einsum("ni,ni->n", d, np.linalg.solve(cov, d[..., None])[..., 0])
        G = np.concatenate([J1, -J2], axis=2)
        A = np.einsum("nki,nkj->ij", G, np.linalg.solve(cov, G)) / len(d)
        k = len(cols)
        S = np.zeros((2 * k, 2 * k))
        S[:k, :k], S[k:, k:] = S1, S2
        AS = A @ S
        nu = float(np.trace(AS) ** 2 / np.sum(AS * AS.T))
        return cls(scanner, frame, np.asarray(index, np.int64), d, cov, z2, nu)

    @property
    def rms_difference_mm(self) -> float:
        return float(np.sqrt(np.mean(np.sum(self.d**2, axis=1))))

    @property
    def rms_predicted_mm(self) -> float:
        """sqrt(mean tr C_d)."""
        return float(np.sqrt(np.mean(np.trace(self.cov_d, axis1=1, axis2=2))))

    @property
    def ratio(self) -> float:
        return self.rms_difference_mm / self.rms_predicted_mm

    @property
    def mean_z2_over_3(self) -> float:
        return float(np.mean(self.z2) / 3)

    @property
    def threshold(self) -> float:
        """max(CONSISTENT_MAX, chi^2_nu quantile (1 - FALSE_ALARM) / nu)."""
        nu = self.effective_dof
        return float(max(CONSISTENT_MAX, scipy.stats.chi2.ppf(1 - FALSE_ALARM, nu) / nu))

    @property
    def model_error_mm(self) -> float:
        """sqrt(max(0, mean|d|^2 - mean tr C_d) / 2), per half-calibration (module docstring)."""
        return float(np.sqrt(max(0.0, self.rms_difference_mm**2 - self.rms_predicted_mm**2) / 2))

    @property
    def verdict(self) -> str:
        return "consistent" if self.mean_z2_over_3 <= self.threshold else "model error"

    def to_dict(self) -> dict:
        return {"n_points": len(self.d), "rms_difference_mm": self.rms_difference_mm,
                "rms_predicted_mm": self.rms_predicted_mm, "ratio": self.ratio,
                "mean_z2_over_3": self.mean_z2_over_3, "effective_dof": self.effective_dof,
                "threshold": self.threshold, "model_error_mm": self.model_error_mm, "verdict": self.verdict}


@dataclass(frozen=True)
class CrossValidation:
    """Result of :func:`cross_validate`.

    Attributes
    ----------
    halves : (BundleResult, BundleResult)
        The two half-calibrations (``.rig``, ``.uncertainty.covariance``, ``.layout``;
        :meth:`sensor_covariances` gives their sensor covariances).
    measurements : (tuple of str, tuple of str)
        The measurements of each half.
    comparisons : dict
        scanner name -> {frame -> :class:`PointComparison`} for every frame of ``FRAMES``.
    """

    halves: tuple
    measurements: tuple
    comparisons: dict

    def sensor_covariances(self) -> tuple[np.ndarray, np.ndarray]:
        """Each half's covariance of all sensor parameters, (14 n_sensors, 14 n_sensors)."""
        return tuple(sensor_covariance(h.layout.sensor_index, h.uncertainty.covariance) for h in self.halves)

    def verdict(self, scanner: str) -> str:
        """``"model error"`` if a frame of ``VERDICT_FRAMES`` fails, else ``"consistent"``."""
        bad = any(self.comparisons[scanner][f].verdict != "consistent" for f in VERDICT_FRAMES)
        return "model error" if bad else "consistent"

    def model_error_mm(self, scanner: str) -> float:
        """The largest model-error figure of the scanner's ``VERDICT_FRAMES`` (mm, per half-calibration)."""
        return max(self.comparisons[scanner][f].model_error_mm for f in VERDICT_FRAMES)

    def parameter_differences(self) -> dict:
        """Sensor parameters free in both halves: (theta_1 - theta_2) / sqrt(u_1^2 + u_2^2).

        Returns a dict: ``max_normalised`` and its ``parameter`` (``sensor.param``),
        ``rms_normalised`` (1 expected if the halves agree within their uncertainty),
        ``n_parameters`` and the five ``largest`` (parameter, difference, u_combined,
        normalised).
        """
        h1, h2 = self.halves
        u1, u2 = (np.sqrt(np.clip(np.diag(c), 0, None)) for c in self.sensor_covariances())
        diff = (h1.rig.params - h2.rig.params).reshape(-1)
        u = np.sqrt(u1**2 + u2**2)
        ok = np.flatnonzero((h1.layout.sensor_index.reshape(-1) >= 0) & (h2.layout.sensor_index.reshape(-1) >= 0)
                            & (u > 0))
        names = [f"{s.name}.{p}" for s in h1.rig.sensors for p in PARAM_NAMES]
        z = diff[ok] / u[ok]
        order = np.argsort(-np.abs(z))
        largest = [{"parameter": names[ok[k]], "difference": float(diff[ok[k]]), "u_combined": float(u[ok[k]]),
                    "normalised": float(z[k])} for k in order[:5]]
        return {"max_normalised": float(abs(z[order[0]])), "parameter": names[ok[order[0]]],
                "rms_normalised": float(np.sqrt(np.mean(z**2))), "n_parameters": len(z), "largest": largest}

    def to_dict(self) -> dict:
        """JSON-ready summary: halves, per-scanner comparisons per frame, parameter differences."""
        halves = []
        for h, meas in zip(self.halves, self.measurements):
            halves.append({"measurements": list(meas), "n_points": h.after.n_points,
                           "rms_eps1_mm": h.after.rms_eps1_mm, "rms_eps2_mm": h.after.rms_eps2_mm,
                           "rms_f_mm": h.after.rms_f_mm, "iterations": h.iterations, "converged": h.converged,
                           "convergence": h.extra.get("convergence", {}).get("verdict")})
        scanners = {name: {"verdict": self.verdict(name), "model_error_mm": self.model_error_mm(name),
                           **{f: c.to_dict() for f, c in frames.items()}}
                    for name, frames in self.comparisons.items()}
        overall = "consistent" if all(s["verdict"] == "consistent" for s in scanners.values()) else "model error"
        return {"verdict": overall, "verdict_frames": list(VERDICT_FRAMES), "consistent_max": CONSISTENT_MAX,
                "false_alarm": FALSE_ALARM, "halves": halves, "scanners": scanners,
                "parameters": self.parameter_differences()}


def cross_validate(problem: BundleProblem, options: BundleOptions | None = None, n_points_per_scanner: int = 2000,
                   seed: int = 0, split: tuple | None = None) -> CrossValidation:
    """Calibrate two halves of ``problem``'s measurements and compare their points.

    Parameters
    ----------
    problem : BundleProblem
        The full calibration's problem with its solution (rig, poses) as start values
        (``result.problem.with_start(result.rig, result.poses)``): each half starts
        there (the halves are independent data; the start only needs to be in the basin,
        and starting there is fast).
    options : BundleOptions, optional
        The halves' adjustment; default ``BundleOptions(start="given")``.
    n_points_per_scanner : int
        Control points of each scanner sampled (without replacement, uniformly over the
        full problem) for the comparison; all if it has fewer.
    seed : int
        Seed of that sample (each point's draw is keyed by its coordinates,
        :mod:`fringecal.calibration.keyed`: the sample does not depend on the order).
    split : (sequence of str, sequence of str), optional
        The halves' measurements; default :func:`split_measurements` (alternating).

    Returns
    -------
    CrossValidation
    """
    if n_points_per_scanner < 10:
        raise ValueError(f"n_points_per_scanner must be at least 10 (a rigid alignment and per-point covariances "
                         f"need them), got {n_points_per_scanner}")
    halves = split_measurements(problem) if split is None else tuple(tuple(str(m) for m in h) for h in split)
    opts = BundleOptions(start="given") if options is None else options
    fits = tuple(bundle_adjust(subproblem(problem, h), opts) for h in halves)
    draw = keyed_uniform(row_keys(problem.cam_mm, problem.prj_mm), seed)  # per point, whatever its place
    index, scanner_of = [], []
    for si in range(len(problem.rig.scanners)):
        idx = np.flatnonzero(problem.scanner_idx == si)
        if len(idx) > n_points_per_scanner:
            idx = np.sort(idx[np.argsort(draw[idx], kind="stable")[:n_points_per_scanner]])
        index.append(idx)
        scanner_of.append(np.full(len(idx), si))
    index, scanner_of = np.concatenate(index), np.concatenate(scanner_of)
    (P1, J1, S1), (P2, J2, S2) = (_half_points(h, problem, index, scanner_of) for h in fits)
    own = [np.flatnonzero(scanner_of == si) for si in range(len(problem.rig.scanners))]
    ref = own[[sc.name for sc in problem.rig.scanners].index(problem.rig.reference)]
    groups = {"scanner": [(g, g) for g in own], "reference": [(ref, np.arange(len(index)))], "world": None}
    comparisons = {sc.name: {} for sc in problem.rig.scanners}
    for frame in FRAMES:
        d, R1, R2 = _in_frame(P1, P2, J1, J2, groups[frame])
        for sc, rows in zip(problem.rig.scanners, own):
            comparisons[sc.name][frame] = PointComparison.of(sc.name, frame, index[rows], d[rows], R1[rows], R2[rows],
                                                             S1, S2)
    return CrossValidation(fits, tuple(tuple(h) for h in halves), comparisons)
