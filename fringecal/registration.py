"""Rigid registration of point sets by SVD (thesis eqs. 6-1..6-7), and the similarity
(rigid plus one scale factor) of Umeyama.

The estimator follows scikit-image's style: ``RigidRegistration.from_estimate``
returns a fitted model, ``residuals`` reports per-point distances. :func:`umeyama`
also fits a scale: a scanner whose own calibration is a fraction of a percent off in
scale measures the artefact's distances that fraction short or long (labelling
estimates that scale per scanner, :mod:`fringecal.spheres.labelling`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fringecal.frames import Frame

__all__ = ["RigidRegistration", "DegenerateGeometryError", "kabsch", "umeyama"]


class DegenerateGeometryError(ValueError):
    """Too few points, or points that do not fix a rigid transform (collinear)."""


def kabsch(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares rotation M and translation T with dst ~ M src + T.

    Eqs. 6-2..6-6 with the determinant guard of Umeyama, so M is always a proper
    rotation (det +1), never a reflection.

    Parameters
    ----------
    src, dst : ndarray, shape (n, 3)

    Returns
    -------
    M : ndarray, shape (3, 3)
    T : ndarray, shape (3,)
    """
    src = np.asarray(src, float)
    dst = np.asarray(dst, float)
    a0 = src.mean(axis=0)
    b0 = dst.mean(axis=0)
    H = (dst - b0).T @ (src - a0)  # eq. 6-4: B A^T
    u, _, vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(u @ vt))
    if d == 0:
        d = 1.0
    M = u @ np.diag([1.0, 1.0, d]) @ vt  # eq. 6-5 with reflection guard
    T = b0 - M @ a0  # eq. 6-6
    return M, T


def umeyama(src: np.ndarray, dst: np.ndarray, scale_bounds=None) -> tuple[float, np.ndarray, np.ndarray]:
    """Least-squares similarity: scale s, rotation M, translation T with dst ~ s M src + T.

    Umeyama (1991): the rotation of :func:`kabsch` (proper, never a reflection) and
    ``s = tr(D S) / var(src)``. ``scale_bounds=(lo, hi)`` clips the scale (the least-
    squares translation is then taken for the clipped scale; the rotation does not
    depend on the scale).

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> src = rng.normal(size=(5, 3)) * 300
    >>> M = Frame.from_params([0, 0, 0, 0.1, -0.2, 3.0]).R
    >>> s, M_fit, T = umeyama(src, 0.994 * src @ M.T + [10.0, -20.0, 3000.0])
    >>> round(s, 12), bool(np.allclose(M_fit, M)), np.round(T, 9).tolist()
    (0.994, True, [10.0, -20.0, 3000.0])
    """
    src = np.asarray(src, float)
    dst = np.asarray(dst, float)
    a0 = src.mean(axis=0)
    b0 = dst.mean(axis=0)
    A = src - a0
    H = (dst - b0).T @ A
    u, S, vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(u @ vt)) or 1.0
    D = np.array([1.0, 1.0, d])
    M = u @ np.diag(D) @ vt
    var = float(np.sum(A * A))
    s = float(np.sum(S * D) / var) if var > 0 else 1.0
    if scale_bounds is not None:
        s = float(np.clip(s, *scale_bounds))
    return s, M, b0 - s * M @ a0


@dataclass(frozen=True)
class RigidRegistration:
    """A fitted rigid transform ``T_world_local`` from corresponding points.

    ``frame`` maps local points (for a pose: CMM artefact coordinates) into the
    world, ``x_world = R^T x_local + t`` (docs/conventions.md), so ``frame.angles`` are the
    pose's Euler angles and ``frame.t`` its translation.

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> local = rng.normal(size=(5, 3)) * 300
    >>> true = Frame.from_params([100, -50, 2000, 0.1, -0.2, 3.0])
    >>> reg = RigidRegistration.from_estimate(local, true.to_world(local))
    >>> bool(np.allclose(reg.frame.params, true.params))
    True
    >>> float(reg.rms) < 1e-9
    True
    """

    frame: Frame
    rms: float
    n_points: int

    @classmethod
    def from_estimate(cls, local, world, near=None, min_points: int = 3,
                      collinear_tol: float = 1e-3) -> "RigidRegistration":
        """Estimate T_world_local from ``local`` (n, 3) and ``world`` (n, 3).

        Raises
        ------
        DegenerateGeometryError
            Fewer than ``min_points`` points, or points so close to a line that the
            rotation about it is undetermined (second singular value of the centred
            local points below ``collinear_tol`` times the first).
        """
        local = np.asarray(local, float)
        world = np.asarray(world, float)
        if local.shape != world.shape or local.ndim != 2 or local.shape[1] != 3:
            raise ValueError(f"need two (n, 3) arrays, got {local.shape} and {world.shape}")
        n = len(local)
        if n < min_points:
            raise DegenerateGeometryError(f"{n} points; at least {min_points} are needed for a pose")
        sv = np.linalg.svd(local - local.mean(axis=0), compute_uv=False)
        if sv[0] == 0 or sv[1] < collinear_tol * sv[0]:
            raise DegenerateGeometryError(
                f"the {n} points are collinear (singular values {np.round(sv, 3).tolist()}); "
                "the rotation about their line is undetermined"
            )
        M, T = kabsch(local, world)
        frame = Frame.from_matrix(M.T, T, near=near)
        res = np.linalg.norm(frame.to_world(local) - world, axis=1)
        return cls(frame, float(np.sqrt(np.mean(res**2))), n)

    def residuals(self, local, world) -> np.ndarray:
        """Distances |T(local) - world|, shape (n,)."""
        return np.linalg.norm(self.frame.to_world(local) - np.asarray(world, float), axis=1)
