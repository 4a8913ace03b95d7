"""Artefact poses <-> platform poses <-> leg lengths <-> encoder counts.

The chain of frames (named after what they map, docs/conventions.md)::

    T_world_artefact = T_world_base o T_base_top(platform pose) o T_top_artefact

``T_world_base`` places the platform's BASE frame in the rig's world (for the thesis
rig the world is scanner one's frame); ``T_top_artefact`` is the mounting of the
artefact (its CMM frame) on the TOP platform. :class:`HexapodRig` holds the three and
converts both ways: planned artefact pose -> platform pose -> leg lengths -> counts,
and encoder counts -> forward kinematics -> the artefact pose actually reached.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from fringecal.frames import Frame
from fringecal.hexapod.config import HexapodConfig
from fringecal.hexapod.kinematics import (
    forward_kinematics,
    inverse_kinematics,
    leg_jacobian,
    pose_from_frame,
    pose_to_frame,
)
from fringecal.hexapod.workspace import check_poses, describe_violations

__all__ = [
    "HexapodRig",
    "counts_from_lengths",
    "lengths_from_counts",
    "centre_base_on_poses",
    "thesis_grid",
    "PLAN_COLUMNS",
    "frames_from_table",
    "quantisation_bound",
    "plan_with_stations",
]

POSE_COLUMNS = ["px_mm", "py_mm", "pz_mm", "alpha_rad", "beta_rad", "gamma_rad"]
BASE_COLUMNS = ["base_tx_mm", "base_ty_mm", "base_tz_mm", "base_omega_rad", "base_phi_rad", "base_kappa_rad"]
LENGTH_COLUMNS = [f"length_{i}_mm" for i in range(1, 7)]
STROKE_COLUMNS = [f"stroke_{i}_mm" for i in range(1, 7)]
COUNT_COLUMNS = [f"counts_{i}" for i in range(1, 7)]
PLAN_COLUMNS = (["measurement", "station"] + BASE_COLUMNS + POSE_COLUMNS + LENGTH_COLUMNS
                + STROKE_COLUMNS + COUNT_COLUMNS + ["reachable", "limits"])


def counts_from_lengths(config: HexapodConfig, lengths) -> np.ndarray:
    """Encoder counts (int64, (..., 6)) for leg lengths: round((L - L_retracted) * counts/mm)."""
    a = config.actuator
    stroke = np.asarray(lengths, float) - a.retracted_length_mm
    return np.rint(stroke * a.counts_per_mm).astype(np.int64)


def lengths_from_counts(config: HexapodConfig, counts) -> np.ndarray:
    """Leg lengths (mm, (..., 6)) for encoder counts."""
    a = config.actuator
    return a.retracted_length_mm + np.asarray(counts, float) / a.counts_per_mm


def frames_from_table(poses: pd.DataFrame) -> list[Frame]:
    """Frames from a table with tx_mm..kappa_rad columns (PosePlanTable, PosesTable)."""
    cols = ["tx_mm", "ty_mm", "tz_mm", "omega_rad", "phi_rad", "kappa_rad"]
    return [Frame.from_params(r) for r in poses[cols].to_numpy(float)]


@dataclass(frozen=True)
class HexapodRig:
    """A platform placed in a rig: config, ``T_world_base`` and ``T_top_artefact``."""

    config: HexapodConfig
    T_world_base: Frame
    T_top_artefact: Frame
    _T_base_world: Frame = field(init=False, repr=False, compare=False)
    _T_artefact_top: Frame = field(init=False, repr=False, compare=False)

    def __post_init__(self):
        object.__setattr__(self, "_T_base_world", self.T_world_base.inverse())
        object.__setattr__(self, "_T_artefact_top", self.T_top_artefact.inverse())

    @classmethod
    def from_config(cls, config: HexapodConfig, T_world_base: Frame | None = None,
                    T_top_artefact: Frame | None = None) -> "HexapodRig":
        """The config's placement and mounting unless others are given."""
        return cls(config, T_world_base or config.T_world_base.frame,
                   T_top_artefact or config.T_top_artefact.frame)

    def platform_pose_for(self, T_world_artefact: Frame) -> np.ndarray:
        """Platform pose (6,) that puts the artefact at ``T_world_artefact``."""
        T_base_top = self._T_base_world.compose(T_world_artefact).compose(self._T_artefact_top)
        return pose_from_frame(T_base_top)

    def artefact_pose_for(self, platform_pose) -> Frame:
        """``T_world_artefact`` for a platform pose (6,)."""
        return self.T_world_base.compose(pose_to_frame(platform_pose)).compose(self.T_top_artefact)

    def counts_for(self, T_world_artefact: Frame) -> tuple[np.ndarray, np.ndarray]:
        """(counts (6,) int, platform pose (6,)) for a planned artefact pose; no range check."""
        pose = self.platform_pose_for(T_world_artefact)
        return counts_from_lengths(self.config, inverse_kinematics(self.config.platform, pose)), pose

    def artefact_pose_from_counts(self, counts, near=None) -> tuple[Frame, np.ndarray]:
        """(T_world_artefact, platform pose) from encoder counts, by forward kinematics
        started at ``near`` (a platform pose; default the home pose)."""
        start = self.config.home_pose.vector if near is None else np.asarray(near, float)
        fk = forward_kinematics(self.config.platform, lengths_from_counts(self.config, counts), start)
        return self.artefact_pose_for(fk.poses), fk.poses

    def plan(self, artefact_poses: pd.DataFrame, station: str = "1") -> pd.DataFrame:
        """Plan table (fringecal.schemas.HexapodPlanTable) for a PosePlanTable of T_world_artefact.

        One row per measurement: the platform pose, leg lengths, strokes, counts, and
        whether the pose is reachable, with the constraints it breaks in ``limits``.
        """
        frames = frames_from_table(artefact_poses)
        poses = np.array([self.platform_pose_for(T) for T in frames]).reshape(-1, 6)
        check = check_poses(self.config, poses)
        counts = counts_from_lengths(self.config, check.lengths_mm)
        df = pd.DataFrame({"measurement": artefact_poses["measurement"].astype(str).to_numpy(),
                           "station": station})
        for cols, values in ((BASE_COLUMNS, np.tile(self.T_world_base.params, (len(poses), 1))),
                             (POSE_COLUMNS, poses), (LENGTH_COLUMNS, check.lengths_mm),
                             (STROKE_COLUMNS, check.strokes_mm), (COUNT_COLUMNS, counts)):
            for c, v in zip(cols, np.asarray(values).T):
                df[c] = v
        df["reachable"] = check.ok
        df["limits"] = ["; ".join(describe_violations(self.config, check, i)) or "ok" for i in range(len(poses))]
        return df[PLAN_COLUMNS]


