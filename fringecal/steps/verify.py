"""Ball-bar verification (thesis 6.9.3, VDI/VDE 2634;
:func:`fringecal.verification.verify.verify_ballbar`): measure the bar in every
position's stores with the calibrated sensors, which sphere each scanner sees found
from the data alone, and compare every measured length with the certified one.

Writes ``verification.json`` (lengths, errors, pass/fail against the MPE, the GUM
statement, positions that could not be measured) and the measured centres. A run
without ball-bar measurements is not verified: both files are then absent.
"""

from __future__ import annotations

import logging

from fringecal.calibration.file import read_calibration
from fringecal.rundir import RunDir
from fringecal.steps.base import Settings, Step, black_box_scanners, black_boxes_only, stores_of_kind
from fringecal.verification.black_box import verify_with_black_boxes
from fringecal.verification.verify import verify_ballbar

__all__ = ["Verify", "ballbar_stores"]

log = logging.getLogger(__name__)


def fit_factors(bundle_summary: dict, settings) -> dict:
    """scanner -> ``max(1, kappa)`` of the bundle step's ``sighting_dispersion``, the
    factor on its sphere fits' uncertainty; empty when ``uncertainty.sphere_scatter`` is
    off or the summary has none."""
    if not settings.uncertainty.sphere_scatter:
        return {}
    return {s: max(1.0, float(d["kappa"])) for s, d in (bundle_summary.get("sighting_dispersion") or {}).items()}


def ballbar_stores(rd: RunDir) -> dict[str, dict[str, str]]:
    """position -> scanner -> store path of the run's ball-bar measurements."""
    table = rd.acquisition.load()
    out: dict[str, dict[str, str]] = {}
    for r in table[table["kind"] == "ballbar"].itertuples():
        out.setdefault(str(r.pose), {})[str(r.scanner)] = str(rd.store(r.measurement).path)
    return out


class Verify(Step):
    name = "verify"
    title = "verification"
    settings = ("verification", "extraction.rejection", "control_points.max_incidence_deg",
                "control_points.pixel_integration_px")

    def reads(self, rd: RunDir, cfg: Settings, item: str):
        stores = [rd.store(m) for m in stores_of_kind(rd, "ballbar")]
        boxes = [rd.black_boxes, rd.sensors_prior] if black_box_scanners(rd) else []
        if black_boxes_only(rd):  # black boxes only
            return [rd.ballbar, rd.bundle_summary, rd.acquisition] + stores + boxes
        return [rd.calibration, rd.covariance, rd.crossval, rd.crossval_halves, rd.ballbar, rd.bundle_summary,
                rd.acquisition] + stores + boxes

    def writes(self, rd: RunDir, cfg: Settings, item: str):
        return [rd.verification, rd.ballbar_centres]

    def run(self, rd: RunDir, cfg: Settings, item: str, **context) -> None:
        if not stores_of_kind(rd, "ballbar") or not rd.ballbar.exists():
            rd.verification.remove()
            rd.ballbar_centres.remove()
            log.warning("no ball-bar measurements: the calibration is not verified")
            return
        diagonal = rd.bundle_summary.load()["volume_diagonal_mm"]
        if black_box_scanners(rd):
            self.run_black_boxes(rd, cfg, diagonal)
            return
        halves = rd.crossval_halves.load() if rd.crossval_halves.exists() else None
        points_verdict = rd.crossval.load().get("verdict") if rd.crossval.exists() else None
        cal = read_calibration(rd.calibration.path)  # the rig and its observed regions, in one read
        centres, failures, result, budget = verify_ballbar(ballbar_stores(rd), cal.rig, rd.ballbar.load(),
                                                           cfg.extraction.rejection, cfg.verification, diagonal,
                                                           rd.covariance.load(), halves, points_verdict,
                                                           fit_factors(rd.bundle_summary.load(), cfg.verification),
                                                           cal.observed_regions)
        outside = {p: e for p, e in (result.observed_region or {}).items() if e["outside"]}
        if outside:
            log.warning("ball-bar measured partly where the calibration extrapolates, outside the region of the "
                        "images its control points covered (share of the sphere fits' pixels): %s",
                        ", ".join(f"{p} {100 * e['fraction']:.0f} %" for p, e in outside.items()))
        for f in failures.itertuples():
            log.warning("ball-bar position %s, scanner %s: %s", f.position, f.scanner, f.reason)
        rd.ballbar_centres.save(centres)
        if budget and budget["not_covered"]:
            log.warning("ball-bar length error beyond its expanded uncertainty at %s: an error source the "
                        "uncertainty budget does not hold", ", ".join(budget["not_covered"]))
        if budget and budget.get("monte_carlo") and not budget["monte_carlo"]["all_agree"]:
            for line in budget["monte_carlo"]["disagreements"]:
                log.warning("Monte Carlo (JCGM 101 clause 8) does not confirm the linear length uncertainty at %s",
                            line)
        rd.verification.save({"calibrated": result.to_dict(), "uncertainty": budget,
                              "failures": failures.to_dict("records"),
                              "recorded_by": {p: list(s) for p, s in ballbar_stores(rd).items()}})

    def run_black_boxes(self, rd: RunDir, cfg: Settings, diagonal: float) -> None:
        """Modelled and black-box scanners together (:mod:`fringecal.verification.black_box`)."""
        centres, failures, result, budget = verify_with_black_boxes(
            ballbar_stores(rd), None if black_boxes_only(rd) else rd.calibration.load(), rd.black_boxes.load(),
            rd.ballbar.load(),
            cfg.extraction.rejection, cfg.verification, diagonal, cfg.control_points.max_incidence_deg,
            cfg.control_points.pixel_integration_px)
        for f in failures.itertuples():
            log.warning("ball-bar position %s, scanner %s: %s", f.position, f.scanner or "-", f.reason)
        rd.ballbar_centres.save(centres)
        rd.verification.save({"calibrated": result, "uncertainty": budget, "failures": failures.to_dict("records"),
                              "recorded_by": {p: list(s) for p, s in ballbar_stores(rd).items()}})
