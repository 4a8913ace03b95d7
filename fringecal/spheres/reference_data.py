"""Reference data sets with an exactly known least-squares solution (ISO 10360-6 style).

ISO 10360-6 tests fitting software with data sets whose least-squares solution is
known. We build them the way the standard's generators do: choose the reference
parameters, put nominal points on the ideal surface, and displace each point along
the surface normal by a residual ``e_i`` drawn from the *null space of J^T*, where
``J`` is the Jacobian of the orthogonal residuals at the reference parameters. Then
the residuals at the reference are exactly ``e``, the gradient ``J^T e`` of the sum
of squares is zero, and (for residuals small against the radius or the data extent)
the reference parameters are *the* least-squares optimum. Any correct orthogonal
fit must return them to rounding error, whatever the noise level.

Sphere residuals ``|p - c| - R`` have Jacobian rows ``[-u_i, -1]`` (u_i the unit
normal), so ``e`` must satisfy ``sum e_i = 0`` and ``sum e_i u_i = 0``; the same set
is also exact for a fit with the radius fixed to the reference value. Plane
residuals ``n . (p - q)`` with the plane shifted along ``n`` and tilted about the
in-plane axes ``a, b`` need ``sum e_i = 0``, ``sum e_i s_i = 0``, ``sum e_i t_i = 0``
(s, t the in-plane coordinates).

Examples
--------
>>> from fringecal.spheres.fit import SphereModel
>>> ref = sphere_reference_data([1e4, -1e4, 1e4], 25.0, 500, cap_half_angle_deg=70,
...                             noise_rms_mm=0.05, seed=3)
>>> fit = SphereModel.from_estimate(ref.points)
>>> float(np.abs(fit.centre - ref.centre).max()) < 1e-7, abs(fit.radius - ref.radius) < 1e-7
(True, True)
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = [
    "ReferenceDataSet",
    "sphere_reference_data",
    "plane_reference_data",
    "reference_suite",
    "null_space_residuals",
]


@dataclass(frozen=True)
class ReferenceDataSet:
    """Points with their exact least-squares solution.

    For ``kind == "sphere"``: ``centre`` (3,), ``radius``; for ``"plane"``:
    ``point`` (3,) on the plane (the centroid of the points) and unit ``normal``.
    ``residuals`` (n,) are the exact residuals at the solution; ``name`` says
    which case it is.
    """

    name: str
    kind: str
    points: np.ndarray = field(repr=False)
    residuals: np.ndarray = field(repr=False)
    centre: np.ndarray | None = None
    radius: float | None = None
    point: np.ndarray | None = None
    normal: np.ndarray | None = None


def null_space_residuals(J: np.ndarray, rms: float, rng: np.random.Generator) -> np.ndarray:
    """Random residuals (n,) with the given RMS, orthogonal to every column of J (n, p)."""
    e = rng.standard_normal(len(J))
    Q, _ = np.linalg.qr(J)
    e -= Q @ (Q.T @ e)
    e -= Q @ (Q.T @ e)  # a second projection removes what rounding left of the first
    if rms == 0:
        return np.zeros(len(J))
    return e * (rms / np.sqrt(np.mean(e * e)))


def _orthonormal_basis(axis) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    a = np.asarray(axis, float)
    a = a / np.linalg.norm(a)
    helper = np.eye(3)[np.argmin(np.abs(a))]
    b = np.cross(a, helper)
    b /= np.linalg.norm(b)
    return a, b, np.cross(a, b)


def sphere_reference_data(centre, radius: float, n_points: int, cap_half_angle_deg: float = 180.0,
                          axis=(0.0, 0.0, 1.0), noise_rms_mm: float = 0.0, seed: int = 0,
                          name: str | None = None) -> ReferenceDataSet:
    """Points on a sphere cap whose least-squares sphere is exactly (centre, radius).

    Parameters
    ----------
    centre : array_like, shape (3,)
    radius : float
    n_points : int
    cap_half_angle_deg : float
        Half-angle of the covered cap about ``axis`` (180 = full sphere; a scanner
        sees a cap of about 70 degrees).
    axis : array_like, shape (3,)
        Direction from the centre to the middle of the cap.
    noise_rms_mm : float
        RMS of the orthogonal residuals (keep it well below the radius).
    seed : int
    """
    rng = np.random.default_rng(seed)
    centre = np.asarray(centre, float)
    a, b, c = _orthonormal_basis(axis)
    # area-uniform on the cap: cos(theta) uniform in [cos(alpha), 1]
    cos_t = rng.uniform(np.cos(np.radians(cap_half_angle_deg)), 1.0, n_points)
    sin_t = np.sqrt(1 - cos_t**2)
    az = rng.uniform(0, 2 * np.pi, n_points)
    u = (cos_t[:, None] * a + (sin_t * np.cos(az))[:, None] * b + (sin_t * np.sin(az))[:, None] * c)
    J = np.c_[-u, -np.ones(n_points)]
    e = null_space_residuals(J, noise_rms_mm, rng)
    points = centre + (radius + e)[:, None] * u
    label = name or (f"sphere R={radius:g} cap={cap_half_angle_deg:g}deg "
                     f"offset={np.linalg.norm(centre):.3g}mm noise={noise_rms_mm:g}mm")
    return ReferenceDataSet(label, "sphere", points, e, centre=centre, radius=float(radius))


def plane_reference_data(point, normal, n_points: int, extent_mm=(160.0, 80.0), noise_rms_mm: float = 0.0,
                         seed: int = 0, name: str | None = None) -> ReferenceDataSet:
    """Points on a rectangle of the plane through ``point`` with unit ``normal``,
    whose least-squares plane is exactly that plane and passes through ``point``
    (which is the points' centroid)."""
    rng = np.random.default_rng(seed)
    n, a, b = _orthonormal_basis(normal)
    st = rng.uniform(-0.5, 0.5, (n_points, 2)) * np.asarray(extent_mm, float)
    st -= st.mean(axis=0)  # the reference point is the centroid
    J = np.c_[np.ones(n_points), st]
    e = null_space_residuals(J, noise_rms_mm, rng)
    point = np.asarray(point, float)
    points = point + st[:, :1] * a + st[:, 1:] * b + e[:, None] * n
    label = name or (f"plane {extent_mm[0]:g}x{extent_mm[1]:g}mm offset={np.linalg.norm(point):.3g}mm "
                     f"noise={noise_rms_mm:g}mm")
    return ReferenceDataSet(label, "plane", points, e, point=point, normal=n)


def reference_suite(seed: int = 0, n_points: int = 400) -> list[ReferenceDataSet]:
    """The standard set: full spheres and 70-degree caps (and a 35-degree cap), planes,
    offsets from 0 to 1e4 mm, noise from 0 to 0.1 mm, in arbitrary orientations."""
    rng = np.random.default_rng(seed)
    out = []
    for offset in (0.0, 1e3, 1e4):
        for noise in (0.0, 0.001, 0.01, 0.1):
            direction = rng.normal(size=3)
            direction /= np.linalg.norm(direction)
            centre = offset * direction
            axis = rng.normal(size=3)
            for cap in (180.0, 70.0, 35.0):
                out.append(sphere_reference_data(centre, 25.0, n_points, cap, axis, noise,
                                                 seed=int(rng.integers(2**31))))
            out.append(sphere_reference_data(centre, 10.0, n_points, 70.0, -axis, noise,
                                             seed=int(rng.integers(2**31))))
            out.append(plane_reference_data(centre, axis, n_points, (160.0, 80.0), noise,
                                            seed=int(rng.integers(2**31))))
    return out
