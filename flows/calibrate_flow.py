"""Flow behind ``fringecal calibrate --run RUN_DIR``."""

from __future__ import annotations

from pathlib import Path

from prefect import flow

from fringecal.calibration.run import RUN_INPUTS
from tasks.calibrate import calibrate_task
from tasks.refs import ref_for


@flow(name="calibrate", log_prints=True)
def calibrate_flow(run_dir: str) -> dict:
    """Bundle adjustment of a run directory's control points (one coarse task)."""
    inputs = {k: ref_for(Path(run_dir) / rel, "file") for k, rel in RUN_INPUTS.items()
              if (Path(run_dir) / rel).exists()}
    return calibrate_task(run_dir, inputs)
