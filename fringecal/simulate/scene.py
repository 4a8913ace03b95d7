"""Scenes for the virtual scanner: solid primitives grouped into named objects.

A :class:`Scene` is a list of :class:`SceneObject`; each object has a name, a kind
(``"sphere"``, ``"end_cap"``, ``"rod"``, ``"plate"``, ...), a material name (looked up
in :class:`~fringecal.simulate.config.RenderConfig.materials`), optionally the id of
the artefact sphere it belongs to, and one or more primitives (:class:`Sphere`,
:class:`Cylinder`, :class:`Box`, :class:`Plane`). Primitives are closed solids (the
plane is infinite and two-sided), so where two overlap only the outer surface is
visible, e.g. an end cap hides the part of its sphere it encloses.

:meth:`Scene.cast` finds the first hit of many rays (vectorised, numba).

>>> scene = Scene((SceneObject("ball", "sphere", "sphere", (Sphere([0, 0, 100], 10),), "1"),))
>>> hits = scene.cast(np.zeros(3), np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]]))
>>> hits.t.tolist(), hits.object_index.tolist()
([90.0, inf], [0, -1])
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit, prange

from . import geometry as g

__all__ = ["Sphere", "Cylinder", "Box", "Plane", "SceneObject", "Scene", "Hits"]


def _unit(v) -> np.ndarray:
    v = np.asarray(v, float).reshape(3)
    n = np.linalg.norm(v)
    if not n > 0:
        raise ValueError("direction must be non-zero")
    return v / n


@dataclass(frozen=True)
class Sphere:
    """Solid sphere: ``centre`` (3,) mm and ``radius`` mm."""

    centre: np.ndarray
    radius: float

    def packed(self) -> list[tuple[int, np.ndarray]]:
        row = np.zeros(g.N_PRIM_COLS)
        row[g.P:g.P + 3] = np.asarray(self.centre, float)
        row[g.RADIUS] = self.radius
        row[g.BOUND:g.BOUND + 3], row[g.BOUND_R] = row[g.P:g.P + 3], self.radius
        return [(g.SPHERE, row)]


@dataclass(frozen=True)
class Cylinder:
    """Closed circular cylinder from ``start`` to ``end`` (axis points, mm)."""

    start: np.ndarray
    end: np.ndarray
    radius: float

    def packed(self) -> list[tuple[int, np.ndarray]]:
        # Long thin cylinders are packed as stacked pieces at most 4 radii long, so
        # their bounding spheres stay tight and culling per image tile works.
        s, e = np.asarray(self.start, float), np.asarray(self.end, float)
        length = float(np.linalg.norm(e - s))
        axis = _unit(e - s)
        n = max(1, int(np.ceil(length / (4 * self.radius))))
        rows = []
        for i in range(n):
            a, b = s + axis * (length * i / n), s + axis * (length * (i + 1) / n)
            row = np.zeros(g.N_PRIM_COLS)
            row[g.P:g.P + 3], row[g.A:g.A + 3] = a, axis
            row[g.RADIUS], row[g.LENGTH] = self.radius, length / n
            row[g.BOUND:g.BOUND + 3] = (a + b) / 2
            row[g.BOUND_R] = np.hypot(length / n / 2, self.radius)
            rows.append((g.CYLINDER, row))
        return rows


@dataclass(frozen=True)
class Box:
    """Oriented box: ``centre``, ``axes`` (3, 3) whose rows are its unit local axes in
    world coordinates, and ``half_size`` (3,) along them."""

    centre: np.ndarray
    axes: np.ndarray
    half_size: np.ndarray

    def packed(self) -> list[tuple[int, np.ndarray]]:
        axes = np.asarray(self.axes, float).reshape(3, 3)
        if not np.allclose(axes @ axes.T, np.eye(3), atol=1e-9):
            raise ValueError("box axes must be orthonormal rows")
        half = np.asarray(self.half_size, float).reshape(3)
        row = np.zeros(g.N_PRIM_COLS)
        row[g.P:g.P + 3] = np.asarray(self.centre, float)
        row[g.A:g.A + 9] = axes.ravel()
        row[g.HALF:g.HALF + 3] = half
        row[g.BOUND:g.BOUND + 3], row[g.BOUND_R] = row[g.P:g.P + 3], np.linalg.norm(half)
        return [(g.BOX, row)]


@dataclass(frozen=True)
class Plane:
    """Infinite two-sided plane through ``point`` with ``normal``."""

    point: np.ndarray
    normal: np.ndarray

    def packed(self) -> list[tuple[int, np.ndarray]]:
        row = np.zeros(g.N_PRIM_COLS)
        row[g.P:g.P + 3] = np.asarray(self.point, float)
        row[g.A:g.A + 3] = _unit(self.normal)
        row[g.BOUND_R] = np.inf
        return [(g.PLANE, row)]


@dataclass(frozen=True)
class SceneObject:
    """One object of a scene: ``kind`` labels it for the truth maps, ``material`` names
    its optical properties in the render configuration, ``sphere_id`` ties spheres (and
    their end caps) to the artefact definition."""

    name: str
    kind: str
    material: str
    primitives: tuple
    sphere_id: str | None = None

    def __post_init__(self):
        object.__setattr__(self, "primitives", tuple(self.primitives))
        if not self.primitives:
            raise ValueError(f"scene object {self.name!r} has no primitives")


@dataclass(frozen=True)
class Hits:
    """First hits of rays, arrays of shape (n,) or (n, 3); ``t`` = inf and index -1
    where a ray hits nothing."""

    t: np.ndarray
    point: np.ndarray
    normal: np.ndarray
    primitive_index: np.ndarray
    object_index: np.ndarray


@dataclass(frozen=True)
class Scene:
    """Objects in world coordinates (mm)."""

    objects: tuple[SceneObject, ...]

    def __post_init__(self):
        object.__setattr__(self, "objects", tuple(self.objects))
        names = [o.name for o in self.objects]
        if len(set(names)) != len(names):
            dup = sorted({n for n in names if names.count(n) > 1})
            raise ValueError(f"duplicate scene object names {dup}")
        if len(self.objects) > np.iinfo(np.int16).max:
            raise ValueError("a scene holds at most 32767 objects")

    def __add__(self, other: "Scene") -> "Scene":
        return Scene(self.objects + other.objects)

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(o.name for o in self.objects)

    @property
    def sphere_ids(self) -> tuple[str, ...]:
        """Sphere ids of the objects of kind ``"sphere"``, in object order; the truth
        map ``sphere_index`` indexes this tuple."""
        return tuple(o.sphere_id for o in self.objects if o.kind == "sphere")

    def object_sphere_index(self) -> np.ndarray:
        """Per object, its index in :attr:`sphere_ids` (-1 unless kind is sphere)."""
        out = np.full(len(self.objects), -1, np.int16)
        k = 0
        for i, o in enumerate(self.objects):
            if o.kind == "sphere":
                out[i] = k
                k += 1
        return out

    def without(self, *kinds: str) -> "Scene":
        """The scene minus all objects of the given kinds."""
        return Scene(tuple(o for o in self.objects if o.kind not in kinds))

    def packed(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(prims (n, N_PRIM_COLS) float, kinds (n,) int64, object index (n,) int64).

        One object's primitive may pack into several rows (long cylinders are split)."""
        rows, kinds, owner = [], [], []
        for i, o in enumerate(self.objects):
            for prim in o.primitives:
                for k, row in prim.packed():
                    rows.append(row)
                    kinds.append(k)
                    owner.append(i)
        prims = np.array(rows, float).reshape(len(rows), g.N_PRIM_COLS)
        return prims, np.array(kinds, np.int64), np.array(owner, np.int64)

    def cast(self, origins, directions, tmin: float = 0.0) -> Hits:
        """First hit of each ray ``origins + t directions`` (t > tmin) by brute force.

        Parameters
        ----------
        origins : array_like, shape (3,) or (n, 3)
        directions : array_like, shape (n, 3), unit vectors
        """
        d = np.ascontiguousarray(np.asarray(directions, float).reshape(-1, 3))
        o = np.ascontiguousarray(np.broadcast_to(np.asarray(origins, float), d.shape))
        prims, kinds, owner = self.packed()
        t, prim, normal = _cast_all(prims, kinds, o, d, float(tmin))
        obj = np.where(prim >= 0, owner[np.maximum(prim, 0)] if len(owner) else -1, -1)
        hit = np.isfinite(t)
        point = np.full(d.shape, np.nan)
        point[hit] = o[hit] + t[hit, None] * d[hit]
        return Hits(t, point, normal, prim, obj.astype(np.int64))


@njit(parallel=True, cache=True)
def _cast_all(prims, kinds, o, d, tmin):
    n = d.shape[0]
    t_out = np.empty(n)
    prim_out = np.empty(n, np.int64)
    normal = np.full((n, 3), np.nan)
    cand = np.arange(prims.shape[0])
    for i in prange(n):
        t, j, nx, ny, nz = g.nearest_hit(prims, kinds, cand, cand.shape[0],
                                         o[i, 0], o[i, 1], o[i, 2], d[i, 0], d[i, 1], d[i, 2], tmin)
        t_out[i] = t
        prim_out[i] = j
        if j >= 0:
            normal[i, 0], normal[i, 1], normal[i, 2] = nx, ny, nz
    return t_out, prim_out, normal
