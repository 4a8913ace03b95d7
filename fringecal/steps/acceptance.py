"""The acceptance test per VDI/VDE 2634 parts 2 and 3 (:mod:`fringecal.acceptance`):
every sphere, dumbbell and flat position measured with the calibrated sensors from
its stores alone, the ball-bar's lengths of the verification as E, each quality
parameter against its limit with its uncertainty and the ISO 14253-1 verdict.

Writes ``acceptance.json`` (:func:`fringecal.acceptance.evaluate.certificate`) and
``tables/acceptance_values.csv``. A run with neither acceptance objects nor a
verified ball-bar, or with ``acceptance.enabled: false``, has no acceptance test:
both files are then absent.
"""

from __future__ import annotations

import logging
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pandas as pd

from fringecal.acceptance.evaluate import VALUE_COLUMNS, certificate, form_u
from fringecal.acceptance.measure import AcceptanceMeasurementError, measure_flat_store, measure_sphere_store
from fringecal.acceptance.standards import AcceptanceStandards
from fringecal.rundir import RunDir
from fringecal.spheres.robust import RejectionConfig
from fringecal.steps.base import Settings, Step, stores_of_kind
from fringecal.steps.verify import measure_ballbar
from fringecal.verification.lengths import ballbar_lengths
from fringecal.verification.measure import measure_positions
from fringecal.verification.uncertainty import ballbar_uncertainty

__all__ = ["Acceptance", "acceptance_stores", "measure_acceptance", "length_values", "ACCEPTANCE_KINDS"]

log = logging.getLogger(__name__)

#: Acquisition kinds of the acceptance objects.
ACCEPTANCE_KINDS = ("sphere", "dumbbell", "flat")


def acceptance_stores(rd: RunDir) -> dict[str, dict[str, dict[str, str]]]:
    """kind -> position -> scanner -> store path of the run's acceptance measurements."""
    table = rd.acquisition.load()
    out: dict[str, dict[str, dict[str, str]]] = {k: {} for k in ACCEPTANCE_KINDS}
    for r in table[table["kind"].isin(ACCEPTANCE_KINDS)].itertuples():
        out[r.kind].setdefault(str(r.pose), {})[str(r.scanner)] = str(rd.store(r.measurement).path)
    return out


def length_values(budget: dict | None, lengths: pd.DataFrame, parameter: str, test: str, k: float,
                  cell: bool) -> list[dict]:
    """Value rows of measured lengths: their errors and ``k`` times their budget's u
    (NaN without a budget: conformance can then not be proven)."""
    entries = {e["measurement"]: e for e in (budget or {}).get("lengths", [])}
    rows = []
    for r in lengths.itertuples():
        e = entries.get(str(r.measurement))
        scanner = "cell" if cell else (r.scanner_a if r.scanner_a == r.scanner_b else f"{r.scanner_a}/{r.scanner_b}")
        rows.append({"test": test, "parameter": parameter, "position": str(r.measurement), "scanner": scanner,
                     "value_mm": float(r.error_mm), "U_mm": k * e["u_mm"] if e else float("nan"),
                     "n_points": 0, "n_excluded": 0})
    return rows


def _probe(kind: str, job, rig, standards, config, rejection) -> tuple[list[dict], list[dict]]:
    position, scanner, store = job
    k = config.coverage_factor
    try:
        if kind == "sphere":
            s = standards.sphere
            m = measure_sphere_store(store, rig.scanner(scanner), s, config.exclude_fraction,
                                     config.max_incidence_deg, rejection)
            return [{"test": kind, "parameter": "P_F", "position": position, "scanner": scanner,
                     "value_mm": m.form_mm, "U_mm": k * form_u(s.form_mm), "n_points": m.n_points,
                     "n_excluded": m.n_excluded},
                    {"test": kind, "parameter": "P_S", "position": position, "scanner": scanner,
                     "value_mm": m.size_mm, "U_mm": k * float(np.hypot(s.diameter_u_mm, m.diameter_u_fit_mm)),
                     "n_points": m.n_points, "n_excluded": m.n_excluded}], []
        f = standards.flat
        m = measure_flat_store(store, rig.scanner(scanner), f, config.exclude_fraction, config.max_incidence_deg)
        return [{"test": kind, "parameter": "F", "position": position, "scanner": scanner,
                 "value_mm": m.flatness_mm, "U_mm": k * float(np.hypot(form_u(f.flatness_mm), f.flatness_u_mm)),
                 "n_points": m.n_points, "n_excluded": m.n_excluded}], []
    except AcceptanceMeasurementError as err:
        return [], [{"test": kind, "position": position, "scanner": scanner, "reason": str(err)}]


