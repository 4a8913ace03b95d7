"""Pandera models for every table that crosses a boundary (docs/contracts.md).

Extra columns are allowed; the listed ones are required. Identifiers (sphere,
rod, measurement, scanner, sensor) are strings, so a ball-bar's ``A``/``B`` and the
thesis's ``1``..``15`` live in the same column type.

:func:`read_table` reads a CSV and validates it with lazy error collection; every
problem is reported in one :class:`TableError` naming the file, the line (the header
is line 1) and the column, and the rule that broke.
"""

from __future__ import annotations

import csv
import hashlib
import io
import re
import sys
import threading
import types
from collections import OrderedDict
from pathlib import Path
from typing import Optional

import numpy as np
import pandas as pd


def _without_pandera_dask_types() -> None:
    """Keep pandera from importing dask.dataframe when it builds the first schema.

    pandera looks up the dask annotation types (``pandera.typing.dask``) the first time
    any model builds its schema, and that import of dask.dataframe costs 0.5-1 s, most of
    what a small command such as ``fringecal fit sphere`` spends. Every table here is a
    pandas table, so the lookup is answered with "dask not installed". This only holds
    when schemas load before anything imports ``pandera.typing.dask``; if dask types were
    registered earlier, they stay.
    """
    name = "pandera.typing.dask"
    if name not in sys.modules:
        stub = types.ModuleType(name, "Stand-in set by fringecal's schemas: no dask DataFrame models.")
        stub.DASK_INSTALLED = False
        sys.modules[name] = stub


_without_pandera_dask_types()

import pandera.pandas as pa  # noqa: E402
from pandera.typing import Series  # noqa: E402

from fringecal.atomic import atomic_path  # noqa: E402
from fringecal.names import name_problem, not_a_file  # noqa: E402
from fringecal.sensor import PARAM_NAMES  # noqa: E402

__all__ = [
    "TableError",
    "ArtefactTable",
    "RodsTable",
    "SphereCentresTable",
    "PosesTable",
    "PosePlanTable",
    "SensorParametersTable",
    "ThermalLogTable",
    "ControlPointsTable",
    "HexapodPlanTable",
    "AcquiredPosesTable",
    "HexapodMovesTable",
    "AcquisitionTable",
    "DriftCentresTable",
    "TrussForcesTable",
    "TrussDisplacementsTable",
    "SupportsTable",
    "MoistureUptakeTable",
    "HumidityLengthsTable",
    "RodConsistencyTable",
    "SphereFitsTable",
    "LabelOutcomesTable",
    "ScannerLinksTable",
    "PointsTable",
    "REJECTION_REASONS",
    "CalibratedSensorsTable",
    "CalibratedPosesTable",
    "SphereResidualsTable",
    "MeasurementResidualsTable",
    "BinnedResidualsTable",
    "read_table",
    "read_any_table",
    "read_csv_text",
    "validate_table",
    "write_table",
    "FREE_COLUMNS",
    "NAME_COLUMNS",
    "MAX_SPHERES",
    "MAX_POINTS",
]

FREE_COLUMNS = tuple(f"free_{n}" for n in PARAM_NAMES)

#: the most spheres an artefact (or a ball-bar) table may hold: see ArtefactTable
MAX_SPHERES = 200
#: the most points a points table may hold (2**24): see PointsTable
MAX_POINTS = 1 << 24

#: columns whose values become file or folder names (a run's stores, a data set's folders,
#: an export's files): each value must be one safe path component (:mod:`fringecal.names`)
NAME_COLUMNS = ("measurement", "scanner", "sensor", "position", "pose")


class TableError(ValueError):
    """A table broke its contract. ``problems`` lists (line, column, message).

    One problem is one line (``FILE: line 3, column 'x_mm': value 'inf' is not a finite
    number``); several are a first line counting them and naming the first, then one
    line each.
    """

    def __init__(self, source: str, problems: list[tuple[Optional[int], Optional[str], str]]):
        self.source = source
        self.problems = problems
        if len(problems) == 1:
            line, column, message = problems[0]
            where = _where(line, column)
            super().__init__(f"{source}: {where}: {message}" if where else f"{source}: {message}")
            return
        line, column, message = problems[0]
        first = f"the first on {_where(line, column)}: {message}" if _where(line, column) else f"the first: {message}"
        lines = [f"{source}: {len(problems)} problem(s), {first}"]
        for line, column, message in problems[:50]:
            lines.append(f"  {_where(line, column) or 'table'}: {message}")
        if len(problems) > 50:
            lines.append(f"  ... and {len(problems) - 50} more")
        super().__init__("\n".join(lines))


def _where(line: Optional[int], column: Optional[str]) -> str:
    where = []
    if line is not None:
        where.append(f"line {line}")
    if column is not None:
        where.append(f"column '{column}'")
    return ", ".join(where)


class _Base(pa.DataFrameModel):
    class Config:
        coerce = True
        strict = False

    #: columns holding identifiers, read as text
    _id_columns = ()
    #: column sets that must be unique together (beyond single-field uniqueness)
    _unique_together = ()
    #: number columns that may hold +-inf (none: every number must be finite)
    _infinite_allowed = ()
    #: the most rows an input table may have (what the method can use; None: no bound),
    #: checked before the cells are parsed so that a huge table is refused in seconds
    _max_rows = None
    #: why that bound (the end of the refusal's message)
    _max_rows_reason = ""


class ArtefactTable(_Base):
    """Artefact definition: one row per sphere, centre in the CMM frame."""

    sphere_id: Series[str] = pa.Field(unique=True, str_length={"min_value": 1})
    x_mm: Series[float] = pa.Field()
    y_mm: Series[float] = pa.Field()
    z_mm: Series[float] = pa.Field()
    diameter_mm: Series[float] = pa.Field(gt=0)
    u_mm: Optional[Series[float]] = pa.Field(ge=0)

    _id_columns = ("sphere_id",)
    _max_rows = MAX_SPHERES
    _max_rows_reason = (f"the labelling compares every candidate's distances with all m^2 distances of the "
                        f"artefact (8 m^3 bytes: 64 MB at {MAX_SPHERES} spheres, 1 GB at 500); the thesis's "
                        "artefact has 15")


