"""Simulated runs only: the calibration against the truth.

Reads ``truth/`` (the only pipeline step that does): each sensor's parameter errors
against the true values and against its reported uncertainty, the residual floor
(epsilon-1, epsilon-2 with the true sensors and poses on the same control points),
and the ball-bar measured with the true sensors -- the error the noise alone leaves,
against which the calibration's own ball-bar error is judged.
"""

from __future__ import annotations

import numpy as np

from ..rundir import RunDir
from .base import Settings, Step, stores_of_kind
from .verify import measure_ballbar

__all__ = ["Evaluate", "parameter_errors"]

_KEY = [0, 1, 2, 3, 4, 5, 8]  # position, angles, principal distance


def parameter_errors(calibrated, truth) -> tuple[list[dict], float, float]:
    """Per-sensor errors (position, angles, principal distance, worst |error| / u) and
    the largest position and angle errors over the sensors."""
    names = [s.name for s in calibrated.sensors]
    rows, pos, ang = [], 0.0, 0.0
    for est, true in zip(calibrated.sensors, truth.sensors):
        d = est.params - true.params
        u = None if calibrated.uncertainty is None else calibrated.uncertainty[names.index(est.name)]
        ratio = None if u is None else float(np.max(np.abs(d[_KEY]) / np.where(u[_KEY] > 0, u[_KEY], np.inf)))
        rows.append({"sensor": est.name, "position_error_mm": float(np.linalg.norm(d[:3])),
                     "angle_error_rad": float(np.abs(d[3:6]).max()), "c_error_mm": float(d[8]),
                     "max_sigma_ratio_position_angles_c": ratio})
        pos, ang = max(pos, float(np.linalg.norm(d[:3]))), max(ang, float(np.abs(d[3:6]).max()))
    return rows, pos, ang


class Evaluate(Step):
    name = "evaluate"
    title = "evaluation against truth"
    settings = ("bundle.gamma1", "bundle.gamma2", "verification", "extraction.rejection", "reference_scanner")
    modules = ("fringecal.calibration", "fringecal.pipeline.verify", "fringecal.verification")

    def reads(self, rd: RunDir, cfg: Settings, item: str):
        return [rd.truth.sensors, rd.truth.poses, rd.calibration, rd.control_points, rd.artefact, rd.ballbar,
                rd.bundle_summary, rd.acquisition] + [rd.store(m) for m in stores_of_kind(rd, "ballbar")]

    def writes(self, rd: RunDir, cfg: Settings, item: str):
        return [rd.evaluation, rd.ballbar_centres_true]

    def run(self, rd: RunDir, cfg: Settings, item: str, **context) -> None:
        from ..calibration import BundleOptions, BundleProblem, bundle_adjust

        truth = rd.truth.sensors.load(cfg.reference_scanner)
        per_sensor, pos, ang = parameter_errors(rd.calibration.load(), truth)
        cps = rd.control_points.load()
        poses = rd.truth.poses.load()
        problem = BundleProblem.from_tables(truth, rd.artefact.load(), cps,
                                            poses[poses.measurement.isin(set(cps.measurement))],
                                            gamma1=cfg.bundle.gamma1, gamma2=cfg.bundle.gamma2)
        floor = bundle_adjust(problem, BundleOptions(max_iterations=1, start="given")).before
        doc = {"max_position_error_mm": pos, "max_angle_error_rad": ang, "sensors": per_sensor,
               "rms_f_mm_true_params": floor.rms_f_mm, "rms_eps1_mm_true_params": floor.rms_eps1_mm,
               "rms_eps2_mm_true_params": floor.rms_eps2_mm}
        if stores_of_kind(rd, "ballbar") and rd.ballbar.exists():
            diagonal = rd.bundle_summary.load()["volume_diagonal_mm"]
            centres, failures, result = measure_ballbar(rd, truth, cfg.extraction.rejection, cfg.verification,
                                                        diagonal)
            rd.ballbar_centres_true.save(centres)
            doc["verification_true_params"] = {**result.to_dict(), "failures": failures.to_dict("records")}
        else:
            rd.ballbar_centres_true.remove()
        rd.evaluation.save(doc)
