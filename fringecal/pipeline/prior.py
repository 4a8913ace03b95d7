"""Each scanner's prior calibration, the starting point of the thesis's refinement.

In the thesis every scanner arrived calibrated in its own frame from a planar artefact
(section 6.1); its point clouds gave the sphere centres that located the big artefact.
A simulated run needs the same: :func:`simulate_prior_rig` expresses the true sensors
of every scanner in that scanner's own frame (the reference scanner's frame is the
world; another scanner's frame is the world shifted along x and turned about y) and
adds the errors of a planar calibration: pinhole position and angles, principal point
and principal distance off by configured amounts, and no lens distortion. The
reference camera's external parameters stay exact because they define the world frame.
"""

from __future__ import annotations

import numpy as np

from ..frames import Frame
from ..linking import sensor_in_frame
from ..rig import Rig, Scanner

__all__ = ["simulate_prior_rig", "scanner_frames"]


def scanner_frames(rig: Rig, offset_mm: float, rotation_rad: float) -> dict[str, Frame]:
    """``T_world_scanner`` of every scanner's own frame (identity for the reference)."""
    out = {}
    k = 0
    for s in rig.scanners:
        if s.name == rig.reference:
            out[s.name] = Frame.from_params(np.zeros(6))
        else:
            k += 1
            out[s.name] = Frame.from_params([k * offset_mm, 0.0, 0.0, 0.0, k * rotation_rad, 0.0])
    return out


def simulate_prior_rig(truth: Rig, config, seed: int | None = None) -> tuple[Rig, dict[str, Frame]]:
    """A rig whose sensors are each scanner's prior calibration in its own frame.

    Parameters
    ----------
    truth : Rig
        True sensors in the world frame.
    config : fringecal.runconfig.PriorCalibrationConfig

    Returns
    -------
    prior : Rig
        Same names, formats, free flags and reference; each sensor's parameters are in
        its scanner's own frame, with errors.
    T_world_scanner : dict scanner -> Frame
        The true placement of each scanner's frame (for evaluation only).
    """
    rng = np.random.default_rng(config.seed if seed is None else seed)
    frames = scanner_frames(truth, config.frame_offset_mm, config.frame_rotation_rad)
    ref_camera = truth.scanner(truth.reference).camera.name
    scanners = []
    for s in truth.scanners:
        T_scanner_world = frames[s.name].inverse()
        pair = []
        for sensor in s.sensors:
            local = sensor_in_frame(sensor, T_scanner_world, near=sensor.angles)
            p = local.params.copy()
            if sensor.name != ref_camera:
                p[0:3] += rng.normal(0, config.position_error_mm, 3)
                p[3:6] += rng.normal(0, config.angle_error_rad, 3)
            p[6:8] += rng.normal(0, config.principal_point_error_mm, 2)
            p[8] += rng.normal(0, config.principal_distance_error_mm)
            if not config.keep_distortion:
                p[9:] = 0.0
            pair.append(local.with_params(p))
        scanners.append(Scanner(s.name, *pair))
    return Rig(tuple(scanners), truth.reference, truth.free), frames
