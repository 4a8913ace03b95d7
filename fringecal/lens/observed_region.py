"""Where on a sensor's image plane the calibration saw control points: the convex hull
of them, and their count on a coarse grid over the format.

A calibrated model is only known where it was observed. Between the control points a
smooth model interpolates (the images of the artefact's spheres leave gaps, which the 14
parameters and a correction field bridge); beyond them it extrapolates: the 14
parameters with the lens's own shape, a correction field (:mod:`fringecal.lens.field`,
a degree-4 polynomial) freely, and neither is tested there. So the calibration records,
per sensor, the convex hull of its control points, and ``fringecal measure`` flags every
point whose camera pixel or projector phase pair falls outside it
(:mod:`fringecal.measure.cloud`).

Why a hull and not the observed cells: on the default run the cells holding control
points cover 14-18 % of each format, the gaps between sphere images included, and would
flag 53-100 % of every ball-bar position, whose lengths are measured within 40.5 um;
the hull tells interpolation from extrapolation instead.

The hull is that of the points in cells holding at least ``MIN_POINTS_PER_CELL`` (5)
control points of a grid of ``CELLS_ACROSS`` (16) cells across the format's width (and as
many down its height as keep them near square): a sphere image gives tens to hundreds of
points in the cells it covers, while a stray point alone in its cell would stretch the
hull over a part of the image nothing else observed. The grid's counts are kept too, to
show where the points lay.

Coordinates are measured image-plane mm from the format's centre (camera pixels by
:meth:`fringecal.sensor.SensorFormat.pixel_to_mm`, projector phases by
:meth:`~fringecal.sensor.SensorFormat.phase_to_mm`): the correction field's domain, and
the same for a binned camera as for the full one. A point on or beyond the format's
edge, or NaN, is never inside.

>>> x = np.linspace(0.05, 7.5, 64)                  # the right half of a 15.1 mm format
>>> y = np.linspace(-7.5, 7.5, 64)
>>> right = np.stack(np.meshgrid(x, y), axis=-1).reshape(-1, 2)
>>> region = ObservedRegion.from_observations(right, 15.1, 15.1)
>>> region.counts.shape, round(region.fraction, 3), round(region.fraction_of_cells, 3)
((16, 16), 0.49, 0.5)
>>> region.contains([[3.0, 1.0], [-3.0, 1.0], [9.0, 0.0], [np.nan, 0.0]]).tolist()
[True, False, False, False]
>>> ObservedRegion.from_dict(region.to_dict()) == region
True
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["ObservedRegion", "CELLS_ACROSS", "MIN_POINTS_PER_CELL", "MIN_FRACTION", "grid_shape", "outside",
           "too_small"]

#: cells across the format's width
CELLS_ACROSS = 16
#: control points a cell needs to count as observed
MIN_POINTS_PER_CELL = 5
#: share of its format below which a sensor's region is too small to leave unremarked:
#: the calibration saw about as little of that image as one artefact pose at the far
#: stand-off shows a projector. On the default run (``fringecal run``) one pose alone
#: covers 34-50 % of each camera's format and 17-24 % of each projector's (17-19 % at the
#: six farthest poses); all twelve cover 62 % and 36-37 %, the tests' four poses
#: (1, 5, 9, 12) 57-59 % and 25-26 % (docs/measure.md, with the recount's snippet)
MIN_FRACTION = 0.20
#: what the recorded grid's coordinates are (the ``unit`` of :meth:`ObservedRegion.to_dict`)
UNIT = "measured image-plane mm from the format's centre (camera pixels, projector phases)"


def grid_shape(width_mm: float, height_mm: float, across: int = CELLS_ACROSS) -> tuple[int, int]:
    """(rows, columns) of the grid over a format: ``across`` columns, rows by the aspect.

    >>> grid_shape(19.0, 14.3), grid_shape(15.1, 15.1)
    ((12, 16), (16, 16))
    """
    return max(1, int(round(across * height_mm / width_mm))), int(across)


def outside(regions, sightings) -> np.ndarray:
    """Whether each of n points lies outside the observed region of any sensor that saw
    it -> bool (n,).

    ``regions``: sensor name -> :class:`ObservedRegion` (None or a sensor missing: not
    known, flags nothing); ``sightings``: (sensor name, image_mm (n, 2)) of the same n
    points, e.g. a scanner's camera pixels and projector phases as image-plane mm.
    """
    out = None
    for name, image_mm in sightings:
        region = (regions or {}).get(name)
        if out is None:
            out = np.zeros(len(image_mm), bool)
        if region is not None:
            out |= ~region.contains(image_mm)
    return np.zeros(0, bool) if out is None else out


def too_small(regions, min_fraction: float = MIN_FRACTION) -> dict:
    """The regions (sensor name -> :class:`ObservedRegion`) covering less than
    ``min_fraction`` of their format.

    >>> full = ObservedRegion(2.0, 2.0, np.zeros((1, 1)), [[-1, -1], [1, -1], [1, 1], [-1, 1]])
    >>> corner = ObservedRegion(2.0, 2.0, np.zeros((1, 1)), [[-1, -1], [-0.2, -1], [-0.2, -0.2], [-1, -0.2]])
    >>> {n: round(r.fraction, 2) for n, r in too_small({"C1": full, "P1": corner}).items()}
    {'P1': 0.16}
    """
    return {name: r for name, r in (regions or {}).items() if r.fraction < min_fraction}


def _convex_hull(points: np.ndarray) -> np.ndarray:
    """Vertices (m, 2) of the convex hull of ``points`` (n, 2), counter-clockwise, none
    on a straight edge (Andrew's monotone chain); (0, 2) when they span no area."""
    p = np.unique(np.asarray(points, float).reshape(-1, 2), axis=0)  # sorted by x, then y
    if len(p) < 3:
        return np.zeros((0, 2))

    def chain(pts):
        out = []
        for q in pts:
            while len(out) >= 2 and _cross(out[-2], out[-1], q) <= 0:
                out.pop()
            out.append(q)
        return out[:-1]

    hull = np.array(chain(p) + chain(p[::-1]))
    return hull if len(hull) >= 3 else np.zeros((0, 2))


def _cross(o, a, b) -> float:
    return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])


