"""The flow behind ``fringecal run``: the thesis experiment end to end.

acquire (hexapod moves, render + decode per measurement) -> prior calibrations ->
sphere extraction, first pass per measurement -> labelling, poses, scanner links ->
second pass and control points per measurement -> start values (link + DLT) ->
bundle adjustment -> truth evaluation -> ball-bar verification -> summary and report.

Every step is a cached task whose results (small references) live in
``RUN_DIR/.prefect``; a rerun with the same config is all cache hits, a changed setting
reruns what depends on it, and a run killed midway resumes from what finished. A
cached result whose files were deleted or changed since is recomputed. Per-measurement
tasks are submitted together and run on the flow's task runner (bounded threads by
default, a Dask cluster with ``--runner dask``).
"""

from __future__ import annotations

import datetime as _dt
import json
import time
from pathlib import Path

import numpy as np
from prefect import flow

from fringecal.acquisition import AcquisitionInputs, measurement_digest, plan_acquisition, planned_poses
from fringecal.artefact import load_artefact
from fringecal.ballbar import thesis_positions, vdi7_positions
from fringecal.config import thesis_dir
from fringecal.rundir import RunDir, output_record, package_versions, write_json_atomic
from fringecal.runconfig import RunConfig, load_run_config
from fringecal.store import is_complete
from tasks.acquire import acquire_measurement_task, acquisition_table_task, move_hexapod_task
from tasks.pipeline import (ballbar_store_task, bundle_task, first_pass_task, initialise_task, label_task,
                            prior_task, report_task, second_pass_task, truth_task, verify_task)
from tasks.refs import CODE_VERSION, Ref, digest_path, ref_for

from . import progress
from .acquire_flow import MEASUREMENTS_TABLE, POSES_TABLE, _table_matches, _up_to_date

__all__ = ["run_flow", "write_manifest"]


class _Tasks:
    """Calls tasks with the run's result storage, recomputes stale cached results and
    records which tasks ran and which came from the cache."""

    def __init__(self, rd: RunDir):
        self.storage = rd.root / ".prefect"
        self.ran: list[str] = []
        self.cached: list[str] = []

    def _opts(self, task, refresh: bool = False):
        return task.with_options(result_storage=self.storage, refresh_cache=refresh or None)

    def _note(self, name: str, state) -> None:
        (self.cached if state.name == "Cached" else self.ran).append(name)

    def call(self, task, *args, refresh: bool = False, **kwargs):
        state = self._opts(task, refresh)(*args, return_state=True, **kwargs)
        value = state.result()
        if not refresh and state.name == "Cached" and not _refs_intact(value):
            return self.call(task, *args, refresh=True, **kwargs)
        self._note(task.name, state)
        return value

    def submit(self, task, *args, refresh: bool = False, **kwargs):
        return self._opts(task, refresh).submit(*args, **kwargs)

    def gather(self, futures: dict, resubmit, step: str) -> dict:
        """Results of submitted tasks; stale cached ones are resubmitted with refresh."""
        out = {}
        for key, fut in futures.items():
            value = fut.result()
            state = fut.state
            if state.name == "Cached" and not _refs_intact(value):
                fut = resubmit(key)
                value = fut.result()
                state = fut.state
            self._note(f"{step}:{key}", state)
            out[key] = value
            progress.advance(step)
        return out


def _refs_intact(value) -> bool:
    """Every file a (nested) result refers to still exists with the same content;
    stores count as intact while complete (later steps add variables to them)."""
    if isinstance(value, Ref):
        return is_complete(value.path) if value.kind == "store" else value.exists_unchanged()
    if isinstance(value, dict):
        return all(_refs_intact(v) for v in value.values())
    if isinstance(value, (list, tuple)):
        return all(_refs_intact(v) for v in value)
    return True


