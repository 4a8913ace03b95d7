"""Calibration: DLT start values, control points and the object-space bundle adjustment
(thesis sections 2.2.3, 2.3.2-2.3.7, 6.3-6.5, 6.9). See docs/calibration.md."""

from .bundle import BundleOptions, BundleResult, ResidualStatistics, StartValueError, bundle_adjust
from .controlpoints import incidence_map, select_control_points
from .diagnostics import DegenerateCalibrationError, Diagnosis
from .dlt import DLTError, DLTEstimate, dlt
from .initial import initial_rig_from_dlt
from .model import BundleProblem
from .results import residual_tables, summary, write_outputs

__all__ = [
    "BundleOptions", "BundleProblem", "BundleResult", "DLTError", "DLTEstimate",
    "DegenerateCalibrationError", "Diagnosis", "ResidualStatistics", "StartValueError", "bundle_adjust",
    "dlt", "incidence_map", "initial_rig_from_dlt", "residual_tables",
    "select_control_points", "summary", "write_outputs",
]
