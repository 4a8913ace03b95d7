"""Bundle adjustment: every sensor and one artefact pose per measurement refined from
the control points (thesis 2.3.7, 6.4-6.5), with uncertainties and a diagnosis of
degenerate set-ups. Writes the calibration (JSON and XML), its tables, the residual
histograms and ``bundle_summary.json``, all or nothing.
"""

from __future__ import annotations

import logging
import time

from .. import compile_clock
from ..rundir import RunDir
from .base import Settings, Step

__all__ = ["Bundle", "load_problem"]

log = logging.getLogger(__name__)


def load_problem(rd: RunDir, reference: str | None, gamma1: float = 1.0, gamma2: float = 1.0):
    """The :class:`~fringecal.calibration.BundleProblem` of a run directory's start
    values and control points; one clear error naming the file, line and column."""
    from ..calibration import BundleProblem
    from ..config import ConfigError

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
    modules = ("fringecal.calibration", "fringecal.pipeline.ballbar_uncertainty")

    def reads(self, rd: RunDir, cfg: Settings, item: str):
        return [rd.artefact, rd.sensors_initial, rd.control_points, rd.poses_initial]

    def writes(self, rd: RunDir, cfg: Settings, item: str):
        return [rd.calibration, rd.calibration.xml, rd.sensors_calibrated, rd.poses_calibrated,
                rd.residuals_per_sphere, rd.residuals_per_measurement, rd.histogram("eps1"), rd.histogram("eps2"),
                rd.bundle_summary, rd.covariance]

    def run(self, rd: RunDir, cfg: Settings, item: str, **context) -> None:
        from ..calibration import bundle_adjust
        from ..calibration.bootstrap import bootstrap_calibrations
        from ..calibration.results import write_outputs

        b = cfg.bundle
        problem = load_problem(rd, cfg.reference_scanner, b.gamma1, b.gamma2)
        t0, c0 = time.perf_counter(), compile_clock.thread_seconds()
        result = bundle_adjust(problem, b.options())
        compile_seconds = compile_clock.thread_seconds() - c0
        seconds = time.perf_counter() - t0 - compile_seconds  # the adjustment's own time, as on any later run
        for d in result.diagnostics:
            log.warning("%s: %s", d.kind, d.message)
        log.info("F RMS %.4f -> %.4f mm in %d iterations (start: %s)", result.before.rms_f_mm, result.after.rms_f_mm,
                 result.iterations, result.extra.get("start"))
        t1 = time.perf_counter()
        bootstrap = bootstrap_calibrations(result, b.bootstrap_draws, b.bootstrap_seed)
        timing = {"bundle_seconds": seconds, "bundle_compile_seconds": compile_seconds,
                  "bootstrap_draws": b.bootstrap_draws, "bootstrap_seconds": time.perf_counter() - t1}
        write_outputs(result, rd, b.volume_diagonal_mm, timing, covariances=self._covariances(cfg),
                      provenance=self.provenance(rd, cfg, item), bootstrap=bootstrap)

    @staticmethod
    def _covariances(cfg: Settings):
        from ..pipeline.ballbar_uncertainty import parameter_covariances

        u = cfg.verification.uncertainty
        u_scale = abs(u.artefact_cte_per_c) * u.artefact_temperature_u_c
        return lambda arrays: parameter_covariances(arrays, u_scale, u.artefact_u_factor)

    def provenance(self, rd: RunDir, cfg: Settings, item: str) -> dict:
        """What the calibration was computed from: its input files' digests, its
        settings (and their digest), the package versions."""
        from ..digests import digest_path, digest_value
        from ..rundir import package_versions

        settings = cfg.keyed()
        return {"inputs": {f.rel: digest_path(f.path) for f in self.reads(rd, cfg, item)},
                "settings": settings, "settings_digest": digest_value(settings), "versions": package_versions()}