def _area(hull: np.ndarray) -> float:
    x, y = hull[:, 0], hull[:, 1]
    return 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y)) if len(hull) else 0.0


@dataclass(frozen=True, eq=False)
class ObservedRegion:
    """Where one sensor's control points lay: their convex hull and grid counts.

    Attributes
    ----------
    width_mm, height_mm : float
        The format (image plane), centred on its middle.
    counts : ndarray of int, shape (ny, nx)
        Control points per cell of the grid over the format; row 0 at the most negative
        image-plane y (a camera's first pixel row), column 0 at the most negative x.
    hull : ndarray, shape (m, 2)
        Vertices of the convex hull of the points in observed cells (mm, counter-clockwise;
        m = 0: nothing observed, nothing inside).
    min_points : int
        Points a cell needs to count as observed.
    """

    width_mm: float
    height_mm: float
    counts: np.ndarray = field(repr=False)
    hull: np.ndarray = field(repr=False)
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
        h = np.asarray(self.hull, float).reshape(-1, 2) if np.size(self.hull) else np.zeros((0, 2))
        if len(h) and (len(h) < 3 or not np.all(np.isfinite(h))):
            raise ValueError(f"the hull needs at least 3 finite vertices, got {len(h)}")
        turns = [_cross(h[i - 2], h[i - 1], h[i]) for i in range(len(h))]
        if len(h) and min(turns) <= 0:
            raise ValueError("the hull's vertices must run counter-clockwise around a convex polygon")
        if np.any(np.abs(h) > np.array([self.width_mm, self.height_mm]) / 2 * (1 + 1e-9)):
            raise ValueError("the hull has vertices off the format")
        c = c.astype(np.int64)
        c.setflags(write=False)
        h.setflags(write=False)
        object.__setattr__(self, "counts", c)
        object.__setattr__(self, "hull", h)
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
        empty = cls(width_mm, height_mm, np.zeros((ny, nx), np.int64), np.zeros((0, 2)), min_points)
        pts = np.asarray(image_mm, float).reshape(-1, 2)
        cell = empty._cells(pts)
        counts = np.bincount(cell[cell >= 0], minlength=ny * nx).reshape(ny, nx)
        dense = (counts >= min_points).reshape(-1)
        kept = pts[(cell >= 0) & dense[np.maximum(cell, 0)]]
        return cls(width_mm, height_mm, counts, _convex_hull(kept), min_points)

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
        """Fraction of the format's area inside the hull."""
        return _area(self.hull) / (self.width_mm * self.height_mm)

    @property
    def fraction_of_cells(self) -> float:
        """Fraction of the format's cells that are observed (all cells are equal)."""
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
        """Whether each point (..., 2) mm lies in the hull (on its edge counts) -> bool (...,).

        O(log m) per point for m vertices: the hull is a fan of triangles from its first
        vertex, ordered by angle; a point's angle finds its triangle (binary search), and
        only that triangle's outer edge is tested. 1.6 million points take about 0.3 s
        whatever the hull (the test of every edge took 1.6 s on a 205-vertex one).
        """
        m = np.asarray(image_mm, float)
        flat = m.reshape(-1, 2)
        h = self.hull
        if not len(h):
            return np.zeros(m.shape[:-1], bool)
        tol = 1e-12 * max(self.width_mm, self.height_mm) ** 2
        d = h[1:] - h[0]                                   # fan directions, counter-clockwise
        ref = d[0]
        fan = np.arctan2(ref[0] * d[:, 1] - ref[1] * d[:, 0], ref @ d.T)  # 0 .. < pi, increasing
        finite = np.isfinite(flat).all(axis=1)            # NaN and inf: never inside
        q = flat[finite] - h[0]
        angle = np.arctan2(ref[0] * q[:, 1] - ref[1] * q[:, 0], q @ ref)
        k = np.clip(np.searchsorted(fan, angle, side="left"), 1, len(fan) - 1)  # triangle 0, k - 1, k
        a, b = d[k - 1], d[k]
        outer = (b[:, 0] - a[:, 0]) * (q[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (q[:, 0] - a[:, 0])
        span = 1e-12
        inside = np.zeros(len(flat), bool)
        inside[finite] = ((angle >= -span) & (angle <= fan[-1] + span) & (outer >= -tol)) \
            | (np.einsum("ij,ij->i", q, q) <= tol)        # the fan's own vertex
        return inside.reshape(m.shape[:-1])

    def depth_inside(self, image_mm) -> np.ndarray:
        """How far each point (n, 2) mm lies inside the hull -> (n,) mm: its least
        distance inside an edge, negative outside (beyond the nearest edge's line), NaN
        for NaN and -inf with no hull.

        >>> square = ObservedRegion(4.0, 4.0, np.zeros((1, 1)), [[-1, -1], [1, -1], [1, 1], [-1, 1]])
        >>> square.depth_inside([[0.0, 0.0], [0.5, 0.0], [1.5, 0.2]]).tolist()
        [1.0, 0.5, -0.5]
        """
        c = np.asarray(image_mm, float).reshape(-1, 2)
        h = self.hull
        if not len(h):
            return np.full(len(c), -np.inf)
        e = np.roll(h, -1, axis=0) - h                          # edges, counter-clockwise
        inward = (e[:, 0] * (c[:, None, 1] - h[:, 1]) - e[:, 1] * (c[:, None, 0] - h[:, 0])) / np.linalg.norm(e, axis=1)
        return inward.min(axis=1)

    def contains_disc(self, centres_mm, radii_mm) -> np.ndarray:
        """Whether each disc (centres (n, 2) mm, radii (n,) or scalar mm) lies wholly in
        the hull -> bool (n,): its centre at least its radius inside every edge (a
        sphere's image inside what the calibration observed).

        >>> square = ObservedRegion(4.0, 4.0, np.zeros((1, 1)), [[-1, -1], [1, -1], [1, 1], [-1, 1]])
        >>> square.contains_disc([[0.0, 0.0], [0.5, 0.0], [0.5, 0.0], [np.nan, 0.0]], [1.0, 0.5, 0.6, 0.1]).tolist()
        [True, True, False, False]
        """
        depth = self.depth_inside(centres_mm)
        with np.errstate(invalid="ignore"):
            return depth >= np.broadcast_to(np.asarray(radii_mm, float), depth.shape)  # False for NaN

    def to_dict(self) -> dict:
        """JSON-ready: the format, the hull's vertices, the grid's counts (rows of ``nx``
        values, ``ny`` rows), the threshold, and the covered fractions (for a reader;
        :meth:`from_dict` recomputes them)."""
        ny, nx = self.shape
        return {"format_mm": [self.width_mm, self.height_mm], "unit": UNIT, "hull_mm": self.hull.tolist(),
                "fraction_observed": self.fraction, "cells": [nx, ny], "min_points_per_cell": self.min_points,
                "fraction_of_cells_observed": self.fraction_of_cells, "points_per_cell": self.counts.tolist()}

    @classmethod
    def from_dict(cls, d: dict) -> "ObservedRegion":
        """Inverse of :meth:`to_dict`; ValueError naming what is wrong."""
        if not isinstance(d, dict):
            raise ValueError(f"an observed region is an object, not {type(d).__name__}")
        try:
            width, height = (float(v) for v in d["format_mm"])
            nx, ny = (int(v) for v in d["cells"])
            counts = np.asarray(d["points_per_cell"], float)
            hull = np.asarray(d["hull_mm"], float)
            threshold = d["min_points_per_cell"]
        except (KeyError, TypeError, ValueError) as err:
            raise ValueError(f"an observed region needs format_mm [w, h], hull_mm [[x, y], ...], cells [nx, ny], "
                             f"points_per_cell and min_points_per_cell ({type(err).__name__}: {err})") from None
        if counts.shape != (ny, nx):
            raise ValueError(f"points_per_cell has shape {counts.shape}, cells says {ny} rows of {nx}")
        if hull.size and (hull.ndim != 2 or hull.shape[1] != 2):
            raise ValueError(f"hull_mm must be a list of [x, y] vertices, got shape {hull.shape}")
        if isinstance(threshold, bool) or not isinstance(threshold, int):
            raise ValueError(f"min_points_per_cell must be a whole number, got {threshold!r}")
        return cls(width, height, counts, hull, threshold)

    def __eq__(self, other) -> bool:
        if not isinstance(other, ObservedRegion):
            return NotImplemented
        return (self.width_mm, self.height_mm, self.min_points) == (other.width_mm, other.height_mm,
                                                                    other.min_points) \
            and np.array_equal(self.counts, other.counts) and np.array_equal(self.hull, other.hull)

    __hash__ = None
