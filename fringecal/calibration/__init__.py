"""Calibration: DLT start values, control points and the object-space bundle adjustment."""