def measure_acceptance(stores: dict, rig, standards, config, rejection: dict, length_config, covariance,
                       workers: int = 2) -> tuple[pd.DataFrame, list[dict]]:
    """The raw values of every sphere, flat and dumbbell position measured with ``rig``.

    Parameters
    ----------
    stores : kind -> position -> scanner -> store path (:func:`acceptance_stores`)
    rig : the calibrated rig (or any rig to test, e.g. a miscalibrated one)
    standards : :class:`~fringecal.acceptance.standards.AcceptanceStandards`
    config : :class:`~fringecal.acceptance.standards.AcceptanceConfig`
    rejection : the run's ``extraction.rejection`` settings
    length_config : :class:`~fringecal.verification.settings.LengthUncertaintyConfig` (the
        dumbbell's length budget; its Monte Carlo check is not run here)
    covariance : the run's ``calibration_covariance.npz`` arrays, or None

    Returns
    -------
    values : DataFrame with :data:`fringecal.acceptance.evaluate.VALUE_COLUMNS`
    failures : list of dict (test, position, scanner, reason)
    """

    rej = RejectionConfig(**rejection)
    rows, failures = [], []
    jobs = [(kind, (pos, sc, path)) for kind in ("sphere", "flat") if getattr(standards, kind) is not None
            for pos, by_scanner in stores.get(kind, {}).items() for sc, path in by_scanner.items()]
    with ThreadPoolExecutor(max_workers=workers) as pool:
        for r, f in pool.map(lambda j: _probe(j[0], j[1], rig, standards, config, rej), jobs):
            rows += r
            failures += f
    bell = standards.dumbbell
    if bell is not None and stores.get("dumbbell"):
        centres, fails, pixels = measure_positions(stores["dumbbell"], rig, bell.artefact(), rej, workers, pixels=True)
        failures += [{"test": "dumbbell", "position": f.position, "scanner": f.scanner, "reason": f.reason}
                     for f in fails.itertuples()]
        lengths = ballbar_lengths(centres, "dumbbell centres")
        lengths["error_mm"] = lengths["length_mm"] - bell.length_mm
        budget = None
        if covariance is not None and len(lengths):
            cfg = length_config.model_copy(update={"monte_carlo_draws": 0, "coverage_factor": config.coverage_factor})
            budget = ballbar_uncertainty(centres, pixels, stores["dumbbell"], rig, lengths, bell.length_mm,
                                         covariance, cfg, config.limits.SD, bell.length_u_mm, ("A", "B"), workers)
        rows += length_values(budget, lengths, "SD", "dumbbell", config.coverage_factor, cell=False)
    return pd.DataFrame(rows, columns=VALUE_COLUMNS), failures


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
    modules = ("fringecal.acceptance", "fringecal.verification.measure", "fringecal.verification.uncertainty")

    def reads(self, rd: RunDir, cfg: Settings, item: str):
        stores = [rd.store(m) for kind in ACCEPTANCE_KINDS for m in stores_of_kind(rd, kind)]
        return [rd.calibration, rd.covariance, rd.verification, rd.acceptance_standards, rd.acquisition,
                rd.truth.acceptance_positions] + stores

    def writes(self, rd: RunDir, cfg: Settings, item: str):
        return [rd.acceptance, rd.acceptance_values]

    def run(self, rd: RunDir, cfg: Settings, item: str, **context) -> None:
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
        doc, values = acceptance_document(rd, rd.calibration.load(), standards, cfg.acceptance, cfg.extraction.rejection,
                                          cfg.verification.uncertainty, rd.covariance.load(), stores,
                                          verification=rd.verification.load() if verified else None)
        for f in doc["failures"]:
            log.warning("acceptance %s position %s, scanner %s: %s", f["test"], f["position"], f["scanner"],
                        f["reason"])
        rd.acceptance_values.save(values)
        rd.acceptance.save(doc)


def acceptance_document(rd: RunDir, rig, standards, config, rejection: dict, length_config, covariance,
                        stores: dict, verification: dict | None = None, ballbar=None) -> tuple[dict, pd.DataFrame]:
    """The acceptance document and its values for ``rig``.

    E comes from ``verification`` (the run's ``verification.json``) when given, else
    the ball-bar is measured with ``rig`` (``ballbar``: the verification settings;
    used to test a rig other than the run's calibration)."""

    values, failures = measure_acceptance(stores, rig, standards, config, rejection, length_config, covariance)
    if verification is None and ballbar is not None:
        diagonal = rd.bundle_summary.load()["volume_diagonal_mm"]
        _, fails, result, budget = measure_ballbar(rd, rig, rejection, ballbar, diagonal, covariance)
        verification = {"calibrated": result.to_dict(), "uncertainty": budget,
                        "failures": fails.to_dict("records")}
    if verification is not None:
        e = _e_values(verification, config.coverage_factor)
        values = pd.concat([values, e], ignore_index=True) if len(values) else e
    scanners = [s.name for s in rig.scanners]
    doc = certificate(values, config.limits, config.coverage_factor, config.exclude_fraction, scanners, failures,
                      _positions(rd))
    return doc, values


def _e_values(verification: dict, k: float) -> pd.DataFrame:
    positions = pd.DataFrame(verification["calibrated"]["positions"])
    lengths = pd.DataFrame({"measurement": positions["measurement"].astype(str), "error_mm": positions["error_mm"],
                            "scanner_a": "", "scanner_b": ""})
    return pd.DataFrame(length_values(verification.get("uncertainty"), lengths, "E", "ballbar", k, cell=True),
                        columns=VALUE_COLUMNS)