class RodsTable(_Base):
    """Rods joining spheres, with CMM-measured centre-to-centre lengths."""

    rod_id: Series[str] = pa.Field(unique=True)
    sphere_a: Series[str] = pa.Field()
    sphere_b: Series[str] = pa.Field()
    length_mm: Series[float] = pa.Field(gt=0)

    _id_columns = ("rod_id", "sphere_a", "sphere_b")
    _max_rows = MAX_SPHERES * (MAX_SPHERES - 1) // 2
    _max_rows_reason = (f"a rod joins two spheres, each pair at most once: {MAX_SPHERES * (MAX_SPHERES - 1) // 2:,} "
                        f"pairs of the largest artefact ({MAX_SPHERES} spheres)")


class SphereCentresTable(_Base):
    """Measured sphere centres, one row per (measurement, scanner, sphere)."""

    measurement: Series[str] = pa.Field()
    scanner: Series[str] = pa.Field()
    sphere_id: Series[str] = pa.Field()
    x_mm: Series[float] = pa.Field()
    y_mm: Series[float] = pa.Field()
    z_mm: Series[float] = pa.Field()
    radius_mm: Optional[Series[float]] = pa.Field(gt=0)
    rms_mm: Optional[Series[float]] = pa.Field(ge=0)
    n_points: Optional[Series[int]] = pa.Field(ge=0)

    _id_columns = ("measurement", "scanner", "sphere_id")
    _unique_together = (("measurement", "scanner", "sphere_id"),)


#: Point-rejection reasons with a ``rejected_<reason>`` column in :class:`SphereFitsTable`
#: (fringecal.spheres.robust): caller flags from image space, then the geometric tests.
REJECTION_REASONS = ("invalid", "edge", "saturated", "low_modulation", "phase_error", "glint",
                     "rod", "silhouette", "residual")


class SphereFitsTable(SphereCentresTable):
    """Every sphere candidate fitted in a measurement, labelled or not.

    Extends :class:`SphereCentresTable`: the rows with a non-empty ``sphere_id`` are
    valid sphere centres (``centres_from_fits``). ``candidate`` identifies the
    candidate within its (measurement, scanner); ``sphere_id`` is empty until (or
    unless) labelling assigns one. The image region is the candidate's bounding box
    in camera pixels. ``rejected_<reason>`` count the points rejected per reason
    (:data:`REJECTION_REASONS`; other caller flags may add more such columns).
    """

    sphere_id: Series[str] = pa.Field(nullable=True)
    candidate: Series[str] = pa.Field(str_length={"min_value": 1})
    radius_mm: Series[float] = pa.Field(gt=0)
    rms_mm: Series[float] = pa.Field(ge=0)
    n_points: Series[int] = pa.Field(ge=3)
    u_x_mm: Series[float] = pa.Field(ge=0, nullable=True)
    u_y_mm: Series[float] = pa.Field(ge=0, nullable=True)
    u_z_mm: Series[float] = pa.Field(ge=0, nullable=True)
    radius_fixed: Optional[Series[bool]] = pa.Field()
    cap_angle_deg: Series[float] = pa.Field(ge=0, le=180)
    coverage: Series[float] = pa.Field(ge=0, le=1)
    n_rejected: Series[int] = pa.Field(ge=0)
    u_min_px: Optional[Series[float]] = pa.Field(ge=0, nullable=True)
    v_min_px: Optional[Series[float]] = pa.Field(ge=0, nullable=True)
    u_max_px: Optional[Series[float]] = pa.Field(ge=0, nullable=True)
    v_max_px: Optional[Series[float]] = pa.Field(ge=0, nullable=True)
    rejected_invalid: Optional[Series[int]] = pa.Field(ge=0)
    rejected_edge: Optional[Series[int]] = pa.Field(ge=0)
    rejected_saturated: Optional[Series[int]] = pa.Field(ge=0)
    rejected_low_modulation: Optional[Series[int]] = pa.Field(ge=0)
    rejected_phase_error: Optional[Series[int]] = pa.Field(ge=0)
    rejected_glint: Optional[Series[int]] = pa.Field(ge=0)
    rejected_rod: Optional[Series[int]] = pa.Field(ge=0)
    rejected_silhouette: Optional[Series[int]] = pa.Field(ge=0)
    rejected_residual: Optional[Series[int]] = pa.Field(ge=0)

    _id_columns = ("measurement", "scanner", "sphere_id", "candidate")
    _infinite_allowed = ("u_x_mm", "u_y_mm", "u_z_mm")  # an output: a fit's unbounded uncertainty
    _unique_together = (("measurement", "scanner", "candidate"),)


class LabelOutcomesTable(_Base):
    """Labelling per (measurement, scanner): ``labelled`` or ``refused`` with the reason
    (fringecal.spheres.labelling.REFUSAL_REASONS) and a message naming the alternatives."""

    measurement: Series[str] = pa.Field()
    scanner: Series[str] = pa.Field()
    status: Series[str] = pa.Field(isin=["labelled", "refused"])
    reason: Series[str] = pa.Field(nullable=True)
    method: Series[str] = pa.Field(nullable=True)
    n_candidates: Series[int] = pa.Field(ge=0)
    n_labelled: Series[int] = pa.Field(ge=0)
    rms_mm: Series[float] = pa.Field(ge=0, nullable=True)
    message: Series[str] = pa.Field(nullable=True)

    _id_columns = ("measurement", "scanner", "status", "reason", "method", "message")
    _unique_together = (("measurement", "scanner"),)


class ScannerLinksTable(_Base):
    """T_reference_scanner per scanner (fringecal.spheres.linking), with the spread of the
    per-measurement estimates and the path of scanners it was chained through."""

    scanner: Series[str] = pa.Field(unique=True)
    reference: Series[str] = pa.Field()
    tx_mm: Series[float] = pa.Field()
    ty_mm: Series[float] = pa.Field()
    tz_mm: Series[float] = pa.Field()
    omega_rad: Series[float] = pa.Field(ge=-2 * np.pi, le=2 * np.pi)
    phi_rad: Series[float] = pa.Field(ge=-2 * np.pi, le=2 * np.pi)
    kappa_rad: Series[float] = pa.Field(ge=-2 * np.pi, le=2 * np.pi)
    n_measurements: Series[int] = pa.Field(ge=0)
    n_rejected: Series[int] = pa.Field(ge=0)
    translation_spread_mm: Series[float] = pa.Field(ge=0, nullable=True)
    rotation_spread_rad: Series[float] = pa.Field(ge=0, nullable=True)
    u_translation_mm: Series[float] = pa.Field(ge=0, nullable=True)
    u_rotation_rad: Series[float] = pa.Field(ge=0, nullable=True)
    via: Series[str] = pa.Field()

    _id_columns = ("scanner", "reference", "via")
    _infinite_allowed = ("translation_spread_mm", "rotation_spread_rad", "u_translation_mm", "u_rotation_rad")


