"""Simulated acquisition: the simulated rig, the hexapod moves, and each measurement
rendered, decoded and stored with its ground truth kept apart.

Typical use (what the simulated steps of ``fringecal run`` and ``fringecal simulate`` do)::

    sr = load_simulated_rig(cfg.simulate)                        # truth, prior, artefact, plan
    moves = move_hexapod(sr.planned, cfg.simulate.acquisition.hexapod)   # reached poses
    scene = artefact_scene(sr.artefact, sr.rods, moves[0].reached, sr.hardware)
    simulate_measurement("1-scanner1", sr.truth.scanners[0], scene, cfg.simulate.acquisition,
                         cfg.decode, "1-scanner1.zarr", truth_out="truth/1-scanner1.zarr")

The names below load their submodule on first use (PEP 562), so that importing a light
submodule -- ``fringecal.acquisition.live`` for ``fringecal acquire`` -- does not load the
renderer. Pipeline steps import the submodules themselves, which keeps their cache keys
tied to the files they use.
"""

import importlib

_EXPORTS = {
    "measure": ("TRUTH_VARIABLES", "AcquiredMeasurement", "camera_format_attr", "measurement_rng", "render_frames",
                "simulate_measurement", "truth_from_store", "truth_variables"),
    "plan": ("POSE_COLUMNS", "PoseMove", "move_hexapod", "poses_table"),
    "simulated": ("SimulatedRig", "acquisition_table", "input_files", "load_simulated_rig", "scanners_seeing"),
}
_MODULE_OF = {name: module for module, names in _EXPORTS.items() for name in names}

__all__ = sorted(_MODULE_OF)


def __getattr__(name: str):
    if name in _MODULE_OF:
        return getattr(importlib.import_module(f".{_MODULE_OF[name]}", __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
