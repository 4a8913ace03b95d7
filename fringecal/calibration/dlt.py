"""Direct linear transformation (thesis section 2.2.3, eqs. 2-10..2-18 and 6-8..6-13).

Without distortion, a sensor maps a world point X to image-plane coordinates by

    x' = R (X - X0),   xi = xi_H - c x'/z',   eta = eta_H - c y'/z'      (z' > 0 in front)

which is the 3x4 projective map  w (xi, eta, 1)^T = P (X, 1)^T  with

    P = lambda K R [I | -X0],   K = [[-c, 0, xi_H], [0, -c, eta_H], [0, 0, 1]],

and w = lambda z'. The eleven DLT parameters of eq. 2-10 are P / P[2, 3]. We estimate P
up to scale as the right singular vector of the homogeneous system (eq. 2-11 with the
twelfth entry free) after Hartley normalisation of both point sets (image points to
centroid 0 and mean distance sqrt 2, world points to centroid 0 and mean distance sqrt 3),
which keeps the system well conditioned where raw millimetre coordinates at a 3 m
stand-off would not be.

Decomposition, with m1, m2, m3 the rows of M = P[:, :3] = lambda K R:

    X0 = -M^-1 P[:, 3]                                          (eq. 2-18)
    |lambda| = |m3|; its sign makes z' = (m3 . X + P[2, 3]) / lambda > 0 for the points
    xi_H = m1.m3 / |m3|^2,  eta_H = m2.m3 / |m3|^2              (eqs. 2-13, 2-14)
    c_x = sqrt(|m1|^2/|m3|^2 - xi_H^2), c_y likewise, c = (c_x + c_y)/2   (2-15..2-17)
    r3 = m3/lambda,  r1 = (xi_H r3 - m1/lambda)/c_x,  r2 = (eta_H r3 - m2/lambda)/c_y
                                                               (eqs. 6-10..6-12, our signs)

R is then replaced by the nearest rotation (SVD) and its angles taken by
:func:`fringecal.rotation.angles_from_matrix` (eq. 6-13, but with atan2 and a choice of
branch near a reference). The thesis's ``-c`` sign convention is what makes r1 and r2
come out with the ``xi_H r3 - m1/lambda`` form.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fringecal.rotation import angles_from_matrix, rotation_matrix

__all__ = ["DLTError", "DLTEstimate", "dlt"]

#: Points whose centred coordinates have smallest/largest singular value below this are coplanar.
COPLANAR_RATIO = 1e-6


class DLTError(ValueError):
    """The DLT cannot be solved from these points (too few, coplanar, degenerate)."""


def _normaliser(points: np.ndarray) -> np.ndarray:
    """Similarity (d+1, d+1) taking points (n, d) to centroid 0, mean distance sqrt(d)."""
    d = points.shape[1]
    centroid = points.mean(axis=0)
    mean_dist = np.mean(np.linalg.norm(points - centroid, axis=1))
    s = np.sqrt(d) / mean_dist
    T = np.eye(d + 1)
    T[:d, :d] *= s
    T[:d, d] = -s * centroid
    return T


@dataclass(frozen=True)
class DLTEstimate:
    """A sensor's nine undistorted parameters from the DLT.

    Attributes
    ----------
    params : ndarray (9,)
        x0, y0, z0, omega, phi, kappa, xi_h, eta_h, c (fringecal.sensor order).
    camera_matrix : ndarray (3, 4)
        P scaled so that P[2, 3] = 1: its first eleven entries are L1..L11 of eq. 2-10.
    c_x, c_y : float
        The two principal distances of eqs. 2-15, 2-16 (their difference and ``skew``
        show how far the data are from the 9-parameter model).
    skew : float
        (r1 . r2) before orthonormalisation, 0 for exact data.
    algebraic_residual : float
        Smallest singular value of the normalised DLT system divided by sqrt(2n): the RMS
        algebraic residual (eq. 6-9) in normalised units.
    reprojection_rms_mm : float
        RMS distance between the given image points and the fitted model's projections.
    n_points : int
    """

    params: np.ndarray
    camera_matrix: np.ndarray
    c_x: float
    c_y: float
    skew: float
    algebraic_residual: float
    reprojection_rms_mm: float
    n_points: int

    @property
    def params14(self) -> np.ndarray:
        """The 14 sensor parameters with zero distortion."""
        return np.concatenate([self.params, np.zeros(5)])

    @classmethod
    def from_estimate(cls, points_world, image_mm, near_angles=None) -> "DLTEstimate":
        """Estimate from >= 6 non-coplanar world points (n, 3) and image points (n, 2) mm.

        ``near_angles`` (3,) picks the Euler-angle branch nearest a reference.

        Examples
        --------
        >>> from fringecal.sensor import Sensor, SensorFormat
        >>> truth = [694.0, -211.6, 2585.8, -3.037, -0.264, 3.139, -0.06, 0.29, 52.7] + [0] * 5
        >>> cam = Sensor("C1", "camera", SensorFormat(2048, 2048, 15.1, 15.1), truth)
        >>> X = np.random.default_rng(1).uniform([-500, -200, -900], [300, 400, -400], (20, 3))
        >>> est = DLTEstimate.from_estimate(X, cam.project(X))
        >>> bool(np.allclose(est.params, truth[:9], atol=1e-6))
        True
        """
        X = np.asarray(points_world, float)
        x = np.asarray(image_mm, float)
        if X.ndim != 2 or X.shape[1] != 3 or x.shape != (X.shape[0], 2):
            raise DLTError(f"need points (n, 3) and image points (n, 2), got {X.shape} and {x.shape}")
        good = np.all(np.isfinite(X), axis=1) & np.all(np.isfinite(x), axis=1)
        X, x = X[good], x[good]
        n = len(X)
        if n < 6:
            raise DLTError(f"the DLT needs at least 6 control points, got {n}")
        sv = np.linalg.svd(X - X.mean(axis=0), compute_uv=False)
        if sv[2] <= COPLANAR_RATIO * sv[0]:
            raise DLTError(f"the {n} control points are coplanar (thickness/extent = {sv[2] / sv[0]:.1e}); "
                           "the DLT needs points spread in depth, e.g. from several artefact poses")
        Tx = _normaliser(x)
        TX = _normaliser(X)
        xh = (np.c_[x, np.ones(n)] @ Tx.T)[:, :2]
        Xh = np.c_[X, np.ones(n)] @ TX.T
        A = np.zeros((2 * n, 12))
        A[0::2, 0:4] = Xh
        A[0::2, 8:12] = -xh[:, :1] * Xh
        A[1::2, 4:8] = Xh
        A[1::2, 8:12] = -xh[:, 1:2] * Xh
        _, s, vt = np.linalg.svd(A, full_matrices=False)
        if s[-2] <= 1e-10 * s[0]:
            raise DLTError(f"the DLT system is degenerate (two vanishing singular values, "
                           f"{s[-2] / s[0]:.1e}): the points do not determine a projection "
                           "(for example all on one line or on a twisted cubic through the pinhole)")
        P = np.linalg.inv(Tx) @ vt[-1].reshape(3, 4) @ TX
        M, p4 = P[:, :3], P[:, 3]
        if abs(np.linalg.det(M)) < 1e-12 * np.linalg.norm(M) ** 3:
            raise DLTError("the DLT camera matrix is singular: the pinhole cannot be recovered")
        X0 = -np.linalg.solve(M, p4)
        m1, m2, m3 = M
        nm3 = np.linalg.norm(m3)
        w = np.c_[X, np.ones(n)] @ P[2]
        lam = nm3 * (1.0 if np.sum(np.sign(w)) >= 0 else -1.0)
        if np.any(np.sign(w) != np.sign(lam)):
            raise DLTError("the control points lie on both sides of the fitted sensor: "
                           "the image points do not belong to one sensor looking at them")
        xi_h = m1 @ m3 / nm3**2
        eta_h = m2 @ m3 / nm3**2
        cx2 = m1 @ m1 / nm3**2 - xi_h**2
        cy2 = m2 @ m2 / nm3**2 - eta_h**2
        if cx2 <= 0 or cy2 <= 0:
            raise DLTError("the DLT gives no real principal distance (eqs. 2-15/2-16): degenerate data")
        c_x, c_y = np.sqrt(cx2), np.sqrt(cy2)
        r3 = m3 / lam
        r1 = (xi_h * r3 - m1 / lam) / c_x
        r2 = (eta_h * r3 - m2 / lam) / c_y
        R_raw = np.stack([r1, r2, r3])
        u, _, vt3 = np.linalg.svd(R_raw)
        R = u @ vt3
        if np.linalg.det(R) < 0:
            raise DLTError("the DLT rotation is a reflection: the image axes are mirrored "
                           "relative to the model (check the pixel/phase to mm conversion)")
        angles = angles_from_matrix(R, near=near_angles)
        c = 0.5 * (c_x + c_y)
        params = np.concatenate([X0, angles, [xi_h, eta_h, c]])
        rms = float(np.sqrt(np.mean(np.sum((_project9(params, X) - x) ** 2, axis=1))))
        return cls(params, P / P[2, 3], float(c_x), float(c_y), float(r1 @ r2),
                   float(s[-1] / np.sqrt(2 * n)), rms, n)

    def residuals(self, points_world, image_mm) -> np.ndarray:
        """Reprojection residuals (n, 2) mm of the nine-parameter model."""
        return _project9(self.params, np.asarray(points_world, float)) - np.asarray(image_mm, float)


def _project9(params, X):
    R = rotation_matrix(*params[3:6])
    xs = (X - params[:3]) @ R.T
    return params[6:8] - params[8] * xs[:, :2] / xs[:, 2:3]


def dlt(points_world, image_mm, near_angles=None) -> DLTEstimate:
    """Shorthand for :meth:`DLTEstimate.from_estimate`."""
    return DLTEstimate.from_estimate(points_world, image_mm, near_angles)
