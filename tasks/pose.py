"""Task adapter for pose estimation (thesis section 6.2.1)."""

from __future__ import annotations

from pathlib import Path

from prefect import get_run_logger, task

from fringecal.artefact import load_artefact
from fringecal.pose import estimate_poses
from schemas import PosesTable, SphereCentresTable, read_table, write_table

from .refs import Ref, cache_key, ref_for


def _key(context, parameters) -> str:
    return cache_key("estimate-poses", parameters, ("fringecal.pose",))


@task(name="estimate-poses", cache_key_fn=_key, persist_result=True)
def estimate_poses_task(artefact: Ref, centres: Ref, out: str) -> dict[str, Ref | list]:
    """Poses of every (measurement, scanner) group; skipped groups are logged by name."""
    logger = get_run_logger()
    art = load_artefact(artefact.path)
    table = read_table(centres.path, SphereCentresTable)
    result = estimate_poses(table, art, source=centres.path)
    for r in result.skipped.itertuples():
        logger.warning("measurement %s, scanner %s: no pose (%s)", r.measurement, r.scanner, r.reason)
    write_table(result.poses, Path(out), PosesTable if len(result.poses) else None)
    return {"poses": ref_for(out, "table"), "skipped": result.skipped.to_dict("records")}
