"""The acceptance test of a calibrated rig per VDI/VDE 2634 parts 2 and 3: every
sphere, flat and dumbbell position measured with the rig from its stores alone
(:mod:`.measure`; a black-box scanner's in its clouds, :mod:`.cloud`), the ball-bar's
lengths as E, each quality parameter against its limit with its uncertainty and the
ISO 14253-1 verdict (:mod:`.evaluate`).
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pandas as pd

from fringecal.acceptance.cloud import cloud_acceptance_values
from fringecal.acceptance.evaluate import DEPTH_COLUMNS, VALUE_COLUMNS, certificate, form_u
from fringecal.acceptance.measure import AcceptanceMeasurementError, measure_flat_store, measure_sphere_store
from fringecal.acceptance.observed import objects_outside
from fringecal.acceptance.standards import AcceptanceConfig, AcceptanceStandards, ScannerSpecification
from fringecal.rig import Rig
from fringecal.spheres.robust import RejectionConfig
from fringecal.verification.lengths import ballbar_lengths
from fringecal.verification.measure import measure_positions
from fringecal.verification.settings import LengthUncertaintyConfig
from fringecal.verification.uncertainty import ballbar_uncertainty

__all__ = ["acceptance_document", "measure_acceptance", "length_values", "camera_depths", "outside_volume"]


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


def camera_depths(rig: Rig, scanner: str, points) -> np.ndarray:
    """Depths (mm) of world points (n, 3) along ``scanner``'s camera axis."""
    return rig.scanner(scanner).camera.to_sensor(np.atleast_2d(np.asarray(points, float)))[:, 2]


def _probe(kind: str, job, rig, standards, config, rejection) -> tuple[list[dict], list[dict], dict]:
    """The value rows and failures of one sphere or flat store, and the camera pixels its
    fit kept: {(position, scanner, kind): (rows, cols)} (empty when it failed)."""
    position, scanner, store = job
    k = config.coverage_factor
    try:
        if kind == "sphere":
            s = standards.sphere
            m = measure_sphere_store(store, rig.scanner(scanner), s, config.exclude_fraction,
                                     config.max_incidence_deg, rejection)
            depth = float(camera_depths(rig, scanner, m.centre)[0])
            return [{"test": kind, "parameter": "P_F", "position": position, "scanner": scanner,
                     "value_mm": m.form_mm, "U_mm": k * form_u(s.form_mm), "n_points": m.n_points,
                     "n_excluded": m.n_excluded, "depth_mm": depth},
                    {"test": kind, "parameter": "P_S", "position": position, "scanner": scanner,
                     "value_mm": m.size_mm, "U_mm": k * float(np.hypot(s.diameter_u_mm, m.diameter_u_fit_mm)),
                     "n_points": m.n_points, "n_excluded": m.n_excluded, "depth_mm": depth}], [], \
                {(position, scanner, kind): m.pixels}
        f = standards.flat
        m = measure_flat_store(store, rig.scanner(scanner), f, config.exclude_fraction, config.max_incidence_deg)
        return [{"test": kind, "parameter": "F", "position": position, "scanner": scanner,
                 "value_mm": m.flatness_mm, "U_mm": k * float(np.hypot(form_u(f.flatness_mm), f.flatness_u_mm)),
                 "n_points": m.n_points, "n_excluded": m.n_excluded,
                 "depth_mm": float(camera_depths(rig, scanner, m.point)[0])}], [], {(position, scanner, kind): m.pixels}
    except AcceptanceMeasurementError as err:
        return [], [{"test": kind, "position": position, "scanner": scanner, "reason": str(err)}], {}


