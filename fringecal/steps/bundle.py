"""Bundle adjustment: every sensor and one artefact pose per measurement refined from
the control points (thesis 2.3.7, 6.4-6.5, :func:`fringecal.calibration.bundle.bundle_adjust`),
with uncertainties, a diagnosis of degenerate set-ups and the wild-bootstrap replicas.
Writes the calibration (JSON and XML), its tables (the residuals per sphere image, per
measurement and binned over every camera's and projector's image), the residual histograms, the
covariance arrays and ``bundle_summary.json``, all or nothing.
"""

from __future__ import annotations

import io
import json
import logging
import time
from dataclasses import replace

import numpy as np
import pandas as pd

from fringecal import compile_clock, threads
from fringecal.atomic import atomic_paths
from fringecal.calibration.blackbox import ModelPrior, adjust_black_boxes, export_table, inconsistent_views
from fringecal.calibration.bootstrap import bootstrap_calibrations
from fringecal.calibration.models import choose_sensor_model
from fringecal.calibration.file import REPLICA_KINDS, replicas_document
from fringecal.calibration.jackknife import MIN_REPLICAS, jackknife_calibrations
from fringecal.calibration.model import POSE_COLUMNS, BundleProblem
from fringecal.calibration.propagation import parameter_covariances
from fringecal.calibration.results import (binned_residuals, covariance_arrays, observed_regions, residual_tables,
                                           summary)
from fringecal.config import ConfigError
from fringecal.digests import digest_path, digest_value
from fringecal.frames import Frame
from fringecal.lens.observed_region import MIN_FRACTION, too_small
from fringecal.report.plotting import residual_histograms_png
from fringecal.rundir import RunDir, package_versions
from fringecal.schemas import validate_table
from fringecal.spheres.dispersion import sighting_dispersion
from fringecal.steps.base import (DataProblem, Settings, Step, Value, black_box_scanners, black_boxes_only,
                                   phase_ripple_document, stores_of)

__all__ = ["Bundle", "load_problem"]

log = logging.getLogger(__name__)


def load_problem(rd: RunDir, reference: str | None, gamma1: float = 1.0, gamma2: float = 1.0):
    """The :class:`~fringecal.calibration.model.BundleProblem` of a run directory's start
    values and control points; one clear error naming the file, line and column."""
    files = [rd.artefact, rd.sensors_initial, rd.control_points, rd.poses_initial]
    missing = [str(f.path) for f in files if not f.exists()]
    if missing:
        raise FileNotFoundError(f"calibration inputs missing: {', '.join(missing)}")
    rig = rd.sensors_initial.load()
    if reference is not None:
        names = [s.name for s in rig.scanners]
        if reference not in names:
            raise ConfigError(f"reference_scanner {reference!r} is not one of the scanners in "
                              f"{rd.sensors_initial.path} ({names})")
        rig = rd.sensors_initial.load(reference)
    return BundleProblem.from_tables(rig, rd.artefact.load(), rd.control_points.load(), rd.poses_initial.load(),
                                     gamma1, gamma2, source=str(rd.control_points.path),
                                     poses_source=str(rd.poses_initial.path))


