"""Fewer camera pixels over the same sensor: small, fast images for tests and demos.

Eq. 2-21 maps pixel (0, 0) and (M-1, N-1) to the sensor corners whatever M and N,
so a scaled camera sees the same field of view with larger pixels.
"""

from __future__ import annotations

from dataclasses import replace

from ..rig import Rig, Scanner
from ..sensor import SensorFormat

__all__ = ["scaled_format", "scaled_scanner", "scaled_rig"]


def scaled_format(fmt: SensorFormat, width_px: int, height_px: int | None = None) -> SensorFormat:
    """``fmt`` with ``width_px`` x ``height_px`` pixels (height keeps the aspect ratio
    if omitted) over the same physical size.

    >>> scaled_format(SensorFormat(2048, 2048, 15.1, 15.1), 256)
    SensorFormat(width_px=256, height_px=256, width_mm=15.1, height_mm=15.1)
    """
    if height_px is None:
        height_px = max(2, round(width_px * fmt.height_px / fmt.width_px))
    if width_px < 2 or height_px < 2:
        raise ValueError(f"a camera needs at least 2 x 2 pixels, not {width_px} x {height_px}")
    return SensorFormat(int(width_px), int(height_px), fmt.width_mm, fmt.height_mm)


def scaled_scanner(scanner: Scanner, width_px: int, height_px: int | None = None) -> Scanner:
    """``scanner`` with its camera resampled to ``width_px`` x ``height_px``."""
    cam = replace(scanner.camera, format=scaled_format(scanner.camera.format, width_px, height_px))
    return replace(scanner, camera=cam)


def scaled_rig(rig: Rig, width_px: int, height_px: int | None = None) -> Rig:
    """Every camera of ``rig`` resampled (projectors, parameters and flags unchanged)."""
    return replace(rig, scanners=tuple(scaled_scanner(s, width_px, height_px) for s in rig.scanners))
