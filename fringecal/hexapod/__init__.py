"""The Stewart-platform hexapod of thesis chapter 4.

- :mod:`.kinematics`: 6-3 model, inverse kinematics (eqs. 4-1..4-20), forward kinematics
- :mod:`.config`: the platform YAML (``configs/hexapod/thesis_platform.yaml``)
- :mod:`.workspace`: strokes and joint limits, reach along each axis
- :mod:`.planning`: artefact poses <-> platform poses <-> leg lengths <-> counts
- :mod:`.protocol`: the ASCII protocol of the control box
- :mod:`.driver`: the safe pyserial driver and command files
- :mod:`.simulator`: a simulated control box at the pyserial URL ``hexsim://``
- :mod:`.mover`: move the artefact to a planned pose, return the pose reached
- :mod:`.drift`: the stability check of section 4.5.2

Importing this package registers the ``hexsim://`` URL handler with pyserial.
"""

import serial as _serial

if "fringecal.hexapod" not in _serial.protocol_handler_packages:
    _serial.protocol_handler_packages.append("fringecal.hexapod")

from fringecal.hexapod.config import HexapodConfig, load_hexapod_config  # noqa: E402
from fringecal.hexapod.drift import DriftReport, drift_check  # noqa: E402
from fringecal.hexapod.driver import HexapodDriver, HexapodFault, TargetRejected  # noqa: E402
from fringecal.hexapod.kinematics import (  # noqa: E402
    ForwardKinematicsError,
    PlatformGeometry,
    forward_kinematics,
    inverse_kinematics,
)
from fringecal.hexapod.mover import ArtefactMove, PlatformMover  # noqa: E402
from fringecal.hexapod.planning import HexapodRig  # noqa: E402
from fringecal.hexapod.workspace import check_poses, reach_report  # noqa: E402

__all__ = [
    "ArtefactMove",
    "DriftReport",
    "ForwardKinematicsError",
    "HexapodConfig",
    "HexapodDriver",
    "HexapodFault",
    "HexapodRig",
    "PlatformGeometry",
    "PlatformMover",
    "TargetRejected",
    "check_poses",
    "drift_check",
    "forward_kinematics",
    "inverse_kinematics",
    "load_hexapod_config",
    "reach_report",
]