class Bundle(Step):
    name = "bundle"
    title = "bundle adjustment"
    # the artefact's share of the calibration's covariance, carried by calibration.json
    settings = ("bundle", "reference_scanner", "verification.uncertainty.artefact_u_factor",
                "verification.uncertainty.artefact_temperature_u_c", "verification.uncertainty.artefact_cte_per_c")
    modules = ("fringecal.calibration",)

    def reads(self, rd: RunDir, cfg: Settings, item: str):
        if black_boxes_only(rd):  # black boxes only
            return [rd.sensors_prior, rd.artefact, rd.scanner_links, rd.label_outcomes, rd.acquisition] + \
                [rd.fits_final(m) for m in stores_of(rd, "artefact", black_box=True)]
        boxes = [rd.scanner_links, rd.label_outcomes, rd.acquisition] + \
            [rd.fits_final(m) for m in stores_of(rd, "artefact", black_box=True)] if black_box_scanners(rd) else []
        ripple = phase_ripple_document(rd)  # keyed by value: a cell without one never changes it
        return [rd.artefact, rd.sensors_initial, rd.control_points, rd.poses_initial] + boxes + \
            ([Value("phase ripple of the scanners", ripple)] if ripple else [])

    def writes(self, rd: RunDir, cfg: Settings, item: str):
        if black_boxes_only(rd):
            return [rd.black_boxes, rd.black_boxes_export, rd.bundle_summary]
        boxes = [rd.black_boxes, rd.black_boxes_export] if black_box_scanners(rd) else []
        return [rd.calibration, rd.calibration.xml, rd.sensors_calibrated, rd.poses_calibrated,
                rd.residuals_per_sphere, rd.residuals_per_measurement, rd.residuals_binned, rd.histogram("eps1"),
                rd.histogram("eps2"), rd.bundle_summary, rd.covariance] + boxes

    def run(self, rd: RunDir, cfg: Settings, item: str, **context) -> None:
        b = cfg.bundle
        if black_boxes_only(rd):
            return self.run_black_boxes_only(rd, cfg)
        problem = load_problem(rd, cfg.reference_scanner, b.gamma1, b.gamma2)
        t0, c0 = time.perf_counter(), compile_clock.thread_seconds()
        result, model = choose_sensor_model(problem, b, workers=threads.granted())
        compile_seconds = compile_clock.thread_seconds() - c0
        # the adjustment's own time, as on any later run; the thin-prism check is timed apart
        # (on a first run its kernels' compilation is in both: hence the floor)
        check_seconds = (model.get("prism_wald") or {}).get("seconds", 0.0)
        seconds = max(0.0, time.perf_counter() - t0 - compile_seconds - check_seconds)
        for d in result.diagnostics:
            log.warning("%s: %s", d.kind, d.message)
        log.info("F RMS %.4f -> %.4f mm in %d iterations (start: %s)", result.before.rms_f_mm, result.after.rms_f_mm,
                 result.iterations, result.extra.get("start"))
        log.info("sensor model %s (%s); %s", model["model"], model["chosen_by"], model["residual_pattern"]["message"])
        if "prism_wald" in model:
            log.info("%s", model["prism_wald"]["message"])
        t1 = time.perf_counter()
        bootstrap = bootstrap_calibrations(result, b.bootstrap_draws, b.bootstrap_seed, workers=threads.granted())
        timing = {"bundle_seconds": seconds, "bundle_compile_seconds": compile_seconds,
                  "prism_check_seconds": check_seconds,
                  "bootstrap_draws": b.bootstrap_draws, "bootstrap_seconds": time.perf_counter() - t1}
        arrays = covariance_arrays(result)
        if len(bootstrap):
            arrays["bootstrap_params"] = np.asarray(bootstrap, float)
        jackknife = None
        if b.jackknife:
            jackknife = jackknife_calibrations(result, seed=b.bootstrap_seed, workers=threads.granted())
            timing["jackknife_seconds"] = jackknife.seconds
            if jackknife.usable:
                arrays["jackknife_params"] = jackknife.params
                arrays["jackknife_noise_params"] = jackknife.noise_params
                arrays["jackknife_left_out"] = np.array(jackknife.left_out, dtype=str)
            else:
                log.warning("jackknife: %d replicas of %d measurements (at least %d needed): the lengths get no "
                            "model-error term", len(jackknife.left_out), len(result.problem.measurements),
                            MIN_REPLICAS)
        u = cfg.verification.uncertainty
        covariances = parameter_covariances(arrays, abs(u.artefact_cte_per_c) * u.artefact_temperature_u_c,
                                            u.artefact_u_factor)
        boxes = black_box_adjustment(rd, result, cfg.reference_scanner, b.black_box_scale)
        doc = {**summary(result, b.volume_diagonal_mm), **timing, "sensor_model": model}
        if jackknife is not None:
            doc["jackknife"] = jackknife.to_dict()
        dispersion = sighting_dispersion(result.problem, result.rig)
        doc["sighting_dispersion"] = {s: d.to_dict() for s, d in dispersion.items()}
        if dispersion:
            log.info("sphere centres' scatter between spheres / their fits' u (kappa): %s",
                     ", ".join(f"{s} {d.kappa:.2f}" for s, d in dispersion.items()))
        if boxes is not None:
            doc["black_boxes"] = {"s0": boxes.s0, "dof": boxes.dof,
                                  "rms_mm": {s: v.rms_mm for s, v in boxes.scanners.items()},
                                  "modelled_shift_max_sigma": boxes.joint["max_shift_sigma"]}
            result = with_black_box_update(result, boxes)
        write_outputs(rd, result, doc, arrays, covariances, self.provenance(rd, cfg, item),
                      None if boxes is None else boxes.to_dict(), phase_ripple_document(rd))
        if boxes is None:
            rd.black_boxes.remove()
            rd.black_boxes_export.remove()
        else:
            rd.black_boxes.save({**boxes.to_dict(), "joint_covariance": joint_covariance(result, boxes)})
            rd.black_boxes_export.save(export_table(boxes.scanners.values()))

    def run_black_boxes_only(self, rd: RunDir, cfg: Settings) -> None:
        """A rig of black boxes only: every transform (the reference's fixed) and every
        artefact pose adjusted at once (:func:`fringecal.calibration.blackbox.adjust_black_boxes`
        without a prior); ``bundle_summary.json`` says so (``black_boxes_only``)."""
        t0 = time.perf_counter()
        boxes = black_box_adjustment(rd, None, cfg.reference_scanner, cfg.bundle.black_box_scale)
        residuals = boxes.residuals[["dx_mm", "dy_mm", "dz_mm"]].to_numpy(float)
        rms = float(np.sqrt(np.mean(np.sum(residuals**2, axis=1)))) if len(residuals) else float("nan")
        artefact = rd.artefact.load()
        placed = np.concatenate([Frame.from_params([getattr(r, c) for c in POSE_COLUMNS]).to_world(artefact.centres)
                                 for r in boxes.poses.itertuples()])
        diagonal = cfg.bundle.volume_diagonal_mm or float(np.linalg.norm(placed.max(axis=0) - placed.min(axis=0)))
        doc = {"black_boxes_only": True, "converged": True, "n_control_points": int(len(residuals)),
               "volume_diagonal_mm": diagonal,
               "volume_diagonal_source": "given (bundle.volume_diagonal_mm)" if cfg.bundle.volume_diagonal_mm
               else "bounding box of the artefact's sphere centres at the adjusted poses",
               "n_centres": int(len(residuals)), "rms_centre_mm": rms, "bundle_seconds": time.perf_counter() - t0,
               "black_boxes": {"s0": boxes.s0, "dof": boxes.dof,
                               "rms_mm": {s: v.rms_mm for s, v in boxes.scanners.items()}}}
        rd.black_boxes.save({**boxes.to_dict(), "joint_covariance": joint_covariance(None, boxes)})
        rd.black_boxes_export.save(export_table(boxes.scanners.values()))
        rd.bundle_summary.save(doc)

    def provenance(self, rd: RunDir, cfg: Settings, item: str) -> dict:
        """What the calibration was computed from: its input files' digests, its
        settings (and their digest), the package versions."""
        settings = cfg.keyed()
        return {"inputs": {f.rel: digest_path(f.path) for f in self.reads(rd, cfg, item) if not isinstance(f, Value)},
                "settings": settings, "settings_digest": digest_value(settings), "versions": package_versions()}


