"""Where on a sensor's image plane the calibration saw control points: a coarse occupancy
grid over the format.

A calibrated model is only known where it was observed. The 14 parameters extrapolate
with the lens's own shape, but a correction field (:mod:`fringecal.lens.field`, a
degree-4 polynomial) extrapolates freely beyond its data, and neither is tested there.
So the calibration records, per sensor, the cells of a grid over its format that held
control points of the adjustment, and ``fringecal measure`` flags every point whose
camera pixel or projector phase pair falls outside them (:mod:`fringecal.measure.cloud`).

Coordinates are measured image-plane mm from the format's centre (camera pixels by
:meth:`fringecal.sensor.SensorFormat.pixel_to_mm`, projector phases by
:meth:`~fringecal.sensor.SensorFormat.phase_to_mm`): the correction field's domain, and
the same for a binned camera as for the full one.

Grid: ``CELLS_ACROSS`` (16) cells across the format's width and as many down its height
as keep the cells near square (12 for a 4:3 format, 16 for a square one). A cell counts
as observed when it holds at least ``MIN_POINTS_PER_CELL`` (5) control points: a sphere
image gives tens to hundreds of points in the cells it covers, while a cell touched by a
sphere's rim or by a stray point holds one or two, which constrain nothing there. A
point on or beyond the format's edge, or NaN, is never inside.

>>> x = np.linspace(0.05, 7.5, 64)                  # the right half of a 15.1 mm format
>>> y = np.linspace(-7.5, 7.5, 64)
>>> right = np.stack(np.meshgrid(x, y), axis=-1).reshape(-1, 2)
>>> region = ObservedRegion.from_observations(right, 15.1, 15.1)
>>> region.counts.shape, region.fraction
((16, 16), 0.5)
>>> region.contains([[3.0, 1.0], [-3.0, 1.0], [9.0, 0.0], [np.nan, 0.0]]).tolist()
[True, False, False, False]
>>> ObservedRegion.from_dict(region.to_dict()) == region
True
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["ObservedRegion", "CELLS_ACROSS", "MIN_POINTS_PER_CELL", "grid_shape"]

#: cells across the format's width
CELLS_ACROSS = 16
#: control points a cell needs to count as observed
MIN_POINTS_PER_CELL = 5
#: what the recorded grid's coordinates are (the ``unit`` of :meth:`ObservedRegion.to_dict`)
UNIT = "measured image-plane mm from the format's centre (camera pixels, projector phases)"


def grid_shape(width_mm: float, height_mm: float, across: int = CELLS_ACROSS) -> tuple[int, int]:
    """(rows, columns) of the grid over a format: ``across`` columns, rows by the aspect.

    >>> grid_shape(19.0, 14.3), grid_shape(15.1, 15.1)
    ((12, 16), (16, 16))
    """
    return max(1, int(round(across * height_mm / width_mm))), int(across)


@dataclass(frozen=True, eq=False)
class ObservedRegion:
    """The control points of one sensor counted on a grid over its format.

    Attributes
    ----------
    width_mm, height_mm : float
        The format (image plane) the grid covers, centred on its middle.
    counts : ndarray of int, shape (ny, nx)
        Control points per cell; row 0 at the most negative image-plane y (a camera's
        first pixel row), column 0 at the most negative x.
    min_points : int
        Points a cell needs to count as observed.
    """

    width_mm: float
    height_mm: float
    counts: np.ndarray = field(repr=False)
    min_points: int = MIN_POINTS_PER_CELL

    def __post_init__(self):
        c = np.asarray(self.counts)
        if c.ndim != 2 or c.size == 0 or not np.issubdtype(c.dtype, np.number) or not np.all(np.isfinite(c)) \
                or np.any(c < 0) or np.any(c != np.round(c)):
            raise ValueError(f"counts must be a non-empty (ny, nx) grid of whole numbers >= 0, got shape {c.shape}")
        if not (self.width_mm > 0 and self.height_mm > 0):
            raise ValueError(f"the format must have a positive size, got {self.width_mm} x {self.height_mm} mm")
        if int(self.min_points) != self.min_points or self.min_points < 1:
            raise ValueError(f"min_points must be a whole number >= 1, got {self.min_points}")
        c = c.astype(np.int64)
        c.setflags(write=False)
        object.__setattr__(self, "counts", c)
        object.__setattr__(self, "width_mm", float(self.width_mm))
        object.__setattr__(self, "height_mm", float(self.height_mm))
        object.__setattr__(self, "min_points", int(self.min_points))

    @classmethod
    def from_observations(cls, image_mm, width_mm: float, height_mm: float, shape: tuple[int, int] | None = None,
                          min_points: int = MIN_POINTS_PER_CELL) -> "ObservedRegion":
        """The region of observations ``image_mm`` (..., 2) on a ``width_mm`` x
        ``height_mm`` format; ``shape`` (ny, nx) defaults to :func:`grid_shape`. NaN
        points and points off the format are not counted."""
        ny, nx = grid_shape(width_mm, height_mm) if shape is None else (int(shape[0]), int(shape[1]))
        empty = cls(width_mm, height_mm, np.zeros((ny, nx), np.int64), min_points)
        cell = empty._cells(image_mm).reshape(-1)
        counts = np.bincount(cell[cell >= 0], minlength=ny * nx).reshape(ny, nx)
        return cls(width_mm, height_mm, counts, min_points)

    @property
    def shape(self) -> tuple[int, int]:
        """(ny, nx) cells."""
        return self.counts.shape

    @property
    def observed(self) -> np.ndarray:
        """(ny, nx) bool: cells with at least ``min_points`` points."""
        return self.counts >= self.min_points

    @property
    def fraction(self) -> float:
        """Fraction of the format's area in observed cells (all cells are equal)."""
        return float(np.mean(self.observed))

    def _cells(self, image_mm) -> np.ndarray:
        """Flat cell index (...,) of each point (..., 2), -1 off the format or NaN."""
        m = np.asarray(image_mm, float)
        ny, nx = self.shape
        size = np.array([self.width_mm, self.height_mm])
        with np.errstate(invalid="ignore"):
            rel = m / size + 0.5                               # 0..1 over the format
            on = np.all((rel >= 0) & (rel <= 1), axis=-1)      # False for NaN
        rel = np.where(on[..., None], rel, 0.0)                # off the format, NaN, inf: not cast
        ix = np.minimum(np.floor(rel[..., 0] * nx), nx - 1).astype(np.int64)
        iy = np.minimum(np.floor(rel[..., 1] * ny), ny - 1).astype(np.int64)
        return np.where(on, iy * nx + ix, -1)

    def contains(self, image_mm) -> np.ndarray:
        """Whether each point (..., 2) mm lies in an observed cell -> bool (...,)."""
        cell = self._cells(image_mm)
        return np.where(cell >= 0, self.observed.reshape(-1)[np.maximum(cell, 0)], False)

    def to_dict(self) -> dict:
        """JSON-ready: the format, the grid's counts (rows of ``nx`` values, ``ny`` rows),
        the threshold, and the covered fraction (for a reader; :meth:`from_dict` recomputes it)."""
        ny, nx = self.shape
        return {"format_mm": [self.width_mm, self.height_mm], "cells": [nx, ny], "unit": UNIT,
                "min_points_per_cell": self.min_points, "fraction_observed": self.fraction,
                "points_per_cell": self.counts.tolist()}

    @classmethod
    def from_dict(cls, d: dict) -> "ObservedRegion":
        """Inverse of :meth:`to_dict`; ValueError naming what is wrong."""
        if not isinstance(d, dict):
            raise ValueError(f"an observed region is an object, not {type(d).__name__}")
        try:
            width, height = (float(v) for v in d["format_mm"])
            nx, ny = (int(v) for v in d["cells"])
            counts = np.asarray(d["points_per_cell"], float)
            threshold = d["min_points_per_cell"]
        except (KeyError, TypeError, ValueError) as err:
            raise ValueError(f"an observed region needs format_mm [w, h], cells [nx, ny], points_per_cell and "
                             f"min_points_per_cell ({type(err).__name__}: {err})") from None
        if counts.shape != (ny, nx):
            raise ValueError(f"points_per_cell has shape {counts.shape}, cells says {ny} rows of {nx}")
        if isinstance(threshold, bool) or not isinstance(threshold, int):
            raise ValueError(f"min_points_per_cell must be a whole number, got {threshold!r}")
        return cls(width, height, counts, threshold)

    def __eq__(self, other) -> bool:
        if not isinstance(other, ObservedRegion):
            return NotImplemented
        return (self.width_mm, self.height_mm, self.min_points) == (other.width_mm, other.height_mm,
                                                                    other.min_points) \
            and np.array_equal(self.counts, other.counts)

    __hash__ = None
