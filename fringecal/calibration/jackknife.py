"""Delete-one-measurement jackknife of the calibration, against the same jackknife of
worlds that hold only the noise the adjustment's covariance assumes.

Each replica is the calibration re-adjusted without one measurement (one artefact pose:
its control points and its pose), from the calibration's solution. For a quantity
``q`` derived from the sensors (a ball-bar length), the replicas' values ``q_(i)`` give
the jackknife variance (Quenouille, Tukey; Efron & Stein 1981;
:func:`fringecal.verification.budget.jackknife_variance`)

    var_J(q) = (n - 1) / n * sum_i (q_(i) - mean q_(.))^2,

which holds everything that differs between the measurements: the observation noise the
adjustment's covariance states, and also what that covariance cannot see because it
takes every control point's error as independent -- a smooth phase error of one
measurement moves all its points together; a scanner drifts between measurements.

The jackknife overstates, though, where the measurements are few and unequal: leaving
out a pose that alone shows part of the volume costs more than 1/n of the information,
and ``(n - 1) / n`` does not know it. On the simulated thesis rig with 8 poses at 320 px,
ideal profile (noise only), var_J was about twice the linear calibration term's
variance on average over 150 ball-bar lengths, and the coverage of U rose from 0.967
to 0.980 when the plain excess was added (``benchmarks/length_coverage.py``, commit
b3fd933). So the calibration is also jackknifed in
``noise_draws`` worlds that hold the noise alone: the projector observations replaced
by those the calibrated model predicts plus each control point's own residual times a
random sign (the wild bootstrap's replicas, :mod:`.bootstrap`, with signs of their own),
each such world jackknifed over the same measurements. Their mean variance
``var_J,noise`` is what the jackknife shows when the covariance holds everything, with
the same geometry and the same over-statement. The model error of ``q`` is then

    u_model(q) = u_linear(q) * sqrt(max(0, var_J(q) / var_J,noise(q) - 1)),

``u_linear`` its linear calibration term: zero where the measurements scatter as the
noise makes them, and the excess, at the linear term's scale, where they scatter more
(:func:`fringecal.verification.budget.jackknife_model_error`). An unmodelled error that
differs between measurements is over-stated by the jackknife as the noise is; the ratio
removes both alike.

Why not the halves of :mod:`.crossval` for that figure: a half-calibration has half the
poses, and its error along a weak direction grows faster than its stated u when
something unmodelled pushes it there. On the simulated thesis rig (realistic profile,
320 px, 8 poses: halves of 4) one seed in 16 had half-calibrations 4-7 mm apart on the
ball-bar (37 times their predicted u) while the full calibration erred by 0.15-0.26 mm;
the halves' excess put 4.3 mm into every length's budget. A replica keeps all poses but
one, so its geometry is nearly the calibration's. Errors common to every measurement (an
artefact that differs from its table, a lens term outside the model) move every replica
alike; neither the jackknife nor the halves can see them.

A measurement whose removal leaves a problem that cannot be calibrated (a scanner left
without the views it needs) gets no replica, in the noise worlds neither; the record
names it, and the variances are taken over the replicas there are (``MIN_REPLICAS`` at
least: the bundle step stores fewer as none).
"""

from __future__ import annotations

import logging
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace

import numpy as np

from fringecal.calibration.bootstrap import predicted_projector_mm
from fringecal.calibration.bundle import BundleOptions, BundleResult, StartValueError, minimise
from fringecal.calibration.crossval import subproblem
from fringecal.calibration.diagnostics import DegenerateCalibrationError, check_rank, check_structure
from fringecal.calibration.model import BundleProblem, Evaluator, ParameterLayout
from fringecal.calibration.keyed import keyed_signs, row_keys
from fringecal.threads import numba_threads

__all__ = ["MIN_REPLICAS", "NOISE_DRAWS", "Jackknife", "jackknife_calibrations", "adjust_each", "leave_one_out",
           "noise_worlds", "readjusted", "readjusted_solution"]

log = logging.getLogger(__name__)

#: fewest replicas a jackknife variance is taken from
MIN_REPLICAS = 3
#: noise-only worlds jackknifed for the baseline (its variance's relative scatter is
#: about sqrt(2 / (NOISE_DRAWS (n - 1))): 0.27 with 8 measurements)
NOISE_DRAWS = 4
#: first sign stream of the noise worlds (the bootstrap's replicas use 0, 1, ...)
_NOISE_STREAM = 1_000_000


@dataclass(frozen=True)
class Jackknife:
    """The replicas of a delete-one-measurement jackknife and of its noise-only baseline.

    left_out : the measurement each replica leaves out, (n,)
    params : (n, n_sensors, 14) each replica's sensor parameters, rig order
    noise_params : (draws, n, n_sensors, 14) the same replicas in each noise-only world
    skipped : measurement -> why it has no replica
    seconds : wall time of all replicas
    """

    left_out: tuple[str, ...]
    params: np.ndarray = field(repr=False)
    noise_params: np.ndarray = field(repr=False)
    skipped: dict
    seconds: float

    @property
    def usable(self) -> bool:
        return len(self.left_out) >= MIN_REPLICAS and len(self.noise_params) > 0

    def to_dict(self) -> dict:
        return {"replicas": len(self.left_out), "left_out": list(self.left_out), "skipped": dict(self.skipped),
                "noise_draws": int(len(self.noise_params)), "min_replicas": MIN_REPLICAS}


