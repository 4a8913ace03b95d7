"""Triangulation of camera/projector ray pairs (thesis section 2.3.3).

The scattering point is the midpoint of the two points of closest approach of the
camera ray (o1 + s d1) and the projector ray (o2 + t d2); epsilon-1 is their
distance. We report epsilon-1 *signed*, ``eps1 = (o2 - o1) . n`` with
``n = (d1 x d2) / |d1 x d2|``, as the thesis's histograms do (figure 6-10, +-1 mm):
the sign says on which side of the camera ray the projector ray passes, and a signed
residual is smooth where the unsigned distance has a kink, which the bundle adjustment
needs. ``abs(eps1)`` is the closest-approach distance.
"""

from __future__ import annotations

import numpy as np

__all__ = ["closest_points", "closest_approach", "triangulate", "sphere_hits"]


def closest_points(o1, d1, o2, d2) -> tuple[np.ndarray, np.ndarray]:
    """The point on each ray 1 closest to ray 2 and on ray 2 closest to ray 1, each
    (..., 3) (NaN for parallel rays); arguments as :func:`closest_approach`."""
    o1, d1, o2, d2 = (np.asarray(a, float) for a in (o1, d1, o2, d2))
    w0 = o1 - o2
    a = np.sum(d1 * d1, axis=-1)
    b = np.sum(d1 * d2, axis=-1)
    c = np.sum(d2 * d2, axis=-1)
    d = np.sum(d1 * w0, axis=-1)
    e = np.sum(d2 * w0, axis=-1)
    den = a * c - b * b
    with np.errstate(divide="ignore", invalid="ignore"):
        s1 = (b * e - c * d) / den
        s2 = (a * e - b * d) / den
    return o1 + s1[..., None] * d1, o2 + s2[..., None] * d2


def closest_approach(o1, d1, o2, d2) -> tuple[np.ndarray, np.ndarray]:
    """Midpoint of closest approach and signed epsilon-1 of two rays.

    Parameters
    ----------
    o1, o2 : array_like, shape (..., 3)
        Ray origins (sensor pinholes).
    d1, d2 : array_like, shape (..., 3)
        Ray directions (need not be unit).

    Returns
    -------
    s : ndarray, shape (..., 3)
        Midpoint of the two points of closest approach.
    eps1 : ndarray, shape (...)
        Signed closest-approach distance. NaN where the rays are parallel.

    Examples
    --------
    >>> s, e = closest_approach([0, 0, 0], [1, 0, 0], [0, 1, 1], [0, 0, 1])
    >>> s.tolist(), float(e)
    ([0.0, 0.5, 0.0], -1.0)
    """
    o1, d1, o2, d2 = (np.asarray(a, float) for a in (o1, d1, o2, d2))
    p1, p2 = closest_points(o1, d1, o2, d2)
    with np.errstate(divide="ignore", invalid="ignore"):
        n = np.cross(d1, d2)
        n /= np.linalg.norm(n, axis=-1, keepdims=True)
        eps1 = np.sum((o2 - o1) * n, axis=-1)
    return 0.5 * (p1 + p2), eps1


def triangulate(camera, projector, pixels_uv, tau) -> tuple[np.ndarray, np.ndarray]:
    """Point cloud from camera pixels and decoded projector phases.

    Parameters
    ----------
    camera, projector : fringecal.sensor.Sensor
    pixels_uv : array_like, shape (..., 2)
        0-based camera (column, row).
    tau : array_like, shape (..., 2)
        (tau_x, tau_y) in rad at those pixels.

    Returns
    -------
    points : ndarray, shape (..., 3), world mm
    eps1 : ndarray, shape (...), mm
    """
    o1, d1 = camera.rays(camera.image_mm(pixels_uv))
    o2, d2 = projector.rays(projector.image_mm(tau))
    return closest_approach(o1, d1, o2, d2)


def sphere_hits(origin, directions, centres, radius) -> np.ndarray:
    """First intersections (..., 3) of rays ``origin + t directions`` (unit directions)
    with spheres, one sphere per ray (shapes broadcast: centres (..., 3), radius (...));
    NaN where a ray misses its sphere."""
    oc = origin - centres
    b = np.einsum("...k,...k->...", directions, oc)
    disc = b * b - (np.einsum("...k,...k->...", oc, oc) - radius * radius)
    with np.errstate(invalid="ignore"):
        t = np.where(disc >= 0, -b - np.sqrt(disc), np.nan)
    return origin + t[..., None] * directions
