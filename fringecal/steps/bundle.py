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

import numpy as np

from fringecal import compile_clock, threads
from fringecal.atomic import atomic_paths
from fringecal.calibration.bootstrap import bootstrap_calibrations
from fringecal.calibration.models import choose_sensor_model
from fringecal.calibration.file import rig_to_dict, xml_text
from fringecal.calibration.model import BundleProblem
from fringecal.calibration.propagation import parameter_covariances
from fringecal.calibration.results import binned_residuals, covariance_arrays, residual_tables, summary
from fringecal.config import ConfigError
from fringecal.digests import digest_path, digest_value
from fringecal.report.plotting import residual_histograms_png
from fringecal.rundir import RunDir, package_versions
from fringecal.schemas import validate_table
from fringecal.steps.base import Settings, Step

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
        return [rd.artefact, rd.sensors_initial, rd.control_points, rd.poses_initial]

    def writes(self, rd: RunDir, cfg: Settings, item: str):
        return [rd.calibration, rd.calibration.xml, rd.sensors_calibrated, rd.poses_calibrated,
                rd.residuals_per_sphere, rd.residuals_per_measurement, rd.residuals_binned, rd.histogram("eps1"),
                rd.histogram("eps2"), rd.bundle_summary, rd.covariance]

    def run(self, rd: RunDir, cfg: Settings, item: str, **context) -> None:
        b = cfg.bundle
        problem = load_problem(rd, cfg.reference_scanner, b.gamma1, b.gamma2)
        t0, c0 = time.perf_counter(), compile_clock.thread_seconds()
        result, model = choose_sensor_model(problem, b)
        compile_seconds = compile_clock.thread_seconds() - c0
        seconds = time.perf_counter() - t0 - compile_seconds  # the adjustment's own time, as on any later run
        for d in result.diagnostics:
            log.warning("%s: %s", d.kind, d.message)
        log.info("F RMS %.4f -> %.4f mm in %d iterations (start: %s)", result.before.rms_f_mm, result.after.rms_f_mm,
                 result.iterations, result.extra.get("start"))
        log.info("sensor model %s (%s); %s", model["model"], model["chosen_by"], model["residual_pattern"]["message"])
        t1 = time.perf_counter()
        bootstrap = bootstrap_calibrations(result, b.bootstrap_draws, b.bootstrap_seed, workers=threads.granted())
        timing = {"bundle_seconds": seconds, "bundle_compile_seconds": compile_seconds,
                  "bootstrap_draws": b.bootstrap_draws, "bootstrap_seconds": time.perf_counter() - t1}
        arrays = covariance_arrays(result)
        if len(bootstrap):
            arrays["bootstrap_params"] = np.asarray(bootstrap, float)
        u = cfg.verification.uncertainty
        covariances = parameter_covariances(arrays, abs(u.artefact_cte_per_c) * u.artefact_temperature_u_c,
                                            u.artefact_u_factor)
        write_outputs(rd, result, {**summary(result, b.volume_diagonal_mm), **timing, "sensor_model": model},
                      arrays, covariances, self.provenance(rd, cfg, item))

    def provenance(self, rd: RunDir, cfg: Settings, item: str) -> dict:
        """What the calibration was computed from: its input files' digests, its
        settings (and their digest), the package versions."""
        settings = cfg.keyed()
        return {"inputs": {f.rel: digest_path(f.path) for f in self.reads(rd, cfg, item)},
                "settings": settings, "settings_digest": digest_value(settings), "versions": package_versions()}


def write_outputs(rd: RunDir, result, doc: dict, arrays: dict, covariances, provenance: dict) -> list:
    """Write the calibration of ``result`` (a :class:`~fringecal.calibration.bundle.BundleResult`)
    into ``rd``, all or nothing: ``calibration.json`` (with ``covariances``, the
    :class:`~fringecal.calibration.propagation.ParameterCovariances`, and ``provenance``)
    and its XML twin, the parameter, pose and residual tables, the residual histograms,
    ``bundle_summary.json`` (``doc``) and the covariance ``arrays``. Every file is first
    written under a temporary name and renamed into place only when all are complete."""
    meta = {"after": doc["after"], "before": doc["before"], "one_part_in_1p96_sigma": doc["one_part_in_1p96_sigma"],
            "volume_diagonal_mm": doc["volume_diagonal_mm"], "n_control_points": doc["n_control_points"],
            "iterations": doc["iterations"], "converged": doc["converged"]}
    model = doc.get("sensor_model")
    per_sphere, per_meas = residual_tables(result)
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
        tmp[rd.calibration.rel].write_text(json.dumps(rig_to_dict(result.rig, meta, covariances, provenance, model),
                                                      indent=2) + "\n")
        tmp[rd.calibration.xml.rel].write_text(xml_text(result.rig, meta))
        for f, df in tables.items():
            df.to_csv(tmp[f.rel], index=False, float_format="%.10g")
        for f, png in figures.items():
            tmp[f.rel].write_bytes(png)
        tmp[rd.bundle_summary.rel].write_text(json.dumps(doc, indent=1, default=float) + "\n", encoding="utf-8")
        tmp[rd.covariance.rel].write_bytes(npz.getvalue())
    return files
