"""Bundle-adjustment benchmark: fringecal's solver against scipy.optimize.least_squares.

Prints (and with ``--out`` writes) one JSON document. Cases (``benchmarks/_cases.py``;
each in its own process, so its peak memory is its own):

* ``thesis``: the thesis-scale problem: table 6-8 rig (2 scanners = 4 sensors), the 12
  poses of table 6-1, control points every 10 px with a 75 degree rim limit (13,564
  points; the thesis had 13,604), from the DLT start of fringecal.simulate.control_points.
* ``ring4``: four copies of the thesis scanners on a ring, 50 random poses, every 10 px
  (two projectors near gimbal lock: the case that needs rotations stepped as rotations).
* ``ring6``: the six-scanner ring of ``configs/run_ring6.yaml``, the 12 thesis poses.
* ``large``: 8 scanners on a ring (copies of the thesis scanners), 50 random artefact
  poses, control points every 5 px: about 10^6 control points, from the DLT start.

For each: fringecal's median wall time over ``--repeat`` runs (start="given": one
Levenberg-Marquardt adjustment; the default start="auto", which would also adjust from
start values computed from the control points if the first minimum looked like a
separate one, timed once), iterations, evaluations, and the same
problem solved by scipy.optimize.least_squares (trf, exact dense Jacobian for the thesis
case; for the others a sparse Jacobian with lsmr and a wall-time cap, ``--scipy-cap``,
after which the best cost reached is reported). Numba compilation is excluded (a warm-up
run first) and reported separately. Memory: the process's peak RSS after fringecal's runs
(simulated tables included), the peak of numpy allocations during one adjustment
(tracemalloc), and the peak RSS after scipy. ``--smoke``: the thesis and ring4 cases
thinned (``_cases.py``), in this process, one repeat, scipy capped at 0.3 s.

Usage: PYTHONPATH=. python benchmarks/bundle.py [--cases thesis,ring4,ring6,large] [--repeat 5] [--out FILE]
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import resource
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _cases import bundle_problem  # noqa: E402
from _common import add_options, conditions, finish  # noqa: E402


def _problem(case: str, smoke: bool = False):
    return bundle_problem(case, smoke)


def _rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


class _TimeUp(Exception):
    pass


def _scipy(problem, cap_s: float, sparse: bool) -> dict:
    import scipy.optimize
    import scipy.sparse

    from fringecal.calibration.model import Evaluator

    ev = Evaluator(problem)
    cols = ev.global_columns()
    p = ev.layout.n
    x0 = ev.layout.pack(problem.rig.params, problem.poses)
    n = problem.n_points
    t0 = time.perf_counter()
    best = {"cost": np.inf, "nfev": 0, "njev": 0}
    mask2 = np.broadcast_to((cols >= 0)[:, None, :], (n, 2, cols.shape[1]))
    indices = np.broadcast_to(cols[:, None, :], mask2.shape)[mask2].astype(np.int32)
    indptr = np.concatenate([[0], np.cumsum(np.repeat((cols >= 0).sum(axis=1), 2))]).astype(np.int64)

    def check():
        if time.perf_counter() - t0 > cap_s:
            raise _TimeUp

    def fun(x):
        check()
        r = ev.evaluate(x, False).res.ravel()
        best["nfev"] += 1
        c = float(r @ r)
        if c < best["cost"]:
            best["cost"], best["x"] = c, x.copy()
        return np.where(np.isfinite(r), r, 1e3)

    def jac(x):
        check()
        best["njev"] += 1
        _, J, _ = ev.jacobian_rows(x)
        if sparse:  # rows alpha1_0, alpha2_0, alpha1_1, ... with each point's free local slots
            return scipy.sparse.csr_matrix((J[mask2], indices, indptr), shape=(2 * n, p))
        Jd = np.zeros((2 * n, p))
        for s in range(cols.shape[1]):
            m = cols[:, s] >= 0
            k = np.flatnonzero(m)
            Jd[2 * k, cols[m, s]] += J[m, 0, s]
            Jd[2 * k + 1, cols[m, s]] += J[m, 1, s]
        return Jd

    status = "converged"
    try:
        sol = scipy.optimize.least_squares(fun, x0, jac=jac, method="trf", x_scale="jac",
                                           tr_solver="lsmr" if sparse else "exact",
                                           ftol=1e-10, xtol=1e-10, gtol=1e-10, max_nfev=200)
        status = sol.message
    except _TimeUp:
        status = f"stopped by the {cap_s:.0f} s cap"
    elapsed = time.perf_counter() - t0
    res = ev.evaluate(best["x"], False).res
    return {"wall_s": elapsed, "status": status, "nfev": best["nfev"], "njev": best["njev"],
            "rms_f_mm": float(np.sqrt(best["cost"] / n)), "rms_eps1_mm": float(np.sqrt(np.mean(res[:, 0] ** 2))),
            "rms_eps2_mm": float(np.sqrt(np.mean(res[:, 1] ** 2)))}


def run_case(case: str, repeat: int, cap_s: float, with_scipy: bool, smoke: bool = False) -> dict:
    import numba

    from fringecal.calibration.bundle import BundleOptions, ResidualStatistics, bundle_adjust
    from fringecal.calibration.model import Evaluator

    t0 = time.perf_counter()
    from fringecal.calibration import kernels  # noqa: F401  (load compiled kernels)

    problem, truth_problem, t_sim = _problem(case, smoke)
    out = {"case": case, "n_control_points": problem.n_points, "n_scanners": len(problem.rig.scanners),
           "n_sensors": len(problem.rig.sensors), "n_measurements": len(problem.measurements),
           "simulation_s": t_sim, "numba_threads": numba.get_num_threads()}
    ev = Evaluator(truth_problem)
    tres = ev.evaluate(ev.layout.pack(truth_problem.rig.params, truth_problem.poses), False).res
    out["truth"] = ResidualStatistics.of(tres).to_dict()
    tw = time.perf_counter()
    first = bundle_adjust(problem, BundleOptions(start="given"))
    out["first_run_s_including_compile_or_cache_load"] = time.perf_counter() - tw
    out["n_free_parameters"] = first.layout.n
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        r = bundle_adjust(problem, BundleOptions(start="given"))
        times.append(time.perf_counter() - t)
    lm_s = r.report  # iterations etc. of the last run
    out["fringecal"] = {"median_s": float(np.median(times)), "all_s": times, "iterations": lm_s.iterations,
                        "evaluations": lm_s.evaluations, "jacobians": lm_s.jacobians, "converged": lm_s.converged,
                        "message": lm_s.message, "coarse_stage": r.extra.get("coarse"),
                        "before": r.before.to_dict(), "after": r.after.to_dict()}
    t = time.perf_counter()
    rb = bundle_adjust(problem)  # the default start="auto"
    out["fringecal_default_start_auto"] = {"s": time.perf_counter() - t, "start": rb.extra["start"],
                                           "alternatives": rb.extra["alternatives"], "after": rb.after.to_dict()}
    out["fringecal_peak_rss_mb"] = _rss_mb()  # process high-water mark, simulated data included
    import tracemalloc

    tracemalloc.start()
    bundle_adjust(problem, BundleOptions(start="given"))
    out["fringecal_adjustment_peak_traced_mb"] = tracemalloc.get_traced_memory()[1] / 2**20
    tracemalloc.stop()
    if with_scipy:
        out["scipy"] = _scipy(problem, cap_s, sparse=(case not in ("thesis",)))
        out["scipy"]["cap_s"] = cap_s
        out["ratio_scipy_over_fringecal"] = out["scipy"]["wall_s"] / out["fringecal"]["median_s"]
    out["peak_rss_mb"] = _rss_mb()
    out["case_wall_s"] = time.perf_counter() - t0
    return out


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", default="thesis,ring4,ring6,large")
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--scipy-cap", type=float, default=120.0)
    ap.add_argument("--no-scipy", action="store_true")
    a = add_options(ap).parse_args(argv)
    doc = conditions("bundle", argv, a.smoke)
    doc["cases"] = []
    if a.smoke:  # in this process: no spawned interpreter, seconds in all
        for case in ("thesis", "ring4"):
            doc["cases"].append(run_case(case, 1, 0.3, not a.no_scipy, smoke=True))
        return finish(doc, a.out)
    ctx = mp.get_context("spawn")
    for case in a.cases.split(","):
        with ctx.Pool(1) as pool:
            doc["cases"].append(pool.apply(run_case, (case, a.repeat, a.scipy_cap, not a.no_scipy)))
    return finish(doc, a.out)


if __name__ == "__main__":
    main()
