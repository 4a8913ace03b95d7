"""Synthetic point clouds with per-point truth, for testing fits and rejection.

A small ray caster at the point-cloud level (the image renderer lives in
``fringecal.simulate``): camera rays on a regular angular grid hit the nearest of a
few primitives (sphere, finite cylinders, annuli, rectangles); a hit counts only if
the projector also sees it (no shadow). Each point keeps the name of the primitive
it came from, so a test can check that no rod or end-cap point survives a fit.

The artefact's node geometry follows ``configs/thesis/materials.yaml``: a rod of
21.8 mm diameter leaves the sphere along the line through its centre; its mild
steel end cap (same outer diameter, 25 mm long) seats on the sphere with a 12 mm
bore, so the cap's end face is an annulus from 6 to 10.9 mm radius just off the
sphere surface.

Examples
--------
>>> cloud = sphere_node_cloud([0, 0, 0], 25.0, rod_axes=[[1, 0, 0.2]], camera=[0, 0, 2500],
...                           projector=[1200, 0, 2500], noise_mm=0.0, seed=0)
>>> sorted(map(str, set(cloud.truth)))
['endcap', 'rod', 'sphere']
>>> s = cloud.points[cloud.truth == "sphere"]
>>> float(np.abs(np.linalg.norm(s, axis=1) - 25.0).max()) < 1e-9
True
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = [
    "Sphere", "Cylinder", "Annulus", "Rectangle",
    "SyntheticCloud", "trace", "sphere_node_cloud", "sphere_plate_cloud",
]


def _unit(v) -> np.ndarray:
    v = np.asarray(v, float)
    return v / np.sqrt(np.einsum("...i,...i->...", v, v))[..., None]


def _dot(v, a) -> np.ndarray:
    """Rows of v (n, 3) dotted with a (3,), without BLAS (threaded gemv stalls on a busy machine)."""
    return v[..., 0] * a[0] + v[..., 1] * a[1] + v[..., 2] * a[2]


@dataclass(frozen=True)
class Sphere:
    centre: np.ndarray
    radius: float
    name: str = "sphere"

    def intersect(self, o, d):
        """Nearest positive ray parameter (n,) (inf if none) and unit normals (n, 3)."""
        w = o - self.centre
        b = np.einsum("ij,ij->i", w, d)
        c = np.einsum("ij,ij->i", w, w) - self.radius**2
        disc = b * b - c
        with np.errstate(invalid="ignore"):
            s = np.sqrt(disc)
        t1, t2 = -b - s, -b + s
        t = np.where(t1 > 1e-9, t1, np.where(t2 > 1e-9, t2, np.inf))
        t = np.where(disc >= 0, t, np.inf)
        hit = o + np.where(np.isfinite(t), t, 0)[:, None] * d
        return t, _unit(hit - self.centre)


@dataclass(frozen=True)
class Cylinder:
    """Open cylinder of ``radius`` about ``base + s axis`` for s in [s0, s1]."""

    base: np.ndarray
    axis: np.ndarray
    radius: float
    s0: float
    s1: float
    name: str = "rod"

    def intersect(self, o, d):
        a = _unit(self.axis)
        w = o - self.base
        da, wa = _dot(d, a), _dot(w, a)
        dp = d - da[:, None] * a
        wp = w - wa[:, None] * a
        A = np.einsum("ij,ij->i", dp, dp)
        B = 2 * np.einsum("ij,ij->i", dp, wp)
        C = np.einsum("ij,ij->i", wp, wp) - self.radius**2
        disc = B * B - 4 * A * C
        with np.errstate(invalid="ignore", divide="ignore"):
            s = np.sqrt(disc)
            roots = np.stack([(-B - s) / (2 * A), (-B + s) / (2 * A)])
        best = np.full(len(o), np.inf)
        for t in roots:
            along = wa + t * da
            ok = (disc >= 0) & (t > 1e-9) & (along >= self.s0) & (along <= self.s1) & (t < best)
            best = np.where(ok, t, best)
        hit = o + np.where(np.isfinite(best), best, 0)[:, None] * d
        rel = hit - self.base
        return best, _unit(rel - _dot(rel, a)[:, None] * a)


@dataclass(frozen=True)
class Annulus:
    """Flat ring at ``centre`` with unit ``normal``, radii r0..r1, seen from both sides."""

    centre: np.ndarray
    normal: np.ndarray
    r0: float
    r1: float
    name: str = "endcap"

    def intersect(self, o, d):
        n = _unit(self.normal)
        den = _dot(d, n)
        with np.errstate(divide="ignore", invalid="ignore"):
            t = _dot(self.centre - o, n) / den
        hit = o + np.where(np.isfinite(t), t, 0)[:, None] * d
        rel = hit - self.centre
        r = np.linalg.norm(rel - _dot(rel, n)[:, None] * n, axis=1)
        ok = np.isfinite(t) & (t > 1e-9) & (r >= self.r0) & (r <= self.r1)
        return np.where(ok, t, np.inf), np.where((den < 0)[:, None], n, -n)


@dataclass(frozen=True)
class Rectangle:
    """Flat rectangle: centre, unit normal, in-plane axes u, v and half extents."""

    centre: np.ndarray
    normal: np.ndarray
    u: np.ndarray
    half_u: float
    half_v: float
    name: str = "plate"

    def intersect(self, o, d):
        n = _unit(self.normal)
        u = _unit(self.u)
        v = np.cross(n, u)
        den = _dot(d, n)
        with np.errstate(divide="ignore", invalid="ignore"):
            t = _dot(self.centre - o, n) / den
        hit = o + np.where(np.isfinite(t), t, 0)[:, None] * d
        rel = hit - self.centre
        ok = np.isfinite(t) & (t > 1e-9) & (np.abs(_dot(rel, u)) <= self.half_u) & (np.abs(_dot(rel, v)) <= self.half_v)
        return np.where(ok, t, np.inf), np.where((den < 0)[:, None], n, -n)


def trace(primitives, origin, directions):
    """Nearest hit of each ray: (t (n,), index of the primitive (n,) or -1, normals (n, 3))."""
    o = np.broadcast_to(np.asarray(origin, float), directions.shape)
    best = np.full(len(directions), np.inf)
    which = np.full(len(directions), -1)
    normals = np.zeros_like(directions)
    for k, prim in enumerate(primitives):
        t, nrm = prim.intersect(o, directions)
        closer = t < best
        best = np.where(closer, t, best)
        which = np.where(closer, k, which)
        normals = np.where(closer[:, None], nrm, normals)
    return best, which, normals


@dataclass(frozen=True)
class SyntheticCloud:
    """Points (n, 3) with truth labels (n,), the camera grid index (n, 2) of each
    point (row, column) and the true incidence angles (n,) at the camera."""

    points: np.ndarray = field(repr=False)
    truth: np.ndarray = field(repr=False)
    pixel: np.ndarray = field(repr=False)
    incidence_rad: np.ndarray = field(repr=False)
    camera: np.ndarray
    projector: np.ndarray


def _render(primitives, camera, projector, target, half_width_mm, pixel_mm, noise_mm, rng):
    camera = np.asarray(camera, float)
    projector = np.asarray(projector, float)
    target = np.asarray(target, float)
    view = _unit(target - camera)
    side = _unit(np.cross(view, [0.0, 1.0, 0.0] if abs(view[1]) < 0.9 else [1.0, 0.0, 0.0]))
    up = np.cross(side, view)
    n = int(np.ceil(2 * half_width_mm / pixel_mm)) + 1
    g = np.linspace(-half_width_mm, half_width_mm, n)
    gu, gv = np.meshgrid(g, g)
    dirs = _unit(target + gu.ravel()[:, None] * side + gv.ravel()[:, None] * up - camera)
    t, which, normals = trace(primitives, camera, dirs)
    hit = np.isfinite(t)
    pts = camera + t[hit, None] * dirs[hit]
    which, normals, dirs_hit = which[hit], normals[hit], dirs[hit]
    pix = np.stack(np.unravel_index(np.flatnonzero(hit), gu.shape), axis=1)
    # lit by the projector: the surface faces it and nothing lies in between
    to_p = _unit(projector - pts)
    faces = np.einsum("ij,ij->i", normals, to_p) > 0
    ts, _, _ = trace(primitives, pts + 1e-6 * normals, to_p)
    lit = faces & ~np.isfinite(ts)
    pts, which, pix, dirs_hit, normals = pts[lit], which[lit], pix[lit], dirs_hit[lit], normals[lit]
    incidence = np.arccos(np.clip(-np.einsum("ij,ij->i", normals, dirs_hit), -1, 1))
    if noise_mm:
        pts = pts + rng.normal(0.0, noise_mm, len(pts))[:, None] * dirs_hit
    names = np.array([p.name for p in primitives])
    return SyntheticCloud(pts, names[which], pix, incidence, camera, projector)


def _node_primitives(centre, radius, rod_axes, rod_radius, bore_radius, endcap_length, rod_length):
    prims = [Sphere(centre, radius, "sphere")]
    for axis in rod_axes:
        a = _unit(axis)
        seat = np.sqrt(radius**2 - bore_radius**2)  # where the bore rim touches the sphere
        prims.append(Annulus(centre + seat * a, a, bore_radius, rod_radius, "endcap"))
        prims.append(Cylinder(centre, a, rod_radius, seat, seat + endcap_length, "endcap"))
        prims.append(Cylinder(centre, a, rod_radius, seat + endcap_length, seat + endcap_length + rod_length, "rod"))
    return prims


def sphere_node_cloud(centre, radius: float = 25.0, rod_axes=(), camera=(0.0, 0.0, 2500.0),
                      projector=(1200.0, 0.0, 2500.0), rod_radius: float = 10.9, bore_radius: float = 6.0,
                      endcap_length: float = 25.0, rod_length: float = 40.0, pixel_mm: float = 0.35,
                      noise_mm: float = 0.02, n_glints: int = 0, glint_mm: float = 1.0,
                      seed: int = 0) -> SyntheticCloud:
    """An artefact node as a scanner sees it: a sphere with rods (and end caps) leaving
    along ``rod_axes`` (k, 3), sampled on a camera grid of ``pixel_mm`` at the sphere.

    ``noise_mm`` is Gaussian noise along the camera ray. ``n_glints`` sphere points
    get an extra error of up to ``glint_mm`` along the ray and the truth ``"glint"``.
    """
    rng = np.random.default_rng(seed)
    centre = np.asarray(centre, float)
    prims = _node_primitives(centre, radius, rod_axes, rod_radius, bore_radius, endcap_length, rod_length)
    half = radius + 0.6 * (endcap_length + rod_length) if len(rod_axes) else 1.2 * radius
    cloud = _render(prims, camera, projector, centre, half, pixel_mm, noise_mm, rng)
    if n_glints:
        on_sphere = np.flatnonzero(cloud.truth == "sphere")
        pick = rng.choice(on_sphere, size=min(n_glints, len(on_sphere)), replace=False)
        rays = _unit(cloud.points[pick] - cloud.camera)
        err = rng.choice([-1.0, 1.0], len(pick)) * rng.uniform(0.2, 1.0, len(pick)) * glint_mm
        pts = cloud.points.copy()
        pts[pick] += err[:, None] * rays
        truth = cloud.truth.astype(object)
        truth[pick] = "glint"
        cloud = SyntheticCloud(pts, truth.astype(str), cloud.pixel, cloud.incidence_rad, cloud.camera,
                               cloud.projector)
    return cloud


def sphere_plate_cloud(plate_normal, distance_mm: float = 50.645, sphere_radius: float = 10.0,
                       plate_size_mm=(160.0, 80.0), stalk_radius: float = 4.0, centre=(0.0, 0.0, 0.0),
                       camera=(600.0, 0.0, 2500.0), projector=(-600.0, 0.0, 2500.0), pixel_mm: float = 0.35,
                       noise_mm: float = 0.02, sphere_bias_mm: float = 0.0, seed: int = 0) -> SyntheticCloud:
    """The chapter 5 sphere-plate artefact: a sphere of ``sphere_radius`` whose centre is
    ``distance_mm`` in front of a flat plate with unit normal ``plate_normal``, on a
    stalk. The sphere centre sits at ``centre``.

    ``sphere_bias_mm`` mimics the intensity-gradient error of chapter 5: each sphere
    point moves along the camera ray by ``bias * (n . b)``, where ``n`` is the surface
    normal and ``b`` the unit baseline from camera to projector (the side of the
    sphere facing the projector is brighter). It shifts the fitted sphere by an amount
    that depends on the plate's orientation only through what is visible, so the
    sphere-to-plane distance then varies with tilt and rotation.
    """
    rng = np.random.default_rng(seed)
    n = _unit(plate_normal)
    centre = np.asarray(centre, float)
    helper = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = _unit(helper - (helper @ n) * n)
    plate_centre = centre - distance_mm * n
    prims = [
        Sphere(centre, sphere_radius, "sphere"),
        Cylinder(plate_centre, n, stalk_radius, 0.0, distance_mm - 0.9 * sphere_radius, "stalk"),
        Rectangle(plate_centre, n, u, plate_size_mm[0] / 2, plate_size_mm[1] / 2, "plate"),
    ]
    cloud = _render(prims, camera, projector, plate_centre, max(plate_size_mm) * 0.6, pixel_mm, noise_mm, rng)
    if sphere_bias_mm:
        on = cloud.truth == "sphere"
        pts = cloud.points.copy()
        normal = _unit(pts[on] - centre)
        baseline = _unit(np.asarray(projector, float) - np.asarray(camera, float))
        rays = _unit(pts[on] - cloud.camera)
        pts[on] += (sphere_bias_mm * _dot(normal, baseline))[:, None] * rays
        cloud = SyntheticCloud(pts, cloud.truth, cloud.pixel, cloud.incidence_rad, cloud.camera, cloud.projector)
    return cloud
