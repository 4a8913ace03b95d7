"""Ball-bar verification (thesis 6.9.3, VDI/VDE 2634): measure the bar in every
position's stores with the calibrated sensors, which sphere each scanner sees found
from the data alone, and compare every measured length with the certified one.

Writes ``verification.json`` (lengths, errors, pass/fail against the MPE, the GUM
statement, positions that could not be measured) and the measured centres. A run
without ball-bar measurements is not verified: both files are then absent.
"""

from __future__ import annotations

import logging

from fringecal.rundir import RunDir
from fringecal.spheres.robust import RejectionConfig
from fringecal.steps.base import Settings, Step, stores_of_kind
from fringecal.verification.lengths import ballbar_lengths, evaluate_ballbar
from fringecal.verification.measure import measure_positions
from fringecal.verification.uncertainty import ballbar_uncertainty

__all__ = ["Verify", "ballbar_stores", "measure_ballbar"]

log = logging.getLogger(__name__)


def ballbar_stores(rd: RunDir) -> dict[str, dict[str, str]]:
    """position -> scanner -> store path of the run's ball-bar measurements."""
    table = rd.acquisition.load()
    out: dict[str, dict[str, str]] = {}
    for r in table[table["kind"] == "ballbar"].itertuples():
        out.setdefault(str(r.pose), {})[str(r.scanner)] = str(rd.store(r.measurement).path)
    return out


def measure_ballbar(rd: RunDir, rig, rejection: dict, verification, diagonal_mm: float, covariance=None,
                    halves=None, points_verdict=None):
    """Centres, failures and the evaluated lengths of the run's ball-bar with ``rig``;
    with ``covariance`` (the run's ``calibration_covariance.npz`` arrays) also every
    length's uncertainty budget (:func:`fringecal.verification.uncertainty.ballbar_uncertainty`),
    else None in its place."""

    bar = rd.ballbar.load()
    stores = ballbar_stores(rd)
    centres, failures, pixels = measure_positions(stores, rig, bar, RejectionConfig(**rejection), pixels=True)
    lengths = ballbar_lengths(centres, "ball-bar centres")
    reference_length = float(((bar.centres[1] - bar.centres[0]) ** 2).sum() ** 0.5)
    budget = None
    if covariance is not None and len(lengths):
        budget = ballbar_uncertainty(centres, pixels, stores, rig, lengths, reference_length, covariance,
                                     verification.uncertainty, verification.mpe_mm,
                                     verification.certificate_u_mm / verification.certificate_k, bar.ids[:2],
                                     halves=halves, points_verdict=points_verdict)
        # the lengths corrected for the calibration's bias (bootstrap), when it was estimated
        lengths = lengths.assign(length_mm=[e["length_mm"] for e in budget["lengths"]])
    result = evaluate_ballbar(lengths.length_mm, reference_length, lengths.measurement, verification.mpe_mm,
                              diagonal_mm, verification.certificate_u_mm, verification.certificate_k,
                              verification.coverage_factor)
    return centres, failures, result, budget


class Verify(Step):
    name = "verify"
    title = "verification"
    settings = ("verification", "extraction.rejection")
    modules = ("fringecal.verification.measure", "fringecal.verification.lengths")

    def reads(self, rd: RunDir, cfg: Settings, item: str):
        stores = [rd.store(m) for m in stores_of_kind(rd, "ballbar")]
        return [rd.calibration, rd.covariance, rd.crossval, rd.crossval_halves, rd.ballbar, rd.bundle_summary,
                rd.acquisition] + stores

    def writes(self, rd: RunDir, cfg: Settings, item: str):
        return [rd.verification, rd.ballbar_centres]

    def run(self, rd: RunDir, cfg: Settings, item: str, **context) -> None:
        if not stores_of_kind(rd, "ballbar") or not rd.ballbar.exists():
            rd.verification.remove()
            rd.ballbar_centres.remove()
            log.warning("no ball-bar measurements: the calibration is not verified")
            return
        diagonal = rd.bundle_summary.load()["volume_diagonal_mm"]
        halves = rd.crossval_halves.load() if rd.crossval_halves.exists() else None
        points_verdict = rd.crossval.load().get("verdict") if rd.crossval.exists() else None
        centres, failures, result, budget = measure_ballbar(rd, rd.calibration.load(), cfg.extraction.rejection,
                                                            cfg.verification, diagonal, rd.covariance.load(),
                                                            halves, points_verdict)
        for f in failures.itertuples():
            log.warning("ball-bar position %s, scanner %s: %s", f.position, f.scanner, f.reason)
        rd.ballbar_centres.save(centres)
        if budget and budget["not_covered"]:
            log.warning("ball-bar length error beyond its expanded uncertainty at %s: an error source the "
                        "uncertainty budget does not hold", ", ".join(budget["not_covered"]))
        rd.verification.save({"calibrated": result.to_dict(), "uncertainty": budget,
                              "failures": failures.to_dict("records"),
                              "recorded_by": {p: list(s) for p, s in ballbar_stores(rd).items()}})
