"""Dry run of a live acquisition against the real controller: queries only.

``fringecal acquire --dry-run`` checks the data set, the hexapod config and the capture
template as a real run does (:func:`~.live.prepare`), then opens the box and sends only
queries: ``ID?`` (on opening, and once more for the identity shown) and ``POS?`` (the
encoders and IDLE/BUSY). From the encoders it computes where the artefact is now, and
checks every measurement still to do: its platform pose inside the workspace, and the
driver's path check (:meth:`~fringecal.hexapod.HexapodDriver.check_target`, which sends
nothing) for the sequence of moves from the current position through the reachable
poses in plan order. It writes nothing, removes no stale staging folder, moves nothing
and captures nothing. (Only a box that answers wrongly to a query gets the driver's
one ``STOP``.)
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np

from fringecal.acquisition.live import EXIT_HEXAPOD, AcquisitionError, LivePlan, check_path, open_mover
from fringecal.frames import Frame
from fringecal.hexapod import ForwardKinematicsError, HexapodFault

__all__ = ["DryRunRow", "DryRun", "dry_run"]


@dataclass(frozen=True)
class DryRunRow:
    """One planned measurement: ``status`` (complete, partial, pending), the scanners
    still ``missing``, and the ``problem`` that would stop it (empty when none)."""

    measurement: str
    status: str
    missing: tuple[str, ...]
    problem: str


@dataclass(frozen=True)
class DryRun:
    """What the box answered and what a real run would do."""

    url: str
    identity: str
    counts: np.ndarray
    busy: bool
    artefact_pose: Optional[Frame]
    pose_problem: str
    rows: tuple[DryRunRow, ...]
    stale: tuple[str, ...]

    def problems(self) -> list[str]:
        """Everything that would stop a real run (empty when it would start)."""
        out = [f"hexapod at {self.url}: the box reports a move running (BUSY)"] if self.busy else []
        if self.pose_problem:
            out.append(f"hexapod at {self.url}: {self.pose_problem}")
        return out + [f"measurement {r.measurement}: {r.problem}" for r in self.rows if r.problem]


def dry_run(plan: LivePlan, url: str) -> DryRun:
    """Query the box at ``url`` and check every move a real run would make (see the module notes).

    Raises
    ------
    AcquisitionError
        The box cannot be opened or answers a query wrongly (status EXIT_HEXAPOD).
    """
    todo = plan.survey.todo()
    problems = {m: f"outside the workspace: {plan.limits[m]}" for m in todo if plan.limits[m] != "ok"}
    with open_mover(url, plan.rig) as mover:
        try:
            identity = mover.driver.identify()
            counts, busy = mover.driver.positions()
        except HexapodFault as err:
            raise AcquisitionError(f"hexapod at {url}: {err}", EXIT_HEXAPOD) from None
        try:
            pose, pose_problem = plan.rig.artefact_pose_from_counts(counts)[0], ""
        except ForwardKinematicsError as err:
            pose, pose_problem = None, f"the encoders {counts.tolist()} give no platform pose: {err}"
        reachable = [m for m in todo if m not in problems]
        problems.update(check_path(mover, plan, reachable, counts))
    rows = tuple(DryRunRow(m, s.status, s.missing, problems.get(m, "")) for m, s in plan.survey.states.items())
    return DryRun(url, identity, counts, busy, pose, pose_problem, rows, tuple(str(p) for p in plan.survey.stale))