def black_box_adjustment(rd: RunDir, result, reference: str, scale: bool):
    """Each black-box scanner's transform (and scale) with every artefact pose, on the
    poses the bundle adjustment found with their covariance (``result``; None: a rig of
    black boxes only, the reference among them)
    (:func:`fringecal.calibration.blackbox.adjust_black_boxes`); None without black boxes."""
    boxes = black_box_scanners(rd)
    if not boxes:
        return None
    links = {str(r.scanner): Frame.from_params([getattr(r, c) for c in POSE_COLUMNS])
             for r in rd.scanner_links.load().itertuples()}
    swapped = inconsistent_views(rd.label_outcomes.load(), boxes)
    if len(swapped):
        table = rd.acquisition.load()
        sources = {(str(r.pose), str(r.scanner)): str(r.source) for r in table.itertuples()}
        first = swapped.iloc[0]
        more = f" (and {len(swapped) - 1} more view(s): {rd.label_outcomes.path})" if len(swapped) > 1 else ""
        raise DataProblem(f"{sources.get((str(first.measurement), str(first.scanner)), first.scanner)}: the cloud of "
                          f"black-box scanner {first.scanner} in measurement {first.measurement} does not fit where "
                          f"the other scanners put the artefact; a cloud of another scanner (a swapped file?): "
                          f"{first.message}{more}")
    unlinked = [s for s in boxes if s not in links]
    if unlinked:
        raise DataProblem(f"{rd.scanner_links.path}: black-box scanner(s) {', '.join(unlinked)} not linked to the "
                          f"reference scanner {reference}: each needs three labelled spheres in a measurement "
                          f"another linked scanner saw (why spheres were not labelled: {rd.label_outcomes.path})")
    finals = [rd.fits_final(m).load() for m in stores_of(rd, "artefact", black_box=True)]
    fits = pd.concat([f for f in finals if len(f)], ignore_index=True)
    if result is None:
        return adjust_black_boxes(fits, rd.artefact.load(), reference, {s: (links[s], 1.0) for s in boxes},
                                  scale=scale)
    lay = result.layout
    prior = ModelPrior(result.x, result.uncertainty.covariance, lay.pose_index, result.poses,
                       result.problem.measurements, lay.names)
    return adjust_black_boxes(fits, result.problem.artefact, reference, {s: (links[s], 1.0) for s in boxes},
                              scale=scale, prior=prior)


