"""Results of a bundle adjustment: residual tables, the summary and the covariance arrays.

RMS values follow the thesis (section 6.9.2): the square root of the mean over control
points. The "one part in N" figure is the combined measurement volume's diagonal divided
by 1.96 times the RMS of epsilon-2 (95 % confidence); the diagonal is the one passed in
(e.g. the thesis's 2.5 x 1 x 1 m^3 volume) or, if none is, the diagonal of the
axis-aligned bounding box of all control points triangulated with the adjusted
parameters (a lower bound of the volume actually calibrated).
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from fringecal.calibration.artefact_sensitivity import artefact_sensitivity
from fringecal.calibration.bundle import BundleResult
from fringecal.calibration.model import BundleProblem, triangulated_points
from fringecal.lens.observed_region import ObservedRegion
from fringecal.schemas import BinnedResidualsTable, MeasurementResidualsTable, SphereResidualsTable, validate_table

__all__ = ["residual_tables", "binned_residuals", "IMAGE_BINS", "volume_diagonal_mm", "summary", "covariance_arrays",
           "observed_regions"]

#: Bins across each sensor's image width for :func:`binned_residuals` (its height gets
#: as many as keep the bins square: 16 x 16 on a square camera, 16 x 12 on a 4:3 projector).
IMAGE_BINS = 16

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


def binned_residuals(result: BundleResult, nx: int = IMAGE_BINS) -> pd.DataFrame:
    """The residuals after the adjustment binned over each sensor's image
    (:class:`~fringecal.schemas.BinnedResidualsTable`): every control point falls in one
    bin of its camera's pixel grid (its pixel) and one of its projector's (its phases,
    as projector pixels); each bin holding points gives their count and the mean and
    RMS of epsilon-1 and epsilon-2. What a residual map and a coverage map of the
    camera and projector images need, without the points themselves."""
    pr = result.problem
    res = np.asarray(result.residuals, float)
    rows = []
    for k, scanner in enumerate(pr.rig.scanners):
        mine = pr.scanner_idx == k
        for sensor, image_mm in ((scanner.camera, pr.cam_mm[mine]), (scanner.projector, pr.prj_mm[mine])):
            fmt = sensor.format
            ny = max(1, int(round(nx * fmt.height_px / fmt.width_px)))
            uv = fmt.mm_to_pixel(image_mm)
            ix = np.clip(np.floor((uv[:, 0] + 0.5) / fmt.width_px * nx), 0, nx - 1).astype(int)
            iy = np.clip(np.floor((uv[:, 1] + 0.5) / fmt.height_px * ny), 0, ny - 1).astype(int)
            cell = iy * nx + ix
            e = res[mine]
            n = np.bincount(cell, minlength=nx * ny)
            sums = [np.bincount(cell, w, minlength=nx * ny) for w in (e[:, 0], e[:, 0] ** 2, e[:, 1], e[:, 1] ** 2)]
            for c in np.flatnonzero(n):
                j, i = divmod(int(c), nx)
                rows.append({"scanner": scanner.name, "sensor": sensor.name, "role": sensor.role, "nx": nx, "ny": ny,
                             "ix": i, "iy": j, "u_px": (i + 0.5) * fmt.width_px / nx - 0.5,
                             "v_px": (j + 0.5) * fmt.height_px / ny - 0.5, "n_points": int(n[c]),
                             "mean_eps1_mm": sums[0][c] / n[c], "rms_eps1_mm": float(np.sqrt(sums[1][c] / n[c])),
                             "mean_eps2_mm": sums[2][c] / n[c], "rms_eps2_mm": float(np.sqrt(sums[3][c] / n[c]))})
    columns = list(BinnedResidualsTable.to_schema().columns)
    return validate_table(pd.DataFrame(rows, columns=columns), BinnedResidualsTable, "residuals binned over the images")


def observed_regions(problem: BundleProblem) -> dict[str, ObservedRegion]:
    """Sensor name -> where its control points of ``problem`` lay on its image plane
    (:class:`~fringecal.lens.observed_region.ObservedRegion`): every camera's pixels
    and every projector's phases of the points the adjustment used, as measured
    image-plane mm (``cam_mm``, ``prj_mm``). A scanner without control points gets an
    empty region (nothing observed)."""
    out = {}
    for k, scanner in enumerate(problem.rig.scanners):
        mine = problem.scanner_idx == k
        for sensor, image_mm in ((scanner.camera, problem.cam_mm[mine]), (scanner.projector, problem.prj_mm[mine])):
            out[sensor.name] = ObservedRegion.from_observations(image_mm, sensor.format.width_mm,
                                                                sensor.format.height_mm)
    return out


def volume_diagonal_mm(result: BundleResult) -> float:
    """Diagonal of the bounding box of the control points triangulated with the result."""
    S = triangulated_points(result.problem, result.rig)
    S = S[np.all(np.isfinite(S), axis=1)]
    return float(np.linalg.norm(S.max(axis=0) - S.min(axis=0)))


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
        "robust_loss": result.options.robust_loss,
        "robust_scales_mm": list(result.robust_scales) if result.options.robust_loss not in ("none", "linear") else None,
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
    :func:`fringecal.calibration.artefact_sensitivity.artefact_sensitivity`;
    ``field_index`` (n_sensors, K) position of each correction-field coefficient (K = 0
    without a free field).
    """

    sens = artefact_sensitivity(result)
    return {"names": np.array(result.layout.names, dtype=str), "covariance": result.uncertainty.covariance,
            "sensor_index": result.layout.sensor_index, "sensor_names": np.array(result.layout.sensor_names, dtype=str),
            "sphere_ids": np.array(result.problem.artefact.ids, dtype=str), "artefact_sensitivity": sens.S,
            "artefact_u": sens.u_artefact, "scale_sensitivity": sens.scale,
            "field_index": result.layout.field_index}
