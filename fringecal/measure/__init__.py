"""Measure with a calibration: a measurement of several scanners -> one registered
point cloud in the global frame (``fringecal measure``)."""

from fringecal.measure.cloud import (
           POINT_DTYPE,
           Cloud,
           MeasureSettings,
           measure_cloud,
           point_uncertainty,
           scanner_points,
)
from fringecal.measure.files import read_cloud, write_cloud
from fringecal.measure.overlap import OverlapStats, overlap_report
from fringecal.measure.run import measure_folder
from fringecal.measure.sources import MeasurementSourceError, measurement_entries

__all__ = ["POINT_DTYPE", "Cloud", "MeasureSettings", "measure_cloud", "point_uncertainty", "scanner_points",
           "read_cloud", "write_cloud", "OverlapStats", "overlap_report", "measure_folder",
           "MeasurementSourceError", "measurement_entries"]
