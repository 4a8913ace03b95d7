"""The acceptance test of a calibrated rig per VDI/VDE 2634 parts 2 and 3: every
sphere, flat and dumbbell position measured with the rig from its stores alone
(:mod:`.measure`), the ball-bar's lengths as E, each quality parameter against its
limit with its uncertainty and the ISO 14253-1 verdict (:mod:`.evaluate`).
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pandas as pd

from fringecal.acceptance.evaluate import VALUE_COLUMNS, certificate, form_u
from fringecal.acceptance.measure import AcceptanceMeasurementError, measure_flat_store, measure_sphere_store
from fringecal.acceptance.standards import AcceptanceConfig, AcceptanceStandards
from fringecal.rig import Rig
from fringecal.spheres.robust import RejectionConfig
from fringecal.verification.lengths import ballbar_lengths
from fringecal.verification.measure import measure_positions
from fringecal.verification.settings import LengthUncertaintyConfig
from fringecal.verification.uncertainty import ballbar_uncertainty

__all__ = ["acceptance_document", "measure_acceptance", "length_values"]


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


def acceptance_document(rig: Rig, standards: AcceptanceStandards, config: AcceptanceConfig, rejection: dict,
                        length_config: LengthUncertaintyConfig, covariance: dict | None, stores: dict,
                        verification: dict | None = None, positions: list[dict] = ()) -> tuple[dict, pd.DataFrame]:
    """The acceptance document (:func:`.evaluate.certificate`) and its values for ``rig``.

    ``stores`` and ``rejection``, ``length_config``, ``covariance`` as for
    :func:`measure_acceptance`; E comes from ``verification`` (a ball-bar verification:
    ``calibrated`` positions and their ``uncertainty``, as ``verification.json`` holds
    them) when given; ``positions`` are where the objects stood, for the report."""
    values, failures = measure_acceptance(stores, rig, standards, config, rejection, length_config, covariance)
    if verification is not None:
        e = _e_values(verification, config.coverage_factor)
        values = pd.concat([values, e], ignore_index=True) if len(values) else e
    scanners = [s.name for s in rig.scanners]
    doc = certificate(values, config.limits, config.coverage_factor, config.exclude_fraction, scanners, failures,
                      list(positions))
    return doc, values


def _e_values(verification: dict, k: float) -> pd.DataFrame:
    positions = pd.DataFrame(verification["calibrated"]["positions"])
    lengths = pd.DataFrame({"measurement": positions["measurement"].astype(str), "error_mm": positions["error_mm"],
                            "scanner_a": "", "scanner_b": ""})
    return pd.DataFrame(length_values(verification.get("uncertainty"), lengths, "E", "ballbar", k, cell=True),
                        columns=VALUE_COLUMNS)
