"""Rotations and rigid frames in the thesis convention.

The rotation matrix is R(omega, phi, kappa) of thesis eq. 2-6. A rigid frame with
origin ``t`` (world coordinates) and angles (omega, phi, kappa) maps

    x_local = R (x_world - t)        x_world = R^T x_local + t

This one rule serves sensors (local = sensor frame, eq. 2-5) and artefact poses
(local = the CMM frame of the artefact definition), see docs/conventions.md.

All functions broadcast over leading axes: angles of shape (...,) give matrices of
shape (..., 3, 3).
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "rotation_matrix",
    "angles_from_matrix",
    "wrap_angle",
    "to_local",
    "to_world",
    "rotation_derivatives",
]


def rotation_matrix(omega, phi, kappa) -> np.ndarray:
    """R(omega, phi, kappa) of thesis eq. 2-6.

    Parameters
    ----------
    omega, phi, kappa : array_like, shape (...)
        Euler angles in radians.

    Returns
    -------
    R : ndarray, shape (..., 3, 3)

    Examples
    --------
    >>> R = rotation_matrix(0.1, -0.2, 0.3)
    >>> bool(np.allclose(R @ R.T, np.eye(3)))
    True
    >>> round(float(R[2, 0]), 6) == round(float(np.sin(-0.2)), 6)
    True
    """
    omega, phi, kappa = np.broadcast_arrays(
        np.asarray(omega, float), np.asarray(phi, float), np.asarray(kappa, float)
    )
    so, co = np.sin(omega), np.cos(omega)
    sp, cp = np.sin(phi), np.cos(phi)
    sk, ck = np.sin(kappa), np.cos(kappa)
    R = np.empty(omega.shape + (3, 3))
    R[..., 0, 0] = cp * ck
    R[..., 0, 1] = co * sk + so * sp * ck
    R[..., 0, 2] = so * sk - co * sp * ck
    R[..., 1, 0] = -cp * sk
    R[..., 1, 1] = co * ck - so * sp * sk
    R[..., 1, 2] = so * ck + co * sp * sk
    R[..., 2, 0] = sp
    R[..., 2, 1] = -so * cp
    R[..., 2, 2] = co * cp
    return R


def rotation_derivatives(omega, phi, kappa) -> np.ndarray:
    """Partial derivatives of R with respect to (omega, phi, kappa).

    Returns
    -------
    dR : ndarray, shape (3, ..., 3, 3)
        ``dR[0] = dR/domega``, ``dR[1] = dR/dphi``, ``dR[2] = dR/dkappa``.
    """
    omega, phi, kappa = np.broadcast_arrays(
        np.asarray(omega, float), np.asarray(phi, float), np.asarray(kappa, float)
    )
    so, co = np.sin(omega), np.cos(omega)
    sp, cp = np.sin(phi), np.cos(phi)
    sk, ck = np.sin(kappa), np.cos(kappa)
    z = np.zeros_like(omega)
    d = np.empty((3,) + omega.shape + (3, 3))
    # d/domega
    d[0, ..., 0, 0] = z
    d[0, ..., 0, 1] = -so * sk + co * sp * ck
    d[0, ..., 0, 2] = co * sk + so * sp * ck
    d[0, ..., 1, 0] = z
    d[0, ..., 1, 1] = -so * ck - co * sp * sk
    d[0, ..., 1, 2] = co * ck - so * sp * sk
    d[0, ..., 2, 0] = z
    d[0, ..., 2, 1] = -co * cp
    d[0, ..., 2, 2] = -so * cp
    # d/dphi
    d[1, ..., 0, 0] = -sp * ck
    d[1, ..., 0, 1] = so * cp * ck
    d[1, ..., 0, 2] = -co * cp * ck
    d[1, ..., 1, 0] = sp * sk
    d[1, ..., 1, 1] = -so * cp * sk
    d[1, ..., 1, 2] = co * cp * sk
    d[1, ..., 2, 0] = cp
    d[1, ..., 2, 1] = so * sp
    d[1, ..., 2, 2] = -co * sp
    # d/dkappa
    d[2, ..., 0, 0] = -cp * sk
    d[2, ..., 0, 1] = co * ck - so * sp * sk
    d[2, ..., 0, 2] = so * ck + co * sp * sk
    d[2, ..., 1, 0] = -cp * ck
    d[2, ..., 1, 1] = -co * sk - so * sp * ck
    d[2, ..., 1, 2] = -so * sk + co * sp * ck
    d[2, ..., 2, 0] = z
    d[2, ..., 2, 1] = z
    d[2, ..., 2, 2] = z
    return d


def wrap_angle(angle, centre=0.0) -> np.ndarray:
    """Wrap angles into (centre - pi, centre + pi].

    >>> float(wrap_angle(3 * np.pi / 2))
    -1.5707963267948966
    >>> round(float(wrap_angle(-3.1, centre=3.0)), 12)
    3.18318530718
    """
    angle = np.asarray(angle, float)
    centre = np.asarray(centre, float)
    return centre - np.remainder(centre - angle + np.pi, 2 * np.pi) + np.pi


def angles_from_matrix(R, near=None) -> np.ndarray:
    """Euler angles (omega, phi, kappa) of a rotation matrix, inverse of eq. 2-6.

    Every rotation has two angle triples, (omega, phi, kappa) and
    (omega + pi, pi - phi, kappa + pi). Without ``near`` the triple with
    phi in [-pi/2, pi/2] is returned, each of omega and kappa in (-pi, pi]. With
    ``near`` (shape (..., 3)), both triples are wrapped to within pi of ``near``
    and the closer one is returned, so angles of a rig close to +-pi (the thesis's
    omega ~ -3.04, kappa ~ 3.14) stay continuous instead of jumping by 2 pi.

    Parameters
    ----------
    R : array_like, shape (..., 3, 3)
    near : array_like, shape (..., 3), optional

    Returns
    -------
    angles : ndarray, shape (..., 3)

    Examples
    --------
    >>> a = np.array([-3.037, -0.264, 3.139])
    >>> bool(np.allclose(angles_from_matrix(rotation_matrix(*a)), a))
    True
    >>> b = angles_from_matrix(rotation_matrix(3.13, 0.1, -3.14), near=[-3.1, 0.0, 3.1])
    >>> [round(float(x), 6) for x in b]
    [-3.153185, 0.1, 3.143185]
    """
    R = np.asarray(R, float)
    s = np.clip(R[..., 2, 0], -1.0, 1.0)
    phi = np.arcsin(s)
    # atan2 on the two entries of each pair keeps full precision near phi = 0 and
    # stays defined right up to the gimbal-lock limit |phi| = pi/2.
    omega = np.arctan2(-R[..., 2, 1], R[..., 2, 2])
    kappa = np.arctan2(-R[..., 1, 0], R[..., 0, 0])
    a = np.stack([omega, phi, kappa], axis=-1)
    if near is None:
        return a
    near = np.broadcast_to(np.asarray(near, float), a.shape)
    b = np.stack([omega + np.pi, np.pi - phi, kappa + np.pi], axis=-1)
    a = wrap_angle(a, near)
    b = wrap_angle(b, near)
    da = np.sum((a - near) ** 2, axis=-1, keepdims=True)
    db = np.sum((b - near) ** 2, axis=-1, keepdims=True)
    return np.where(db < da, b, a)


def to_local(points_world, R, t) -> np.ndarray:
    """x_local = R (x_world - t). points (..., 3), R (3, 3), t (3,)."""
    return (np.asarray(points_world, float) - np.asarray(t, float)) @ np.asarray(R).T


def to_world(points_local, R, t) -> np.ndarray:
    """x_world = R^T x_local + t. points (..., 3), R (3, 3), t (3,)."""
    return np.asarray(points_local, float) @ np.asarray(R) + np.asarray(t, float)
