"""Results of a bundle adjustment: residual tables, histograms, summary and files.

RMS values follow the thesis (section 6.9.2): the square root of the mean over control
points. The "one part in N" figure is the combined measurement volume's diagonal divided
by 1.96 times the RMS of epsilon-2 (95 % confidence); the diagonal is the one passed in
(e.g. the thesis's 2.5 x 1 x 1 m^3 volume) or, if none is, the diagonal of the
axis-aligned bounding box of all control points triangulated with the adjusted
parameters (a lower bound of the volume actually calibrated).
"""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from schemas import MeasurementResidualsTable, SphereResidualsTable, validate_table

from ..atomic import atomic_paths
from ..calibration_file import rig_to_dict, xml_text
from ..triangulation import closest_approach
from .bundle import BundleResult
from .model import BundleProblem

__all__ = ["triangulated_points", "residual_tables", "volume_diagonal_mm", "plot_histograms", "summary", "write_outputs"]

def _frame(result: BundleResult) -> pd.DataFrame:
    pr = result.problem
    return pd.DataFrame({
        "measurement": np.asarray(pr.measurements, dtype=object)[pr.meas_idx],
        "scanner": np.asarray([s.name for s in pr.rig.scanners], dtype=object)[pr.scanner_idx],
        "sphere_id": np.asarray(pr.artefact.ids, dtype=object)[pr.sphere_idx],
        "e1": result.residuals[:, 0], "e2": result.residuals[:, 1],
        "s1": result.residuals_start[:, 0], "s2": result.residuals_start[:, 1],
    })


def _rms(x):
    return float(np.sqrt(np.mean(np.square(x))))


def residual_tables(result: BundleResult) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Per sphere image (SphereResidualsTable) and per measurement (MeasurementResidualsTable)."""
    df = _frame(result)
    per_sphere = df.groupby(["measurement", "scanner", "sphere_id"], sort=False).agg(
        n_points=("e1", "size"), rms_eps1_mm=("e1", _rms), rms_eps2_mm=("e2", _rms),
        mean_eps2_mm=("e2", "mean"), max_abs_eps2_mm=("e2", lambda x: float(np.max(np.abs(x)))),
        rms_eps1_start_mm=("s1", _rms), rms_eps2_start_mm=("s2", _rms)).reset_index()
    per_meas = df.groupby("measurement", sort=False).agg(
        scanners=("scanner", lambda x: ";".join(sorted(set(x)))), n_points=("e1", "size"),
        n_spheres=("sphere_id", "nunique"), rms_eps1_mm=("e1", _rms), rms_eps2_mm=("e2", _rms),
        mean_eps2_mm=("e2", "mean"), rms_eps1_start_mm=("s1", _rms), rms_eps2_start_mm=("s2", _rms)).reset_index()
    return (validate_table(per_sphere, SphereResidualsTable, "residuals per sphere"),
            validate_table(per_meas, MeasurementResidualsTable, "residuals per measurement"))


def triangulated_points(problem: BundleProblem, rig=None) -> np.ndarray:
    """Midpoints of closest approach (n, 3) of every control point with ``rig``'s sensors."""
    rig = problem.rig if rig is None else rig
    S = np.full((problem.n_points, 3), np.nan)
    for si, sc in enumerate(rig.scanners):
        sel = problem.scanner_idx == si
        if sel.any():
            o1, d1 = sc.camera.rays(problem.cam_mm[sel])
            o2, d2 = sc.projector.rays(problem.prj_mm[sel])
            S[sel], _ = closest_approach(o1, d1, o2, d2)
    return S


def volume_diagonal_mm(result: BundleResult) -> float:
    """Diagonal of the bounding box of the control points triangulated with the result."""
    S = triangulated_points(result.problem, result.rig)
    S = S[np.all(np.isfinite(S), axis=1)]
    return float(np.linalg.norm(S.max(axis=0) - S.min(axis=0)))