class PointsTable(_Base):
    """Exported points, one per row (``fringecal fit``)."""

    x_mm: Series[float] = pa.Field()
    y_mm: Series[float] = pa.Field()
    z_mm: Series[float] = pa.Field()

    _max_rows = MAX_POINTS
    _max_rows_reason = ("every pixel of a 4096 x 4096 camera; one scanner's points of one sphere or plane "
                        "cannot be more")


class PosesTable(_Base):
    """Artefact poses T_world_artefact per (measurement, scanner)."""

    measurement: Series[str] = pa.Field()
    scanner: Series[str] = pa.Field()
    tx_mm: Series[float] = pa.Field()
    ty_mm: Series[float] = pa.Field()
    tz_mm: Series[float] = pa.Field()
    omega_rad: Series[float] = pa.Field(ge=-2 * np.pi, le=2 * np.pi)
    phi_rad: Series[float] = pa.Field(ge=-2 * np.pi, le=2 * np.pi)
    kappa_rad: Series[float] = pa.Field(ge=-2 * np.pi, le=2 * np.pi)
    rms_mm: Series[float] = pa.Field(ge=0)
    n_spheres: Series[int] = pa.Field(ge=3)

    _id_columns = ("measurement", "scanner")
    _unique_together = (("measurement", "scanner"),)


class SensorParametersTable(_Base):
    """The 14 parameters of every sensor, with a fixed/free flag per parameter.

    Free flags are columns ``free_<name>`` (``free_x0`` .. ``free_p2``), true when
    the bundle adjustment may change the parameter. ``u_<column>`` columns, when
    present, hold standard uncertainties. Optional thin-prism columns ``s1_per_mm``,
    ``s2_per_mm3``, ``s3_per_mm``, ``s4_per_mm3`` (OpenCV's s1..s4; empty or absent: 0)
    give start values of terms outside the 14 parameters (whether they are adjusted is
    the run's model choice, ``bundle.sensor_model``). Optional ``field_degree`` with
    ``field_f01_mm`` ... (``fringecal.lens.field``; empty: no field) give a sensor's
    correction field.
    """

    sensor: Series[str] = pa.Field(unique=True)
    scanner: Series[str] = pa.Field()
    role: Series[str] = pa.Field(isin=["camera", "projector"])
    x0_mm: Series[float] = pa.Field()
    y0_mm: Series[float] = pa.Field()
    z0_mm: Series[float] = pa.Field()
    omega_rad: Series[float] = pa.Field()
    phi_rad: Series[float] = pa.Field()
    kappa_rad: Series[float] = pa.Field()
    xi_h_mm: Series[float] = pa.Field()
    eta_h_mm: Series[float] = pa.Field()
    c_mm: Series[float] = pa.Field(gt=0)
    k1_per_mm2: Series[float] = pa.Field()
    k2_per_mm4: Series[float] = pa.Field()
    k3_per_mm6: Series[float] = pa.Field()
    p1_per_mm: Series[float] = pa.Field()
    p2_per_mm: Series[float] = pa.Field()
    free_x0: Series[bool] = pa.Field()
    free_y0: Series[bool] = pa.Field()
    free_z0: Series[bool] = pa.Field()
    free_omega: Series[bool] = pa.Field()
    free_phi: Series[bool] = pa.Field()
    free_kappa: Series[bool] = pa.Field()
    free_xi_h: Series[bool] = pa.Field()
    free_eta_h: Series[bool] = pa.Field()
    free_c: Series[bool] = pa.Field()
    free_k1: Series[bool] = pa.Field()
    free_k2: Series[bool] = pa.Field()
    free_k3: Series[bool] = pa.Field()
    free_p1: Series[bool] = pa.Field()
    free_p2: Series[bool] = pa.Field()
    s1_per_mm: Optional[Series[float]] = pa.Field(nullable=True)
    s2_per_mm3: Optional[Series[float]] = pa.Field(nullable=True)
    s3_per_mm: Optional[Series[float]] = pa.Field(nullable=True)
    s4_per_mm3: Optional[Series[float]] = pa.Field(nullable=True)
    field_degree: Optional[Series[float]] = pa.Field(nullable=True, ge=2, le=8)
    field_coefficients: Optional[Series[float]] = pa.Field(nullable=True, alias=r"field_f\d+_mm", regex=True)
    width_px: Optional[Series[int]] = pa.Field(gt=1)
    height_px: Optional[Series[int]] = pa.Field(gt=1)
    width_mm: Optional[Series[float]] = pa.Field(gt=0)
    height_mm: Optional[Series[float]] = pa.Field(gt=0)

    _id_columns = ("sensor", "scanner", "role")


class PosePlanTable(_Base):
    """Artefact poses T_world_artefact per measurement, planned or true (no fit statistics)."""

    measurement: Series[str] = pa.Field(unique=True)
    tx_mm: Series[float] = pa.Field()
    ty_mm: Series[float] = pa.Field()
    tz_mm: Series[float] = pa.Field()
    omega_rad: Series[float] = pa.Field(ge=-2 * np.pi, le=2 * np.pi)
    phi_rad: Series[float] = pa.Field(ge=-2 * np.pi, le=2 * np.pi)
    kappa_rad: Series[float] = pa.Field(ge=-2 * np.pi, le=2 * np.pi)

    _id_columns = ("measurement",)


class ControlPointsTable(_Base):
    """Control points of the bundle adjustment (section 6.4): a camera pixel on a
    fitted sphere, the decoded projector phases there, and the sphere it lies on."""

    measurement: Series[str] = pa.Field()
    scanner: Series[str] = pa.Field()
    sphere_id: Series[str] = pa.Field()
    u_px: Series[float] = pa.Field(ge=0)
    v_px: Series[float] = pa.Field(ge=0)
    tau_x_rad: Series[float] = pa.Field(ge=-np.pi - 1e-9, le=np.pi + 1e-9)
    tau_y_rad: Series[float] = pa.Field(ge=-np.pi - 1e-9, le=np.pi + 1e-9)
    #: the pixel-integration bias already subtracted from tau_x_rad, tau_y_rad
    #: (:mod:`fringecal.spheres.pixel_integration`); absent in tables made without it
    pixel_integration_x_rad: Optional[Series[float]] = pa.Field(ge=-0.01, le=0.01)
    pixel_integration_y_rad: Optional[Series[float]] = pa.Field(ge=-0.01, le=0.01)

    _id_columns = ("measurement", "scanner", "sphere_id")


