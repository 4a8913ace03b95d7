"""Task adapter for pose estimation (thesis section 6.2.1)."""

from __future__ import annotations

from prefect import get_run_logger, task

from fringecal.spheres.pose import estimate_poses_file
from fringecal.tasks.refs import Ref, cache_key, ref_for


def _key(context, parameters) -> str:
    return cache_key("estimate-poses", parameters, ("fringecal.spheres.pose",))


@task(name="estimate-poses", cache_key_fn=_key, persist_result=True)
def estimate_poses_task(artefact: Ref, centres: Ref, out: str) -> dict[str, Ref | list | None]:
    """Poses of every (measurement, scanner) group; skipped groups are logged by name.
    ``poses`` is None when no group gives a pose (nothing written)."""
    logger = get_run_logger()
    result = estimate_poses_file(artefact.path, centres.path, out)
    for r in result.skipped.itertuples():
        logger.warning("measurement %s, scanner %s: no pose (%s)", r.measurement, r.scanner, r.reason)
    poses = ref_for(out, "table") if len(result.poses) else None
    return {"poses": poses, "skipped": result.skipped.to_dict("records")}
