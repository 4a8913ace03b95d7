"""Flow behind ``fringecal pose``."""

from __future__ import annotations

from prefect import flow

from fringecal.tasks.pose import estimate_poses_task
from fringecal.tasks.refs import ref_for


@flow(name="pose", log_prints=True)
def pose_flow(artefact: str, centres: str, out: str) -> dict:
    """Estimate artefact poses from labelled sphere centres; returns refs and skipped groups."""
    return estimate_poses_task(ref_for(artefact, "table"), ref_for(centres, "table"), out)
