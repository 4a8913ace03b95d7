"""Artefact poses from labelled sphere centres (thesis section 6.2.1).

One pose ``T_world_artefact`` per (measurement, scanner) group, by SVD registration
of the measured centres against the artefact definition. Groups that cannot give a
pose (fewer than three spheres, collinear spheres, unknown sphere ids) are reported
by name with the reason and skipped; the others still come out.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import pandas as pd

from fringecal.artefact import Artefact, load_artefact
from fringecal.registration import DegenerateGeometryError, RigidRegistration
from fringecal.schemas import PosesTable, SphereCentresTable, read_table, validate_table, write_table

__all__ = ["PoseResult", "estimate_poses", "estimate_poses_file", "POSE_COLUMNS"]

POSE_COLUMNS = ["measurement", "scanner", "tx_mm", "ty_mm", "tz_mm",
                "omega_rad", "phi_rad", "kappa_rad", "rms_mm", "n_spheres"]


@dataclass(frozen=True)
class PoseResult:
    """Poses table (docs/contracts.md) and the groups that were skipped.

    ``skipped`` has columns ``measurement, scanner, reason``.
    """

    poses: pd.DataFrame
    skipped: pd.DataFrame


def estimate_poses(centres: pd.DataFrame, artefact: Artefact, source: str = "<centres>") -> PoseResult:
    """Estimate one pose per (measurement, scanner) group of a sphere-centres table.

    Examples
    --------
    >>> from fringecal.frames import Frame
    >>> art = Artefact(("1", "2", "3", "4"), [[0, 0, 0], [600, 0, 0], [0, 600, 0], [0, 0, 600]], [50] * 4)
    >>> T = Frame.from_params([100, 200, 300, 0.1, 0.2, 0.3])
    >>> w = T.to_world(art.centres)
    >>> c = pd.DataFrame({"measurement": "m1", "scanner": "s1", "sphere_id": art.ids,
    ...                   "x_mm": w[:, 0], "y_mm": w[:, 1], "z_mm": w[:, 2]})
    >>> res = estimate_poses(c, art)
    >>> res.poses[["tx_mm", "omega_rad"]].round(6).values.tolist()
    [[100.0, 0.1]]
    """
    centres = validate_table(centres, SphereCentresTable, source)
    rows, skipped = [], []
    for (meas, scanner), g in centres.groupby(["measurement", "scanner"], sort=False):
        try:
            local = artefact.centres_of(g["sphere_id"])
        except KeyError as err:
            skipped.append((meas, scanner, str(err.args[0])))
            continue
        world = g[["x_mm", "y_mm", "z_mm"]].to_numpy(float)
        try:
            reg = RigidRegistration.from_estimate(local, world)
        except DegenerateGeometryError as err:
            ids = ", ".join(g["sphere_id"])
            skipped.append((meas, scanner, f"{err} (spheres {ids})"))
            continue
        t, a = reg.frame.t, reg.frame.angles
        rows.append((meas, scanner, *t, *a, reg.rms, reg.n_points))
    poses = pd.DataFrame(rows, columns=POSE_COLUMNS)
    if len(poses):
        poses = validate_table(poses, PosesTable, "poses")
    return PoseResult(poses, pd.DataFrame(skipped, columns=["measurement", "scanner", "reason"]))


def estimate_poses_file(artefact_path, centres_path, out_path) -> PoseResult:
    """Read an artefact table and a sphere-centres table, estimate the poses and write
    them to ``out_path`` atomically; nothing is written when no group gives a pose.

    What ``fringecal pose`` runs, directly or as a Prefect task.
    """

    art = load_artefact(artefact_path)
    table = read_table(centres_path, SphereCentresTable)
    result = estimate_poses(table, art, source=str(centres_path))
    if len(result.poses):
        write_table(result.poses, Path(out_path), PosesTable)
    return result
