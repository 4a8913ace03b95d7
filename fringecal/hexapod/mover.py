"""Move the artefact to a planned pose and report the pose actually reached.

This is the hexapod's interface to the acquisition flow::

    rig = HexapodRig.from_config(load_hexapod_config())          # placement + mounting
    with PlatformMover.open("hexsim://demo", rig) as mover:       # or "/dev/ttyACM0"
        move = mover.move_artefact_to(T_world_artefact_planned)   # Frame -> ArtefactMove
        T_world_artefact = move.reached                           # from the encoders (FK)

``move_artefact_to`` plans (artefact pose -> platform pose -> leg lengths -> counts),
lets the driver check and execute the move (see :mod:`.driver` for the safety rules),
reads the encoders back and returns the artefact pose they imply. Any fault raises
:class:`~fringecal.hexapod.driver.HexapodFault` (motion stopped); an unreachable pose
raises :class:`~fringecal.hexapod.driver.TargetRejected` before anything is sent.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fringecal.frames import Frame
from fringecal.hexapod.driver import HexapodDriver, TargetRejected
from fringecal.hexapod.planning import HexapodRig
from fringecal.hexapod.workspace import check_poses, describe_violations

__all__ = ["ArtefactMove", "PlatformMover"]


@dataclass(frozen=True)
class ArtefactMove:
    """One move: the planned and the reached artefact pose (T_world_artefact), the
    platform poses (6,) behind them, and the target and read encoder counts (6,)."""

    planned: Frame
    reached: Frame
    platform_pose_planned: np.ndarray
    platform_pose_reached: np.ndarray
    counts_target: np.ndarray
    counts_read: np.ndarray

    @property
    def translation_error_mm(self) -> float:
        """Distance between the planned and reached artefact origins."""
        return self.reached.difference(self.planned)[0]

    @property
    def rotation_error_rad(self) -> float:
        """Angle of the rotation between the planned and reached artefact orientations."""
        return self.reached.difference(self.planned)[1]


class PlatformMover:
    """A driver plus a rig: moves the artefact, not the platform."""

    def __init__(self, driver: HexapodDriver, rig: HexapodRig):
        self.driver = driver
        self.rig = rig

    @classmethod
    def open(cls, url: str, rig: HexapodRig) -> "PlatformMover":
        return cls(HexapodDriver.open(url, rig.config), rig)

    def close(self):
        self.driver.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def move_artefact_to(self, T_world_artefact: Frame) -> ArtefactMove:
        """Move so the artefact reaches ``T_world_artefact``; return what was reached."""
        counts, pose = self.rig.counts_for(T_world_artefact)
        check = check_poses(self.rig.config, pose)
        if not check.ok:
            raise TargetRejected("the artefact pose needs a platform pose outside the workspace: "
                                 + "; ".join(describe_violations(self.rig.config, check)))
        read = self.driver.move_counts(counts)
        reached, reached_pose = self.rig.artefact_pose_from_counts(read, near=pose)
        return ArtefactMove(T_world_artefact, reached, pose, reached_pose, counts, read)

    def reached_artefact_pose(self) -> Frame:
        """T_world_artefact from the current encoder readings."""
        return self.rig.artefact_pose_for(self.driver.current_pose())
