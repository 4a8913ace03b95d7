"""Simulated acquisition: the simulated rig, the hexapod moves, and each measurement
rendered, decoded and stored with its ground truth kept apart.

Typical use (what the simulated steps of ``fringecal run`` and ``fringecal simulate`` do)::

    sr = load_simulated_rig(cfg.simulate)                        # truth, prior, artefact, plan
    moves = move_hexapod(sr.planned, cfg.simulate.acquisition.hexapod)   # reached poses
    scene = artefact_scene(sr.artefact, sr.rods, moves[0].reached, sr.hardware)
    simulate_measurement("1-scanner1", sr.truth.scanners[0], scene, cfg.simulate.acquisition,
                         cfg.decode, "1-scanner1.zarr", truth_out="truth/1-scanner1.zarr")
"""

from .measure import (TRUTH_VARIABLES, AcquiredMeasurement, camera_format_attr, measurement_rng, render_frames,
                      simulate_measurement, truth_from_store, truth_variables)
from .plan import POSE_COLUMNS, PoseMove, move_hexapod, poses_table
from .simulated import SimulatedRig, acquisition_table, input_files, load_simulated_rig, scanners_seeing

__all__ = [
    "SimulatedRig", "load_simulated_rig", "input_files", "scanners_seeing", "acquisition_table", "PoseMove", "move_hexapod", "poses_table", "POSE_COLUMNS",
    "AcquiredMeasurement", "simulate_measurement", "render_frames", "measurement_rng", "truth_variables",
    "truth_from_store", "camera_format_attr", "TRUTH_VARIABLES",
]
