"""Task adapters of ``fringecal run`` after acquisition: prior calibration, sphere
extraction (two passes around labelling), start values, bundle adjustment, truth
evaluation, ball-bar verification and the report.

Every task reads its inputs from references, writes its outputs atomically into the
run directory and returns references. Cache keys come from the inputs' digests, the
settings the task uses and the code version (:func:`tasks.refs.cache_key`), so a
changed setting reruns exactly the tasks that depend on it.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
from prefect import get_run_logger, task

from fringecal.artefact import load_artefact, load_rods
from fringecal.rig import load_rig
from fringecal.rundir import write_json_atomic
from schemas import (ControlPointsTable, LabelOutcomesTable, PosePlanTable, PosesTable, ScannerLinksTable,
                     SensorParametersTable, SphereCentresTable, SphereFitsTable, read_table, write_table)

from .refs import Ref, cache_key, ref_for

__all__ = ["prior_task", "first_pass_task", "label_task", "second_pass_task", "initialise_task", "bundle_task",
           "truth_task", "ballbar_store_task", "verify_task", "report_task"]


def _key(name):
    return lambda context, parameters: cache_key(name, parameters)


def _cfg(doc: dict):
    from fringecal.runconfig import RunConfig

    return RunConfig.model_validate(doc)


def _scaled_rig(path: str, width_px: int, reference: str):
    from fringecal.simulate.resolution import scaled_rig

    return scaled_rig(load_rig(path, reference=reference), width_px)


@task(name="prior-calibration", cache_key_fn=_key("prior-calibration"), persist_result=True)
def prior_task(truth_sensors: Ref, reference: str, width_px: int, prior: dict, out: str, out_frames: str) -> dict:
    """Each scanner's simulated prior calibration in its own frame (and the true frames)."""
    from fringecal.pipeline.prior import simulate_prior_rig
    from fringecal.runconfig import PriorCalibrationConfig

    truth = _scaled_rig(truth_sensors.path, width_px, reference)
    rig, frames = simulate_prior_rig(truth, PriorCalibrationConfig.model_validate(prior))
    write_table(rig.to_frame(), out, SensorParametersTable)
    rows = [{"scanner": s, **dict(zip(["tx_mm", "ty_mm", "tz_mm", "omega_rad", "phi_rad", "kappa_rad"], T.params))}
            for s, T in frames.items()]
    write_table(pd.DataFrame(rows), out_frames)
    return {"sensors": ref_for(out, "table"), "frames": ref_for(out_frames, "table")}


@task(name="extract-first-pass", cache_key_fn=_key("extract-first-pass"), persist_result=True)
def first_pass_task(store: Ref, sensors: Ref, artefact: Ref, extraction: dict, pose: str, scanner: str,
                    out: str) -> Ref:
    """Triangulate one measurement with its scanner's prior sensors and fit every sphere candidate."""
    from fringecal.pipeline.extract import first_pass
    from fringecal.runconfig import ExtractionConfig

    rig = load_rig(sensors.path)
    art = load_artefact(artefact.path)
    rows, failures = first_pass(store.path, rig.scanner(scanner), float(np.median(art.radii)),
                                ExtractionConfig.model_validate(extraction), pose)
    for f in failures.itertuples():
        get_run_logger().warning("measurement %s, scanner %s, candidate %s: not fitted (%s)",
                                 pose, scanner, f.candidate, f.reason)
    write_table(rows, out, SphereFitsTable if len(rows) else None)
    return ref_for(out, "table")


