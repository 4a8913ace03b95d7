"""Each scanner's prior calibration, the starting point of the global calibration.

In the thesis every scanner arrived calibrated in its own frame from a planar artefact
(section 6.1); its point clouds gave the sphere centres that located the big artefact.
A simulated run needs the same, and nothing in it may come from the true placement
beyond the documented error sizes (:class:`~fringecal.simulate.settings.PriorCalibrationConfig`):

- **Frame.** A stereo calibration delivers a scanner in its camera's frame: the camera
  at the origin looking along its own axes. :func:`scanner_frames` gives each scanner's
  ``T_world_scanner`` (its true camera pose); the prior's camera has position and
  angles exactly zero, and the projector sits where the truth puts it relative to the
  camera, with errors. The reference scanner's frame becomes the world of the
  calibration, so the calibrated rig is expressed in the reference camera's frame.
- **Scale.** A planar calibration's commonest large error is the scale of the
  camera-projector baseline: every distance it measures is off by the same factor.
  Each scanner's baseline is scaled by a factor drawn from ``scale_error_range``
  (relative; negative: distances short), which scales the whole point cloud about the
  camera's pinhole.
- **Geometry.** Projector position (``position_error_mm`` per coordinate) and angles
  (``angle_error_rad``) on top, and interior parameters of both sensors off by
  ``principal_point_error_mm`` and ``principal_distance_error_mm``.
- **Distortion.** Each prior carries its own distortion estimate: every true
  coefficient off by a relative error of ``distortion_error_fraction`` (Gaussian),
  never the true values themselves.

All errors are Gaussian with the given standard deviations (the scale factor uniform in
its range), drawn from ``seed``.
"""

from __future__ import annotations

import numpy as np

from fringecal.frames import Frame
from fringecal.rig import Rig, Scanner
from fringecal.sensor import sensor_in_frame

__all__ = ["simulate_prior_rig", "scanner_frames"]


def scanner_frames(rig: Rig) -> dict[str, Frame]:
    """``T_world_scanner`` of every scanner's own frame: its camera's frame."""
    return {s.name: Frame.from_matrix(s.camera.R, s.camera.pinhole) for s in rig.scanners}


def simulate_prior_rig(truth: Rig, config, seed: int | None = None) -> tuple[Rig, dict[str, Frame]]:
    """A rig whose sensors are each scanner's prior calibration in its own frame.

    Parameters
    ----------
    truth : Rig
        True sensors in the world frame.
    config : fringecal.simulate.settings.PriorCalibrationConfig

    Returns
    -------
    prior : Rig
        Same names, formats, free flags and reference; each sensor's parameters are in
        its scanner's own (camera) frame, with errors.
    T_world_scanner : dict scanner -> Frame
        The true placement of each scanner's frame (for evaluation only).
    """
    rng = np.random.default_rng(config.seed if seed is None else seed)
    frames = scanner_frames(truth)
    lo, hi = config.scale_error_range
    scanners = []
    for s in truth.scanners:
        T_scanner_world = frames[s.name].inverse()
        scale = 1.0 + rng.uniform(lo, hi)
        pair = []
        for sensor in s.sensors:
            local = sensor_in_frame(sensor, T_scanner_world, near=np.zeros(3) if sensor is s.camera else None)
            p = local.params.copy()
            if sensor is s.camera:
                p[0:6] = 0.0
            else:
                p[0:3] = scale * p[0:3] + rng.normal(0, config.position_error_mm, 3)
                p[3:6] += rng.normal(0, config.angle_error_rad, 3)
            p[6:8] += rng.normal(0, config.principal_point_error_mm, 2)
            p[8] += rng.normal(0, config.principal_distance_error_mm)
            p[9:] *= 1.0 + rng.normal(0, config.distortion_error_fraction, p[9:].shape)
            pair.append(local.with_params(p))
        scanners.append(Scanner(s.name, *pair))
    return Rig(tuple(scanners), truth.reference, truth.free), frames
