"""Scenes for the virtual scanner: solid primitives grouped into named objects.

A :class:`Scene` is a list of :class:`SceneObject`; each object has a name, a kind
(``"sphere"``, ``"end_cap"``, ``"rod"``, ``"plate"``, ...), a material name (looked up
in :class:`~fringecal.simulate.config.RenderConfig.materials`), optionally the id of
the artefact sphere it belongs to, and one or more primitives (:class:`Sphere`,
:class:`Cylinder`, :class:`Box`, :class:`Plane`, :class:`Panel`). Primitives are
closed solids (the plane is infinite and two-sided, the panel a two-sided open sheet),
so where two overlap only the outer surface is visible, e.g. an end cap hides the
part of its sphere it encloses.

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

from fringecal.simulate import geometry as g

__all__ = ["Sphere", "Cylinder", "Box", "Plane", "Panel", "SceneObject", "Scene", "Hits"]


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
class Panel:
    """A free-form curved panel: the two-sided sheet z = f(x, y) over |x| <= a, |y| <= b
    of its own frame (``origin`` (3,) mm, ``axes`` (3, 3) whose rows are its unit x, y,
    z axes in world coordinates, right-handed), with

        f(x, y) = kx x^2 / 2 + ky y^2 / 2 + c30 u^3 + c21 u^2 v + c12 u v^2 + c03 v^3,

    u = x / a, v = y / b; ``half_size`` (a, b) mm, ``curvature`` (kx, ky) 1/mm (1/R:
    the paraboloid osculates a sphere of radius R at the vertex; 0 is straight, a
    negative curvature bends towards -z) and ``cubic`` (c30, c21, c12, c03) mm (each
    the cubic term's height at the patch edge). World points follow
    ``x_world = axes^T x_local + origin``. The numpy methods below are the reference
    the compiled intersection is tested against."""

    origin: np.ndarray
    axes: np.ndarray
    half_size: np.ndarray
    curvature: np.ndarray = (0.0, 0.0)
    cubic: np.ndarray = (0.0, 0.0, 0.0, 0.0)

    def __post_init__(self):
        object.__setattr__(self, "origin", np.asarray(self.origin, float).reshape(3))
        axes = np.asarray(self.axes, float).reshape(3, 3)
        if not np.allclose(axes @ axes.T, np.eye(3), atol=1e-9) or np.linalg.det(axes) < 0:
            raise ValueError("panel axes must be orthonormal, right-handed rows")
        object.__setattr__(self, "axes", axes)
        half = np.asarray(self.half_size, float).reshape(2)
        if not np.all(half > 0):
            raise ValueError(f"panel half sizes must be positive, got {half.tolist()}")
        object.__setattr__(self, "half_size", half)
        object.__setattr__(self, "curvature", np.asarray(self.curvature, float).reshape(2))
        object.__setattr__(self, "cubic", np.asarray(self.cubic, float).reshape(4))

    def height(self, x, y) -> np.ndarray:
        """f(x, y) (mm) at local coordinates x, y (any matching shapes)."""
        x, y = np.asarray(x, float), np.asarray(y, float)
        (kx, ky), (a, b), (c30, c21, c12, c03) = self.curvature, self.half_size, self.cubic
        u, v = x / a, y / b
        return 0.5 * (kx * x * x + ky * y * y) + c30 * u ** 3 + c21 * u * u * v + c12 * u * v * v + c03 * v ** 3

    def gradient(self, x, y) -> tuple[np.ndarray, np.ndarray]:
        """(df/dx, df/dy) at local x, y."""
        x, y = np.asarray(x, float), np.asarray(y, float)
        (kx, ky), (a, b), (c30, c21, c12, c03) = self.curvature, self.half_size, self.cubic
        u, v = x / a, y / b
        return (kx * x + (3 * c30 * u * u + 2 * c21 * u * v + c12 * v * v) / a,
                ky * y + (c21 * u * u + 2 * c12 * u * v + 3 * c03 * v * v) / b)

    def to_world(self, local) -> np.ndarray:
        """Local points (..., 3) -> world."""
        return np.asarray(local, float) @ self.axes + self.origin

    def to_local(self, world) -> np.ndarray:
        """World points (..., 3) -> local."""
        return (np.asarray(world, float) - self.origin) @ self.axes.T

    def surface_points(self, x, y) -> np.ndarray:
        """World points (..., 3) of the surface above local x, y."""
        x, y = np.broadcast_arrays(np.asarray(x, float), np.asarray(y, float))
        return self.to_world(np.stack([x, y, self.height(x, y)], axis=-1))

    def normals(self, x, y) -> np.ndarray:
        """Unit world normals (..., 3) on the +z side at local x, y."""
        fx, fy = self.gradient(x, y)
        n = np.stack(np.broadcast_arrays(-fx, -fy, np.ones_like(fx)), axis=-1)
        return (n / np.linalg.norm(n, axis=-1, keepdims=True)) @ self.axes

    def distance(self, world, iterations: int = 20) -> tuple[np.ndarray, np.ndarray]:
        """Signed distance (mm, + on the +z side) of world points (n, 3) from the
        unbounded surface, and the local (x, y) (n, 2) of their foot points (Newton on
        the foot point's conditions, from the point's own x, y; for points within a
        few mm of a surface whose slopes stay moderate)."""
        p = self.to_local(np.asarray(world, float).reshape(-1, 3))
        x, y = p[:, 0].copy(), p[:, 1].copy()
        (kx, ky), (a, b), (c30, c21, c12, c03) = self.curvature, self.half_size, self.cubic
        for _ in range(iterations):
            f = self.height(x, y)
            fx, fy = self.gradient(x, y)
            u, v = x / a, y / b
            fxx = kx + (6 * c30 * u + 2 * c21 * v) / (a * a)
            fxy = (2 * c21 * u + 2 * c12 * v) / (a * b)
            fyy = ky + (2 * c12 * u + 6 * c03 * v) / (b * b)
            # foot point: (x - px) + (f - pz) fx = 0, (y - py) + (f - pz) fy = 0
            dz = f - p[:, 2]
            r1, r2 = x - p[:, 0] + dz * fx, y - p[:, 1] + dz * fy
            j11 = 1 + fx * fx + dz * fxx
            j12 = fx * fy + dz * fxy
            j22 = 1 + fy * fy + dz * fyy
            det = j11 * j22 - j12 * j12
            sx, sy = (j22 * r1 - j12 * r2) / det, (j11 * r2 - j12 * r1) / det
            x, y = x - sx, y - sy
            if np.all(np.abs(sx) + np.abs(sy) < 1e-12):
                break
        foot = np.stack([x, y, self.height(x, y)], axis=-1)
        fx, fy = self.gradient(x, y)
        n = np.stack([-fx, -fy, np.ones_like(fx)], axis=-1)
        n /= np.linalg.norm(n, axis=-1, keepdims=True)
        return np.einsum("ij,ij->i", p - foot, n), np.stack([x, y], axis=-1)

    def height_range(self) -> tuple[float, float]:
        """(lowest, highest) f may take over the patch: a bound, exact without the cubic."""
        (kx, ky), (a, b) = self.curvature, self.half_size
        c = float(np.abs(self.cubic).sum())
        lo = min(0.0, kx * a * a / 2) + min(0.0, ky * b * b / 2) - c
        hi = max(0.0, kx * a * a / 2) + max(0.0, ky * b * b / 2) + c
        return lo, hi

    def packed(self) -> list[tuple[int, np.ndarray]]:
        row = np.zeros(g.N_PRIM_COLS)
        row[g.P:g.P + 3] = self.origin
        row[g.A:g.A + 3], row[g.B:g.B + 3] = self.axes[0], self.axes[1]
        row[g.PANEL_K:g.PANEL_K + 2] = self.curvature
        row[g.PANEL_HALF:g.PANEL_HALF + 2] = self.half_size
        row[g.PANEL_CUBIC:g.PANEL_CUBIC + 4] = self.cubic
        lo, hi = self.height_range()
        row[g.BOUND:g.BOUND + 3] = self.origin + self.axes[2] * (lo + hi) / 2
        row[g.BOUND_R] = np.sqrt(self.half_size @ self.half_size + ((hi - lo) / 2) ** 2) * (1 + 1e-9) + 1e-9
        return [(g.PANEL, row)]


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