def write_manifest(rd: RunDir, cfg: RunConfig, command: str) -> dict:
    """manifest.json: resolved config, its digest, package versions, input digests."""
    doc = cfg.model_dump(mode="json")
    rc = cfg.rig_config()
    inputs = {}
    for name in ("sensors", "sensors_initial", "artefact", "rods", "artefact_poses", "ballbar", "materials"):
        p = getattr(rc, name)
        if p is not None:
            inputs[name] = {"path": str(p), "sha256": digest_path(p)}
    inputs["rig"] = {"path": str(cfg.rig), "sha256": digest_path(cfg.rig)}
    manifest = {"config": doc, "config_digest": RunDir.config_digest(doc), "code_version": CODE_VERSION,
                "versions": package_versions(),
                "inputs": inputs, "created_utc": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
                "command": command}
    write_json_atomic(rd.manifest, manifest)
    return manifest


def _copy_if_changed(src: Path, dst: Path) -> None:
    if dst.exists() and digest_path(dst) == digest_path(src):
        return
    tmp = dst.with_name(f".{dst.name}.tmp")
    tmp.write_bytes(Path(src).read_bytes())
    tmp.replace(dst)


def _write_artefact(cfg: RunConfig, dst: Path) -> None:
    """The run's artefact (CMM coordinates with the configured corrections) as
    ``RUN_DIR/artefact.csv``, rewritten only when its content changes (it keys the cache)."""
    from schemas import ArtefactTable, write_table

    tmp = dst.with_name(f".{dst.name}.new")
    write_table(cfg.artefact().to_frame(), tmp, ArtefactTable)
    if dst.exists() and digest_path(dst) == digest_path(tmp):
        tmp.unlink()
    else:
        tmp.replace(dst)


def _positions(cfg: RunConfig, ballbar) -> list:
    import pandas as pd

    table = cfg.verification.positions or thesis_dir() / "ballbar_verification_table6-9.csv"
    scanners = [s.name for s in AcquisitionInputs.from_run_config(cfg).rig.scanners][:2]
    pos = thesis_positions(pd.read_csv(table, dtype={"measurement": str}), scanners=tuple(scanners))
    if cfg.verification.scheme == "vdi7":
        pos = vdi7_positions(pos, float(np.linalg.norm(ballbar.centres[1] - ballbar.centres[0])))
    return pos