class CalibratedSensorsTable(SensorParametersTable):
    """Sensor parameters after the bundle adjustment with their standard uncertainties
    ``u_<column>`` (same unit as the column; 0 for fixed parameters)."""

    u_x0_mm: Series[float] = pa.Field(ge=0)
    u_y0_mm: Series[float] = pa.Field(ge=0)
    u_z0_mm: Series[float] = pa.Field(ge=0)
    u_omega_rad: Series[float] = pa.Field(ge=0)
    u_phi_rad: Series[float] = pa.Field(ge=0)
    u_kappa_rad: Series[float] = pa.Field(ge=0)
    u_xi_h_mm: Series[float] = pa.Field(ge=0)
    u_eta_h_mm: Series[float] = pa.Field(ge=0)
    u_c_mm: Series[float] = pa.Field(ge=0)
    u_k1_per_mm2: Series[float] = pa.Field(ge=0)
    u_k2_per_mm4: Series[float] = pa.Field(ge=0)
    u_k3_per_mm6: Series[float] = pa.Field(ge=0)
    u_p1_per_mm: Series[float] = pa.Field(ge=0)
    u_p2_per_mm: Series[float] = pa.Field(ge=0)

    _id_columns = ("sensor", "scanner", "role")
    _infinite_allowed = tuple(f"u_{c}" for c in ("x0_mm", "y0_mm", "z0_mm", "omega_rad", "phi_rad", "kappa_rad",
                                                  "xi_h_mm", "eta_h_mm", "c_mm", "k1_per_mm2", "k2_per_mm4",
                                                  "k3_per_mm6", "p1_per_mm", "p2_per_mm"))


class CalibratedPosesTable(PosePlanTable):
    """Adjusted artefact poses T_world_artefact per measurement with standard uncertainties."""

    u_tx_mm: Series[float] = pa.Field(ge=0)
    u_ty_mm: Series[float] = pa.Field(ge=0)
    u_tz_mm: Series[float] = pa.Field(ge=0)
    u_omega_rad: Series[float] = pa.Field(ge=0)
    u_phi_rad: Series[float] = pa.Field(ge=0)
    u_kappa_rad: Series[float] = pa.Field(ge=0)

    _id_columns = ("measurement",)
    _infinite_allowed = ("u_tx_mm", "u_ty_mm", "u_tz_mm", "u_omega_rad", "u_phi_rad", "u_kappa_rad")


class SphereResidualsTable(_Base):
    """Bundle-adjustment residuals per sphere image (measurement, scanner, sphere):
    RMS of epsilon-1 and epsilon-2 after (and at the start of) the adjustment."""

    measurement: Series[str] = pa.Field()
    scanner: Series[str] = pa.Field()
    sphere_id: Series[str] = pa.Field()
    n_points: Series[int] = pa.Field(ge=1)
    rms_eps1_mm: Series[float] = pa.Field(ge=0)
    rms_eps2_mm: Series[float] = pa.Field(ge=0)
    mean_eps2_mm: Series[float] = pa.Field()
    max_abs_eps2_mm: Series[float] = pa.Field(ge=0)
    rms_eps1_start_mm: Series[float] = pa.Field(ge=0)
    rms_eps2_start_mm: Series[float] = pa.Field(ge=0)

    _id_columns = ("measurement", "scanner", "sphere_id")
    _unique_together = (("measurement", "scanner", "sphere_id"),)


class MeasurementResidualsTable(_Base):
    """Bundle-adjustment residuals per measurement (all scanners that saw it)."""

    measurement: Series[str] = pa.Field(unique=True)
    scanners: Series[str] = pa.Field()
    n_points: Series[int] = pa.Field(ge=1)
    n_spheres: Series[int] = pa.Field(ge=1)
    rms_eps1_mm: Series[float] = pa.Field(ge=0)
    rms_eps2_mm: Series[float] = pa.Field(ge=0)
    mean_eps2_mm: Series[float] = pa.Field()
    rms_eps1_start_mm: Series[float] = pa.Field(ge=0)
    rms_eps2_start_mm: Series[float] = pa.Field(ge=0)

    _id_columns = ("measurement", "scanners")


class BinnedResidualsTable(_Base):
    """Bundle-adjustment residuals binned over each sensor's image: one row per
    (sensor, bin) holding control points, on a grid of ``nx`` x ``ny`` bins over the
    camera's pixels or the projector's (bin ``ix``, ``iy`` centred at ``u_px``,
    ``v_px``), with the count (the image's coverage by control points) and the mean
    and RMS of epsilon-1 and epsilon-2 after the adjustment."""

    scanner: Series[str] = pa.Field()
    sensor: Series[str] = pa.Field()
    role: Series[str] = pa.Field(isin=["camera", "projector"])
    nx: Series[int] = pa.Field(ge=1)
    ny: Series[int] = pa.Field(ge=1)
    ix: Series[int] = pa.Field(ge=0)
    iy: Series[int] = pa.Field(ge=0)
    u_px: Series[float] = pa.Field()
    v_px: Series[float] = pa.Field()
    n_points: Series[int] = pa.Field(ge=1)
    mean_eps1_mm: Series[float] = pa.Field()
    rms_eps1_mm: Series[float] = pa.Field(ge=0)
    mean_eps2_mm: Series[float] = pa.Field()
    rms_eps2_mm: Series[float] = pa.Field(ge=0)

    _id_columns = ("scanner", "sensor")
    _unique_together = (("sensor", "ix", "iy"),)


class ThermalLogTable(_Base):
    """A cooling log: time, temperature and a measured length."""

    time_s: Series[float] = pa.Field(ge=0)
    temperature_c: Series[float] = pa.Field(ge=-50, le=150)
    length_mm: Series[float] = pa.Field(gt=0)