def with_black_box_update(result, boxes):
    """The bundle's result with its sensors and poses as the joint adjustment with the
    black boxes moved them (:func:`fringecal.calibration.blackbox._conditioned`): the
    calibration written is the one adjustment's. Its covariance arrays, bootstrap and
    residual tables stay the bundle's own."""
    lay = result.layout
    x = boxes.joint["x"]
    sp, po = lay.unpack(x, result.rig.params, result.poses)
    C = boxes.joint["covariance"][:lay.n, :lay.n]
    std = np.sqrt(np.clip(np.diag(C), 0, None))
    std_s = np.zeros_like(sp)
    free = lay.sensor_index >= 0
    std_s[free] = std[lay.sensor_index[free]]
    return replace(result, x=x, rig=result.rig.with_params(sp, uncertainty=std_s), poses=po)


def joint_covariance(result, boxes) -> dict:
    """The covariance of every sensor parameter (n_sensors * 14, rig order, fixed ones
    zero) and every black box's 7 parameters together, from the joint adjustment
    (what a length measured by a modelled and a black-box scanner needs); ``result``
    None: a rig of black boxes only (no sensor parameters)."""
    idx = np.zeros(0, int) if result is None else result.layout.sensor_index.reshape(-1)
    n_s = idx.size
    names = list(boxes.scanners)
    C = boxes.joint["covariance"]  # [bundle's free parameters, black boxes' free parameters]
    pos = np.full(n_s + 7 * len(names), -1)
    pos[:n_s] = idx
    for b, name in enumerate(names):
        free_idx, free_pos = boxes.joint["free"][name]
        pos[n_s + 7 * b + free_idx] = boxes.joint["n_model"] + free_pos
    out = np.zeros((pos.size, pos.size))
    ok = pos >= 0
    out[np.ix_(ok, ok)] = C[np.ix_(pos[ok], pos[ok])]
    return {"n_sensor_parameters": int(n_s), "black_boxes": names, "matrix": out.tolist()}