@flow(name="fringecal-run")
def run_flow(config: str | dict | None = None, run_dir: str = "runs/latest", overrides: dict | None = None,
             command: str = "fringecal run") -> dict:
    """Run the whole pipeline into ``run_dir``; returns the summary (also summary.json).

    ``config`` is a run-config YAML path (default ``configs/run_thesis.yaml``) or an
    already resolved config (a manifest's ``config``).
    """
    t_start = time.perf_counter()
    cfg = RunConfig.model_validate(config) if isinstance(config, dict) else load_run_config(config, overrides)
    doc = cfg.model_dump(mode="json")
    rc = cfg.rig_config()
    rd = RunDir(run_dir).create()
    write_manifest(rd, cfg, command)
    _write_artefact(cfg, rd.artefact)
    if rc.rods is not None:
        _copy_if_changed(rc.rods, rd.root / "rods.csv")
    T = _Tasks(rd)
    timings: dict[str, float] = {}
    artefact = ref_for(rd.artefact, "table")
    rods = ref_for(rc.rods, "table") if rc.rods is not None else None
    truth_sensors = ref_for(rc.sensors, "table")
    width = cfg.acquisition.camera_width_px

    # -- acquisition -------------------------------------------------------------
    t0 = time.perf_counter()
    inputs = AcquisitionInputs.from_run_config(cfg)
    plans = plan_acquisition(cfg, inputs)
    planned = {pose: Tp.params.tolist() for pose, Tp in planned_poses(plans).items()}
    poses_out = rd.table(POSES_TABLE)
    progress.step("hexapod moves", 1)
    moved = T.call(move_hexapod_task, doc, planned, str(poses_out), refresh=not _table_matches(poses_out, planned))
    progress.advance("hexapod moves")
    digest = measurement_digest(cfg)
    progress.step("acquire measurements", len(plans))

    def acquire(p, refresh=False):
        reached = moved["reached"][p.pose]
        out = rd.store(p.measurement)
        plan = {"measurement": p.measurement, "pose": p.pose, "scanner": p.scanner,
                "planned": p.T_world_artefact.params.tolist()}
        return T.submit(acquire_measurement_task, doc, plan, reached, str(out), digest,
                        refresh=refresh or not _up_to_date(out, digest, p.measurement, reached))

    by_id = {p.measurement: p for p in plans}
    stores = T.gather({p.measurement: acquire(p) for p in plans}, lambda m: acquire(by_id[m], True),
                      "acquire measurements")
    measurements = T.call(acquisition_table_task, list(stores.values()), str(rd.root),
                          str(rd.table(MEASUREMENTS_TABLE)))
    timings["acquisition"] = time.perf_counter() - t0

    # -- prior calibrations and first-pass extraction --------------------------------
    t0 = time.perf_counter()
    prior = T.call(prior_task, truth_sensors, rc.reference_scanner, width, doc["prior"],
                   str(rd.table("sensors_prior")), str(rd.table("scanner_frames_truth")))
    extraction = doc["extraction"]
    progress.step("spheres: first pass", len(plans))

    def first(p, refresh=False):
        return T.submit(first_pass_task, stores[p.measurement], prior["sensors"], artefact, extraction, p.pose,
                        p.scanner, str(rd.tables_dir / "fits_first" / f"{p.measurement}.csv"), refresh=refresh)

    firsts = T.gather({p.measurement: first(p) for p in plans}, lambda m: first(by_id[m], True),
                      "spheres: first pass")
    progress.step("label, pose, link", 1)
    labels = T.call(label_task, [firsts[p.measurement] for p in plans], moved["table"], artefact,
                    rc.reference_scanner, extraction["labelling"], cfg.extraction.use_planned_poses,
                    str(rd.tables_dir))
    progress.advance("label, pose, link")
    progress.step("spheres: second pass", len(plans))

    def second(p, refresh=False):
        return T.submit(second_pass_task, stores[p.measurement], prior["sensors"], artefact, rods,
                        labels["sphere_fits_labelled"], labels["poses"], extraction, doc["control_points"], p.pose,
                        p.scanner, str(rd.tables_dir / "fits_final" / f"{p.measurement}.csv"),
                        str(rd.tables_dir / "control_points" / f"{p.measurement}.csv"), refresh=refresh)

    seconds = T.gather({p.measurement: second(p) for p in plans}, lambda m: second(by_id[m], True),
                       "spheres: second pass")
    timings["sphere extraction"] = time.perf_counter() - t0

    # -- calibration -------------------------------------------------------------------
    t0 = time.perf_counter()
    progress.step("bundle adjustment", 2)
    init = T.call(initialise_task, prior["sensors"], labels, [seconds[p.measurement]["control_points"] for p in plans],
                  artefact, str(rd.root))
    progress.advance("bundle adjustment")
    bundle = T.call(bundle_task, init, artefact, doc["bundle"], rc.reference_scanner, str(rd.root))
    progress.advance("bundle adjustment")
    timings["calibration"] = time.perf_counter() - t0
    truth = T.call(truth_task, bundle["calibration_json"], truth_sensors, rc.reference_scanner, width, moved["table"],
                   init["control_points"], artefact, doc["bundle"], str(rd.root / "truth.json"))

    # -- verification ------------------------------------------------------------------
    t0 = time.perf_counter()
    bb_path = cfg.verification.ballbar or rc.ballbar or thesis_dir() / "ballbar.csv"
    ballbar = ref_for(bb_path, "table")
    bb = load_artefact(bb_path)
    positions = _positions(cfg, bb)
    v_width = cfg.verification.camera_width_px or width
    progress.step("ball-bar measurements", sum(len(p.scanner_of) for p in positions))

    def bb_store(pos, sid, refresh=False):
        scanner = pos.scanner_of[sid]
        out = rd.store(f"{pos.name}-{scanner}")
        return T.submit(ballbar_store_task, doc, digest, pos.name, sid, scanner,
                        pos.T_world_ballbar.params.tolist(), ballbar, str(out), refresh=refresh)

    keys = {f"{p.name}|{sid}": (p, sid) for p in positions for sid in p.scanner_of}
    bb_stores = T.gather({k: bb_store(*v) for k, v in keys.items()}, lambda k: bb_store(*keys[k], True),
                         "ball-bar measurements")
    diagonal = cfg.verification.volume_diagonal_mm or json.loads(
        Path(bundle["summary"].path).read_text())["volume_diagonal_mm"]
    progress.step("verification", 1)
    verified = T.call(verify_task, bb_stores, {p.name: {"T": p.T_world_ballbar.params.tolist(),
                                                        "scanner_of": p.scanner_of} for p in positions},
                      ballbar, bundle["calibration_json"], truth_sensors, rc.reference_scanner, v_width,
                      doc["verification"], extraction, float(diagonal), str(rd.root))
    progress.advance("verification")
    timings["verification"] = time.perf_counter() - t0

    # -- summary and report --------------------------------------------------------------
    summary = _summary(rd, cfg, plans, bundle, truth, verified, timings, time.perf_counter() - t_start, T)
    progress.step("report", 1)
    # summary.json changes every run (timings); the report is current while these are
    report = T.call(report_task, {"bundle": bundle, "verification": verified["verification"], "truth": truth,
                                  "labels": labels, "acquisition": [moved["table"], measurements],
                                  "rods": ref_for(rd.root / "rods.csv") if rc.rods is not None else None},
                    str(rd.root),
                    timings)
    progress.advance("report")
    summary["total_seconds"] = time.perf_counter() - t_start
    summary["tasks"] = {"ran": T.ran, "cached": T.cached}
    summary["outputs"] = output_record(rd, _files([report, bundle, verified, truth, labels, init, moved["table"]]),
                                       [Path(r.path) for r in list(stores.values()) + list(bb_stores.values())])
    write_json_atomic(rd.summary, summary)
    return summary


