"""Steps of the adjustment's rotations as small rotations, not as changes of Euler angles.

The sensors and poses carry their orientation as the angles (omega, phi, kappa) of
thesis eq. 2-6, and the adjustment's result is reported in them. As coordinates to
take steps in they are poor wherever phi nears +-90 degrees (gimbal lock): there a
rotation of one degree can be a change of omega and kappa of tens of degrees in
opposite directions, F is a long curved valley in the angles, and Levenberg-Marquardt
crawls along it. A ring of scanners looking inward from every side has sensors there
(on the simulated four-scanner ring two projectors sit at phi = 84.6 and 95.4 deg:
77 iterations from DLT start values with steps in the angles, 6 with steps as small
rotations, to the same minimum; ``benchmarks/bundle.py``).

:class:`RotationIncrements` lets the solver step in a rotation vector delta instead:
the new rotation is ``R(angles) Exp([delta]x)`` (Rodrigues), written back as the
angles nearest the old ones (:func:`fringecal.rotation.angles_from_matrix`). The
normal equations follow by the chain rule: with A = d angles / d delta at delta = 0
(3 x 3 per rotation, from ``dR/d angles A = R [e_k]x``), N' = T^T N T and b' = T^T b
for the block-diagonal T that is A on each angle triple and 1 elsewhere. The
minimum is the same set of rotations, so the same F; only the path to it changes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fringecal.rotation import angles_from_matrix, rotation_derivatives, rotation_matrix

__all__ = ["RotationIncrements", "rotation_exp"]

#: |cos phi| below which a triple keeps steps in its angles (the chain rule's A is singular there)
GIMBAL_LOCK_COS = 1e-6


def _skew(v: np.ndarray) -> np.ndarray:
    """[v]x, (..., 3) -> (..., 3, 3)."""
    z = np.zeros(v.shape[:-1])
    return np.stack([np.stack([z, -v[..., 2], v[..., 1]], -1),
                     np.stack([v[..., 2], z, -v[..., 0]], -1),
                     np.stack([-v[..., 1], v[..., 0], z], -1)], -2)


def rotation_exp(v: np.ndarray) -> np.ndarray:
    """Exp([v]x): the rotation by |v| radians about v (Rodrigues), (..., 3) -> (..., 3, 3).

    >>> R = rotation_exp(np.array([0.0, 0.0, np.pi / 2]))
    >>> [round(float(a), 12) for a in R @ np.array([1.0, 0.0, 0.0])]
    [0.0, 1.0, 0.0]
    """
    v = np.asarray(v, float)
    theta = np.linalg.norm(v, axis=-1)[..., None, None]
    K = _skew(v)
    small = theta < 1e-8
    safe = np.where(small, 1.0, theta)
    a = np.where(small, 1.0 - theta**2 / 6, np.sin(safe) / safe)
    b = np.where(small, 0.5 - theta**2 / 24, (1.0 - np.cos(safe)) / safe**2)
    return np.eye(3) + a * K + b * (K @ K)


@dataclass(frozen=True)
class RotationIncrements:
    """The angle triples of a parameter vector that the solver steps as rotations.

    ``triples`` (k, 3): positions of (omega, phi, kappa) of one sensor or pose in x;
    only rotations whose three angles are all free are stepped this way.
    """

    triples: np.ndarray

    @classmethod
    def of(cls, layout) -> "RotationIncrements":
        """The free angle triples of a :class:`~fringecal.calibration.model.ParameterLayout`
        (sensor columns 3-5 and pose columns 3-5)."""
        rows = [row for index in (layout.sensor_index[:, 3:6], layout.pose_index[:, 3:6])
                for row in np.asarray(index) if np.all(row >= 0)]
        return cls(np.asarray(rows, np.int64).reshape(-1, 3))

    def _active(self, x: np.ndarray) -> np.ndarray:
        return self.triples[np.abs(np.cos(x[self.triples[:, 1]])) > GIMBAL_LOCK_COS]

    def angle_rates(self, angles: np.ndarray) -> np.ndarray:
        """A = d angles / d delta at delta = 0, (k, 3, 3), for angle triples (k, 3)."""
        R = rotation_matrix(angles[:, 0], angles[:, 1], angles[:, 2])
        dR = np.moveaxis(rotation_derivatives(angles[:, 0], angles[:, 1], angles[:, 2]), 0, 1)
        M = dR.reshape(len(angles), 3, 9).transpose(0, 2, 1)  # (k, 9, 3): columns d vec R / d angle
        target = (R[:, None] @ _skew(np.eye(3))[None]).reshape(len(angles), 3, 9).transpose(0, 2, 1)
        Mt = M.transpose(0, 2, 1)
        return np.linalg.solve(Mt @ M, Mt @ target)  # exact: both span the same tangent space

    def transform(self, x: np.ndarray, N: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Normal matrix and right-hand side in the increments' coordinates: T^T N T, T^T b
        (``b`` (p,), or (m, p) for m right-hand sides)."""
        t = self._active(x)
        if not len(t):
            return N, b
        A = self.angle_rates(x[t])
        N = N.copy()
        b = np.array(b, float, copy=True)
        N[:, t] = np.einsum("pkj,kji->pki", N[:, t], A)
        N[t, :] = np.einsum("kjp,kji->kip", N[t, :], A)
        b[..., t] = np.einsum("...kj,kji->...ki", b[..., t], A)
        return N, b

    def retract(self, x: np.ndarray, d: np.ndarray) -> np.ndarray:
        """x moved by the step d (increments' coordinates): x + d, except that each
        active triple's rotation becomes R(angles) Exp([d_triple]x)."""
        y = x + d
        t = self._active(x)
        if len(t):
            angles = x[t]
            R = rotation_matrix(angles[:, 0], angles[:, 1], angles[:, 2]) @ rotation_exp(d[t])
            y[t] = angles_from_matrix(R, near=angles)
        return y
