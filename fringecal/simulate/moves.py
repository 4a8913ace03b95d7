"""Where the artefact actually is: the hexapod moves of an acquisition.

:func:`move_hexapod` drives the (simulated) hexapod through
the planned poses in order and reads back, from the encoders, the pose each move
reached: that reached pose is what the renderer sees, as the real artefact would be
wherever the platform put it. :func:`poses_table` records both.
"""

from __future__ import annotations

from dataclasses import dataclass

import pandas as pd

from fringecal.frames import POSE_COLUMNS, Frame
from fringecal.hexapod import HexapodFault, HexapodRig, PlatformMover, TargetRejected, load_hexapod_config

__all__ = ["PoseMove", "move_hexapod", "poses_table", "POSE_COLUMNS"]

@dataclass(frozen=True)
class PoseMove:
    """Where the artefact was planned and where it went (``reached``: from the hexapod's
    encoders, or the plan itself when no hexapod is used). ``move`` is the hexapod's
    :class:`~fringecal.hexapod.ArtefactMove` (None without hexapod)."""

    pose: str
    planned: Frame
    reached: Frame
    move: object | None = None

    @property
    def translation_error_mm(self) -> float:
        """Distance between the planned and reached artefact origins."""
        return self.reached.difference(self.planned)[0]

    @property
    def rotation_error_rad(self) -> float:
        """Angle of the rotation between the planned and reached artefact orientations."""
        return self.reached.difference(self.planned)[1]


def move_hexapod(planned: dict[str, Frame], hexapod) -> list[PoseMove]:
    """Move the artefact through ``planned`` (pose id -> T_world_artefact) in order.

    ``hexapod`` is a :class:`~fringecal.simulate.config.HexapodStepConfig`. When enabled, the platform at its ``url``
    (``hexsim://...`` for the simulated box) carries the artefact: each pose is
    planned into encoder counts, driven, and the reached pose computed from the counts
    read back. Without it every pose is reached exactly. A pose the platform cannot
    reach raises :class:`~fringecal.hexapod.TargetRejected`, a controller fault
    :class:`~fringecal.hexapod.HexapodFault`; both name the pose, and nothing after
    it is moved.
    """
    hx = hexapod
    if not hx.enabled:
        return [PoseMove(pose, T, T) for pose, T in planned.items()]

    rig = HexapodRig.from_config(load_hexapod_config(hx.config))
    out = []
    try:
        mover = PlatformMover.open(hx.url, rig)
    except HexapodFault as err:
        raise HexapodFault(err.kind, f"opening the hexapod at {hx.url}: {err}") from None
    with mover:
        for pose, T in planned.items():
            try:
                move = mover.move_artefact_to(T)
            except TargetRejected as err:
                raise TargetRejected(f"artefact pose {pose}: {err}") from None
            except HexapodFault as err:
                raise HexapodFault(err.kind, f"artefact pose {pose}: {err}") from None
            out.append(PoseMove(pose, T, move.reached, move))
    return out


def poses_table(moves: list[PoseMove]) -> pd.DataFrame:
    """One row per pose (``fringecal.schemas.AcquiredPosesTable``): the pose the artefact reached
    (``tx_mm .. kappa_rad``, the truth the measurements were rendered at), the planned
    one (``planned_*``), the differences, and the encoder counts (empty without hexapod)."""
    rows = []
    for m in moves:
        row = {"measurement": m.pose, **dict(zip(POSE_COLUMNS, m.reached.params))}
        row.update({f"planned_{c}": v for c, v in zip(POSE_COLUMNS, m.planned.params)})
        row.update(translation_error_mm=m.translation_error_mm, rotation_error_rad=m.rotation_error_rad,
                   hexapod=m.move is not None)
        counts = m.move.counts_read if m.move is not None else [None] * 6
        row.update({f"counts_{i + 1}": c for i, c in enumerate(counts)})
        rows.append(row)
    df = pd.DataFrame(rows)
    for i in range(6):
        df[f"counts_{i + 1}"] = df[f"counts_{i + 1}"].astype("Int64")
    return df
