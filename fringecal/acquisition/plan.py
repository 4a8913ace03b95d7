"""What a simulated acquisition measures and where the artefact actually is.

:func:`plan_acquisition` lists one measurement per (artefact pose, scanner) of a run
configuration, with the planned ``T_world_artefact`` of the rig's pose table (thesis
table 6-1 by default). :func:`move_hexapod` drives the (simulated) hexapod through
the planned poses in order and reads back, from the encoders, the pose each move
reached: that reached pose is what the renderer sees, as the real artefact would be
wherever the platform put it. :func:`poses_table` records both.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable

import pandas as pd

from ..artefact import Artefact, load_rods
from ..config import ConfigError
from ..frames import Frame
from ..rig import Rig, load_rig
from ..simulate.scenes import ArtefactHardware

__all__ = ["AcquisitionInputs", "MeasurementPlan", "PoseMove", "plan_acquisition", "planned_poses",
           "move_hexapod", "poses_table", "measurement_digest", "POSE_COLUMNS"]

POSE_COLUMNS = ("tx_mm", "ty_mm", "tz_mm", "omega_rad", "phi_rad", "kappa_rad")


@dataclass(frozen=True)
class AcquisitionInputs:
    """The rig data a simulated acquisition needs, loaded and checked once.

    ``poses`` maps pose ids (the pose table's ``measurement`` column) to the planned
    ``T_world_artefact``, in table order.
    """

    rig: Rig
    artefact: Artefact
    rods: pd.DataFrame | None
    hardware: ArtefactHardware
    poses: dict[str, Frame]

    @classmethod
    def from_run_config(cls, run_config) -> "AcquisitionInputs":
        """Load sensors, artefact, rods, materials and poses named by ``run_config.rig``.

        Raises ConfigError (no pose table, bad materials) or TableError (bad CSV),
        each naming the file.
        """
        from schemas import PosePlanTable, TableError, read_table

        rc = run_config.rig_config()
        if rc.artefact_poses is None:
            raise ConfigError(f"{run_config.rig}: artefact_poses is not set; a simulated acquisition needs the "
                              "planned T_world_artefact of every pose (e.g. poses_scanner1_table6-1.csv)")
        try:
            rig = load_rig(rc.sensors, reference=rc.reference_scanner)
        except TableError:
            raise
        except ValueError as err:  # e.g. the reference scanner is not in the sensors file
            raise ConfigError(f"{run_config.rig}: {rc.sensors}: {err}") from None
        artefact = run_config.artefact()
        rods = load_rods(rc.rods, artefact) if rc.rods is not None else None
        try:
            hardware = ArtefactHardware.from_materials(rc.materials)
        except ValueError as err:
            raise ConfigError(str(err)) from None
        table = read_table(rc.artefact_poses, PosePlanTable)
        if table.empty:
            raise ConfigError(f"{rc.artefact_poses}: no artefact poses")
        poses = {str(r.measurement): Frame.from_params([getattr(r, c) for c in POSE_COLUMNS])
                 for r in table.itertuples(index=False)}
        return cls(rig, artefact, rods, hardware, poses)


@dataclass(frozen=True)
class MeasurementPlan:
    """One measurement: id ``<pose>-<scanner>``, and the planned artefact pose."""

    measurement: str
    pose: str
    scanner: str
    T_world_artefact: Frame


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


def plan_acquisition(run_config, inputs: AcquisitionInputs | None = None) -> list[MeasurementPlan]:
    """One :class:`MeasurementPlan` per (pose, scanner): poses in table order, scanners
    in rig order within each pose (the order a real rig measures in)."""
    from ..rundir import measurement_id

    inputs = inputs or AcquisitionInputs.from_run_config(run_config)
    return [MeasurementPlan(measurement_id(pose, s.name), pose, s.name, T)
            for pose, T in inputs.poses.items() for s in inputs.rig.scanners]


def planned_poses(plans: Iterable[MeasurementPlan]) -> dict[str, Frame]:
    """The distinct poses of ``plans``, in order of first appearance."""
    out: dict[str, Frame] = {}
    for p in plans:
        out.setdefault(p.pose, p.T_world_artefact)
    return out


def move_hexapod(planned: dict[str, Frame], run_config) -> list[PoseMove]:
    """Move the artefact through ``planned`` (pose id -> T_world_artefact) in order.

    With ``acquisition.hexapod.enabled`` the platform at ``acquisition.hexapod.url``
    (``hexsim://...`` for the simulated box) carries the artefact: each pose is
    planned into encoder counts, driven, and the reached pose computed from the counts
    read back. Without it every pose is reached exactly. A pose the platform cannot
    reach raises :class:`~fringecal.hexapod.TargetRejected`, a controller fault
    :class:`~fringecal.hexapod.HexapodFault`; both name the pose, and nothing after
    it is moved.
    """
    hx = run_config.acquisition.hexapod
    if not hx.enabled:
        return [PoseMove(pose, T, T) for pose, T in planned.items()]
    from ..hexapod import HexapodFault, HexapodRig, PlatformMover, TargetRejected, load_hexapod_config

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
    """One row per pose (``schemas.AcquiredPosesTable``): the pose the artefact reached
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


def _file_digest(path) -> str | None:
    if path is None:
        return None
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def measurement_digest(run_config) -> str:
    """SHA-256 of everything a measurement depends on besides its pose and id: the
    acquisition settings (without the hexapod, which acts through the reached pose),
    the decoder settings and the contents of the sensors, artefact, rods and
    materials files. Paths are not part of it, only contents."""
    rc = run_config.rig_config()
    acq = run_config.acquisition.model_dump(mode="json", exclude={"hexapod"})
    doc = {
        "acquisition": acq,
        "decode": run_config.decode.model_dump(mode="json"),
        "rig": {"reference": rc.reference_scanner,
                **{k: _file_digest(getattr(rc, k)) for k in ("sensors", "artefact", "rods", "materials")}},
    }
    return hashlib.sha256(json.dumps(doc, sort_keys=True).encode()).hexdigest()
