"""Simulated acquisition: plan the measurements of a run, move the hexapod, render,
decode and store each measurement with its ground truth.

Typical use (what ``fringecal acquire`` does, one task per measurement)::

    inputs = AcquisitionInputs.from_run_config(cfg)
    plans = plan_acquisition(cfg, inputs)                       # one per (pose, scanner)
    moves = move_hexapod(planned_poses(plans), cfg)              # reached T_world_artefact per pose
    reached = {m.pose: m.reached for m in moves}
    for p in plans:
        acquire_measurement(p, reached[p.pose], cfg, run_dir.store(p.measurement), inputs)
"""

from .measure import (TRUTH_VARIABLES, AcquiredMeasurement, acquire_measurement, measurement_rng, store_summary,
                      truth_from_store, truth_variables)
from .plan import (POSE_COLUMNS, AcquisitionInputs, MeasurementPlan, PoseMove, measurement_digest, move_hexapod,
                   plan_acquisition, planned_poses, poses_table)

__all__ = [
    "AcquisitionInputs", "MeasurementPlan", "PoseMove", "plan_acquisition", "planned_poses", "move_hexapod",
    "poses_table", "measurement_digest", "POSE_COLUMNS",
    "AcquiredMeasurement", "acquire_measurement", "measurement_rng", "truth_variables", "truth_from_store",
    "store_summary", "TRUTH_VARIABLES",
]