def _files(value, out=None) -> dict:
    """Path -> digest of every file reference in a nested result."""
    out = {} if out is None else out
    if isinstance(value, Ref):
        out[Path(value.path)] = value.digest
    elif isinstance(value, dict):
        for v in value.values():
            _files(v, out)
    elif isinstance(value, (list, tuple)):
        for v in value:
            _files(v, out)
    return out


def _summary(rd, cfg, plans, bundle, truth, verified, timings, elapsed, T) -> dict:
    b = json.loads(Path(bundle["summary"].path).read_text())
    v = json.loads(Path(verified["verification"].path).read_text())
    t = json.loads(Path(truth.path).read_text())
    cal = v["calibrated"]
    out = {
        "name": cfg.name,
        "n_measurements": len(plans),
        "n_control_points": b["n_control_points"],
        "rms_F_mm_before": b["before"]["rms_f_mm"],
        "rms_F_mm_after": b["after"]["rms_f_mm"],
        "rms_eps1_mm_before": b["before"]["rms_eps1_mm"],
        "rms_eps2_mm_before": b["before"]["rms_eps2_mm"],
        "rms_eps1_mm_after": b["after"]["rms_eps1_mm"],
        "rms_eps2_mm_after": b["after"]["rms_eps2_mm"],
        "one_part_in": b["one_part_in_1p96_sigma"],
        "bundle_seconds": b.get("bundle_seconds", b.get("elapsed_s")),
        "total_seconds": elapsed,
        "timings": timings,
        "verification": {"reference_length_mm": cal["reference_length_mm"], "mean_length_mm": cal["mean_length_mm"],
                         "max_abs_error_mm": cal["max_abs_error_mm"], "volume_diagonal_mm": cal["volume_diagonal_mm"],
                         "one_part_in": cal["one_part_in"], "mpe_mm": cal["mpe_mm"], "pass": cal["pass"],
                         "expanded_uncertainty_mm": cal["uncertainty"]["expanded_mm"],
                         "coverage_factor": cal["uncertainty"]["coverage_factor"], "scheme": v["scheme"]},
        "truth": {"max_position_error_mm": t["max_position_error_mm"], "max_angle_error_rad": t["max_angle_error_rad"],
                  "rms_eps1_mm_true_params": t["rms_eps1_mm_true_params"],
                  "rms_eps2_mm_true_params": t["rms_eps2_mm_true_params"],
                  "verification_max_abs_error_true_params_mm": v.get("true", {}).get("max_abs_error_mm")},
    }
    write_json_atomic(rd.summary, out)
    return out
