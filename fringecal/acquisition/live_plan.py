"""The checks of a live acquisition that need no hardware (:mod:`.live`).

:func:`prepare` reads and checks a data set folder, the hexapod config and the capture
template into a :class:`LivePlan`; :func:`check_reachable` refuses planned poses still to
measure that lie outside the hexapod's workspace; :func:`reach_tolerance` is the largest
artefact error a correct move can leave (the tolerance the reached pose is checked against).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np

from fringecal.acquisition.live_capture import CaptureCommand
from fringecal.acquisition.live_state import Survey, survey
from fringecal.artefact import load_artefact, load_rods
from fringecal.config import ConfigError, load_yaml_model
from fringecal.dataset import (
    ARTEFACT_FILE,
    DATASET_FILE,
    MIN_SPHERES,
    POSES_PLANNED_FILE,
    RODS_FILE,
    SENSORS_PRIOR_FILE,
    DatasetConfig,
    DataSetError,
)
from fringecal.frames import Frame, frames_from_rows
from fringecal.hexapod import HexapodRig, TargetRejected, load_hexapod_config
from fringecal.hexapod.kinematics import leg_jacobian
from fringecal.rig import load_rig
from fringecal.schemas import PosePlanTable, read_table

__all__ = ["TOLERANCE_MARGIN", "LivePlan", "prepare", "check_reachable", "reach_tolerance"]

#: safety factor on the reach tolerance (the linearisation is exact to 0.1 % on table 6-1)
TOLERANCE_MARGIN = 1.1


@dataclass(frozen=True)
class LivePlan:
    """A checked data set ready to acquire: planned poses (plan order), camera format per
    scanner (``sensors_prior.csv`` order), the hexapod rig, the workspace verdict per
    measurement (``limits``: ``ok`` or what its platform pose breaks), the capture
    command, and what is already on disk."""

    root: Path
    planned: dict[str, Frame]
    cameras: dict[str, tuple[int, int]]
    rig: HexapodRig
    limits: dict[str, str]
    capture: Optional[CaptureCommand]
    survey: Survey


def _required(path: Path, what: str) -> Path:
    if not path.is_file():
        raise DataSetError(f"{path}: missing; a live acquisition needs {path.name} ({what})")
    return path


def prepare(dataset, hexapod_config=None, capture: Optional[str] = None) -> LivePlan:
    """Read and check a data set folder, the hexapod config and the capture template.

    Reads tables, YAML and folder listings only; talks to no hardware.

    Raises
    ------
    DataSetError, fringecal.schemas.TableError, FrameStackError, ConfigError, CaptureTemplateError
        All ``ValueError``; the message names the file or folder.
    """

    root = Path(dataset).expanduser().absolute()
    if not root.is_dir():
        raise DataSetError(f"{root}: no such data set folder")
    try:
        config = load_yaml_model(_required(root / DATASET_FILE, "name, reference_scanner"), DatasetConfig)
    except ConfigError as err:
        raise DataSetError(str(err)) from None
    artefact_path = _required(root / ARTEFACT_FILE, "the artefact's CMM table")
    artefact = load_artefact(artefact_path)
    if len(artefact) < MIN_SPHERES:
        raise DataSetError(f"{artefact_path}: {len(artefact)} sphere(s); an artefact needs at least {MIN_SPHERES}")
    if (root / RODS_FILE).is_file():
        load_rods(root / RODS_FILE, artefact)
    prior = _required(root / SENSORS_PRIOR_FILE, "each scanner's prior calibration: the scanners")
    try:
        sensors = load_rig(prior)
    except ValueError as err:
        raise DataSetError(f"{prior}: {err}") from None
    names = [s.name for s in sensors.scanners]
    if config.reference_scanner not in names:
        raise DataSetError(f"{root / DATASET_FILE}: reference_scanner {config.reference_scanner!r} is not a scanner "
                           f"of {prior} (scanners: {', '.join(names)})")
    poses_path = _required(root / POSES_PLANNED_FILE, "the planned T_world_artefact of every measurement")
    poses = read_table(poses_path, PosePlanTable)
    _check_names(poses_path, list(poses["measurement"]), names)
    rig = HexapodRig.from_config(load_hexapod_config(hexapod_config))
    table = rig.plan(poses)
    cameras = {s.name: (s.camera.format.width_px, s.camera.format.height_px) for s in sensors.scanners}
    command = CaptureCommand.parse(capture, cwd=root) if capture is not None else None
    planned = frames_from_rows(poses)
    return LivePlan(root, planned, cameras, rig, dict(zip(table["measurement"], table["limits"])), command,
                    survey(root, list(planned), cameras))


def _check_names(path: Path, measurements: list[str], scanners: list[str]) -> None:
    """Measurement names must be folder names, and every store id ``<m>-<s>`` unique."""
    for m in measurements:
        if m.startswith(".") or "/" in m or "\\" in m or m in ("", ".."):
            raise DataSetError(f"{path}: measurement {m!r} cannot be a folder name (no '/', no leading '.')")
    seen: dict[str, tuple[str, str]] = {}
    for m in measurements:
        for s in scanners:
            other = seen.setdefault(f"{m}-{s}", (m, s))
            if other != (m, s):
                raise DataSetError(f"{path}: measurement {m!r} with scanner {s!r} gives the store id {m}-{s}, as "
                                   f"measurement {other[0]!r} with scanner {other[1]!r} does; rename one")


def check_reachable(plan: LivePlan) -> None:
    """Refuse (TargetRejected, naming every one) planned poses still to measure that need
    a platform pose outside the workspace."""
    bad = [f"measurement {m}: {plan.limits[m]}" for m in plan.survey.todo() if plan.limits[m] != "ok"]
    if bad:
        raise TargetRejected(f"{plan.root / POSES_PLANNED_FILE}: {len(bad)} planned pose(s) outside the hexapod's "
                             f"workspace; nothing was moved: " + "; ".join(bad))


def reach_tolerance(rig: HexapodRig, platform_pose) -> tuple[float, float]:
    """Largest artefact error (translation mm, rotation rad) a correct move can leave at
    ``platform_pose``, times :data:`TOLERANCE_MARGIN`.

    A correct move leaves every leg within ``position_tolerance_counts`` of its target,
    itself rounded to whole counts: ``tolerance + 0.5`` counts of leg length per leg. The
    artefact's error is linear in the six leg errors (leg Jacobian, then the mounting), so
    its largest norm over that box is at one of the 64 corners.
    """
    act = rig.config.actuator
    dl = (act.position_tolerance_counts + 0.5) / act.counts_per_mm
    pose = np.asarray(platform_pose, float)
    columns = np.linalg.inv(leg_jacobian(rig.config.platform, pose))  # d pose / d leg length
    T0, h = rig.artefact_pose_for(pose), 1e-3
    D = np.empty((6, 6))  # d (artefact translation, rotation vector) / d leg length
    for j in range(6):
        T = rig.artefact_pose_for(pose + h * columns[:, j])
        R = T.R @ T0.R.T
        D[:3, j] = (T.t - T0.t) / h
        D[3:, j] = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]]) / (2 * h)
    moved = np.array(list(itertools.product((-dl, dl), repeat=6))) @ D.T
    return (TOLERANCE_MARGIN * float(np.linalg.norm(moved[:, :3], axis=1).max()),
            TOLERANCE_MARGIN * float(np.linalg.norm(moved[:, 3:], axis=1).max()))
