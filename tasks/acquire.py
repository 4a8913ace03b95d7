"""Task adapters for the simulated acquisition: the hexapod moves (one task for all
poses, in order) and one render + decode + store task per measurement."""

from __future__ import annotations

import hashlib
from pathlib import Path

from prefect import get_run_logger, task

from fringecal.acquisition import (AcquisitionInputs, MeasurementPlan, acquire_measurement, move_hexapod,
                                   poses_table, store_summary)
from fringecal.frames import Frame
from fringecal.runconfig import RunConfig
from schemas import AcquiredPosesTable, AcquisitionTable, write_table

from .refs import Ref, cache_key, ref_for


def _hexapod_config_digest(run_config: dict) -> str | None:
    hx = run_config["acquisition"]["hexapod"]
    if not hx["enabled"]:
        return None
    from fringecal.hexapod.config import default_hexapod_config_path

    return hashlib.sha256(Path(hx["config"] or default_hexapod_config_path()).read_bytes()).hexdigest()


def _moves_key(context, p) -> str:
    hx = p["run_config"]["acquisition"]["hexapod"]
    return cache_key("move-hexapod", {"planned": p["planned"], "enabled": hx["enabled"], "url": hx["url"],
                                      "config": _hexapod_config_digest(p["run_config"]), "out": p["out"]})


@task(name="move-hexapod", cache_key_fn=_moves_key, persist_result=True)
def move_hexapod_task(run_config: dict, planned: dict[str, list[float]], out: str) -> dict:
    """Move the artefact through the planned poses (pose -> T_world_artefact params);
    write the poses table ``out``; return ``{"table": Ref, "reached": {pose: params}}``."""
    cfg = RunConfig.model_validate(run_config)
    moves = move_hexapod({pose: Frame.from_params(p) for pose, p in planned.items()}, cfg)
    log = get_run_logger()
    for m in moves:
        log.info("pose %s: reached %.4f mm / %.1f urad from plan", m.pose, m.translation_error_mm,
                 1e6 * m.rotation_error_rad)
    write_table(poses_table(moves), out, AcquiredPosesTable)
    return {"table": ref_for(out, "table"), "reached": {m.pose: m.reached.params.tolist() for m in moves}}


def _measurement_key(context, p) -> str:
    return cache_key("acquire-measurement", {"digest": p["config_digest"], "measurement": p["plan"]["measurement"],
                                             "reached": p["reached"], "out": p["out"]})


@task(name="acquire-measurement", cache_key_fn=_measurement_key, persist_result=True)
def acquire_measurement_task(run_config: dict, plan: dict, reached: list[float], out: str,
                             config_digest: str) -> Ref:
    """Render, decode and store one measurement at the reached artefact pose. The cache
    key is ``config_digest`` (fringecal.acquisition.measurement_digest), the measurement
    id, the reached pose and the code version."""
    cfg = RunConfig.model_validate(run_config)
    mp = MeasurementPlan(plan["measurement"], plan["pose"], plan["scanner"], Frame.from_params(plan["planned"]))
    result = acquire_measurement(mp, Frame.from_params(reached), cfg, out, AcquisitionInputs.from_run_config(cfg))
    s = result.summary
    get_run_logger().info("%s: render %.1f s, decode + store %.1f s, %.1f %% valid, %d sphere pixels",
                          mp.measurement, s["render_s"], s["decode_store_s"], 100 * s["valid_fraction"],
                          s["sphere_pixels"])
    return ref_for(out, "store")


def _table_key(context, p) -> str:
    return cache_key("acquisition-table", p)


@task(name="acquisition-table", cache_key_fn=_table_key, persist_result=True)
def acquisition_table_task(stores: list[Ref], root: str, out: str) -> Ref:
    """The measurements table (schemas.AcquisitionTable) of the stores, paths relative to ``root``."""
    import pandas as pd

    rows = []
    for ref in stores:
        s = store_summary(ref.path)
        rows.append({**s, "store": str(Path(ref.path).relative_to(root))})
    cols = ["measurement", "pose", "scanner", "store", "valid_fraction", "sphere_pixels"]
    write_table(pd.DataFrame(rows, columns=cols), out, AcquisitionTable)
    return ref_for(out, "table")


__all__ = ["move_hexapod_task", "acquire_measurement_task", "acquisition_table_task"]
