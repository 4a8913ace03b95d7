"""Cross-validation: the measurements split in two halves, each calibrated on its own,
and the halves' predictions of the same points compared with the uncertainty they
state (:mod:`fringecal.calibration.crossval`). A difference beyond it is reported as
model error in millimetres. Writes ``crossval.json`` and, for the ball-bar part of the
check in the verification, each half's sensors and their covariance
(``crossval_halves.npz``).
"""

from __future__ import annotations

import logging

import numpy as np

from fringecal.calibration.crossval import cross_validate, split_measurements
from fringecal.calibration.model import POSE_COLUMNS
from fringecal.rundir import RunDir
from fringecal.steps.base import Settings, Step, black_boxes_only
from fringecal.steps.bundle import load_problem

__all__ = ["CrossValidate"]

log = logging.getLogger(__name__)


class CrossValidate(Step):
    name = "cross-validate"
    title = "cross-validation"
    settings = ("bundle", "reference_scanner")
    modules = ("fringecal.calibration",)

    def reads(self, rd: RunDir, cfg: Settings, item: str):
        if black_boxes_only(rd):  # black boxes only
            return [rd.sensors_prior]
        return [rd.artefact, rd.sensors_initial, rd.control_points, rd.poses_initial, rd.calibration,
                rd.poses_calibrated]

    def writes(self, rd: RunDir, cfg: Settings, item: str):
        return [rd.crossval, rd.crossval_halves]

    def run(self, rd: RunDir, cfg: Settings, item: str, **context) -> None:
        b = cfg.bundle
        if black_boxes_only(rd):
            rd.crossval.save({"verdict": "not possible", "reason": "a rig of black boxes only: no sensor model to "
                                                                    "calibrate on half the measurements"})
            rd.crossval_halves.remove()
            return
        problem = load_problem(rd, cfg.reference_scanner, b.gamma1, b.gamma2)
        try:
            split_measurements(problem)
        except ValueError as err:
            log.warning("cross-validation skipped: %s", err)
            rd.crossval.save({"verdict": "not possible", "reason": str(err)})
            rd.crossval_halves.remove()
            return
        poses = rd.poses_calibrated.load().set_index("measurement").loc[list(problem.measurements), list(POSE_COLUMNS)]
        solved = problem.with_start(problem.rig.with_params(rd.calibration.load().params), poses.to_numpy(float))
        cv = cross_validate(solved, b.model_copy(update={"start": "given"}))
        doc = cv.to_dict()
        for name, s in doc["scanners"].items():
            if s["verdict"] != "consistent":
                log.warning("cross-validation, %s: the two halves differ beyond their stated uncertainty: model "
                            "error of %.1f um per half-calibration", name, 1000 * s["model_error_mm"])
        rd.crossval.save(doc)
        (c1, c2) = cv.sensor_covariances()
        rd.crossval_halves.save({"params_a": cv.halves[0].rig.params, "params_b": cv.halves[1].rig.params,
                                 "covariance_a": c1, "covariance_b": c2,
                                 "sensor_names": np.array([s.name for s in problem.rig.sensors], dtype=str)})
