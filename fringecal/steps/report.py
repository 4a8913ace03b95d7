"""The report: one self-contained HTML page of the run for the customer
(:mod:`fringecal.report`), built from the run directory's files only.

What describes one execution of the flow rather than its results -- the step
timings, when it ran and which command started it -- is passed as context: it is
shown on the page but does not decide whether the page is current.
"""

from __future__ import annotations

from fringecal.report import write_report
from fringecal.rundir import RunDir
from fringecal.steps.base import Settings, Step

__all__ = ["Report", "report_inputs"]


def report_inputs(rd: RunDir) -> list:
    """Every file the report shows (those absent give the page a note instead)."""
    return [rd.manifest, rd.artefact, rd.rods, rd.ballbar, rd.acquisition, rd.hexapod_moves,
            rd.label_outcomes, rd.scanner_links, rd.dlt, rd.calibration, rd.bundle_summary,
            rd.residuals_per_sphere, rd.residuals_per_measurement, rd.residuals_binned, rd.histogram("eps1"),
            rd.histogram("eps2"), rd.control_points, rd.poses_calibrated,
            rd.crossval, rd.verification, rd.ballbar_centres, rd.acceptance, rd.acceptance_standards,
            rd.evaluation, rd.black_boxes]


class Report(Step):
    name = "report"
    title = "report"
    modules = ("fringecal.report",)

    def reads(self, rd: RunDir, cfg: Settings, item: str):
        return report_inputs(rd)

    def writes(self, rd: RunDir, cfg: Settings, item: str):
        return [rd.report]

    def run(self, rd: RunDir, cfg: Settings, item: str, timings: dict | None = None, execution: dict | None = None,
            compile_seconds: dict | None = None, **context) -> None:
        write_report(rd, timings, execution, compile_seconds)