class HexapodPlanTable(_Base):
    """Hexapod moves for planned artefact poses (fringecal.hexapod.planning).

    Per measurement: the base placement T_world_base (``base_*``), the platform pose
    (eq. 4-3: TOP origin in BASE and alpha, beta, gamma), leg lengths joint to joint,
    strokes from the retracted length, encoder counts, whether the pose is inside the
    workspace and, if not, the constraints it breaks (``limits``).
    """

    measurement: Series[str] = pa.Field(unique=True)
    station: Series[str] = pa.Field()
    base_tx_mm: Series[float] = pa.Field()
    base_ty_mm: Series[float] = pa.Field()
    base_tz_mm: Series[float] = pa.Field()
    base_omega_rad: Series[float] = pa.Field(ge=-2 * np.pi, le=2 * np.pi)
    base_phi_rad: Series[float] = pa.Field(ge=-2 * np.pi, le=2 * np.pi)
    base_kappa_rad: Series[float] = pa.Field(ge=-2 * np.pi, le=2 * np.pi)
    px_mm: Series[float] = pa.Field()
    py_mm: Series[float] = pa.Field()
    pz_mm: Series[float] = pa.Field()
    alpha_rad: Series[float] = pa.Field(ge=-np.pi, le=np.pi)
    beta_rad: Series[float] = pa.Field(ge=-np.pi, le=np.pi)
    gamma_rad: Series[float] = pa.Field(ge=-np.pi, le=np.pi)
    length_1_mm: Series[float] = pa.Field(gt=0)
    length_2_mm: Series[float] = pa.Field(gt=0)
    length_3_mm: Series[float] = pa.Field(gt=0)
    length_4_mm: Series[float] = pa.Field(gt=0)
    length_5_mm: Series[float] = pa.Field(gt=0)
    length_6_mm: Series[float] = pa.Field(gt=0)
    stroke_1_mm: Series[float] = pa.Field()
    stroke_2_mm: Series[float] = pa.Field()
    stroke_3_mm: Series[float] = pa.Field()
    stroke_4_mm: Series[float] = pa.Field()
    stroke_5_mm: Series[float] = pa.Field()
    stroke_6_mm: Series[float] = pa.Field()
    counts_1: Series[int] = pa.Field()
    counts_2: Series[int] = pa.Field()
    counts_3: Series[int] = pa.Field()
    counts_4: Series[int] = pa.Field()
    counts_5: Series[int] = pa.Field()
    counts_6: Series[int] = pa.Field()
    reachable: Series[bool] = pa.Field()
    limits: Series[str] = pa.Field()

    _id_columns = ("measurement", "station")


class AcquiredPosesTable(PosePlanTable):
    """Artefact poses of a simulated acquisition, one row per pose (``measurement`` is
    the pose id). ``tx_mm .. kappa_rad`` is the pose the artefact reached, at which its
    measurements were rendered (the truth); ``planned_*`` the pose that was asked for;
    with a hexapod, ``counts_1..6`` are the encoder counts read back after the move."""

    planned_tx_mm: Series[float] = pa.Field()
    planned_ty_mm: Series[float] = pa.Field()
    planned_tz_mm: Series[float] = pa.Field()
    planned_omega_rad: Series[float] = pa.Field(ge=-2 * np.pi, le=2 * np.pi)
    planned_phi_rad: Series[float] = pa.Field(ge=-2 * np.pi, le=2 * np.pi)
    planned_kappa_rad: Series[float] = pa.Field(ge=-2 * np.pi, le=2 * np.pi)
    translation_error_mm: Series[float] = pa.Field(ge=0)
    rotation_error_rad: Series[float] = pa.Field(ge=0)
    hexapod: Series[bool] = pa.Field()
    counts_1: Optional[Series[pd.Int64Dtype]] = pa.Field(nullable=True)
    counts_2: Optional[Series[pd.Int64Dtype]] = pa.Field(nullable=True)
    counts_3: Optional[Series[pd.Int64Dtype]] = pa.Field(nullable=True)
    counts_4: Optional[Series[pd.Int64Dtype]] = pa.Field(nullable=True)
    counts_5: Optional[Series[pd.Int64Dtype]] = pa.Field(nullable=True)
    counts_6: Optional[Series[pd.Int64Dtype]] = pa.Field(nullable=True)


class HexapodMovesTable(AcquiredPosesTable):
    """The hexapod's log of a live acquisition (``hexapod_moves.csv`` of a data set,
    :mod:`fringecal.acquisition.live`), one row per complete measurement. As in
    :class:`AcquiredPosesTable`, ``tx_mm .. kappa_rad`` is the artefact pose reached (forward
    kinematics of the encoder counts ``counts_1..6`` read back after the move) and
    ``planned_*`` the pose asked for. ``tolerance_mm`` and ``tolerance_rad`` are the reach
    tolerance the errors were checked against, ``moves`` how often the platform was moved
    to this pose (more than 1 when an interrupted measurement was resumed; the row is the
    last move), ``time_utc`` when that move ended (ISO 8601)."""

    counts_1: Series[int] = pa.Field(ge=0)
    counts_2: Series[int] = pa.Field(ge=0)
    counts_3: Series[int] = pa.Field(ge=0)
    counts_4: Series[int] = pa.Field(ge=0)
    counts_5: Series[int] = pa.Field(ge=0)
    counts_6: Series[int] = pa.Field(ge=0)
    tolerance_mm: Series[float] = pa.Field(ge=0)
    tolerance_rad: Series[float] = pa.Field(ge=0)
    moves: Series[int] = pa.Field(ge=1)
    time_utc: Series[str] = pa.Field(str_length={"min_value": 1})


class AcquisitionTable(_Base):
    """Every acquisition store of a run: id ``<group>-<scanner>``, ``kind`` (``artefact``:
    a calibration measurement; ``ballbar``: a verification position; ``sphere``,
    ``dumbbell``, ``flat``: an acceptance-test position), the measurement
    or position (``pose``), the scanner, the store (relative to the run directory) and
    where its data came from (``simulated``, or the stack's path in the data set)."""

    measurement: Series[str] = pa.Field(unique=True)
    kind: Series[str] = pa.Field(isin=["artefact", "ballbar", "sphere", "dumbbell", "flat"])
    pose: Series[str] = pa.Field()
    scanner: Series[str] = pa.Field()
    store: Series[str] = pa.Field(str_length={"min_value": 1})
    source: Series[str] = pa.Field(str_length={"min_value": 1})

    _id_columns = ("measurement", "kind", "pose", "scanner")
    _unique_together = (("kind", "pose", "scanner"),)