def outside_volume(values: pd.DataFrame, specification: ScannerSpecification) -> tuple[pd.DataFrame, list[dict]]:
    """The values whose position lies in the specified measuring volume, and one
    failure (not judged) per position outside it; values without a depth (E, across
    scanners) are kept. A dumbbell position is inside when both its spheres are."""
    if specification.depth_range_mm is None or "depth_mm" not in values:
        return values, []
    near, far = specification.depth_range_mm
    depth = values["depth_mm"].astype(float)
    low = depth.where(values["depth_near_mm"].isna(), values["depth_near_mm"]) if "depth_near_mm" in values \
        else depth
    out = depth.notna() & ((low < near) | (depth > far))
    failures = []
    for (test, position, scanner), g in values[out].groupby(["test", "position", "scanner"], sort=False):
        lo, hi = float(low[g.index].min()), float(depth[g.index].max())
        where = f"{lo:.0f} mm" if abs(hi - lo) < 0.5 else f"{lo:.0f}-{hi:.0f} mm"
        failures.append({"test": test, "position": position, "scanner": scanner,
                         "reason": f"outside the specified measuring volume (camera depth {where}, the "
                                   f"specification's {near:g}-{far:g} mm): not judged"})
    return values[~out].reset_index(drop=True), failures


def measure_acceptance(stores: dict, rig, standards, config, rejection: dict, length_config, covariance,
                       workers: int = 2, fit_factors: dict | None = None, pixels: bool = False):
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
    fit_factors : scanner -> factor on its sphere fits' uncertainty in the dumbbell's
        budget (:func:`~fringecal.verification.uncertainty.ballbar_uncertainty`)
    pixels : whether to return, third, the camera pixels each fit kept

    Returns
    -------
    values : DataFrame with :data:`fringecal.acceptance.evaluate.VALUE_COLUMNS`
    failures : list of dict (test, position, scanner, reason)
    kept : with ``pixels``, kind -> {(position, scanner, sphere id or kind): (rows, cols)}
        (:func:`fringecal.verification.measure.positions_outside` counts them)
    """

    rej = RejectionConfig(**rejection)
    rows, failures, kept = [], [], {}
    jobs = [(kind, (pos, sc, path)) for kind in ("sphere", "flat") if getattr(standards, kind) is not None
            for pos, by_scanner in stores.get(kind, {}).items() for sc, path in by_scanner.items()]
    with ThreadPoolExecutor(max_workers=workers) as pool:
        for (kind, _), (r, f, px) in zip(jobs, pool.map(lambda j: _probe(j[0], j[1], rig, standards, config, rej),
                                                        jobs)):
            rows += r
            failures += f
            kept.setdefault(kind, {}).update(px)
    bell = standards.dumbbell
    if bell is not None and stores.get("dumbbell"):
        centres, fails, bell_pixels = measure_positions(stores["dumbbell"], rig, bell.artefact(), rej, workers,
                                                        pixels=True)
        kept["dumbbell"] = bell_pixels
        failures += [{"test": "dumbbell", "position": f.position, "scanner": f.scanner, "reason": f.reason}
                     for f in fails.itertuples()]
        lengths = ballbar_lengths(centres, "dumbbell centres")
        lengths["error_mm"] = lengths["length_mm"] - bell.length_mm
        budget = None
        if covariance is not None and len(lengths):
            cfg = length_config.model_copy(update={"monte_carlo_draws": 0, "coverage_factor": config.coverage_factor})
            budget = ballbar_uncertainty(centres, bell_pixels, stores["dumbbell"], rig, lengths, bell.length_mm,
                                         covariance, cfg, config.limits.SD, bell.length_u_mm, ("A", "B"), workers,
                                         fit_factors=fit_factors)
        sd = length_values(budget, lengths, "SD", "dumbbell", config.coverage_factor, cell=False)
        for row in sd:
            ends = centres[(centres["position"].astype(str) == row["position"])]
            z = camera_depths(rig, row["scanner"].split("/")[0], ends[["x_mm", "y_mm", "z_mm"]].to_numpy(float))
            row["depth_near_mm"], row["depth_mm"] = float(z.min()), float(z.max())
        rows += sd
    values = pd.DataFrame(rows, columns=VALUE_COLUMNS + DEPTH_COLUMNS)
    return (values, failures, kept) if pixels else (values, failures)


def _split(stores: dict, boxes: set) -> tuple[dict, dict]:
    """``stores`` (kind -> position -> scanner -> path) of the modelled scanners and of
    the black boxes ``boxes``."""
    parts: tuple[dict, dict] = ({}, {})
    for kind, positions in stores.items():
        for position, by_scanner in positions.items():
            for scanner, path in by_scanner.items():
                part = parts[scanner in boxes]
                part.setdefault(kind, {}).setdefault(position, {})[scanner] = path
    return parts


def acceptance_document(rig: Rig | None, standards: AcceptanceStandards, config: AcceptanceConfig, rejection: dict,
                        length_config: LengthUncertaintyConfig, covariance: dict | None, stores: dict,
                        verification: dict | None = None, positions: list[dict] = (),
                        black_boxes: dict | None = None, fit_factors: dict | None = None,
                        regions: dict | None = None) -> tuple[dict, pd.DataFrame]:
    """The acceptance document (:func:`.evaluate.certificate`) and its values for ``rig``.

    ``stores`` and ``rejection``, ``length_config``, ``covariance`` as for
    :func:`measure_acceptance`; E comes from ``verification`` (a ball-bar verification:
    ``calibrated`` positions and their ``uncertainty``, as ``verification.json`` holds
    them) when given; ``positions`` are where the objects stood, for the report.
    ``black_boxes``: ``black_boxes.json`` when the rig has black-box scanners, whose
    positions in ``stores`` are clouds measured with their transforms
    (:func:`.cloud.cloud_acceptance_values`); ``rig`` None: a rig of black boxes only.
    ``fit_factors`` as for :func:`measure_acceptance`. ``regions``: the calibration's
    observed regions (sensor name -> region; None or empty: not known), against which
    the document states per object the share of its fits' pixels outside
    (``observed_region``, :func:`.observed.objects_outside`)."""
    boxes = {d["scanner"] for d in black_boxes["scanners"]} if black_boxes else set()
    modelled, clouds = _split(stores, boxes)
    values, failures, kept = measure_acceptance(modelled, rig, standards, config, rejection, length_config,
                                                covariance, fit_factors=fit_factors, pixels=True) \
        if rig is not None else (pd.DataFrame(columns=VALUE_COLUMNS + DEPTH_COLUMNS), [], {})
    if any(clouds.values()):
        rows, fails = cloud_acceptance_values(clouds, black_boxes, standards, config, rejection)
        failures += fails
        if rows:
            cloud_values = pd.DataFrame(rows, columns=VALUE_COLUMNS + DEPTH_COLUMNS)
            values = pd.concat([values, cloud_values], ignore_index=True) if len(values) else cloud_values
    values, outside = outside_volume(values, config.specification)
    failures += outside
    if verification is not None:
        e = _e_values(verification, config.coverage_factor)
        values = pd.concat([values, e], ignore_index=True) if len(values) else e
    scanners = ([s.name for s in rig.scanners] if rig is not None else []) + \
        [d["scanner"] for d in (black_boxes or {}).get("scanners", [])]
    doc = certificate(values, config.limits, config.coverage_factor, config.exclude_fraction, scanners, failures,
                      list(positions), config.specification)
    doc["black_boxes"] = sorted(boxes)  # scanners whose values were measured in their clouds
    doc["observed_region"] = objects_outside(modelled, rig, kept, regions, verification)
    return doc, values


def _e_values(verification: dict, k: float) -> pd.DataFrame:
    positions = pd.DataFrame(verification["calibrated"]["positions"])
    lengths = pd.DataFrame({"measurement": positions["measurement"].astype(str), "error_mm": positions["error_mm"],
                            "scanner_a": "", "scanner_b": ""})
    return pd.DataFrame(length_values(verification.get("uncertainty"), lengths, "E", "ballbar", k, cell=True),
                        columns=VALUE_COLUMNS)