@task(name="label-pose-link", cache_key_fn=_key("label-pose-link"), persist_result=True)
def label_task(fits: list[Ref], acquisition_poses: Ref, artefact: Ref, reference: str, labelling: dict,
               use_planned: bool, out_dir: str) -> dict:
    """Label every measurement's spheres, estimate poses, link the scanners."""
    from fringecal.frames import Frame
    from fringecal.spheres.labelling import LabellingConfig
    from fringecal.spheres.steps import label_pose_link
    from schemas import AcquiredPosesTable

    frames = [pd.read_csv(f.path, dtype={"measurement": str, "scanner": str, "candidate": str, "sphere_id": str},
                          keep_default_na=False, na_values=[""]) for f in fits]
    table = pd.concat([f for f in frames if len(f)], ignore_index=True)
    table["sphere_id"] = table["sphere_id"].fillna("")
    planned = None
    if use_planned:
        acq = read_table(acquisition_poses.path, AcquiredPosesTable)
        cols = [f"planned_{c}" for c in ("tx_mm", "ty_mm", "tz_mm", "omega_rad", "phi_rad", "kappa_rad")]
        planned = {str(r.measurement): Frame.from_params([getattr(r, c) for c in cols]) for r in acq.itertuples()}
    res = label_pose_link(table, load_artefact(artefact.path), reference, LabellingConfig(**labelling),
                          planned=planned)
    log = get_run_logger()
    for r in res.poses.skipped.itertuples():
        log.warning("measurement %s, scanner %s: no pose (%s)", r.measurement, r.scanner, r.reason)
    out = Path(out_dir)
    write_table(res.fits, out / "sphere_fits_labelled.csv", SphereFitsTable)
    write_table(res.labels, out / "label_outcomes.csv", LabelOutcomesTable)
    write_table(res.centres, out / "sphere_centres.csv", SphereCentresTable)
    write_table(res.poses.poses, out / "poses.csv", PosesTable if len(res.poses.poses) else None)
    write_table(res.poses.skipped, out / "poses_skipped.csv")
    write_table(res.links_table(), out / "scanner_links.csv", ScannerLinksTable)
    if res.links_error:
        log.warning("scanner links: %s", res.links_error)
    names = ["sphere_fits_labelled", "label_outcomes", "sphere_centres", "poses", "poses_skipped", "scanner_links"]
    return {n: ref_for(out / f"{n}.csv", "table") for n in names}


@task(name="extract-second-pass", cache_key_fn=_key("extract-second-pass"), persist_result=True)
def second_pass_task(store: Ref, sensors: Ref, artefact: Ref, rods: Ref | None, labelled: Ref, poses: Ref,
                     extraction: dict, control_points: dict, pose: str, scanner: str, out_fits: str,
                     out_cps: str) -> dict:
    """Refit the labelled spheres with rod cones; select the control points."""
    from fringecal.pipeline.extract import second_pass
    from fringecal.pipeline.initialise import poses_from_table
    from fringecal.runconfig import ControlPointConfig, ExtractionConfig

    art = load_artefact(artefact.path)
    rod_table = load_rods(rods.path, art) if rods is not None else None
    lab = read_table(labelled.path, SphereFitsTable)
    lab = lab[(lab.measurement == pose) & (lab.scanner == scanner)]
    pose_table = pd.read_csv(poses.path, dtype={"measurement": str, "scanner": str})
    T = poses_from_table(pose_table).get((pose, scanner)) if len(pose_table) else None
    res = second_pass(store.path, load_rig(sensors.path).scanner(scanner), art, rod_table, lab, T,
                      ExtractionConfig.model_validate(extraction), ControlPointConfig.model_validate(control_points),
                      pose)
    write_table(res.fits, out_fits, SphereFitsTable if len(res.fits) else None)
    write_table(res.control_points, out_cps, ControlPointsTable)
    return {"fits": ref_for(out_fits, "table"), "control_points": ref_for(out_cps, "table")}


@task(name="initialise", cache_key_fn=_key("initialise"), persist_result=True)
def initialise_task(sensors: Ref, labels: dict, control_points: list[Ref], artefact: Ref, run_dir: str) -> dict:
    """Link the scanners, DLT start values, one start pose per measurement; write the
    bundle adjustment's inputs (the RUN_DIR contract of ``fringecal calibrate``)."""
    from fringecal.pipeline.initialise import initial_calibration
    from fringecal.rundir import RunDir

    rd = RunDir(run_dir)
    prior = load_rig(sensors.path)
    init = initial_calibration(prior, read_table(labels["sphere_centres"].path, SphereCentresTable),
                               read_table(labels["poses"].path, PosesTable),
                               read_table(labels["scanner_links"].path, ScannerLinksTable),
                               load_artefact(artefact.path))
    cps = pd.concat([read_table(c.path, ControlPointsTable) for c in control_points], ignore_index=True)
    write_table(cps, rd.table("control_points"), ControlPointsTable)
    write_table(init.poses, rd.table("poses_initial"), PosePlanTable)
    write_table(init.rig.to_frame(), rd.table("sensors_initial"), SensorParametersTable)
    write_table(init.dlt, rd.table("dlt"))
    return {"control_points": ref_for(rd.table("control_points"), "table"),
            "poses_initial": ref_for(rd.table("poses_initial"), "table"),
            "sensors_initial": ref_for(rd.table("sensors_initial"), "table")}