class BallbarCentresTable(_Base):
    """Ball-bar sphere centres in the world frame, one row per (position, scanner, sphere)
    (the columns of :class:`SphereCentresTable`, named by position; kept apart so that
    messages list a table's columns in its own order)."""

    position: Series[str] = pa.Field()
    scanner: Series[str] = pa.Field()
    sphere_id: Series[str] = pa.Field()
    x_mm: Series[float] = pa.Field()
    y_mm: Series[float] = pa.Field()
    z_mm: Series[float] = pa.Field()
    radius_mm: Optional[Series[float]] = pa.Field(gt=0)
    rms_mm: Optional[Series[float]] = pa.Field(ge=0)
    n_points: Optional[Series[int]] = pa.Field(ge=0)

    _id_columns = ("position", "scanner", "sphere_id")
    _unique_together = (("position", "scanner", "sphere_id"),)


class DriftCentresTable(_Base):
    """Repeated sphere centres of a platform standing still (drift check, section 4.5.2);
    ``time_s`` (optional) is when each measurement was taken."""

    measurement: Series[str] = pa.Field()
    sphere_id: Series[str] = pa.Field()
    x_mm: Series[float] = pa.Field()
    y_mm: Series[float] = pa.Field()
    z_mm: Series[float] = pa.Field()
    time_s: Optional[Series[float]] = pa.Field(ge=0)

    _id_columns = ("measurement", "sphere_id")
    _unique_together = (("measurement", "sphere_id"),)
class TrussForcesTable(_Base):
    """Member axial forces of a truss analysis (tension positive), e.g. thesis table 3-3."""

    sphere_a: Series[str] = pa.Field()
    sphere_b: Series[str] = pa.Field()
    force_n: Series[float] = pa.Field()
    rod_id: Optional[Series[str]] = pa.Field()
    length_mm: Optional[Series[float]] = pa.Field(gt=0)
    stress_mpa: Optional[Series[float]] = pa.Field()

    _id_columns = ("sphere_a", "sphere_b", "rod_id")
    _unique_together = (("sphere_a", "sphere_b"),)


class TrussDisplacementsTable(_Base):
    """Nodal displacements (truss analysis, gravity-sag correction), mm."""

    sphere_id: Series[str] = pa.Field(unique=True)
    dx_mm: Series[float] = pa.Field()
    dy_mm: Series[float] = pa.Field()
    dz_mm: Series[float] = pa.Field()
    d_mm: Optional[Series[float]] = pa.Field(ge=0)

    _id_columns = ("sphere_id",)


class SupportsTable(_Base):
    """Support constraints: one row per constrained direction (n need not be unit)."""

    sphere_id: Series[str] = pa.Field()
    nx: Series[float] = pa.Field()
    ny: Series[float] = pa.Field()
    nz: Series[float] = pa.Field()

    _id_columns = ("sphere_id",)


class MoistureUptakeTable(_Base):
    """Moisture uptake series: time since the humidity step and the specimen's mass
    (``mass_g``) or moisture content (``moisture_pct``, percent of dry mass); at least one."""

    time_s: Series[float] = pa.Field(ge=0, unique=True)
    mass_g: Optional[Series[float]] = pa.Field(gt=0)
    moisture_pct: Optional[Series[float]] = pa.Field()


class HumidityLengthsTable(_Base):
    """Rod length through a humidity step (thesis table 3-6)."""

    time_h: Series[float] = pa.Field(ge=0)
    length_mm: Series[float] = pa.Field(gt=0)


class RodConsistencyTable(_Base):
    """Per-rod lengths from the rod measured singly, the assembly and coordinates."""

    rod_id: Series[str] = pa.Field(unique=True)
    sphere_a: Series[str] = pa.Field()
    sphere_b: Series[str] = pa.Field()
    single_mm: Series[float] = pa.Field(gt=0)
    assembled_mm: Optional[Series[float]] = pa.Field(gt=0)

    _id_columns = ("rod_id", "sphere_a", "sphere_b")


_BOOL_TEXT = {"true": True, "1": True, "yes": True, "free": True,
              "false": False, "0": False, "no": False, "fixed": False}


def _required_and_optional(model) -> tuple[list[str], list[str]]:
    schema = model.to_schema()
    req = [n for n, c in schema.columns.items() if c.required]
    opt = [n for n, c in schema.columns.items() if not c.required]
    return req, opt


def _describe_check(check: str) -> str:
    check = str(check)
    if check.startswith("coerce_dtype") or check.startswith("dtype"):
        kind = check.split("(")[-1].rstrip(")").strip("'")
        return "is not " + ("a number" if "float" in kind else
                            "an integer" if "int" in kind else
                            "true/false" if "bool" in kind else f"of type {kind}")
    if check == "field_uniqueness":
        return "is a duplicate"
    if check.startswith("greater_than_or_equal_to("):
        return "must be >= " + check[len("greater_than_or_equal_to("):-1]
    if check.startswith("greater_than("):
        return "must be > " + check[len("greater_than("):-1]
    if check.startswith("less_than_or_equal_to("):
        return "must be <= " + check[len("less_than_or_equal_to("):-1]
    if check.startswith("isin("):
        return "must be one of " + check[len("isin("):-1]
    if check.startswith("str_length"):
        return "must not be empty"
    if check == "not_nullable":
        return "is missing"
    return f"breaks rule {check}"


def _as_float(text: str) -> float:
    try:
        return float(text)
    except ValueError:
        return np.nan


def _infinite(s: pd.Series) -> np.ndarray:
    """Positions of +-inf in a number column, given as numbers or as text (``inf``,
    ``-Infinity``, ``1e999``: what the column's coercion to float would turn into inf)."""
    if pd.api.types.is_numeric_dtype(s) and not pd.api.types.is_bool_dtype(s):
        values = s.to_numpy(dtype=float, na_value=np.nan)
    else:
        text = s.astype(str).str.strip()
        try:
            values = text.astype(float).to_numpy()
        except (ValueError, TypeError):  # some cell is not a number: pandera names it
            values = text.map(_as_float).to_numpy(dtype=float)
    return np.flatnonzero(np.isinf(values))