def plot_histograms(result: BundleResult, eps1_png, eps2_png, bins: int = 100) -> None:
    """Histograms of epsilon-1 and epsilon-2 at the start and after (figures 6-10, 6-11)."""
    for k, (path, label) in enumerate(((eps1_png, "epsilon-1"), (eps2_png, "epsilon-2"))):
        fig = Figure(figsize=(9, 3.6), dpi=110)
        FigureCanvasAgg(fig)
        for j, (res, title) in enumerate(((result.residuals_start[:, k], "(a) start values"),
                                          (result.residuals[:, k], "(b) refined parameters"))):
            ax = fig.add_subplot(1, 2, j + 1)
            ax.hist(res[np.isfinite(res)], bins=bins, color="tab:blue" if j else "tab:gray")
            ax.set_title(f"{title}: RMS {1000 * _rms(res[np.isfinite(res)]):.1f} um", fontsize=9)
            ax.set_xlabel(f"{label} (mm)")
            ax.set_ylabel("control points")
        fig.suptitle(f"{label} over {len(res)} control points, {bins} bins", fontsize=10)
        fig.tight_layout()
        fig.savefig(path, format="png")


def _json_safe(obj):
    """``obj`` with non-finite floats as None (strict JSON has no Infinity or NaN)."""
    if isinstance(obj, dict):
        return {k: _json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_json_safe(v) for v in obj]
    if isinstance(obj, (float, np.floating)):
        return float(obj) if np.isfinite(obj) else None
    return obj


def summary(result: BundleResult, diagonal_mm: float | None = None) -> dict:
    """A JSON-ready account of the adjustment (``bundle_summary.json``; docs/calibration.md)."""
    pr = result.problem
    unc = result.uncertainty
    source = "given"
    if diagonal_mm is None:
        diagonal_mm, source = volume_diagonal_mm(result), "bounding box of the triangulated control points"
    lay = result.layout
    classical = np.sqrt(np.clip(np.diag(unc.covariance_classical), 0, None))
    return {
        "n_control_points": pr.n_points,
        "n_measurements": len(pr.measurements),
        "scanners": [s.name for s in pr.rig.scanners],
        "reference_scanner": pr.rig.reference,
        "gamma": [pr.gamma1, pr.gamma2],
        "robust_loss": result.options.loss,
        "robust_scales_mm": list(result.robust_scales) if result.options.loss not in ("none", "linear") else None,
        "start": result.extra.get("start", "given"),
        "starts_tried": result.extra.get("alternatives", {}),
        "before": result.before.to_dict(),
        "after": result.after.to_dict(),
        "volume_diagonal_mm": diagonal_mm,
        "volume_diagonal_source": source,
        "one_part_in_1p96_sigma": result.after.one_part_in(diagonal_mm),
        "iterations": result.report.iterations,
        "evaluations": result.report.evaluations,
        "converged": result.report.converged,
        "message": result.report.message,
        "elapsed_s": result.elapsed_s,
        "n_free_parameters": lay.n,
        "degrees_of_freedom": {"alpha1": unc.dof[0], "alpha2": unc.dof[1], "total": unc.dof_total},
        "sigma_mm": {"alpha1": unc.sigma[0], "alpha2": unc.sigma[1], "sigma0": unc.sigma0},
        "condition_number": unc.condition,
        "weak_directions": [w.describe() for w in unc.weak],
        "high_correlations": [{"a": a, "b": b, "r": r} for a, b, r in unc.high_correlations(0.99)[:50]],
        "shape_ratio": _json_safe(result.extra.get("shape_ratio")),
        "floor_reached": result.floor_reached if "convergence" in result.extra else None,
        "convergence": _json_safe(result.extra.get("convergence")),
        "diagnostics": [d.to_dict() for d in result.diagnostics],
        "dropped_measurements": [{"measurement": m, "reason": r} for m, r in pr.dropped],
        "parameters": [{"name": n, "start": float(s), "value": float(v), "u": float(u), "u_classical": float(c)}
                       for n, s, v, u, c in zip(lay.names, result.x_start, result.x, unc.std, classical)],
        "correlation": {"names": list(lay.names), "matrix": np.round(unc.correlation, 5).tolist()},
    }