def write_outputs(rd: RunDir, result, doc: dict, arrays: dict, covariances, provenance: dict,
                  black_boxes: dict | None = None, phase_ripple: dict | None = None) -> list:
    """Write the calibration of ``result`` (a :class:`~fringecal.calibration.bundle.BundleResult`)
    into ``rd``, all or nothing: ``calibration.json`` (with ``covariances``, the
    :class:`~fringecal.calibration.propagation.ParameterCovariances`, ``provenance`` and
    each sensor's observed region) and its XML twin, the parameter, pose and residual
    tables, the residual histograms,
    ``bundle_summary.json`` (``doc``) and the covariance ``arrays``. Every file is first
    written under a temporary name and renamed into place only when all are complete."""
    meta = {"after": doc["after"], "before": doc["before"], "one_part_in_1p96_sigma": doc["one_part_in_1p96_sigma"],
            "volume_diagonal_mm": doc["volume_diagonal_mm"], "n_control_points": doc["n_control_points"],
            "iterations": doc["iterations"], "converged": doc["converged"],
            "sighting_dispersion": doc.get("sighting_dispersion") or {}}
    model = doc.get("sensor_model")
    per_sphere, per_meas = residual_tables(result)
    regions = observed_regions(result.problem)
    log.info("image plane observed by the control points (share of each format inside their hull): %s",
             ", ".join(f"{name} {100 * r.fraction:.0f} %" for name, r in regions.items()))
    small = too_small(regions)
    if small:
        log.warning("the control points covered less than %.0f %% of the image of %s: the calibration extrapolates "
                    "over the rest of it (more artefact poses, or poses filling that image, would extend it)",
                    100 * MIN_FRACTION, ", ".join(f"{n} ({100 * r.fraction:.0f} %)" for n, r in small.items()))
    tables = {rd.sensors_calibrated: result.sensors_frame(), rd.poses_calibrated: result.poses_frame(),
              rd.residuals_per_sphere: per_sphere, rd.residuals_per_measurement: per_meas,
              rd.residuals_binned: binned_residuals(result)}
    tables = {f: validate_table(df, f.schema, str(f.path)) for f, df in tables.items()}
    figures = dict(zip((rd.histogram("eps1"), rd.histogram("eps2")),
                       residual_histograms_png(result.residuals_start, result.residuals)))
    npz = io.BytesIO()
    np.savez(npz, **arrays)
    files = [rd.calibration, rd.calibration.xml, *tables, *figures, rd.bundle_summary, rd.covariance]
    with atomic_paths([f.path for f in files]) as tmps:
        tmp = dict(zip([f.rel for f in files], tmps))
        replicas = {kind: arrays[f"{kind}_params"] for kind in REPLICA_KINDS if f"{kind}_params" in arrays}
        calibration = rd.calibration.document(
            result.rig, meta, covariances=covariances, provenance=provenance, sensor_model=model,
            replicas=replicas_document(replicas, arrays.get("jackknife_left_out")), phase_ripple=phase_ripple,
            observed_regions=regions, black_boxes=black_boxes)
        rd.calibration.write(calibration, tmp[rd.calibration.rel], tmp[rd.calibration.xml.rel])
        for f, df in tables.items():
            df.to_csv(tmp[f.rel], index=False, float_format="%.10g")
        for f, png in figures.items():
            tmp[f.rel].write_bytes(png)
        tmp[rd.bundle_summary.rel].write_text(json.dumps(doc, indent=1, default=float) + "\n", encoding="utf-8")
        tmp[rd.covariance.rel].write_bytes(npz.getvalue())
    return files