#: tables validated lately, by model and content (:func:`validate_table`)
_VALIDATED: "OrderedDict[tuple, pd.DataFrame]" = OrderedDict()
_VALIDATED_LOCK = threading.Lock()
#: how many validated tables are kept (a run reads the same few tables many times)
VALIDATED_KEPT = 64


def _content_key(df: pd.DataFrame, model) -> tuple | None:
    """What a validation's result depends on: the model, the columns with their dtypes
    and every cell (a 64-bit hash per row, hashed again); None for cells that cannot be
    hashed."""
    try:
        rows = pd.util.hash_pandas_object(df, index=False).to_numpy()
    except TypeError:
        return None
    return (model, tuple(map(str, df.columns)), tuple(map(str, df.dtypes)), len(df),
            hashlib.blake2b(rows.tobytes(), digest_size=16).digest())


def validate_table(df: pd.DataFrame, model, source: str = "<table>") -> pd.DataFrame:
    """Validate a DataFrame against ``model``; return the coerced copy.

    Row numbers in messages are CSV lines (header = line 1) assuming ``df`` has a
    default RangeIndex in file order.

    A run reads the same few tables many times (its artefact, sensors, control points:
    a small run validates some 250 tables, about 100 of them distinct), so the last ``VALIDATED_KEPT`` results are kept by content (the model, the
    columns, their dtypes and every cell, not the file's name or time) and a table seen
    before is returned as a copy of its earlier result. Only tables that pass are kept:
    a table that fails is validated, and named, every time.
    """
    key = _content_key(df, model)
    if key is not None:
        with _VALIDATED_LOCK:
            hit = _VALIDATED.get(key)
            if hit is not None:
                _VALIDATED.move_to_end(key)
        if hit is not None:
            return hit.copy()
    out = _validate(df, model, source)
    if key is not None:
        with _VALIDATED_LOCK:
            _VALIDATED[key] = out.copy()
            while len(_VALIDATED) > VALIDATED_KEPT:
                _VALIDATED.popitem(last=False)
    return out


def _validate(df: pd.DataFrame, model, source: str) -> pd.DataFrame:
    req, opt = _required_and_optional(model)
    columns = model.to_schema().columns
    nullable = {n for n, c in columns.items() if c.nullable}
    floats = {n for n, c in columns.items() if str(c.dtype).startswith("float")} - set(model._infinite_allowed)
    for name, c in columns.items():  # a pattern column (``field_f\d+_mm``): the columns it matches
        if getattr(c, "regex", False):
            matched = [str(col) for col in df.columns if re.fullmatch(name, str(col))]
            opt += matched
            nullable |= set(matched) if c.nullable else set()
            floats |= set(matched) if str(c.dtype).startswith("float") else set()
    problems: list[tuple[Optional[int], Optional[str], str]] = []
    missing = [c for c in req if c not in df.columns]
    if missing:
        raise TableError(source, [(None, None, f"missing required column(s) {missing}; "
                                   f"found {list(map(str, df.columns))}")])
    df = df.reset_index(drop=True).copy()
    for col in list(req) + [c for c in opt if c in df.columns]:
        s = df[col]
        if s.dtype == object or pd.api.types.is_string_dtype(s):
            text = s.astype(str).str.strip()
            empty = s.isna() | text.eq("") | text.str.lower().isin(["nan", "none", "null", "na"])
            if col.startswith("free_"):
                low = text.str.lower()
                bad = ~low.isin(list(_BOOL_TEXT)) & ~empty
                for i in np.flatnonzero(bad.to_numpy()):
                    problems.append((i + 2, col, f"value {s.iloc[i]!r} is not true/false"))
                df[col] = low.map(_BOOL_TEXT)
            elif col in model._id_columns:
                df[col] = text.where(~empty, "") if col in nullable else text
            elif col in nullable:
                df[col] = s.where(~empty, np.nan)
        else:
            empty = s.isna()
        if col in floats:
            for i in _infinite(s):
                problems.append((i + 2, col, f"value {s.iloc[i]!r} is not a finite number"))
        if col in nullable:
            continue  # empty is allowed (an unlabelled candidate, a spread from one estimate)
        for i in np.flatnonzero(empty.to_numpy()):
            problems.append((i + 2, col, "value is missing (empty or NaN)"))
    for group in model._unique_together:
        if all(c in df.columns for c in group):
            dup = df.duplicated(list(group), keep=False)
            first: dict[tuple, int] = {}
            for i in np.flatnonzero(dup.to_numpy()):
                key = tuple(df.loc[i, list(group)])
                if key in first:
                    problems.append((i + 2, ", ".join(group),
                                     f"duplicate {dict(zip(group, key))} (first on line {first[key] + 2})"))
                else:
                    first[key] = i
    problems += _unsafe_names(df, columns)
    try:
        out = model.validate(df, lazy=True)
    except pa.errors.SchemaErrors as err:
        fc = err.failure_cases
        seen = set()
        for _, r in fc.iterrows():
            idx = r.get("index")
            line = int(idx) + 2 if idx is not None and not pd.isna(idx) else None
            col = r.get("column")
            col = None if col is None or pd.isna(col) else str(col)
            check = str(r.get("check"))
            value = r.get("failure_case")
            if check in ("not_nullable",) or (line is not None and (line, col) in
                                              {(p[0], p[1]) for p in problems}):
                continue  # already reported as missing
            if check.startswith("dtype") and (line, col) in seen:
                continue
            seen.add((line, col))
            if check == "field_uniqueness" and line is not None:
                firsts = df.index[df[col].astype(str) == str(value)]
                if not len(firsts):  # a coerced number (1.0) against its text ("1")
                    firsts = df.index[pd.to_numeric(df[col], errors="coerce") == value]
                first_line = int(firsts[0]) + 2
                if first_line == line:
                    continue
                problems.append((line, col, f"value {value!r} is a duplicate (first on line {first_line})"))
                continue
            if check == "column_in_dataframe":
                problems.append((None, str(value), "required column is missing"))
                continue
            if line is None and str(value).startswith(("TypeError(", "ValueError(")):
                continue  # a check that could not run on uncoerced text: the cell's type error says why
            problems.append((line, col, f"value {value!r} {_describe_check(check)}"))
        # a pattern column's case (``field_f\d+_mm``) repeats its cell's, named by its column
        patterns = {n for n, c in columns.items() if getattr(c, "regex", False)}
        named = {(p[0], p[2]) for p in problems if p[1] not in patterns}
        problems = [p for p in problems if p[1] not in patterns or (p[0], p[2]) not in named]
        if not problems:
            problems.append((None, None, str(err)))
    if problems:
        problems.sort(key=lambda p: (p[0] or 0, p[1] or ""))
        raise TableError(source, problems)
    return out