@task(name="bundle-adjustment", cache_key_fn=_key("bundle-adjustment"), persist_result=True)
def bundle_task(inputs: dict, artefact: Ref, bundle: dict, reference: str, run_dir: str) -> dict:
    """The object-space bundle adjustment of the run (fringecal.calibration.calibrate_run),
    with the run's weights and solver settings written to ``calibrate.yaml``."""
    import time

    import yaml

    from fringecal.calibration import calibrate_run

    conf = {"gamma1": bundle["gamma1"], "gamma2": bundle["gamma2"], "robust_loss": bundle["robust_loss"],
            "max_iterations": bundle["max_iterations"], "reference_scanner": reference}
    if bundle["robust_loss"] != "none":
        conf["robust_scale_mm"] = bundle["robust_scale_mm"]
    tmp = Path(run_dir) / ".calibrate.yaml.tmp"
    tmp.write_text(yaml.safe_dump(conf))
    tmp.replace(Path(run_dir) / "calibrate.yaml")
    t0 = time.perf_counter()
    result, paths = calibrate_run(run_dir)
    seconds = time.perf_counter() - t0
    for d in result.diagnostics:
        get_run_logger().warning("%s: %s", d.kind, d.message)
    doc = json.loads(Path(paths["summary"]).read_text())
    doc["bundle_seconds"] = seconds
    write_json_atomic(paths["summary"], doc)
    return {k: ref_for(p) for k, p in paths.items()}


@task(name="truth-evaluation", cache_key_fn=_key("truth-evaluation"), persist_result=True)
def truth_task(calibration: Ref, truth_sensors: Ref, reference: str, width_px: int, acquisition_poses: Ref,
               control_points: Ref, artefact: Ref, bundle: dict, out: str) -> Ref:
    """For simulated runs: parameter errors against the truth and the residual floor
    (epsilon-1, epsilon-2 with the true sensors and poses on the same control points)."""
    from fringecal.calibration import BundleOptions, BundleProblem, bundle_adjust
    from fringecal.calibration_file import read_calibration_json
    from schemas import AcquiredPosesTable

    truth = _scaled_rig(truth_sensors.path, width_px, reference)
    cal = read_calibration_json(calibration.path)
    pos = ang = 0.0
    per_sensor = []
    for est, true in zip(cal.sensors, truth.sensors):
        d = est.params - true.params
        u = None if cal.uncertainty is None else cal.uncertainty[[s.name for s in cal.sensors].index(est.name)]
        per_sensor.append({"sensor": est.name, "position_error_mm": float(np.linalg.norm(d[:3])),
                           "angle_error_rad": float(np.abs(d[3:6]).max()), "c_error_mm": float(d[8]),
                           "max_sigma_ratio_position_angles_c": None if u is None else
                           float(np.max(np.abs(d[[0, 1, 2, 3, 4, 5, 8]]) / np.where(u[[0, 1, 2, 3, 4, 5, 8]] > 0,
                                                                                   u[[0, 1, 2, 3, 4, 5, 8]], np.inf)))})
        pos, ang = max(pos, float(np.linalg.norm(d[:3]))), max(ang, float(np.abs(d[3:6]).max()))
    acq = read_table(acquisition_poses.path, AcquiredPosesTable)
    poses = acq[["measurement", "tx_mm", "ty_mm", "tz_mm", "omega_rad", "phi_rad", "kappa_rad"]]
    cps = read_table(control_points.path, ControlPointsTable)
    problem = BundleProblem.from_tables(truth, load_artefact(artefact.path), cps,
                                        poses[poses.measurement.isin(set(cps.measurement))],
                                        gamma1=bundle["gamma1"], gamma2=bundle["gamma2"])
    floor = bundle_adjust(problem, BundleOptions(max_iterations=1, start="given")).before
    doc = {"max_position_error_mm": pos, "max_angle_error_rad": ang, "sensors": per_sensor,
           "rms_f_mm_true_params": floor.rms_f_mm, "rms_eps1_mm_true_params": floor.rms_eps1_mm,
           "rms_eps2_mm_true_params": floor.rms_eps2_mm}
    write_json_atomic(out, doc)
    return ref_for(out, "json")


def _ballbar_store_key(context, p) -> str:
    # the run config acts through the acquisition digest and the verification's own
    # resolution and seed; other sections (extraction, bundle...) do not change the frames
    v = p["run_config"]["verification"]
    return cache_key("ballbar-measurement", {**{k: x for k, x in p.items() if k != "run_config"},
                                             "width": v["camera_width_px"], "seed": v["seed"]})


