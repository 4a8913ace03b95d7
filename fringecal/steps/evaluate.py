"""Simulated runs only: the calibration against the truth.

Reads ``truth/`` (the only pipeline step that does): each sensor's parameter errors
against the true values and against its reported uncertainty (the truth moved into
the calibration's world, the reference scanner's own frame), the residual floor
(epsilon-1, epsilon-2 with the true sensors and poses on the same control points),
and the ball-bar measured with the true sensors -- the error the noise alone leaves,
against which the calibration's own ball-bar error is judged.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from fringecal.calibration.bundle import BundleOptions, bundle_adjust
from fringecal.calibration.model import BundleProblem
from fringecal.frames import Frame, frame_rows, frames_from_rows
from fringecal.rig import Rig, Scanner
from fringecal.rundir import RunDir
from fringecal.sensor import sensor_in_frame
from fringecal.steps.base import Settings, Step, black_box_scanners, black_boxes_only, stores_of_kind
from fringecal.steps.verify import ballbar_stores
from fringecal.verification.black_box import verify_with_black_boxes
from fringecal.verification.verify import verify_ballbar

__all__ = ["Evaluate", "parameter_errors"]

_KEY = [0, 1, 2, 3, 4, 5, 8]  # position, angles, principal distance


def truth_in_reference_frame(truth, T_world_reference, near):
    """The true rig moved from the simulation's world into the reference scanner's own
    frame, the world of a calibration.

    ``near`` (a rig with the same sensors) picks the branch of every sensor's angles,
    so that angle differences are small numbers, not multiples of pi.
    """

    T_reference_world = T_world_reference.inverse()
    angles = {s.name: s.angles for s in near.sensors}
    scanners = [Scanner(s.name, *(sensor_in_frame(x, T_reference_world, near=angles.get(x.name)) for x in s.sensors))
                for s in truth.scanners]
    return replace(truth, scanners=tuple(scanners))


def poses_in_reference_frame(poses, T_world_reference):
    """A pose table (``T_world_artefact`` rows) as ``T_reference_artefact`` rows."""

    T_reference_world = T_world_reference.inverse()
    return frame_rows({m: T_reference_world.compose(T) for m, T in frames_from_rows(poses).items()})


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


def true_black_boxes(estimated: dict, frames: dict, T_world_reference, truth) -> dict:
    """The black boxes' true transforms (their cameras' frames in the reference frame,
    scale 1) as a ``black_boxes.json`` document without uncertainty."""
    T_reference_world = T_world_reference.inverse()
    scanners = []
    for d in estimated["scanners"]:
        near = np.array([d["omega_rad"], d["phi_rad"], d["kappa_rad"]])
        T = T_reference_world.compose(frames[d["scanner"]])
        T = Frame.from_matrix(T.R, T.t, near=near)
        names = ("tx_mm", "ty_mm", "tz_mm", "omega_rad", "phi_rad", "kappa_rad")
        scanners.append({"scanner": d["scanner"], **dict(zip(names, map(float, T.params))), "scale": 1.0,
                         "covariance": np.zeros((7, 7)).tolist(), "rms_mm": 0.0, "n_centres": 0})
    n_sensor = 0 if truth is None else 14 * len(truth.sensors)  # None: black boxes only
    n = n_sensor + 7 * len(scanners)
    return {"scanners": scanners, "joint_covariance": {"n_sensor_parameters": n_sensor,
                                                       "black_boxes": [d["scanner"] for d in scanners],
                                                       "matrix": np.zeros((n, n)).tolist()}}


def black_box_errors(estimated: dict, truth: dict) -> list[dict]:
    """Each black box's transform error: origin (mm), largest angle (rad), scale, and the
    largest |error| / u over its seven parameters."""
    names = ("tx_mm", "ty_mm", "tz_mm", "omega_rad", "phi_rad", "kappa_rad", "scale")
    out = []
    for est, true in zip(estimated["scanners"], truth["scanners"]):
        d = np.array([est[n] - true[n] for n in names])
        d[3:6] = np.angle(np.exp(1j * d[3:6]))
        u = np.array([est["std"][n] for n in names])
        out.append({"scanner": est["scanner"], "position_error_mm": float(np.linalg.norm(d[:3])),
                    "angle_error_rad": float(np.abs(d[3:6]).max()), "scale_error": float(d[6]),
                    "max_sigma_ratio": float(np.max(np.abs(d[u > 0]) / u[u > 0])) if np.any(u > 0) else None})
    return out


class Evaluate(Step):
    name = "evaluate"
    title = "evaluation against truth"
    settings = ("bundle.gamma1", "bundle.gamma2", "verification", "extraction.rejection", "reference_scanner",
                "control_points.max_incidence_deg", "control_points.pixel_integration_px")
    modules = ("fringecal.calibration", "fringecal.verification.measure", "fringecal.verification.lengths")

    def reads(self, rd: RunDir, cfg: Settings, item: str):
        boxes = [rd.black_boxes, rd.sensors_prior] if black_box_scanners(rd) else []
        if black_boxes_only(rd):  # black boxes only
            return [rd.truth.scanner_frames, rd.ballbar, rd.bundle_summary, rd.acquisition] + \
                [rd.store(m) for m in stores_of_kind(rd, "ballbar")] + boxes
        return [rd.truth.sensors, rd.truth.poses, rd.truth.scanner_frames, rd.calibration, rd.control_points,
                rd.artefact, rd.ballbar, rd.bundle_summary, rd.acquisition] + \
            [rd.store(m) for m in stores_of_kind(rd, "ballbar")] + boxes

    def writes(self, rd: RunDir, cfg: Settings, item: str):
        return [rd.evaluation, rd.ballbar_centres_true]

    def run(self, rd: RunDir, cfg: Settings, item: str, **context) -> None:
        if black_boxes_only(rd):
            return self.run_black_boxes_only(rd, cfg)
        calibrated = rd.calibration.load()
        frames = frames_from_rows(rd.truth.scanner_frames.load(), key="scanner")
        T_world_reference = frames[cfg.reference_scanner]
        truth = truth_in_reference_frame(rd.truth.sensors.load(cfg.reference_scanner), T_world_reference, calibrated)
        boxes = black_box_scanners(rd)
        if boxes:
            keep = [i for i, sc in enumerate(truth.scanners) if sc.name not in boxes]
            truth = Rig(tuple(truth.scanners[i] for i in keep), truth.reference,
                        truth.free[[2 * i + k for i in keep for k in (0, 1)]])
        per_sensor, pos, ang = parameter_errors(calibrated, truth)
        cps = rd.control_points.load()
        poses = poses_in_reference_frame(rd.truth.poses.load(), T_world_reference)
        problem = BundleProblem.from_tables(truth, rd.artefact.load(), cps,
                                            poses[poses.measurement.isin(set(cps.measurement))],
                                            gamma1=cfg.bundle.gamma1, gamma2=cfg.bundle.gamma2)
        floor = bundle_adjust(problem, BundleOptions(max_iterations=1, start="given")).before
        doc = {"max_position_error_mm": pos, "max_angle_error_rad": ang, "sensors": per_sensor,
               "rms_f_mm_true_params": floor.rms_f_mm, "rms_eps1_mm_true_params": floor.rms_eps1_mm,
               "rms_eps2_mm_true_params": floor.rms_eps2_mm}
        if boxes:
            estimated = rd.black_boxes.load()
            true_boxes = true_black_boxes(estimated, frames, T_world_reference, truth)
            doc["black_boxes"] = black_box_errors(estimated, true_boxes)
        if stores_of_kind(rd, "ballbar") and rd.ballbar.exists() and boxes:
            diagonal = rd.bundle_summary.load()["volume_diagonal_mm"]
            centres, failures, result, _ = verify_with_black_boxes(
                ballbar_stores(rd), truth, true_boxes, rd.ballbar.load(), cfg.extraction.rejection, cfg.verification,
                diagonal, cfg.control_points.max_incidence_deg, cfg.control_points.pixel_integration_px)
            rd.ballbar_centres_true.save(centres)
            doc["verification_true_params"] = {**result, "failures": failures.to_dict("records")}
        elif stores_of_kind(rd, "ballbar") and rd.ballbar.exists():
            diagonal = rd.bundle_summary.load()["volume_diagonal_mm"]
            centres, failures, result, _ = verify_ballbar(ballbar_stores(rd), truth, rd.ballbar.load(),
                                                          cfg.extraction.rejection, cfg.verification, diagonal)
            rd.ballbar_centres_true.save(centres)
            doc["verification_true_params"] = {**result.to_dict(), "failures": failures.to_dict("records")}
        else:
            rd.ballbar_centres_true.remove()
        rd.evaluation.save(doc)

    def run_black_boxes_only(self, rd: RunDir, cfg: Settings) -> None:
        """A rig of black boxes only: each transform against the truth, and the ball-bar
        measured on the same sightings with the true transforms (no sensor model: no
        residual floor)."""
        frames = frames_from_rows(rd.truth.scanner_frames.load(), key="scanner")
        estimated = rd.black_boxes.load()
        true_boxes = true_black_boxes(estimated, frames, frames[cfg.reference_scanner], None)
        errors = black_box_errors(estimated, true_boxes)
        doc = {"black_boxes_only": True, "black_boxes": errors,
               "max_position_error_mm": max(e["position_error_mm"] for e in errors),
               "max_angle_error_rad": max(e["angle_error_rad"] for e in errors),
               "rms_f_mm_true_params": None, "rms_eps1_mm_true_params": None, "rms_eps2_mm_true_params": None}
        if stores_of_kind(rd, "ballbar") and rd.ballbar.exists():
            centres, failures, result, _ = verify_with_black_boxes(
                ballbar_stores(rd), None, true_boxes, rd.ballbar.load(), cfg.extraction.rejection, cfg.verification,
                rd.bundle_summary.load()["volume_diagonal_mm"], cfg.control_points.max_incidence_deg,
                cfg.control_points.pixel_integration_px)
            rd.ballbar_centres_true.save(centres)
            doc["verification_true_params"] = {**result, "failures": failures.to_dict("records")}
        else:
            rd.ballbar_centres_true.remove()
        rd.evaluation.save(doc)