def _level(M: np.ndarray, up: np.ndarray) -> np.ndarray:
    """Smallest rotation of the orientation M (local -> world columns) bringing its z axis onto ``up``."""
    z = M[:, 2]
    axis = np.cross(z, up)
    s, c = np.linalg.norm(axis), float(np.dot(z, up))
    if s < 1e-15:
        return M
    k = axis / s
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    Q = np.eye(3) + s * K + (1 - c) * K @ K
    return Q @ M


def centre_base_on_poses(config: HexapodConfig, T_world_artefact: list[Frame], T_top_artefact: Frame,
                         up=(0.0, 1.0, 0.0)) -> Frame:
    """A base placement ``T_world_base`` that serves a set of artefact poses.

    The BASE stands level (its Z along ``up``, world coordinates); its yaw is that of
    the mean TOP orientation the poses need, and its position puts the TOP origin, at
    the home pose, at the centre of the bounding box of the TOP origins the poses need
    (so the largest excursion along each direction is as small as it can be).
    """
    up = np.asarray(up, float) / np.linalg.norm(up)
    T_artefact_top = T_top_artefact.inverse()
    tops = [T.compose(T_artefact_top) for T in T_world_artefact]
    # chordal mean of the TOP orientations (columns = TOP axes in world), levelled
    M = sum(T.R.T for T in tops)
    U, _, Vt = np.linalg.svd(M)
    M = _level(U @ np.diag([1, 1, np.linalg.det(U @ Vt)]) @ Vt, up)
    origins = np.array([T.t for T in tops])
    centre = (origins.min(axis=0) + origins.max(axis=0)) / 2
    T_world_top_home = Frame.from_matrix(M.T, centre)
    return T_world_top_home.compose(pose_to_frame(config.home_pose.vector).inverse())


