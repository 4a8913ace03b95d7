"""Stewart-platform kinematics: the 6-3 model of thesis section 4.3.

Frames (thesis section 4.3): BASE is fixed at the centre of the base hexagon, Z up;
TOP is fixed at the centroid of the top triangle, z normal to it. A platform pose is
``(px, py, pz, alpha, beta, gamma)`` in mm and rad: the TOP origin in BASE and the
angles of eq. 4-3, whose matrix is

    R_base_top = R_Y(beta) R_X(alpha) R_Z(gamma),   X_base = R_base_top x_top + p

(alpha and beta set the approach vector, the TOP z axis, and gamma rolls about it).

Base joints B1..B6 follow eq. 4-1 (parameters b, d), top joints T1..T3 eq. 4-2
(parameter a), and leg i joins B_i to T_ceil(i/2) (eqs. 4-15..4-20): legs 1, 2 meet
at T1, legs 3, 4 at T2, legs 5, 6 at T3. Leg lengths are eq. 4-14.

The printed expansions contain typos, which this module does not copy: eq. 4-15
reads ``- d b / sqrt(3)`` for ``- b / sqrt(3)`` (X_B1 = (2b + d) sqrt(3) / 6); eq. 4-10
reads ``sin(alpha) sin(beta) sin(gamma)`` for ``sin(alpha) cos(beta) sin(gamma)``
(row 3 of eq. 4-3 applied to T2 = (-a/sqrt(3), 0, 0)); the last row of eq. 4-3 lacks a 0.
Leg lengths are computed from eqs. 4-1, 4-2, 4-3/4-4 and 4-14 directly; the tests
check them against the corrected expansions 4-5..4-20.

Forward kinematics (leg lengths -> pose) has no closed form; :func:`forward_kinematics`
solves the six equations L_i(pose) = l_i by damped Newton iterations with the analytic
Jacobian of :func:`leg_jacobian`, from the home pose or any start given.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fringecal.frames import Frame

__all__ = [
    "POSE_NAMES",
    "LEG_TOP_VERTEX",
    "PlatformGeometry",
    "ForwardKinematicsError",
    "FKResult",
    "rotation_base_top",
    "rotation_base_top_derivatives",
    "top_joints_in_base",
    "leg_vectors",
    "inverse_kinematics",
    "leg_jacobian",
    "forward_kinematics",
    "pose_to_frame",
    "pose_from_frame",
]

POSE_NAMES = ("px", "py", "pz", "alpha", "beta", "gamma")
#: top vertex (0-based) of each leg: leg i joins B_i to T_ceil(i/2)
LEG_TOP_VERTEX = np.array([0, 0, 1, 1, 2, 2])
_S3 = np.sqrt(3.0)


@dataclass(frozen=True)
class PlatformGeometry:
    """Base hexagon (b, d) and top triangle (a) of thesis figures 4-4 and 4-5, in mm.

    Examples
    --------
    >>> g = PlatformGeometry(a_mm=1100.0, b_mm=1100.0, d_mm=450.0)
    >>> g.base_vertices[0].round(3)
    array([764.989, 225.   ,   0.   ])
    >>> float(np.linalg.norm(g.top_vertices[0] - g.top_vertices[1]).round(9))
    1100.0
    """

    a_mm: float
    b_mm: float
    d_mm: float

    @property
    def base_vertices(self) -> np.ndarray:
        """B1..B6 in the BASE frame, eq. 4-1, shape (6, 3)."""
        b, d = self.b_mm, self.d_mm
        return np.array([
            [_S3 / 6 * (2 * b + d), d / 2, 0.0],
            [-_S3 / 6 * (b - d), (b + d) / 2, 0.0],
            [-_S3 / 6 * (b + 2 * d), b / 2, 0.0],
            [-_S3 / 6 * (b + 2 * d), -b / 2, 0.0],
            [-_S3 / 6 * (b - d), -(b + d) / 2, 0.0],
            [_S3 / 6 * (2 * b + d), -d / 2, 0.0],
        ])

    @property
    def top_vertices(self) -> np.ndarray:
        """T1..T3 in the TOP frame, eq. 4-2, shape (3, 3)."""
        a = self.a_mm
        return np.array([
            [_S3 / 6 * a, a / 2, 0.0],
            [-_S3 / 3 * a, 0.0, 0.0],
            [_S3 / 6 * a, -a / 2, 0.0],
        ])

    @property
    def top_joints(self) -> np.ndarray:
        """Top end of each leg in the TOP frame, shape (6, 3) (T1, T1, T2, T2, T3, T3)."""
        return self.top_vertices[LEG_TOP_VERTEX]


class ForwardKinematicsError(RuntimeError):
    """The forward-kinematics solve did not converge (or met a singular Jacobian)."""


def _elementary(alpha, beta, gamma):
    a, b, g = np.broadcast_arrays(*(np.asarray(v, float) for v in (alpha, beta, gamma)))
    shape = a.shape + (3, 3)
    z, o = np.zeros(a.shape), np.ones(a.shape)
    sa, ca, sb, cb, sg, cg = np.sin(a), np.cos(a), np.sin(b), np.cos(b), np.sin(g), np.cos(g)

    def m(*rows):
        return np.stack([np.stack(r, axis=-1) for r in rows], axis=-2).reshape(shape)

    rx = m((o, z, z), (z, ca, -sa), (z, sa, ca))
    ry = m((cb, z, sb), (z, o, z), (-sb, z, cb))
    rz = m((cg, -sg, z), (sg, cg, z), (z, z, o))
    drx = m((z, z, z), (z, -sa, -ca), (z, ca, -sa))
    dry = m((-sb, z, cb), (z, z, z), (-cb, z, -sb))
    drz = m((-sg, -cg, z), (cg, -sg, z), (z, z, z))
    return rx, ry, rz, drx, dry, drz


def rotation_base_top(alpha, beta, gamma) -> np.ndarray:
    """Rotation part of T_BASE^TOP (eq. 4-3), ``R_Y(beta) R_X(alpha) R_Z(gamma)``.

    Parameters
    ----------
    alpha, beta, gamma : array_like, shape (...), rad

    Returns
    -------
    R : ndarray, shape (..., 3, 3), with ``X_base = R x_top + p``.

    Examples
    --------
    >>> a, b, g = 0.1, -0.2, 0.3
    >>> R = rotation_base_top(a, b, g)
    >>> eq43_row2 = [np.cos(a) * np.sin(g), np.cos(a) * np.cos(g), -np.sin(a)]
    >>> bool(np.allclose(R[1], eq43_row2))
    True
    """
    rx, ry, rz, *_ = _elementary(alpha, beta, gamma)
    return ry @ rx @ rz


def rotation_base_top_derivatives(alpha, beta, gamma) -> np.ndarray:
    """dR/dalpha, dR/dbeta, dR/dgamma of eq. 4-3, shape (3, ..., 3, 3)."""
    rx, ry, rz, drx, dry, drz = _elementary(alpha, beta, gamma)
    return np.stack([ry @ drx @ rz, dry @ rx @ rz, ry @ rx @ drz])


def _split(poses):
    poses = np.asarray(poses, float)
    if poses.shape[-1] != 6:
        raise ValueError(f"a platform pose has 6 values (px, py, pz, alpha, beta, gamma); got shape {poses.shape}")
    return poses[..., :3], poses[..., 3], poses[..., 4], poses[..., 5]


def top_joints_in_base(geometry: PlatformGeometry, poses) -> np.ndarray:
    """Top end of every leg in the BASE frame (eq. 4-4), shape (..., 6, 3)."""
    p, a, b, g = _split(poses)
    R = rotation_base_top(a, b, g)
    return np.einsum("...ij,lj->...li", R, geometry.top_joints) + p[..., None, :]


def leg_vectors(geometry: PlatformGeometry, poses) -> np.ndarray:
    """Leg vectors T_ceil(i/2) - B_i in the BASE frame, shape (..., 6, 3)."""
    return top_joints_in_base(geometry, poses) - geometry.base_vertices


def inverse_kinematics(geometry: PlatformGeometry, poses) -> np.ndarray:
    """Leg lengths (eq. 4-14) for platform poses.

    Parameters
    ----------
    poses : array_like, shape (..., 6)
        (px, py, pz) in mm and (alpha, beta, gamma) in rad.

    Returns
    -------
    lengths : ndarray, shape (..., 6), mm, joint centre to joint centre.

    Examples
    --------
    >>> g = PlatformGeometry(1100.0, 1100.0, 450.0)
    >>> inverse_kinematics(g, [0, 0, 800.0, 0, 0, 0]).round(3)
    array([972.54, 972.54, 972.54, 972.54, 972.54, 972.54])
    """
    return np.linalg.norm(leg_vectors(geometry, poses), axis=-1)


def leg_jacobian(geometry: PlatformGeometry, poses) -> np.ndarray:
    """dL_i / d(px, py, pz, alpha, beta, gamma), shape (..., 6, 6).

    Row i is ``u_i . dT_i/dpose`` with ``u_i`` the unit leg vector: the translation
    block is ``u_i`` itself and the rotation block ``u_i . (dR/dangle t_i)``.
    """
    p, a, b, g = _split(poses)
    legs = leg_vectors(geometry, poses)
    u = legs / np.linalg.norm(legs, axis=-1, keepdims=True)
    dR = rotation_base_top_derivatives(a, b, g)  # (3, ..., 3, 3)
    dT = np.einsum("k...ij,lj->...lki", dR, geometry.top_joints)  # (..., 6, 3 angles, 3)
    return np.concatenate([u, np.einsum("...li,...lki->...lk", u, dT)], axis=-1)


@dataclass(frozen=True)
class FKResult:
    """Forward-kinematics solution: poses (..., 6), iterations, worst residual (mm)."""

    poses: np.ndarray
    iterations: int
    residual_mm: float


def forward_kinematics(geometry: PlatformGeometry, lengths, start, tol_mm: float = 1e-10,
                       max_iter: int = 50) -> FKResult:
    """Platform poses whose leg lengths are ``lengths``, by damped Newton iterations.

    Parameters
    ----------
    lengths : array_like, shape (..., 6), mm
    start : array_like, shape (6,) or (..., 6)
        Starting pose(s); the solve finds the assembly nearest the start, so pass the
        home pose, the commanded pose or the previous pose.
    tol_mm : float
        Convergence when every leg-length residual is below this.

    Raises
    ------
    ForwardKinematicsError
        When any leg set has not converged after ``max_iter`` iterations or the
        Jacobian is singular; the message gives the count, the worst residual and
        the first offending leg lengths.

    Examples
    --------
    >>> g = PlatformGeometry(1100.0, 1100.0, 450.0)
    >>> truth = np.array([30.0, -20.0, 820.0, 0.02, -0.01, 0.05])
    >>> fk = forward_kinematics(g, inverse_kinematics(g, truth), start=[0, 0, 800, 0, 0, 0])
    >>> bool(np.allclose(fk.poses, truth, rtol=0, atol=1e-9))
    True
    """
    target = np.asarray(lengths, float)
    if target.shape[-1] != 6:
        raise ValueError(f"six leg lengths expected; got shape {target.shape}")
    if not np.all(np.isfinite(target)) or np.any(target <= 0):
        raise ForwardKinematicsError("leg lengths must be finite and positive")
    x = np.broadcast_to(np.asarray(start, float), target.shape).copy()
    r = inverse_kinematics(geometry, x) - target
    it = 0
    for it in range(1, max_iter + 1):
        J = leg_jacobian(geometry, x)
        try:
            step = np.linalg.solve(J, -r[..., None])[..., 0]
        except np.linalg.LinAlgError:
            raise ForwardKinematicsError(
                "forward kinematics met a singular leg Jacobian (the platform is at a "
                "singular configuration for these leg lengths)") from None
        # Halve the step where it does not reduce the residual (damping far from the solution).
        cost = np.max(np.abs(r), axis=-1)
        scale = np.ones(cost.shape)
        for _ in range(30):
            trial = x + scale[..., None] * step
            r_trial = inverse_kinematics(geometry, trial) - target
            worse = np.max(np.abs(r_trial), axis=-1) > cost
            worse &= cost > tol_mm
            if not np.any(worse):
                break
            scale = np.where(worse, scale / 2, scale)
        x, r = trial, r_trial
        if np.max(np.abs(r)) < tol_mm and np.max(np.abs(step)) < 1e-6:
            break
    worst = float(np.max(np.abs(r))) if r.size else 0.0
    if not np.isfinite(worst) or worst >= tol_mm:
        bad = np.max(np.abs(r), axis=-1) >= tol_mm
        first = target[bad][0] if np.ndim(bad) else target
        raise ForwardKinematicsError(
            f"forward kinematics did not converge for {int(np.sum(bad))} of "
            f"{int(np.size(bad))} leg set(s): worst leg-length residual {worst:.3g} mm after "
            f"{it} iterations (first offending lengths {np.round(first, 4).tolist()} mm); "
            "are the lengths reachable from the start pose?")
    return FKResult(poses=x, iterations=it, residual_mm=worst)


def pose_to_frame(pose) -> Frame:
    """T_base_top as a project :class:`~fringecal.frames.Frame` (docs/conventions.md).

    With ``X_base = R43 x_top + p`` and ``x_world = R^T x_local + t`` the frame has
    ``t = p`` and ``R = R43^T``.

    Examples
    --------
    >>> pose = np.array([10.0, 20.0, 800.0, 0.01, -0.02, 0.3])
    >>> bool(np.allclose(pose_from_frame(pose_to_frame(pose)), pose))
    True
    """
    p, a, b, g = _split(pose)
    return Frame.from_matrix(rotation_base_top(a, b, g).T, p)


def pose_from_frame(frame: Frame) -> np.ndarray:
    """Platform pose (px, py, pz, alpha, beta, gamma) of T_base_top, alpha in [-pi/2, pi/2]."""
    R = frame.R.T  # R43
    alpha = np.arcsin(np.clip(-R[1, 2], -1.0, 1.0))
    beta = np.arctan2(R[0, 2], R[2, 2])
    gamma = np.arctan2(R[1, 0], R[1, 1])
    return np.concatenate([frame.t, [alpha, beta, gamma]])
