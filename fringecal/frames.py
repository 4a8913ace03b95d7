"""Rigid frames: an origin and thesis Euler angles (docs/conventions.md).

A :class:`Frame` is named after what it maps: ``T_world_artefact`` takes points
from the artefact (CMM) frame into the world, with
``x_world = R^T x_local + t`` and ``x_local = R (x_world - t)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fringecal.rotation import angles_from_matrix, rotation_matrix, to_local, to_world

__all__ = ["Frame", "POSE_COLUMNS", "frame_rows", "frames_from_rows"]

#: Columns of a pose in every pose table (``T_world_<object>`` or ``T_<frame>_<object>``).
POSE_COLUMNS = ("tx_mm", "ty_mm", "tz_mm", "omega_rad", "phi_rad", "kappa_rad")


@dataclass(frozen=True)
class Frame:
    """Origin ``t`` (world, mm) and angles (omega, phi, kappa) in radians.

    Examples
    --------
    >>> T = Frame.from_params([10.0, 0.0, 0.0, 0.0, 0.0, np.pi / 2])
    >>> T.to_world([[1.0, 0.0, 0.0]]).round(12)
    array([[10.,  1.,  0.]])
    >>> T.to_local(T.to_world([[1.0, 2.0, 3.0]])).round(12)
    array([[1., 2., 3.]])
    """

    t: np.ndarray
    angles: np.ndarray

    def __post_init__(self):
        object.__setattr__(self, "t", np.asarray(self.t, float).reshape(3))
        object.__setattr__(self, "angles", np.asarray(self.angles, float).reshape(3))

    @classmethod
    def from_params(cls, params) -> "Frame":
        """From (tx, ty, tz, omega, phi, kappa)."""
        p = np.asarray(params, float).reshape(6)
        return cls(p[:3], p[3:])

    @classmethod
    def from_matrix(cls, R, t, near=None) -> "Frame":
        """From R (local <- world rotation, eq. 2-6) and origin t."""
        return cls(t, angles_from_matrix(R, near=near))

    @property
    def params(self) -> np.ndarray:
        """(tx, ty, tz, omega, phi, kappa), shape (6,)."""
        return np.concatenate([self.t, self.angles])

    @property
    def R(self) -> np.ndarray:
        """Rotation local <- world, shape (3, 3)."""
        return rotation_matrix(*self.angles)

    def to_world(self, points_local) -> np.ndarray:
        """points (..., 3) local -> world."""
        return to_world(points_local, self.R, self.t)

    def to_local(self, points_world) -> np.ndarray:
        """points (..., 3) world -> local."""
        return to_local(points_world, self.R, self.t)

    def compose(self, inner: "Frame") -> "Frame":
        """Frame mapping inner-local -> this frame's world.

        If ``self`` is T_a_b (b -> a) and ``inner`` is T_b_c (c -> b), the result
        is T_a_c (c -> a).
        """
        # x_b = R_i^T x_c + t_i ; x_a = R_s^T x_b + t_s
        R = self.R
        Ri = inner.R
        R_new = Ri @ R  # x_a = (Ri R)^T x_c + ...
        t_new = self.to_world(inner.t)
        # the summed angles only pick the branch; wrapped, a chain of compositions stays
        # within the +-2 pi the pose tables allow
        near = np.angle(np.exp(1j * (self.angles + inner.angles)))
        return Frame.from_matrix(R_new, t_new, near=near)

    def difference(self, other: "Frame") -> tuple[float, float]:
        """(distance between the origins in mm, angle of the relative rotation in rad).

        >>> a = Frame.from_params([0, 0, 0, 0, 0, 0.0])
        >>> [round(v, 12) for v in a.difference(Frame.from_params([3, 4, 0, 0, 0, 0.1]))]
        [5.0, 0.1]
        """
        c = (np.trace(self.R @ other.R.T) - 1) / 2
        return float(np.linalg.norm(self.t - other.t)), float(np.arccos(np.clip(c, -1.0, 1.0)))

    def inverse(self) -> "Frame":
        """T_b_a from T_a_b."""
        R = self.R
        # x_b = R (x_a - t)  =>  as a frame with origin t' and rotation R':
        # x_b = R'^T x_a + t'  with R' = R^T, t' = -R t
        return Frame.from_matrix(R.T, -R @ self.t)


def frame_rows(frames: dict, key: str = "measurement"):
    """A pose table (``key``, tx_mm .. kappa_rad) of name -> Frame."""
    import pandas as pd

    return pd.DataFrame([{key: name, **dict(zip(POSE_COLUMNS, map(float, T.params)))} for name, T in frames.items()],
                        columns=[key, *POSE_COLUMNS])


def frames_from_rows(table, key: str = "measurement") -> dict:
    """name -> Frame of a pose table (inverse of :func:`frame_rows`)."""
    return {str(r[key]): Frame.from_params([float(r[c]) for c in POSE_COLUMNS]) for _, r in table.iterrows()}
