"""Flow behind ``fringecal acquire``: move the hexapod through the planned poses, then
render, decode and store every (pose, scanner) measurement, one task each."""

from __future__ import annotations

from pathlib import Path

from prefect import flow
from prefect.task_runners import ThreadPoolTaskRunner

from fringecal.acquisition import (POSE_COLUMNS, AcquisitionInputs, measurement_digest, plan_acquisition,
                                   planned_poses)
from fringecal.rundir import RunDir
from fringecal.runconfig import RunConfig, load_run_config
from fringecal.store import StoreError, open_store
from tasks.acquire import acquisition_table_task, acquire_measurement_task, move_hexapod_task
from tasks.refs import Ref

#: Table names in RUN_DIR/tables/.
POSES_TABLE = "acquisition_poses"
MEASUREMENTS_TABLE = "acquisition"


# Two measurements at a time at most: each render and decode already uses both cores;
# the second overlaps the single-threaded parts (scene set-up, store compression).
@flow(name="acquire", task_runner=ThreadPoolTaskRunner(max_workers=2))
def acquire_flow(config: str | Path | RunConfig, run_dir: str | Path) -> dict:
    """Acquire every measurement of ``config`` (a run-config YAML or a RunConfig) into
    ``run_dir``.

    Returns ``{"stores": {measurement id: Ref}, "poses": Ref, "measurements": Ref}``:
    the stores ``measurements/<pose>-<scanner>.zarr`` and the tables
    ``tables/acquisition_poses.csv`` (planned and reached pose per pose) and
    ``tables/acquisition.csv`` (one row per measurement). A store or table that is
    missing or incomplete is rebuilt even when the cache holds a result for it.
    """
    cfg = config if isinstance(config, RunConfig) else load_run_config(config)
    rd = RunDir(run_dir).create()
    plans = plan_acquisition(cfg, AcquisitionInputs.from_run_config(cfg))
    doc = cfg.model_dump(mode="json")
    poses_out = rd.table(POSES_TABLE)
    planned = {pose: T.params.tolist() for pose, T in planned_poses(plans).items()}
    moved = move_hexapod_task.with_options(refresh_cache=not _table_matches(poses_out, planned))(
        doc, planned, str(poses_out))
    digest = measurement_digest(cfg)
    futures = {}
    for p in plans:
        out = rd.store(p.measurement)
        reached = moved["reached"][p.pose]
        task = acquire_measurement_task.with_options(refresh_cache=not _up_to_date(out, digest, p.measurement, reached))
        plan = {"measurement": p.measurement, "pose": p.pose, "scanner": p.scanner,
                "planned": p.T_world_artefact.params.tolist()}
        futures[p.measurement] = task.submit(doc, plan, reached, str(out), digest)
    stores: dict[str, Ref] = {m: f.result() for m, f in futures.items()}
    table = acquisition_table_task(list(stores.values()), str(rd.root), str(rd.table(MEASUREMENTS_TABLE)))
    return {"stores": stores, "poses": moved["table"], "measurements": table}


def _table_matches(path: Path, planned: dict[str, list[float]]) -> bool:
    """The poses table exists and lists exactly these planned poses."""
    from schemas import AcquiredPosesTable, TableError, read_table

    try:
        t = read_table(path, AcquiredPosesTable)
    except (FileNotFoundError, TableError):
        return False
    got = {r.measurement: [getattr(r, f"planned_{c}") for c in POSE_COLUMNS] for r in t.itertuples(index=False)}
    return got.keys() == planned.keys() and all(
        max(abs(a - b) for a, b in zip(got[k], v)) < 1e-6 for k, v in planned.items())


def _up_to_date(path: Path, digest: str, measurement: str, reached: list[float]) -> bool:
    """The store is complete and was made from these inputs (so a cached result that
    points at it is still true; another run may have rewritten it since)."""
    try:
        with open_store(path) as ds:
            a = ds.attrs
    except StoreError:
        return False
    pose = a.get("T_world_artefact", {})
    return (a.get("config_digest") == digest and a.get("measurement") == measurement
            and [pose.get(c) for c in POSE_COLUMNS] == list(reached))
