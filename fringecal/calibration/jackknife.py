"""Delete-one-measurement jackknife of the calibration: how much a result moves between
the measurements it was calibrated from.

Each replica is the calibration re-adjusted without one measurement (one artefact pose:
its control points and its pose), from the calibration's solution. For a quantity
``q`` derived from the sensors (a ball-bar length), the replicas' values ``q_(i)`` give
the jackknife variance (Quenouille, Tukey; Efron & Stein 1981;
:func:`fringecal.verification.budget.jackknife_variance`)

    var_J(q) = (n - 1) / n * sum_i (q_(i) - mean q_(.))^2,

which holds everything that differs between the measurements: the observation noise the
adjustment's covariance states, and also what the covariance cannot see because it
takes every control point's error as independent -- a smooth phase error of one
measurement moves all its points together; the scanner drifts between measurements --
and the adjustment's non-linearity along weak directions. Its excess over the linear
term, ``sqrt(max(0, var_J - u_linear^2))``, is the verification's ``model error
(cross-validation)`` of a length (:mod:`fringecal.verification.uncertainty`).

Why not the halves of :mod:`.crossval` for that figure: a half-calibration has half the
poses, and its error along a weak direction grows faster than its stated u when
something unmodelled pushes it there. On the simulated thesis rig (realistic profile,
320 px, 8 poses: halves of 4) one seed in 16 had half-calibrations 4-7 mm apart on the
ball-bar (37 times their predicted u) while the full calibration erred by 0.15-0.26 mm;
the halves' excess then put 4.3 mm into every length's budget. A replica keeps all but
one pose, so its geometry is nearly the calibration's: in that seed the jackknife gives
34-160 um per length. Errors common to every measurement (an artefact that differs
from its table, a lens term outside the model) move every replica alike; neither the
jackknife nor the halves can see them.

Measured on kept coverage runs (`benchmarks/length_coverage.py --keep`, 320 px, 8 poses)
and the default runs (512 px, 12 poses), jackknife spread / linear calibration term of
the ball-bar lengths: ideal profile about 1 (0.6-1.3 at 512 px; up to 2.5 at 320 px
where the bootstrap finds the adjustment non-linear), realistic profile 1.1-3.8 at 320 px
and 2-13 at 512 px (the smooth phase error of each measurement).

A measurement whose removal leaves a problem that cannot be calibrated (a scanner left
without the views it needs) gets no replica; the record names it, and the variance is
taken over the replicas there are (``MIN_REPLICAS`` at least: the bundle step stores
fewer as none).
"""

from __future__ import annotations

import logging
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np

from fringecal.calibration.bundle import BundleOptions, StartValueError, bundle_adjust
from fringecal.calibration.crossval import subproblem
from fringecal.calibration.diagnostics import DegenerateCalibrationError
from fringecal.calibration.model import BundleProblem
from fringecal.threads import numba_threads

__all__ = ["MIN_REPLICAS", "Jackknife", "jackknife_calibrations"]

log = logging.getLogger(__name__)

#: fewest replicas a jackknife variance is taken from
MIN_REPLICAS = 3


@dataclass(frozen=True)
class Jackknife:
    """The replicas of a delete-one-measurement jackknife.

    left_out : the measurement each replica leaves out, (n,)
    params : (n, n_sensors, 14) each replica's sensor parameters, rig order
    skipped : measurement -> why it has no replica
    seconds : wall time of all replicas
    """

    left_out: tuple[str, ...]
    params: np.ndarray = field(repr=False)
    skipped: dict
    seconds: float

    @property
    def usable(self) -> bool:
        return len(self.left_out) >= MIN_REPLICAS

    def to_dict(self) -> dict:
        return {"replicas": len(self.left_out), "left_out": list(self.left_out), "skipped": dict(self.skipped),
                "min_replicas": MIN_REPLICAS}


def jackknife_calibrations(problem: BundleProblem, options: BundleOptions, workers: int = 1) -> Jackknife:
    """Re-adjust ``problem`` once without each of its measurements.

    ``problem`` carries the calibration's solution as start values
    (``problem.with_start(rig, poses)``); ``options`` as the calibration's, with
    ``start="given"``. ``workers`` replicas run at once, each on one numba thread.
    """
    names = [str(m) for m in problem.measurements]
    t0 = time.perf_counter()

    def replica(m: str):
        try:
            fit = bundle_adjust(subproblem(problem, [x for x in names if x != m]), options)
        except (DegenerateCalibrationError, StartValueError) as err:
            return m, None, f"{type(err).__name__}: {str(err).splitlines()[0]}"
        return m, fit.rig.params, None

    def on_one_thread(m: str):  # each replica's kernels on one thread: the replicas run in parallel
        with numba_threads(1):
            return replica(m)

    if workers <= 1:
        results = [replica(m) for m in names]
    else:
        with ThreadPoolExecutor(max_workers=workers) as pool:
            results = list(pool.map(on_one_thread, names))
    kept = [(m, p) for m, p, _ in results if p is not None]
    skipped = {m: why for m, _, why in results if why is not None}
    for m, why in skipped.items():
        log.info("jackknife: no replica without measurement %s (%s)", m, why)
    shape = (0,) + problem.rig.params.shape
    params = np.stack([p for _, p in kept]) if kept else np.empty(shape)
    return Jackknife(tuple(m for m, _ in kept), params, skipped, round(time.perf_counter() - t0, 3))