def noise_worlds(result: BundleResult, draws: int, seed: int = 0, mirrored: bool = False) -> list[BundleProblem]:
    """``result``'s problem, from its solution, with the projector observations of
    ``draws`` noise-only worlds: the calibrated model's prediction plus each control
    point's residual times a sign keyed by the point's coordinates (points whose ray
    misses their sphere keep their observation). ``mirrored``: each world followed by
    its mirror, every sign reversed (2 ``draws`` worlds; the mean of a pair's estimates
    holds no term linear in the noise)."""
    problem = result.problem.with_start(result.rig, result.poses)
    predicted = predicted_projector_mm(result)
    ok = np.isfinite(predicted).all(axis=1)[:, None]
    residual = problem.prj_mm - predicted
    keys = row_keys(problem.cam_mm, problem.prj_mm)
    signs = [keyed_signs(keys, seed, _NOISE_STREAM + d)[:, None] for d in range(draws)]
    if mirrored:
        signs = [s for v in signs for s in (v, -v)]
    return [replace(problem, prj_mm=np.where(ok, predicted + s * residual, problem.prj_mm)) for s in signs]


def readjusted(problem: BundleProblem, options: BundleOptions) -> np.ndarray:
    """Sensor parameters (n_sensors, 14) of ``problem`` adjusted from its start values
    (:func:`readjusted_solution`)."""
    layout, x = readjusted_solution(problem, options)
    return layout.sensor_rows(x, problem.rig, problem.poses)


def readjusted_solution(problem: BundleProblem, options: BundleOptions) -> tuple[ParameterLayout, np.ndarray]:
    """The layout and unknowns x of ``problem`` adjusted from its start values: the
    adjustment's own minimisation (:func:`.bundle.minimise`, stopping as a bootstrap
    replica does), after the checks that refuse a degenerate problem (its structure, the
    rank at the start), without what a replica does not need (the noise-floor test, the
    uncertainty, the diagnoses at the solution)."""
    found = check_structure(problem)
    if any(d.severity == "error" for d in found):
        raise DegenerateCalibrationError(found)
    ev = Evaluator(problem, chunk_size=options.chunk_size)
    x0 = ev.layout.pack_rig(problem.rig, problem.poses)
    e0 = ev.evaluate(x0, True)
    if not (e0.ok.all() and np.isfinite(e0.cost)):
        raise StartValueError(f"the start values cannot form rays at {int(np.sum(~e0.ok))} control points")
    rank = check_rank(e0.normal(problem.gamma1, problem.gamma2), ev.layout, problem, "start values")
    if any(d.severity == "error" for d in rank):
        raise DegenerateCalibrationError(found + rank)
    report, _, _ = minimise(ev, x0, e0, options, coarse=False, replica=True)
    return ev.layout, report.x


def adjust_each(makers: list, options: BundleOptions, adjust, workers: int = 1) -> list[tuple]:
    """``adjust(make(), options)`` for each problem maker of ``makers``, in their order:
    ``(value, None)``, or ``(None, why)`` where the problem cannot be calibrated
    (degenerate, or no start values); ``workers`` adjustments at once, each on one numba
    thread."""

    def one(make):
        try:
            return adjust(make(), options), None
        except DegenerateCalibrationError as err:
            return None, "degenerate: " + "; ".join(d.message for d in err.diagnoses if d.severity == "error")
        except StartValueError as err:
            return None, f"start values: {err}"

    def on_one_thread(make):  # each adjustment's kernels on one thread: the adjustments run in parallel
        with numba_threads(1):
            return one(make)

    if workers <= 1:
        return [one(m) for m in makers]
    with ThreadPoolExecutor(max_workers=workers) as pool:
        return list(pool.map(on_one_thread, makers))


def leave_one_out(problems: list[BundleProblem], names: list[str], options: BundleOptions, adjust,
                  workers: int = 1) -> list[tuple]:
    """``adjust(subproblem, options)`` of every problem without each measurement of
    ``names`` in turn, in the order (problem, measurement) (:func:`adjust_each`)."""
    makers = [lambda k=k, m=m: subproblem(problems[k], [x for x in names if x != m])
              for k in range(len(problems)) for m in names]
    return adjust_each(makers, options, adjust, workers)


def jackknife_calibrations(result: BundleResult, noise_draws: int = NOISE_DRAWS, seed: int = 0,
                           workers: int = 1) -> Jackknife:
    """Re-adjust ``result``'s problem once without each of its measurements, and the same
    in ``noise_draws`` noise-only worlds (:func:`noise_worlds`), with the result's options
    from its solution (:func:`readjusted`); ``workers`` adjustments at once, each on one
    numba thread."""
    options = result.options.model_copy(update={"start": "given"})
    problems = [result.problem.with_start(result.rig, result.poses)]
    problems += noise_worlds(result, noise_draws, seed)
    names = [str(m) for m in result.problem.measurements]
    t0 = time.perf_counter()
    done = leave_one_out(problems, names, options, readjusted, workers)
    tasks = [(k, m) for k in range(len(problems)) for m in names]
    params = [[done[k * len(names) + j][0] for j in range(len(names))] for k in range(len(problems))]
    why = {m: w for (k, m), (_, w) in zip(tasks, done) if k == 0 and w is not None}
    keep = [j for j, m in enumerate(names) if m not in why]
    complete = [k for k in range(1, len(problems)) if all(params[k][j] is not None for j in keep)]
    for m, w in why.items():
        log.info("jackknife: no replica without measurement %s (%s)", m, w)
    shape = (result.rig.params.shape[0], result.rig.params.shape[1] + result.layout.n_field_terms)

    def stack(k):
        return np.stack([params[k][j] for j in keep]) if keep else np.empty((0,) + shape)

    noise = np.stack([stack(k) for k in complete]) if complete else np.empty((0, len(keep)) + shape)
    return Jackknife(tuple(names[j] for j in keep), stack(0), noise, why, round(time.perf_counter() - t0, 3))
