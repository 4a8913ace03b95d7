"""Object-space bundle adjustment of any number of scanners (thesis sections 2.3.5-2.3.6, 6.5).

Minimises F = gamma1 sum alpha1^2 + gamma2 sum alpha2^2 (eq. 2-24; alpha1 the signed
closest-approach distance of camera and projector rays at a control point, alpha2 =
|S - S_t| - r with S the midpoint and S_t the CMM sphere centre moved by the pose of that
measurement, eq. 6-15) over the free parameters of every sensor and one pose per
measurement, shared by all scanners that saw it. See :mod:`.kernels` for the residuals
and derivatives, :mod:`.solver` for the Levenberg-Marquardt iteration and its
convergence criteria, :mod:`.uncertainty` for the covariances and :mod:`.diagnostics`
for degenerate set-ups.

Large problems (more than twice ``BundleOptions.coarse_points`` control points) are first
adjusted on every k-th control point of each sphere image (about ``coarse_points`` in
all); the adjustment on all points starts from there if that lowered F, and only has a
few iterations left to do. Each stage is a monotone LM run on its own F.

Start values: sphere residuals have separate minima, a few mm above the noise floor, into
which rough start values (a few mm and mrad) lead. Every minimum is tested for its noise
floor without the truth (:mod:`.convergence`); only a first descent that fails the test
makes :func:`bundle_adjust` adjust again from start values computed from the control
points (:mod:`.start`), and a result none of whose starts reached the floor carries the
verdict ``not_reached`` and the error diagnosis ``floor_not_reached``.

Optional robust loss (Huber or Cauchy, by iteratively reweighted least squares): F uses
rho(alpha) instead of alpha^2 with a scale per term; unless given, the scale is
``ROBUST_K`` times 1.4826 MAD of that term's residuals, re-estimated after each pass of
the adjustment (at most ``robust_passes``), and each pass is a monotone LM run with its
scale fixed.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Literal, Optional, Union

import numpy as np
import pandas as pd
from pydantic import Field, field_validator

from fringecal.calibration.convergence import SEPARATE_MINIMUM_RATIO, noise_floor_check, same_minimum
from fringecal.calibration.diagnostics import DegenerateCalibrationError, Diagnosis, check_rank, check_structure
from fringecal.calibration.increments import RotationIncrements
from fringecal.calibration.model import POSE_COLUMNS, BundleProblem, Evaluator, ParameterLayout
from fringecal.calibration.solver import LMOptions, LMReport, irls_weights, levenberg_marquardt
from fringecal.calibration.start import reinitialise
from fringecal.calibration.uncertainty import Uncertainty, estimate_uncertainty, score_meat
from fringecal.config import StrictModel
from fringecal.rig import Rig

__all__ = ["BundleOptions", "BundleResult", "ResidualStatistics", "StartValueError", "bundle_adjust",
           "SEPARATE_MINIMUM_RATIO"]

#: robust-loss scale in units of the residuals' robust standard deviation
ROBUST_K = {"huber": 1.345, "cauchy": 2.385}


class StartValueError(ValueError):
    """The start values cannot be evaluated (rays cannot be formed at some control points)."""


class BundleOptions(StrictModel):
    """Settings of the bundle adjustment: the ``bundle:`` section of a run configuration,
    passed as it is to :func:`bundle_adjust` (eq. 2-24; :mod:`.solver` for the tolerances).

    ``gamma1``, ``gamma2`` weight epsilon-1 and epsilon-2 (:class:`.model.BundleProblem`).
    ``robust_loss`` (``none``, ``huber``, ``cauchy``) with its ``robust_scale_mm``
    (one value or (alpha1, alpha2); None: from the residuals). ``start``: which start
    values to adjust from (:func:`bundle_adjust`). ``volume_diagonal_mm``: the
    measurement volume's diagonal for the one-part-in-N figures (None: the bounding box
    of the control points triangulated with the result). ``bootstrap_draws``:
    wild-bootstrap re-adjustments for the calibration's bias and spread
    (:mod:`.bootstrap`); 0: none, the lengths are then not corrected for the
    adjustment's non-linearity. ``jackknife``: re-adjust once without each measurement
    (:mod:`.jackknife`) for the lengths' model-error term; false: none, the lengths
    then carry no model error. ``coarse_points``: subsample size of the first stage of
    large problems (0: off); ``chunk_size``: control points per parallel work item.
    ``black_box_scale``: adjust a scale factor of every black-box scanner
    (:mod:`.blackbox`) besides its exterior.
    ``sensor_model``: the sensors' model (:mod:`.models`: ``brown14`` the thesis's 14
    parameters, ``thin_prism`` / ``thin_prism4`` with OpenCV's thin-prism terms, ``field``
    with a correction field over each image plane, ``auto`` chosen by held-out
    measurements; :func:`bundle_adjust` itself adjusts the terms the problem's rig frees,
    ``prism_free``, ``field_free``); ``model_selection``: ``screened`` cross-validates
    only when the 14-parameter residuals keep a pattern over the images, ``always`` every run.
    ``covariance``: ``sandwich`` (each point's own residuals, heteroscedasticity-consistent)
    or ``per-term`` (one variance factor per residual term; :mod:`.uncertainty`).
    """

    gamma1: float = Field(1.0, gt=0)
    gamma2: float = Field(1.0, gt=0)
    robust_loss: Literal["none", "huber", "cauchy"] = "none"
    robust_scale_mm: Optional[Union[float, tuple[float, float]]] = None
    robust_passes: int = Field(3, ge=1)
    max_iterations: int = Field(100, ge=1)  # per LM run
    ftol: float = Field(1e-10, gt=0)
    xtol: float = Field(1e-10, gt=0)
    gtol: float = Field(1e-10, gt=0)
    start: Literal["given", "data", "auto", "best"] = "auto"
    volume_diagonal_mm: Optional[float] = Field(None, gt=0)
    bootstrap_draws: int = Field(32, ge=0, le=1000)
    bootstrap_seed: int = 0
    jackknife: bool = True
    chunk_size: int = Field(2048, ge=1)
    coarse_points: int = Field(150_000, ge=0)
    black_box_scale: bool = False
    sensor_model: Literal["auto", "brown14", "thin_prism", "thin_prism4", "field"] = "auto"
    model_selection: Literal["screened", "always"] = "screened"
    covariance: Literal["sandwich", "per-term"] = "sandwich"

    @field_validator("robust_scale_mm")
    @classmethod
    def _positive_scale(cls, v):
        if v is not None and min(np.atleast_1d(v)) <= 0:
            raise ValueError(f"robust_scale_mm must be > 0 (mm), got {v}")
        return v


@dataclass(frozen=True)
class ResidualStatistics:
    """RMS values as the thesis reports them (section 6.9.2): the square root of the mean
    over control points of gamma1 alpha1^2 + gamma2 alpha2^2 (F), alpha1^2 (epsilon-1) and
    alpha2^2 (epsilon-2)."""

    n_points: int
    rms_f_mm: float
    rms_eps1_mm: float
    rms_eps2_mm: float

    @classmethod
    def of(cls, res: np.ndarray, gamma=(1.0, 1.0)) -> "ResidualStatistics":
        ms = np.mean(res**2, axis=0)
        return cls(len(res), float(np.sqrt(gamma[0] * ms[0] + gamma[1] * ms[1])),
                   float(np.sqrt(ms[0])), float(np.sqrt(ms[1])))

    def one_part_in(self, diagonal_mm: float, k: float = 1.96) -> float:
        """Volume diagonal / (k * RMS epsilon-2): the thesis's 'one part in N' (k = 1.96)."""
        return float(diagonal_mm / (k * self.rms_eps2_mm))

    def to_dict(self) -> dict:
        return {"n_points": self.n_points, "rms_f_mm": self.rms_f_mm, "rms_eps1_mm": self.rms_eps1_mm,
                "rms_eps2_mm": self.rms_eps2_mm}


@dataclass(frozen=True)
class BundleResult:
    """Everything an adjustment produced. Arrays of control points are in problem order
    (``problem.row`` maps them to rows of the input table)."""

    problem: BundleProblem
    options: BundleOptions
    layout: ParameterLayout
    x_start: np.ndarray
    x: np.ndarray
    rig: Rig
    poses: np.ndarray
    pose_std: np.ndarray
    residuals_start: np.ndarray
    residuals: np.ndarray
    before: ResidualStatistics
    after: ResidualStatistics
    uncertainty: Uncertainty
    report: LMReport
    robust_scales: tuple
    diagnostics: tuple
    elapsed_s: float
    extra: dict = field(default_factory=dict)

    @property
    def converged(self) -> bool:
        return self.report.converged

    @property
    def iterations(self) -> int:
        return self.report.iterations

    @property
    def floor_reached(self) -> bool:
        """Whether the verdict of :mod:`.convergence` is ``noise_floor``."""
        return bool(self.extra.get("convergence", {}).get("floor_reached", False))

    def sensors_frame(self) -> pd.DataFrame:
        """SensorParametersTable rows with ``u_<column>`` standard uncertainties (0 = fixed)."""
        return self.rig.to_frame()

    def poses_frame(self) -> pd.DataFrame:
        """T_world_artefact per measurement with ``u_<column>`` standard uncertainties."""
        df = self.problem.poses_frame(self.poses)
        for j, c in enumerate(POSE_COLUMNS):
            df[f"u_{c}"] = self.pose_std[:, j]
        return df

    def parameter_table(self) -> pd.DataFrame:
        """One row per free parameter: name, start, value, standard uncertainty."""
        return pd.DataFrame({"parameter": list(self.layout.names), "start": self.x_start, "value": self.x,
                             "u": self.uncertainty.std})

    def errors(self) -> list[Diagnosis]:
        return [d for d in self.diagnostics if d.severity == "error"]

    def warnings(self) -> list[Diagnosis]:
        return [d for d in self.diagnostics if d.severity == "warning"]


def _check_start(problem: BundleProblem, evaluation):
    if evaluation.ok.all() and np.isfinite(evaluation.cost):
        return
    bad = ~evaluation.ok
    parts = []
    for si, sc in enumerate(problem.rig.scanners):
        k = int(np.sum(bad & (problem.scanner_idx == si)))
        if k:
            parts.append(f"{k} of scanner {sc.name}")
    raise StartValueError("the start values cannot form rays at " + ", ".join(parts) + " control points "
                          "(distortion folds over, or camera and projector rays are parallel); check the "
                          "start parameters' distortion and the control points' phases")


def _robust_scales(res, loss):
    mad = np.median(np.abs(res - np.median(res, axis=0)), axis=0) * 1.4826
    return tuple(float(max(s, 1e-9) * ROBUST_K[loss]) for s in mad)


def _post_diagnostics(problem, layout, unc: Uncertainty, rig: Rig, found: list[Diagnosis]) -> list[Diagnosis]:
    """Attach numbers to structural warnings: c vs distance correlation, weakest parameters."""
    names = list(layout.names)
    index = {n: i for i, n in enumerate(names)}
    out = []
    for d in found:
        if d.kind == "single_standoff":
            corrs = []
            for si, sc in enumerate(problem.rig.scanners):
                if sc.name != d.subject:
                    continue
                for sensor in sc.sensors:
                    r = _c_distance_correlation(sensor, index, unc, rig)
                    if r is not None:
                        corrs.append(f"corr(c, distance) of {sensor.name} = {r:+.4f}")
            if corrs:
                d = Diagnosis(d.kind, d.severity, d.subject, d.message + " (" + "; ".join(corrs) + ")", d.parameters)
        elif d.kind == "single_pose":
            own = [i for i, n in enumerate(names) if n in d.parameters]
            worst = sorted(own, key=lambda i: -max(abs(unc.correlation[i, j]) for j in range(len(names)) if j != i))
            pairs = [p for p in unc.high_correlations(0.99) if p[0] in d.parameters or p[1] in d.parameters][:6]
            text = "; ".join(f"corr({a}, {b}) = {c:+.3f}" for a, b, c in pairs)
            if text:
                d = Diagnosis(d.kind, d.severity, d.subject, d.message + f" (strongest correlations: {text})",
                              tuple(names[i] for i in worst[:8]))
        out.append(d)
    return out


def _c_distance_correlation(sensor, index, unc: Uncertainty, rig: Rig):
    keys = [f"{sensor.name}.{n}" for n in ("x0", "y0", "z0", "c")]
    if not all(k in index for k in keys):
        return None
    idx = [index[k] for k in keys]
    C = unc.covariance[np.ix_(idx, idx)]
    axis = rig.sensors[[s.name for s in rig.sensors].index(sensor.name)].R[2]
    var_a = axis @ C[:3, :3] @ axis
    cov_ac = axis @ C[:3, 3]
    if var_a <= 0 or C[3, 3] <= 0:
        return None
    return float(cov_ac / np.sqrt(var_a * C[3, 3]))


#: the starts computed from the control points (label, :func:`.start.reinitialise` mode,
#: basis), tried in this order after the given start values; basis "given": from the
#: given start values, "lowest": from the lowest minimum found so far (its sensors give
#: better sphere-centre images)
DATA_STARTS = (("control points", "dlt", "given"),
               ("control points, resection", "resection", "given"),
               ("control points, from the lowest minimum", None, "lowest"))


def bundle_adjust(problem: BundleProblem, options: BundleOptions = BundleOptions()) -> BundleResult:
    """Adjust sensors and poses of ``problem``; raises :class:`DegenerateCalibrationError`
    for degenerate set-ups and :class:`StartValueError` for unusable start values.

    Every adjustment is tested for its noise floor without the truth
    (:func:`.convergence.noise_floor_check`: epsilon-1 and epsilon-2 against the noise
    left by free fits within each sphere image). ``options.start``:

    * ``"auto"`` (default): from the given start values; only if that minimum does not
      reach the noise floor, from the starts of ``DATA_STARTS`` in turn
      (:func:`.start.reinitialise`: sphere-centre images from each scanner's own
      triangulation, poses by resection in the reference camera, the other sensors by
      the DLT, then by resection, then both again from the lowest minimum so far),
      stopping at the first that reaches it. A first descent that reaches the floor (the
      usual case from DLT start values) costs only the test;
    * ``"given"``: the given start values only; ``"data"``: the data starts only;
      ``"best"``: every start.

    The result is the lowest minimum of F among the starts that reached the floor, else
    among all. ``extra["start"]`` names its start, ``extra["convergence"]`` holds the
    verdict (``noise_floor``, ``lowest_minimum``, ``unconfirmed`` or ``not_reached``;
    :mod:`.convergence`) with every start's figures; ``not_reached`` adds the error
    diagnosis ``floor_not_reached``. ``before`` always describes the given start values.
    """
    t0 = time.perf_counter()
    found = check_structure(problem)
    if any(d.severity == "error" for d in found):
        raise DegenerateCalibrationError(found)
    if options.start not in ("given", "data", "auto", "best"):
        raise ValueError(f"unknown start {options.start!r}; choose given, data, auto or best")
    runs: list[tuple[str, BundleResult]] = []
    failed: dict = {}
    errors: dict = {}

    def attempt(label, prob, must=False):
        t = time.perf_counter()
        try:
            r = _adjust(prob, options, found)
        except (DegenerateCalibrationError, StartValueError) as err:
            if must:
                raise
            failed[label] = str(err)
            errors[label] = err
            return None
        check = noise_floor_check(problem, r.rig, r.residuals, r.uncertainty.dof)
        r.extra.update(floor=check, shape_ratio=check.shape_ratio, seconds=time.perf_counter() - t)
        runs.append((label, r))
        return r

    def lowest(candidates):
        # a later start wins only if clearly lower (not by rounding at the same minimum)
        lab, best = candidates[0]
        for lb, r in candidates[1:]:
            if r.extra["cost"] < best.extra["cost"] * (1 - 1e-9):
                lab, best = lb, r
        return lab, best

    if options.start != "data":
        # from the given start values only: their failure is the answer; otherwise the
        # data starts may still succeed (a start so rough that the rays fold over or the
        # normal matrix is singular there), and the error is raised if none does
        attempt("given", problem, must=options.start == "given")
    if options.start != "given":
        modes = {}
        for label, mode, basis in DATA_STARTS:
            if options.start in ("auto", "data") and _settled(runs, lowest):
                break
            if basis == "lowest":
                if not runs:
                    break
                base_label, base = lowest(runs)
                base_prob = problem.with_start(base.rig, base.poses)
                # the mode whose start came lower, DLT if neither ran
                ran = [(r.extra["cost"], modes[lb]) for lb, r in runs if lb in modes]
                mode = min(ran)[1] if ran else "dlt"
                label = f"{label} ({base_label}, {'DLT' if mode == 'dlt' else mode})"
            else:
                base_prob = problem
            try:
                prob, _ = reinitialise(base_prob, mode)
            except (ValueError, ArithmeticError) as err:  # DLTError, UndistortError, LinAlgError
                failed[label] = str(err)
                continue
            if attempt(label, prob):
                modes[label] = mode
        if not runs:
            if "given" in errors:
                raise errors["given"]
            raise StartValueError("no start computed from the control points could be adjusted: "
                                  + "; ".join(f"{k}: {v}" for k, v in failed.items()))
    reached = [(lb, r) for lb, r in runs if r.extra["floor"].reached]
    label, best = lowest(reached or runs)
    conv = _verdict(label, best, runs, bool(reached), failed)
    best.extra["start"] = label
    best.extra["convergence"] = conv
    best.extra["alternatives"] = {lab: {"rms_f_mm": r.after.rms_f_mm, "iterations": r.iterations,
                                        "shape_ratio": r.extra["shape_ratio"],
                                        "ratio_eps1": r.extra["floor"].ratio_eps1,
                                        "ratio_eps2": r.extra["floor"].ratio_eps2} for lab, r in runs}
    if failed:
        best.extra["failed_starts"] = dict(failed)
    if label != "given":
        ev = Evaluator(problem, chunk_size=options.chunk_size)
        res0 = ev.evaluate(ev.layout.pack_rig(problem.rig, problem.poses), False).res
        best = _replace_start(best, problem, res0)
    diags = list(best.diagnostics) + _convergence_diagnoses(conv, best)
    from dataclasses import replace as _dc_replace

    return _dc_replace(best, diagnostics=tuple(diags), elapsed_s=time.perf_counter() - t0)


def _settled(runs: list, lowest) -> bool:
    """Whether further starts are pointless: one reached the noise floor, or two ended in
    the same lowest minimum without a separate minimum's ratio (the verdict is then
    ``lowest_minimum`` whatever a third start does)."""
    if any(r.extra["floor"].reached for _, r in runs):
        return True
    if len(runs) < 2:
        return False
    _, best = lowest(runs)
    return best.extra["floor"].ratio <= SEPARATE_MINIMUM_RATIO and any(
        r is not best and same_minimum(r, best) for _, r in runs)


def _verdict(label: str, best: BundleResult, runs: list, reached: bool, failed: dict) -> dict:
    """The convergence verdict of the chosen minimum (:mod:`.convergence`)."""
    check = best.extra["floor"]
    agree = [lb for lb, r in runs if r is not best and same_minimum(r, best)]
    if reached:
        verdict = "noise_floor"
    elif check.ratio <= SEPARATE_MINIMUM_RATIO and agree:
        verdict = "lowest_minimum"
    elif check.ratio <= SEPARATE_MINIMUM_RATIO and len(runs) == 1 and not failed:
        verdict = "unconfirmed"
    else:
        verdict = "not_reached"
    starts = []
    for lb, r in runs:
        f = r.extra["floor"]
        starts.append({"start": lb, "rms_f_mm": r.after.rms_f_mm, "rms_eps1_mm": r.after.rms_eps1_mm,
                       "rms_eps2_mm": r.after.rms_eps2_mm, "ratio_eps1": f.ratio_eps1, "ratio_eps2": f.ratio_eps2,
                       "floor_reached": f.reached, "failing_scanners": f.failing_scanners,
                       "iterations": r.iterations, "seconds": r.extra.get("seconds"),
                       "same_minimum_as_result": r is best or lb in agree})
    return {"verdict": verdict, "floor_reached": verdict == "noise_floor", "start": label,
            "check": check.to_dict(), "starts": starts, "agreeing_starts": agree, "failed_starts": dict(failed)}


def _convergence_diagnoses(conv: dict, best: BundleResult) -> list[Diagnosis]:
    check = best.extra["floor"]
    ratios = (f"epsilon-1 and epsilon-2 are {check.ratio_eps1:.2f} and {check.ratio_eps2:.2f} times the "
              "per-point noise estimated within each sphere image (noise floor: 1.00, limit "
              f"{check.limit:.3f})")
    failing = check.failing_scanners
    where = f"; scanners above their limit: {', '.join(failing)}" if failing else ""
    tried = "; ".join(f"{s['start']}: F RMS {1000 * s['rms_f_mm']:.1f} um, ratios {s['ratio_eps1']:.2f}/"
                      f"{s['ratio_eps2']:.2f}" for s in conv["starts"])
    out = []
    if conv["verdict"] == "not_reached":
        out.append(Diagnosis(
            "floor_not_reached", "error", "all",
            f"no start reached the noise floor ({len(conv['starts'])} tried: {tried}"
            + (f"; failed: {', '.join(conv['failed_starts'])}" if conv["failed_starts"] else "")
            + f"). In the lowest minimum found, {ratios}{where}. This result is not a calibration: "
            "give start values closer to the truth (each scanner's own calibration, the poses), check "
            "that the artefact table and the sphere labels belong to these measurements, or add "
            "measurements that spread the spheres through the depth of the volume"))
    elif conv["verdict"] in ("lowest_minimum", "unconfirmed"):
        why = (f"{len(conv['agreeing_starts']) + 1} starts ended in this same minimum, so it is not a separate "
               "one: the data hold errors the model does not absorb (artefact, lens beyond the 14 "
               "parameters, sphere labels)" if conv["verdict"] == "lowest_minimum" else
               "only one start was tried (start='given'); start='auto' tries others")
        out.append(Diagnosis("above_noise_floor", "warning", "all", f"{ratios}{where}: {why}"))
    if not check.ratio_eps2 <= SEPARATE_MINIMUM_RATIO:
        out.append(Diagnosis("separate_minimum", "warning", "all",
                             f"epsilon-2 is {check.ratio_eps2:.1f} times the RMS distance to spheres fitted freely "
                             "to each sphere image: the measured caps have the right shape but do not sit on the "
                             "spheres the adjusted poses put there. The adjustment has probably stopped in a "
                             "separate minimum (try other start values), or the artefact definition does not "
                             "fit the spheres measured"))
    return out


def _replace_start(result: "BundleResult", problem: BundleProblem, res0: np.ndarray) -> "BundleResult":
    from dataclasses import replace as _dc_replace

    layout = result.layout
    return _dc_replace(result, x_start=layout.pack_rig(problem.rig, problem.poses),
                       residuals_start=res0,
                       before=ResidualStatistics.of(res0, (problem.gamma1, problem.gamma2)))


def minimise(ev: Evaluator, x0: np.ndarray, e0, options: BundleOptions, coarse: bool = True,
             replica: bool = False) -> tuple[LMReport, tuple, Optional[dict]]:
    """Minimise F of ``ev``'s problem from ``x0`` (``e0``: ``ev.evaluate(x0, True)``) as
    ``options`` say: Levenberg-Marquardt with every rotation stepped as a small rotation
    (:mod:`.increments`), after a first stage on a subsample of a large problem
    (``coarse``), and with a robust loss in passes of fixed scale. ``replica``: a
    bootstrap replica, which stops as soon as the next step promises less than ``ftol``
    (:class:`.solver.LMOptions` ``stop_on_promise``).

    Returns the solver's report (its ``x`` the minimum, its ``evaluation`` there with
    the normal equations of the last pass's loss), the robust scales ((1, 1) without a
    robust loss) and the coarse stage's figures (None without one).
    """
    problem, layout = ev.problem, ev.layout
    gamma = (problem.gamma1, problem.gamma2)
    lm = LMOptions(options.max_iterations, options.ftol, options.xtol, options.gtol, stop_on_promise=replica)
    rotations = RotationIncrements.of(layout)  # steps of every free rotation as a small rotation
    scales = (1.0, 1.0)
    x = x0
    stage = None
    e0_lm = e0
    if coarse and options.coarse_points and problem.n_points > 2 * options.coarse_points:
        # converge on a uniform subsample of every sphere image first; the adjustment on
        # all points then only has the last few iterations to do
        every = int(np.ceil(problem.n_points / options.coarse_points))
        first = levenberg_marquardt(Evaluator(problem.thinned(every), layout, options.chunk_size).evaluate,
                                    x, gamma, LMOptions(options.max_iterations, max(options.ftol, 1e-8),
                                                        options.xtol, options.gtol), increments=rotations)
        e_c = ev.evaluate(first.x, True)
        if e_c.cost < e0.cost:
            x, e0_lm = first.x, e_c
        stage = {"every": every, "iterations": first.iterations, "evaluations": first.evaluations,
                 "message": first.message}
    if options.robust_loss in ("none", "linear"):
        return levenberg_marquardt(ev.evaluate, x, gamma, lm, start=e0_lm, increments=rotations), scales, stage
    if options.robust_loss not in ROBUST_K:
        raise ValueError(f"unknown robust loss {options.robust_loss!r}; choose none, huber or cauchy")
    fixed = options.robust_scale_mm
    res = e0.res
    total_it = total_ev = total_jac = 0
    history = []
    for _ in range(max(1, options.robust_passes)):
        new = (fixed, fixed) if np.isscalar(fixed) else (tuple(fixed) if fixed else _robust_scales(res, options.robust_loss))
        if scales != (1.0, 1.0) and all(abs(a - b) <= 0.05 * b for a, b in zip(new, scales)):
            break
        scales = new
        report = levenberg_marquardt(ev.robust(options.robust_loss, scales).evaluate, x, gamma, lm,
                                     increments=rotations)
        x = report.x
        total_it += report.iterations
        total_ev += report.evaluations
        total_jac += report.jacobians
        history += report.history
        res = ev.evaluate(x, False).res
        if fixed is not None:
            break
    report = LMReport(x, report.cost, total_it, total_ev, total_jac, report.converged, report.message, history,
                      report.evaluation)
    return report, scales, stage


def _adjust(problem: BundleProblem, options: BundleOptions, found: list) -> BundleResult:
    """One Levenberg-Marquardt adjustment from the problem's start values."""
    t0 = time.perf_counter()
    gamma = (problem.gamma1, problem.gamma2)
    ev = Evaluator(problem, chunk_size=options.chunk_size)
    layout = ev.layout
    x0 = layout.pack_rig(problem.rig, problem.poses)
    e0 = ev.evaluate(x0, True)
    _check_start(problem, e0)
    rank = check_rank(e0.normal(*gamma), layout, problem, "start values")
    if any(d.severity == "error" for d in rank):
        raise DegenerateCalibrationError(found + rank)
    report, scales, coarse = minimise(ev, x0, e0, options)
    x = report.x
    e1 = report.evaluation  # at x, with the (robust) normal equations
    plain = ev.evaluate(x, False) if options.robust_loss not in ("none", "linear") else e1
    weights = irls_weights(plain.res, options.robust_loss, scales)
    meat = None
    if options.covariance == "sandwich":
        _, J, ok = ev.jacobian_rows(x)
        start, stop, _, _ = problem.groups()
        meat = score_meat(J, ev.global_columns(), plain.res, weights * ok[:, None], gamma, layout.n, start, stop)
        del J
    unc = estimate_uncertainty(e1.N1, e1.N2, plain.res, weights, gamma, layout.names, meat,
                               layout.field_slots(problem.field_prior_weight))
    sp, po = layout.unpack(x, problem.rig.params, problem.poses)
    std_s = np.zeros_like(sp)
    m = layout.sensor_index >= 0
    std_s[m] = unc.std[layout.sensor_index[m]]
    std_p = np.zeros_like(po)
    m = layout.pose_index >= 0
    std_p[m] = unc.std[layout.pose_index[m]]
    prism = ev.prism(x)
    fields = ev.fields(x) if problem.rig.has_field else None
    rig = problem.rig.with_params(sp, uncertainty=std_s, prism=prism, fields=fields)
    std_prism = np.zeros_like(prism)
    m = layout.prism_index >= 0
    std_prism[m] = unc.std[layout.prism_index[m]]
    from dataclasses import replace as _dc_replace

    if layout.prism_free:
        rig = _dc_replace(rig, prism_uncertainty=std_prism)
    if layout.field_free:
        std_field = np.zeros(layout.field_index.shape)
        m = layout.field_index >= 0
        std_field[m] = unc.std[layout.field_index[m]]
        rig = _dc_replace(rig, field_uncertainty=std_field)
    rank_end = check_rank(e1.normal(*gamma), layout, problem, "solution", unc)
    diags = _post_diagnostics(problem, layout, unc, rig, found) + rank_end
    return BundleResult(problem, options, layout, x0, x, rig, po, std_p, e0.res, plain.res,
                        ResidualStatistics.of(e0.res, gamma), ResidualStatistics.of(plain.res, gamma), unc,
                        report, scales, tuple(diags), time.perf_counter() - t0,
                        {"cost": float(gamma[0] * np.sum(plain.res[:, 0] ** 2) + gamma[1] * np.sum(plain.res[:, 1] ** 2)),
                         "coarse": coarse, "prism_std": std_prism})
