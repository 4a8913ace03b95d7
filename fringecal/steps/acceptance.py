"""The acceptance test per VDI/VDE 2634 parts 2 and 3
(:func:`fringecal.acceptance.document.acceptance_document`): every sphere, dumbbell and
flat position measured with the calibrated sensors from its stores alone (a black-box
scanner's in its clouds, carried by its calibrated transform and scale:
:mod:`fringecal.acceptance.cloud`), the ball-bar's lengths of the verification as E,
each quality parameter against its limit with its uncertainty and the ISO 14253-1
verdict.

Writes ``acceptance.json`` (:func:`fringecal.acceptance.evaluate.certificate`, with per
object the share of its fits' pixels outside the calibration's observed region:
:mod:`fringecal.acceptance.observed`; one warning names the objects with any) and
``tables/acceptance_values.csv``. A run with neither acceptance objects nor a
verified ball-bar, or with ``acceptance.enabled: false``, has no acceptance test:
both files are then absent.
"""

from __future__ import annotations

import logging

from fringecal.acceptance.document import acceptance_document
from fringecal.acceptance.observed import partly_outside
from fringecal.acceptance.standards import AcceptanceStandards
from fringecal.calibration.file import read_calibration
from fringecal.rundir import RunDir
from fringecal.steps.base import Settings, Step, black_box_scanners, black_boxes_only, stores_of_kind
from fringecal.steps.verify import fit_factors

__all__ = ["Acceptance", "acceptance_stores", "ACCEPTANCE_KINDS"]

log = logging.getLogger(__name__)

#: Acquisition kinds of the acceptance objects.
ACCEPTANCE_KINDS = ("sphere", "dumbbell", "flat")


def acceptance_stores(rd: RunDir) -> dict[str, dict[str, dict[str, str]]]:
    """kind -> position -> scanner -> store path of the run's acceptance measurements
    (a black-box scanner's stores are its clouds)."""
    table = rd.acquisition.load()
    out: dict[str, dict[str, dict[str, str]]] = {k: {} for k in ACCEPTANCE_KINDS}
    for r in table[table["kind"].isin(ACCEPTANCE_KINDS)].itertuples():
        out[r.kind].setdefault(str(r.pose), {})[str(r.scanner)] = str(rd.store(r.measurement).path)
    return out


def _positions(rd: RunDir) -> list[dict]:
    """Where each position was (simulated runs: the planned placement), for the report."""
    if not rd.truth.acceptance_positions.exists():
        return []
    table = rd.truth.acceptance_positions.load()
    cols = [c for c in ("measurement", "test", "scanner", "tx_mm", "ty_mm", "tz_mm", "omega_rad", "phi_rad",
                        "kappa_rad") if c in table.columns]
    return table[cols].to_dict("records")


class Acceptance(Step):
    name = "acceptance"
    title = "acceptance test"
    settings = ("acceptance", "extraction.rejection", "verification.uncertainty")

    def reads(self, rd: RunDir, cfg: Settings, item: str):
        stores = [rd.store(m) for kind in ACCEPTANCE_KINDS for m in stores_of_kind(rd, kind)]
        common = [rd.verification, rd.acceptance_standards, rd.acquisition, rd.truth.acceptance_positions] + stores
        boxes = [rd.black_boxes] if black_box_scanners(rd) else []
        if black_boxes_only(rd):  # black boxes only: no sensors
            return [rd.sensors_prior] + common + boxes
        return [rd.calibration, rd.covariance, rd.bundle_summary] + common + boxes

    def writes(self, rd: RunDir, cfg: Settings, item: str):
        return [rd.acceptance, rd.acceptance_values]

    def run(self, rd: RunDir, cfg: Settings, item: str, **context) -> None:
        modelled = not black_boxes_only(rd)
        stores = acceptance_stores(rd)
        standards = (AcceptanceStandards(**rd.acceptance_standards.load()) if rd.acceptance_standards.exists()
                     else AcceptanceStandards())
        verified = rd.verification.exists()
        if not cfg.acceptance.enabled or not (verified or any(stores.values())):
            rd.acceptance.remove()
            rd.acceptance_values.remove()
            log.warning("no acceptance test: %s", "acceptance.enabled is false" if not cfg.acceptance.enabled
                        else "no acceptance objects and no verified ball-bar")
            return
        cal = read_calibration(rd.calibration.path) if modelled else None  # the rig and its observed regions
        doc, values = acceptance_document(cal.rig if modelled else None, standards, cfg.acceptance,
                                          cfg.extraction.rejection, cfg.verification.uncertainty,
                                          rd.covariance.load() if modelled else None, stores,
                                          rd.verification.load() if verified else None, _positions(rd),
                                          rd.black_boxes.load() if black_box_scanners(rd) else None,
                                          fit_factors(rd.bundle_summary.load(), cfg.verification) if modelled else None,
                                          cal.observed_regions if modelled else None)
        outside = partly_outside(doc["observed_region"])
        if outside:
            log.warning("acceptance objects measured partly where the calibration extrapolates, outside the region "
                        "of the images its control points covered (share of the fits' pixels): %s; per position in "
                        "%s (observed_region) and the report's acceptance values", "; ".join(outside),
                        rd.acceptance.rel)
        for f in doc["failures"]:
            log.warning("acceptance %s position %s, scanner %s: %s", f["test"], f["position"], f["scanner"],
                        f["reason"])
        rd.acceptance_values.save(values)
        rd.acceptance.save(doc)