def thesis_grid(T_world_first: Frame, lateral_offsets_mm=(0.0, 100.0, 200.0),
                standoffs_mm=(2000.0, 2330.0, 2670.0, 3000.0), lateral_axis=(1.0, 0.0, 0.0),
                away_axis=(0.0, 0.0, -1.0)) -> pd.DataFrame:
    """The thesis's pose grid (section 6.9.1) as a PosePlanTable.

    Three lateral offsets at each of four stand-offs, measurements numbered 1..12 as
    the thesis took them (all lateral offsets at the nearest stand-off first). The
    first pose is ``T_world_first``; the others are pure translations along
    ``lateral_axis`` and, by the stand-off increase, along ``away_axis`` (world
    directions; for the thesis rig world +x is lateral and -z points away from the
    scanners, which sit at z ~ +2.6 m).
    """
    lat = np.asarray(lateral_axis, float) / np.linalg.norm(lateral_axis)
    away = np.asarray(away_axis, float) / np.linalg.norm(away_axis)
    rows = []
    for s in standoffs_mm:
        for o in lateral_offsets_mm:
            t = T_world_first.t + o * lat + (s - standoffs_mm[0]) * away
            rows.append([str(len(rows) + 1), *t, *T_world_first.angles, float(s), float(o)])
    return pd.DataFrame(rows, columns=["measurement", "tx_mm", "ty_mm", "tz_mm", "omega_rad", "phi_rad", "kappa_rad",
                                       "standoff_mm", "lateral_mm"])


def plan_with_stations(config: HexapodConfig, artefact_poses: pd.DataFrame, group_column: str,
                       T_top_artefact: Frame | None = None) -> tuple[pd.DataFrame, dict[str, Frame]]:
    """Plan with one base station per group of poses (the platform rolled on its castors).

    Each group (rows sharing ``group_column``, e.g. the grid's ``standoff_mm``) gets a
    base placement from :func:`centre_base_on_poses`; stations are numbered 1.. in order
    of appearance. Returns the plan table and ``{station: T_world_base}``.
    """
    mount = T_top_artefact or config.T_top_artefact.frame
    plans, stations = [], {}
    for k, (_, group) in enumerate(artefact_poses.groupby(group_column, sort=False), start=1):
        T_world_base = centre_base_on_poses(config, frames_from_table(group), mount)
        stations[str(k)] = T_world_base
        plans.append(HexapodRig(config, T_world_base, mount).plan(group, station=str(k)))
    return pd.concat(plans, ignore_index=True), stations


def quantisation_bound(config: HexapodConfig, platform_pose) -> np.ndarray:
    """Largest platform-pose error (6,) (mm, rad) from rounding leg lengths to whole counts.

    Linearised: ``|d pose_k| <= q sum_j |(J^-1)_kj|`` with ``q = 0.5 / counts_per_mm``
    and J the leg Jacobian at ``platform_pose``.
    """

    J = leg_jacobian(config.platform, np.asarray(platform_pose, float))
    q = 0.5 / config.actuator.counts_per_mm
    return q * np.abs(np.linalg.inv(J)).sum(axis=-1)
