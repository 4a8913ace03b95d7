"""Calibration: DLT start values, control points and the object-space bundle adjustment
(thesis sections 2.2.3, 2.3.2-2.3.7, 6.3-6.5, 6.9). See docs/calibration.md."""

from fringecal.calibration.bundle import BundleOptions, BundleResult, ResidualStatistics, StartValueError, bundle_adjust
from fringecal.calibration.controlpoints import incidence_map, select_control_points
from fringecal.calibration.diagnostics import DegenerateCalibrationError, Diagnosis
from fringecal.calibration.dlt import DLTError, DLTEstimate, dlt
from fringecal.calibration.initial import initial_rig_from_dlt
from fringecal.calibration.model import BundleProblem
from fringecal.calibration.results import residual_tables, summary

__all__ = [
    "BundleOptions", "BundleProblem", "BundleResult", "DLTError", "DLTEstimate",
    "DegenerateCalibrationError", "Diagnosis", "ResidualStatistics", "StartValueError", "bundle_adjust",
    "dlt", "incidence_map", "initial_rig_from_dlt", "residual_tables",
    "select_control_points", "summary",
]
