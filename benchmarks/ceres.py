"""fringecal's bundle adjustment against Ceres on the same residuals.

    PYTHONPATH=. python benchmarks/ceres.py [--cases thesis,ring4,ring6] [--repeats 3]
        [--run-dir NAME=RUN_DIR ...] [--out FILE]

Needs pyceres (``pip install -e ".[bench]"``). The problems are those of
``benchmarks/_cases.py`` (simulated control points, DLT start values) and, with
``--run-dir NAME=RUN_DIR``, the bundle step's inputs of a run directory (its control
points and the ``initialise`` step's start values: e.g. ``fringecal run -c
run_ring6 --until initialise --out runs/ring6``). Ceres
(pyceres: Levenberg-Marquardt, sparse normal Cholesky, Jacobi scaling, one thread)
minimises exactly fringecal's residuals: one cost block per (scanner, measurement)
group, whose residuals (alpha1, alpha2 of every control point) and analytic Jacobian
come from fringecal's own compiled kernel (``kernels.residual_rows``), with three
parameter blocks (camera 14, projector 14, pose 6; fixed parameters held by a subset
manifold, a wholly fixed sensor constant). Both stop at the same tolerances (function,
parameter and gradient 1e-10); the final costs are compared (F = 2 x Ceres's cost).

Per case: iterations (steps tried: fringecal's LM trial points, Ceres's successful
plus unsuccessful steps) and Jacobian evaluations of both; fringecal with its angle
triples stepped as rotations (the adjustment) and, for reference, as Euler angles
(the solver before issue 32); wall time medians of ``--repeats`` (fringecal's whole
``bundle_adjust``, uncertainty and diagnoses included, and its minimisation alone;
Ceres's ``solve``); the relative difference of the final costs.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _cases import bundle_problem  # noqa: E402
from _common import add_options, conditions, finish  # noqa: E402


def _group_cost(ev, start: int, stop: int, chunk: int = 2048):
    """A pyceres cost function for control points start:stop (one scanner, one measurement)."""
    import pyceres

    from fringecal.calibration import kernels
    from fringecal.rotation import rotation_derivatives, rotation_matrix

    pr, a = ev.problem, ev._arrays
    n = stop - start
    edges = np.arange(0, n, chunk, dtype=np.int64)
    c_start, c_stop = edges, np.minimum(edges + chunk, n).astype(np.int64)
    c_group = np.zeros(len(edges), np.int64)
    one = np.zeros(1, np.int64)
    sphere_idx = np.ascontiguousarray(pr.sphere_idx[start:stop])
    cam, prj = np.ascontiguousarray(pr.cam_mm[start:stop]), np.ascontiguousarray(pr.prj_mm[start:stop])
    no_prism, no_field = np.zeros((2, 4)), np.zeros((stop - start, 0, 2))
    res, ok, J = np.empty((n, 2)), np.empty(n, np.bool_), np.empty((n, 2, kernels.N_LOCAL))
    w = np.sqrt([pr.gamma1, pr.gamma2])

    class GroupCost(pyceres.CostFunction):
        def __init__(self):
            pyceres.CostFunction.__init__(self)
            self.set_num_residuals(2 * n)
            self.set_parameter_block_sizes([14, 14, 6])

        def Evaluate(self, parameters, residuals, jacobians):  # noqa: N802 (pyceres's name)
            cam_p, prj_p, pose = (np.asarray(p, float) for p in parameters)
            sp = np.stack([cam_p, prj_p])
            sR = rotation_matrix(sp[:, 3], sp[:, 4], sp[:, 5])
            sdR = np.ascontiguousarray(np.moveaxis(rotation_derivatives(sp[:, 3], sp[:, 4], sp[:, 5]), 0, 1))
            pR = rotation_matrix(pose[3:4], pose[4:5], pose[5:6])
            pdR = np.ascontiguousarray(np.moveaxis(rotation_derivatives(pose[3:4], pose[4:5], pose[5:6]), 0, 1))
            kernels.residual_rows(c_start, c_stop, c_group, one, one + 1, one, sp, no_prism, sR, sdR,
                                  np.ascontiguousarray(pose[None, :3]), pR, pdR, sphere_idx, a["centres"],
                                  a["radii"], cam, prj, no_field, no_field, res, ok, J)
            if not ok.all():
                return False
            residuals[:] = (res * w).ravel()
            if jacobians is not None:
                rows = (J * w[None, :, None]).reshape(2 * n, kernels.N_LOCAL)
                for block, (lo, hi) in enumerate(((0, 14), (14, 28), (28, 34))):
                    if jacobians[block] is not None:
                        jacobians[block][:] = rows[:, lo:hi].ravel()
            return True

    return GroupCost()


def ceres_solve(problem, max_iterations: int = 200, tol: float = 1e-10) -> dict:
    """Adjust ``problem`` with Ceres; its figures and the final F."""
    import pyceres

    from fringecal.calibration.model import Evaluator

    ev = Evaluator(problem)
    rig = problem.rig
    sensors = [np.array(p, float) for p in rig.params]
    poses = [np.array(p, float) for p in problem.poses]
    cp = pyceres.Problem()
    costs = []
    start, stop, g_scan, g_meas = problem.groups()
    for a, b, s, m in zip(start, stop, g_scan, g_meas):
        costs.append(_group_cost(ev, int(a), int(b)))
        cp.add_residual_block(costs[-1], None, [sensors[2 * s], sensors[2 * s + 1], poses[m]])
    for k, block in enumerate(sensors):
        fixed = np.flatnonzero(~rig.free[k])
        if len(fixed) == 14:
            cp.set_parameter_block_constant(block)
        elif len(fixed):
            cp.set_manifold(block, pyceres.SubsetManifold(14, fixed.tolist()))
    options = pyceres.SolverOptions()
    options.linear_solver_type = pyceres.LinearSolverType.SPARSE_NORMAL_CHOLESKY
    options.trust_region_strategy_type = pyceres.TrustRegionStrategyType.LEVENBERG_MARQUARDT
    options.function_tolerance = options.parameter_tolerance = options.gradient_tolerance = tol
    options.max_num_iterations = max_iterations
    options.num_threads = 1
    options.minimizer_progress_to_stdout = False
    summary = pyceres.SolverSummary()
    t0 = time.perf_counter()
    pyceres.solve(options, cp, summary)
    wall = time.perf_counter() - t0
    x = ev.layout.pack(np.stack(sensors), np.stack(poses))
    F = ev.evaluate(x, False).cost
    return {"wall_s": wall, "iterations": summary.num_successful_steps + summary.num_unsuccessful_steps,
            "jacobian_evaluations": summary.num_jacobian_evaluations, "termination": str(summary.termination_type),
            "message": summary.message, "cost_F": float(F), "ceres_final_cost_x2": 2.0 * summary.final_cost,
            "linear_solver": str(options.linear_solver_type)}


def run_problem(case: str, smoke: bool):
    """The case's problem: simulated (``_cases.py``), or NAME=RUN_DIR's bundle inputs."""
    if "=" not in case:
        problem, _, seconds = bundle_problem(case, smoke)
        return problem, seconds
    from fringecal.run.config import RunConfig
    from fringecal.rundir import RunDir
    from fringecal.steps.bundle import load_problem

    rd = RunDir(case.split("=", 1)[1])
    cfg = RunConfig.model_validate(rd.read_manifest()["config"])
    return load_problem(rd, cfg.reference_scanner, cfg.bundle.gamma1, cfg.bundle.gamma2), 0.0


def run_case(case: str, repeats: int, smoke: bool) -> dict:
    from fringecal.calibration.bundle import BundleOptions, bundle_adjust, minimise
    from fringecal.calibration.model import Evaluator
    from fringecal.calibration.solver import LMOptions, levenberg_marquardt

    problem, t_sim = run_problem(case, smoke)
    opts = BundleOptions(start="given")
    bundle_adjust(problem, opts)  # kernels loaded (or compiled) before anything is timed
    whole, solve, euler = [], [], []
    for _ in range(repeats):
        t = time.perf_counter()
        result = bundle_adjust(problem, opts)
        whole.append(time.perf_counter() - t)
        ev = Evaluator(problem)
        x0 = ev.layout.pack(problem.rig.params, problem.poses)
        t = time.perf_counter()
        rep, _, _ = minimise(ev, x0, ev.evaluate(x0, True), opts)
        solve.append(time.perf_counter() - t)
        t = time.perf_counter()
        eul = levenberg_marquardt(ev.evaluate, x0, (problem.gamma1, problem.gamma2), LMOptions())
        euler.append(time.perf_counter() - t)
    ceres = [ceres_solve(problem) for _ in range(repeats)]
    F = result.extra["cost"]
    out = {"case": case.split("=")[0], "n_control_points": problem.n_points, "n_free_parameters": result.layout.n,
           "simulation_s": round(t_sim, 2),
           "fringecal": {"iterations": rep.iterations, "jacobian_evaluations": rep.jacobians,
                         "message": rep.message, "cost_F": F,
                         "bundle_adjust_median_s": statistics.median(whole),
                         "minimisation_median_s": statistics.median(solve)},
           "fringecal_euler_steps": {"iterations": eul.iterations, "jacobian_evaluations": eul.jacobians,
                                     "message": eul.message, "cost_F": float(eul.cost),
                                     "median_s": statistics.median(euler)},
           "ceres": {**ceres[-1], "wall_median_s": statistics.median(c["wall_s"] for c in ceres)}}
    out["relative_cost_difference_ceres_minus_fringecal"] = (ceres[-1]["cost_F"] - F) / F
    out["ceres_wall_over_fringecal_bundle_adjust"] = out["ceres"]["wall_median_s"] / out["fringecal"]["bundle_adjust_median_s"]
    out["ceres_wall_over_fringecal_minimisation"] = out["ceres"]["wall_median_s"] / out["fringecal"]["minimisation_median_s"]
    out["iterations_at_most_ceres"] = rep.iterations <= out["ceres"]["iterations"]
    return out


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", default="thesis,ring4,ring6")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--run-dir", action="append", default=[], metavar="NAME=RUN_DIR",
                    help="also the bundle inputs of this run directory (repeatable)")
    args = add_options(ap).parse_args(argv)
    doc = conditions("ceres", argv, args.smoke)
    try:
        import pyceres  # noqa: F401
    except ImportError:
        doc["skipped"] = "pyceres is not installed: pip install -e \".[bench]\""
        return finish(doc, args.out)
    cases = ["thesis", "ring4"] if args.smoke else [c for c in args.cases.split(",") if c] + args.run_dir
    doc["threads"] = {"ceres": 1, "fringecal": "one numba thread below 50,000 control points, else all"}
    doc["cases"] = [run_case(c, 1 if args.smoke else args.repeats, args.smoke) for c in cases]
    return finish(doc, args.out)


if __name__ == "__main__":
    main()
