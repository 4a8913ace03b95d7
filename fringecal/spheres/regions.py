"""Glue between image regions and sphere fits.

The image-space step (segmenting sphere candidates in a measurement's maps) hands
each candidate over as a boolean region of the camera image. :func:`fit_region`
collects the region's triangulated points with their pixels and per-pixel flags
(e.g. :func:`boundary_flags` of the valid mask, saturation, low modulation), runs
:func:`~fringecal.spheres.robust.fit_sphere_robust`, and keeps the pixel of every
point, so the kept pixels can become the bundle adjustment's control points and the
region's bounding box goes into the sphere-fits table.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Mapping

import numpy as np
from scipy import ndimage

from fringecal.pointcloud import PointMaps
from fringecal.spheres.poses_and_links import sphere_fit_row
from fringecal.spheres.robust import RejectionConfig, RobustSphereFit, fit_sphere_robust

__all__ = ["boundary_flags", "RegionPoints", "region_points", "RegionFit", "fit_region"]


def boundary_flags(valid, width_px: int = 2) -> np.ndarray:
    """Pixels of ``valid`` (rows, cols) within ``width_px`` of an invalid pixel or the
    image border: where a pixel mixes the surface with the background (edge points)."""
    valid = np.asarray(valid, bool)
    inner = ndimage.binary_erosion(valid, structure=np.ones((3, 3), bool), iterations=width_px,
                                   border_value=0)
    return valid & ~inner


@dataclass(frozen=True)
class RegionPoints:
    """The triangulated points of one image region.

    ``points`` (n, 3) world mm; ``rows``, ``cols`` (n,) their camera pixels; ``flags``
    name -> (n,) bool; ``bbox`` (u_min, v_min, u_max, v_max) in pixels (u = column).
    """

    points: np.ndarray = field(repr=False)
    rows: np.ndarray = field(repr=False)
    cols: np.ndarray = field(repr=False)
    flags: dict = field(repr=False)
    bbox: tuple

    def __len__(self) -> int:
        return len(self.points)


def region_points(maps: PointMaps, region, flag_maps: Mapping[str, np.ndarray] | None = None) -> RegionPoints:
    """Points of the pixels of ``region`` (bool, rows x cols) that were triangulated."""
    region = np.asarray(region, bool)
    if region.shape != maps.x.shape:
        raise ValueError(f"region has shape {region.shape}, the maps {maps.x.shape}")
    rows, cols = np.nonzero(region & maps.valid)
    pts = np.stack([maps.x[rows, cols], maps.y[rows, cols], maps.z[rows, cols]], axis=-1).astype(float)
    flags = {name: np.asarray(m, bool)[rows, cols] for name, m in (flag_maps or {}).items()}
    if len(rows):
        bbox = (int(cols.min()), int(rows.min()), int(cols.max()), int(rows.max()))
    else:
        bbox = (0, 0, 0, 0)
    return RegionPoints(pts, rows, cols, flags, bbox)


@dataclass(frozen=True)
class RegionFit:
    """A robust sphere fit of one image region, with the pixels of its points."""

    fit: RobustSphereFit
    pixels: RegionPoints

    @property
    def kept_pixels(self) -> tuple[np.ndarray, np.ndarray]:
        """(rows, cols) of the points kept by the fit: the sphere's clean pixels."""
        return self.pixels.rows[self.fit.kept], self.pixels.cols[self.fit.kept]

    def row(self, measurement, scanner, candidate, sphere_id: str = "") -> dict:
        """The :class:`fringecal.schemas.SphereFitsTable` row, image region included."""
        return sphere_fit_row(measurement, scanner, candidate, self.fit, bbox=self.pixels.bbox, sphere_id=sphere_id)


def fit_region(maps: PointMaps, region, radius: float | None = None, *, expected_radius: float | None = None,
               flag_maps: Mapping[str, np.ndarray] | None = None, viewpoints=None, rod_axes=None,
               config: RejectionConfig | None = None) -> RegionFit:
    """Fit one sphere candidate given as an image region.

    Parameters
    ----------
    maps : PointMaps
        The measurement's triangulated maps.
    region : bool array, shape (rows, cols)
        The candidate's pixels.
    radius, expected_radius, viewpoints, rod_axes, config
        As :func:`fringecal.spheres.robust.fit_sphere_robust`.
    flag_maps : mapping of str to bool (rows, cols) maps
        Per-pixel rejections (``edge``: :func:`boundary_flags`; ``saturated``,
        ``low_modulation``, ``phase_error``, ``glint`` from the decoder).
    """
    pix = region_points(maps, region, flag_maps)
    fit = fit_sphere_robust(pix.points, radius, expected_radius=expected_radius, flags=pix.flags,
                            viewpoints=viewpoints, rod_axes=rod_axes, config=config)
    return RegionFit(fit, pix)