@task(name="ballbar-measurement", cache_key_fn=_ballbar_store_key, persist_result=True)
def ballbar_store_task(run_config: dict, config_digest: str, position: str, sphere_id: str, scanner: str,
                       T_world_ballbar: list[float], ballbar: Ref, out: str) -> Ref:
    """Render, decode and store one scanner's view of the ball-bar at one position."""
    from fringecal.acquisition import AcquisitionInputs, MeasurementPlan, acquire_measurement
    from fringecal.ballbar import ballbar_rods
    from fringecal.frames import Frame

    cfg = _cfg(run_config)
    inputs = AcquisitionInputs.from_run_config(cfg)
    bb = load_artefact(ballbar.path)
    bb_inputs = AcquisitionInputs(inputs.rig, bb, ballbar_rods(bb), inputs.hardware, inputs.poses)
    width = cfg.verification.camera_width_px or cfg.acquisition.camera_width_px
    cfg_v = cfg.model_copy(update={"acquisition": cfg.acquisition.model_copy(
        update={"camera_width_px": width, "seed": cfg.verification.seed})})
    T = Frame.from_params(T_world_ballbar)
    mid = f"{position}-{scanner}"
    acquire_measurement(MeasurementPlan(mid, position, scanner, T), T, cfg_v, out, bb_inputs)
    return ref_for(out, "store")


@task(name="verification", cache_key_fn=_key("verification"), persist_result=True)
def verify_task(stores: dict, positions: dict, ballbar: Ref, calibration: Ref, truth_sensors: Ref | None,
                reference: str, width_px: int, verification: dict, extraction: dict, volume_diagonal_mm: float,
                run_dir: str) -> dict:
    """Ball-bar lengths with the calibrated sensors (and the true ones, when simulated)."""
    from fringecal.ballbar import BallBarPosition
    from fringecal.calibration_file import read_calibration_json
    from fringecal.frames import Frame
    from fringecal.pipeline.verify import ballbar_centres
    from fringecal.rundir import RunDir
    from fringecal.runconfig import ExtractionConfig
    from fringecal.simulate.resolution import scaled_rig
    from fringecal.verification import ballbar_lengths, evaluate_ballbar

    rd = RunDir(run_dir)
    bb = load_artefact(ballbar.path)
    pos = [BallBarPosition(name, Frame.from_params(p["T"]), p["scanner_of"]) for name, p in positions.items()]
    rigs = {"calibrated": scaled_rig(read_calibration_json(calibration.path), width_px)}
    if truth_sensors is not None:
        rigs["true"] = _scaled_rig(truth_sensors.path, width_px, reference)
    store_paths = {tuple(k.split("|")): v.path for k, v in stores.items()}
    centres, failures = ballbar_centres(store_paths, pos, bb, rigs,
                                        ExtractionConfig.model_validate(extraction).rejection_config())
    reference_length = float(np.linalg.norm(bb.centres[1] - bb.centres[0]))
    out = {}
    for label, table in centres.items():
        write_table(table, rd.table(f"ballbar_centres_{label}"), SphereCentresTable)
        lengths = ballbar_lengths(table, f"ballbar centres ({label})")
        res = evaluate_ballbar(lengths.length_mm, reference_length, lengths.measurement,
                               verification["mpe_mm"], volume_diagonal_mm, verification["certificate_u_mm"],
                               verification["certificate_k"], verification["coverage_factor"])
        out[label] = res.to_dict()
    out["failures"] = failures.to_dict("records")
    out["scheme"] = verification["scheme"]
    write_json_atomic(rd.root / "verification.json", out)
    return {"verification": ref_for(rd.root / "verification.json", "json"),
            **{f"centres_{k}": ref_for(rd.table(f"ballbar_centres_{k}"), "table") for k in centres}}


def _report_key(context, parameters) -> str:
    # the step timings shown in the report describe the run that computed it; they do
    # not decide whether the report is current
    return cache_key("report", {k: v for k, v in parameters.items() if k != "timings"})


@task(name="report", cache_key_fn=_report_key, persist_result=True)
def report_task(inputs: dict, run_dir: str, timings: dict) -> Ref:
    """The self-contained HTML report of the run."""
    from fringecal.report import write_report

    path = write_report(Path(run_dir), timings)
    return ref_for(path, "report")