def _unsafe_names(df: pd.DataFrame, columns) -> list[tuple[int, str, str]]:
    """A problem per distinct value of a name column (:data:`NAME_COLUMNS`) that is not
    one safe path component, on the line where it first appears."""
    problems = []
    for col in (c for c in NAME_COLUMNS if c in df.columns and c in columns):
        s = df[col]
        for value in pd.unique(s):
            if value is None or (isinstance(value, float) and np.isnan(value)) or value == "":
                continue  # missing: reported as such
            problem = name_problem(str(value))
            if problem is not None:
                line = int(np.flatnonzero((s == value).to_numpy())[0]) + 2
                shown = value if len(str(value)) <= 60 else str(value)[:40] + "..." + str(value)[-10:]
                problems.append((line, col, f"value {shown!r}: {problem}"))
    return problems


def read_csv_text(path, max_rows: int | None = None, why: str = "") -> pd.DataFrame:
    """Read a CSV with every cell as text (validation coerces types and names bad cells).

    The file must be UTF-8 (a byte-order mark, as Excel's "CSV UTF-8" writes, and CRLF
    line ends are fine); bytes that are not UTF-8 are reported with their line and column.
    A table of more than ``max_rows`` rows is refused before its cells are parsed
    (``why`` says why the bound); a table whose columns are separated by semicolons or
    tabs (a spreadsheet of another locale) is refused with that hint.
    """
    path = Path(path)
    if (kind := not_a_file(path)) is not None and kind != "a folder":  # a FIFO would be waited on forever
        raise TableError(str(path), [(None, None, f"{kind}, not a CSV file")])
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        raise TableError(str(path), [(None, None, "file not found")]) from None
    except IsADirectoryError:
        raise TableError(str(path), [(None, None, "is a folder; expected a CSV file")]) from None
    except OSError as err:
        raise TableError(str(path), [(None, None, f"cannot be read ({err.strerror or err})")]) from None
    text = _utf8_text(raw, str(path))
    if max_rows is not None and text.count("\n") > max_rows:
        rows = sum(1 for line in text.splitlines()[1:] if line.strip())
        if rows > max_rows:
            raise TableError(str(path), [(None, None, f"{rows:,} rows; at most {max_rows:,} can be used"
                                                      + (f" ({why})" if why else ""))])
    _check_separator(text, str(path))
    try:
        df = pd.read_csv(io.StringIO(text), dtype=str, keep_default_na=False, skipinitialspace=True,
                         comment=None)
    except (pd.errors.ParserError, pd.errors.EmptyDataError) as err:
        raise TableError(str(path), [(None, None, "not a readable CSV table (" + " ".join(str(err).split()) + ")")]
                         ) from None
    df.columns = [c.strip() for c in df.columns]
    return df


def _check_separator(text: str, source: str) -> None:
    """Refuse a header separated by ``;`` or tabs rather than commas (a spreadsheet saved
    with another locale's list separator, often with decimal commas too)."""
    header = text.lstrip("\ufeff").split("\n", 1)[0]
    for sep, what in ((";", "semicolons"), ("\t", "tabs")):
        if "," not in header and header.count(sep) >= 1:
            raise TableError(source, [(1, None, f"the columns are separated by {what}, not commas; fringecal reads "
                                                "comma-separated values with a decimal point (in a spreadsheet "
                                                "set the list separator to ',' and the decimal symbol to '.', "
                                                "or save as 'CSV UTF-8 (comma delimited)' in an English locale)")])


def _utf8_text(raw: bytes, source: str) -> str:
    """``raw`` decoded as UTF-8 (a leading byte-order mark dropped), else a TableError
    naming each line, column and byte that is not UTF-8."""
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError:
        pass
    if raw[:2] in (b"\xff\xfe", b"\xfe\xff"):
        raise TableError(source, [(1, None, "the file is UTF-16 text; save it as UTF-8 (in Excel: "
                                            "'CSV UTF-8 (comma delimited)')")])
    lines = raw.split(b"\n")
    header = next(csv.reader([lines[0].decode("utf-8-sig", "replace").rstrip("\r")]), [])
    problems = []
    for number, line in enumerate(lines, 1):
        try:
            line.decode("utf-8-sig" if number == 1 else "utf-8")
        except UnicodeDecodeError as err:
            before = line[:err.start].decode("utf-8-sig" if number == 1 else "utf-8", "replace")
            field = len(next(csv.reader([before]), [""])) - 1 if before else 0
            column = header[field].strip() if number > 1 and field < len(header) else None
            problems.append((number, column, f"byte 0x{line[err.start]:02x} (character {len(before) + 1} of the "
                                             "line) is not UTF-8 text; save the table as UTF-8 (in Excel: "
                                             "'CSV UTF-8 (comma delimited)')"))
    raise TableError(source, problems)


def read_table(path, model) -> pd.DataFrame:
    """Read a CSV and validate it against ``model`` (one error naming every problem);
    more rows than the model's bound are refused before the cells are parsed."""
    return validate_table(read_csv_text(path, model._max_rows, model._max_rows_reason), model, str(path))


def read_any_table(path, *models) -> pd.DataFrame:
    """Read a CSV that may follow any of ``models``: validated against the first whose
    required columns it has (e.g. sphere centres per ``measurement`` or a ball-bar's per
    ``position``); with none, one error naming what each model misses."""
    df = read_csv_text(path)
    missing = []
    for model in models:
        req, _ = _required_and_optional(model)
        lacks = [c for c in req if c not in df.columns]
        if not lacks:
            return validate_table(df, model, str(path))
        missing.append(f"{lacks} for a {model.__name__}")
    raise TableError(str(path), [(None, None, f"missing required column(s) {' or '.join(missing)}; "
                                              f"found {list(map(str, df.columns))}")])


def write_table(df: pd.DataFrame, path, model=None) -> Path:
    """Validate (when ``model`` is given) and write atomically (:mod:`fringecal.atomic`)."""

    path = Path(path)
    if model is not None:
        df = validate_table(df, model, str(path))
    with atomic_path(path) as tmp:
        df.to_csv(tmp, index=False, float_format="%.10g")
    return path