def covariance_arrays(result: BundleResult) -> dict:
    """What uncertainty propagation needs of an adjustment (``calibration_covariance.npz``):

    ``names`` (p,) of the adjusted vector (sensors, then poses); ``covariance`` (p, p);
    ``sensor_index`` (n_sensors, 14) position of each sensor parameter in it (-1 fixed);
    ``sensor_names``; the artefact's ``sphere_ids``; ``artefact_sensitivity`` (p, 4
    n_spheres) and ``artefact_u`` (4 n_spheres,) and ``scale_sensitivity`` (p,) of
    :func:`fringecal.calibration.artefact_sensitivity.artefact_sensitivity`.
    """
    from .artefact_sensitivity import artefact_sensitivity

    sens = artefact_sensitivity(result)
    return {"names": np.array(result.layout.names, dtype=str), "covariance": result.uncertainty.covariance,
            "sensor_index": result.layout.sensor_index, "sensor_names": np.array(result.layout.sensor_names, dtype=str),
            "sphere_ids": np.array(result.problem.artefact.ids, dtype=str), "artefact_sensitivity": sens.S,
            "artefact_u": sens.u_artefact, "scale_sensitivity": sens.scale}


def write_outputs(result: BundleResult, rd, diagonal_mm: float | None = None, extra: dict | None = None,
                  covariances=None, provenance: dict | None = None, bootstrap: np.ndarray | None = None) -> list:
    """Write the calibration files, tables, histograms and summary of ``result`` into the
    run directory ``rd`` (:class:`fringecal.rundir.RunDir`), all or nothing.

    Every file is first written under a temporary name; only when all are complete
    are they renamed into place. ``extra`` is merged into the summary (e.g. the
    adjustment's wall time). ``covariances(arrays)``, given the covariance arrays,
    returns the :class:`~fringecal.length_uncertainty.ParameterCovariances` that
    ``calibration.json`` carries with ``provenance``
    (:mod:`fringecal.calibration_file`). ``bootstrap`` (draws, n_sensors, 14), the
    sensor parameters of :func:`fringecal.calibration.bootstrap.bootstrap_calibrations`,
    goes into the covariance arrays as ``bootstrap_params``. Returns the files written.
    """
    import io

    doc = {**summary(result, diagonal_mm), **(extra or {})}
    meta = {"after": doc["after"], "before": doc["before"], "one_part_in_1p96_sigma": doc["one_part_in_1p96_sigma"],
            "volume_diagonal_mm": doc["volume_diagonal_mm"], "n_control_points": doc["n_control_points"],
            "iterations": doc["iterations"], "converged": doc["converged"]}
    per_sphere, per_meas = residual_tables(result)
    tables = {rd.sensors_calibrated: result.sensors_frame(), rd.poses_calibrated: result.poses_frame(),
              rd.residuals_per_sphere: per_sphere, rd.residuals_per_measurement: per_meas}
    tables = {f: validate_table(df, f.schema, str(f.path)) for f, df in tables.items()}
    figures = {}
    for term, path in zip(("eps1", "eps2"), (io.BytesIO(), io.BytesIO())):
        figures[rd.histogram(term)] = path
    plot_histograms(result, *figures.values())
    cov_arrays = covariance_arrays(result)
    if bootstrap is not None and len(bootstrap):
        cov_arrays["bootstrap_params"] = np.asarray(bootstrap, float)
    arrays = io.BytesIO()
    np.savez(arrays, **cov_arrays)
    cov = covariances(cov_arrays) if covariances is not None else None
    files = [rd.calibration, rd.calibration.xml, *tables, *figures, rd.bundle_summary, rd.covariance]
    with atomic_paths([f.path for f in files]) as tmps:
        tmp = dict(zip([f.rel for f in files], tmps))
        tmp[rd.calibration.rel].write_text(json.dumps(rig_to_dict(result.rig, meta, cov, provenance), indent=2) + "\n")
        tmp[rd.calibration.xml.rel].write_text(xml_text(result.rig, meta))
        for f, df in tables.items():
            df.to_csv(tmp[f.rel], index=False, float_format="%.10g")
        for f, buf in figures.items():
            tmp[f.rel].write_bytes(buf.getvalue())
        tmp[rd.bundle_summary.rel].write_text(json.dumps(doc, indent=1, default=float) + "\n", encoding="utf-8")
        tmp[rd.covariance.rel].write_bytes(arrays.getvalue())
    return files
