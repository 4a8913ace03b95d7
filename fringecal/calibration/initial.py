"""Start values of the bundle adjustment in one global frame (thesis sections 6.2-6.3).

Every scanner's sphere centres gave an artefact pose per measurement in that
scanner's own frame; the shared poses link each scanner to the reference scanner
(:func:`fringecal.spheres.linking.link_scanners`). The artefact's CMM centres, moved by the
measurement's pose in the reference frame, and their image coordinates in each sensor
(the fitted centre projected through the scanner's prior model) then give a DLT per
sensor in the global frame, as the thesis did for scanner two (eqs. 6-8..6-13). The
reference camera keeps its external parameters: they define the world frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from fringecal.artefact import Artefact
from fringecal.calibration.dlt import DLTError, DLTEstimate
from fringecal.frames import Frame
from fringecal.rig import Rig, rig_in_frame

__all__ = ["InitialCalibration", "initial_calibration", "initial_rig_from_dlt", "links_from_table", "poses_from_table"]

_POSE = ["tx_mm", "ty_mm", "tz_mm", "omega_rad", "phi_rad", "kappa_rad"]


def links_from_table(links: pd.DataFrame) -> dict[str, Frame]:
    """scanner -> T_reference_scanner from a :class:`fringecal.schemas.ScannerLinksTable`."""
    return {str(r.scanner): Frame.from_params([getattr(r, c) for c in _POSE]) for r in links.itertuples()}


def poses_from_table(poses: pd.DataFrame) -> dict[tuple[str, str], Frame]:
    """(measurement, scanner) -> T_scanner_artefact from a :class:`fringecal.schemas.PosesTable`."""
    return {(str(r.measurement), str(r.scanner)): Frame.from_params([getattr(r, c) for c in _POSE])
            for r in poses.itertuples()}


class UnlinkedScanners(ValueError):
    """Scanners without a link to the reference scanner (``scanners``): no artefact pose
    of theirs is known in the reference frame, so no start value either."""

    def __init__(self, scanners: list[str], message: str):
        super().__init__(message)
        self.scanners = list(scanners)


@dataclass(frozen=True)
class InitialCalibration:
    """Start rig (world frame), one start pose per measurement and the DLT report."""

    rig: Rig
    poses: pd.DataFrame  # PosePlanTable: measurement, tx_mm .. kappa_rad
    dlt: pd.DataFrame  # sensor, n_points, reprojection_rms_mm, method


def initial_calibration(prior: Rig, centres: pd.DataFrame, poses: pd.DataFrame, links: pd.DataFrame,
                        artefact: Artefact) -> InitialCalibration:
    """Start values of every sensor and measurement pose in the reference frame.

    Parameters
    ----------
    prior : Rig
        Each scanner's sensors in its own frame (prior calibration).
    centres : DataFrame
        Labelled sphere centres (:class:`fringecal.schemas.SphereCentresTable`) in scanner frames.
    poses : DataFrame
        :class:`fringecal.schemas.PosesTable`: T_scanner_artefact per (measurement, scanner).
    links : DataFrame
        :class:`fringecal.schemas.ScannerLinksTable`: T_reference_scanner per scanner.
    """
    link = links_from_table(links)
    # the reference is its own frame: never "unlinked", even when no pose of it is known
    missing = [s.name for s in prior.scanners if s.name not in link and s.name != prior.reference]
    if missing:
        raise UnlinkedScanners(missing, f"scanner(s) {missing} could not be linked to the reference scanner "
                                        f"{prior.reference!r}: they share no measured artefact pose with it")
    linked = rig_in_frame(prior, link)
    local_pose = poses_from_table(poses)
    world_pose: dict[str, Frame] = {}
    order = [prior.reference] + [s.name for s in prior.scanners if s.name != prior.reference]
    for scanner in order:
        for (meas, sc), T in local_pose.items():
            if sc == scanner and meas not in world_pose:
                world_pose[meas] = link[scanner].compose(T)
    points, image, rows = {}, {}, []
    for s in prior.scanners:
        g = centres[centres["scanner"] == s.name]
        g = g[g["measurement"].isin(list(world_pose))]
        if g.empty:
            continue
        cmm = artefact.centres_of(g["sphere_id"])
        world = np.array([world_pose[m].to_world(c[None])[0] for m, c in zip(g["measurement"], cmm)])
        local = g[["x_mm", "y_mm", "z_mm"]].to_numpy(float)
        for sensor in s.sensors:
            points[sensor.name] = world
            image[sensor.name] = sensor.project(local)
    try:
        rig, estimates = initial_rig_from_dlt(linked, points, image)
        for name, est in estimates.items():
            rows.append({"sensor": name, "n_points": len(points[name]),
                         "reprojection_rms_mm": float(est.reprojection_rms_mm), "method": "dlt"})
    except DLTError as err:
        # too few or coplanar centres for a DLT: start from the linked prior calibration
        rig = linked
        rows = [{"sensor": s.name, "n_points": len(points.get(s.name, [])), "reprojection_rms_mm": np.nan,
                 "method": f"linked prior ({err})"} for s in prior.sensors]
    pose_rows = [{"measurement": m, **dict(zip(_POSE, T.params))} for m, T in sorted(world_pose.items())]
    return InitialCalibration(rig, pd.DataFrame(pose_rows), pd.DataFrame(rows))


def initial_rig_from_dlt(template: Rig, points_world: dict, image_mm: dict,
                         keep_reference_external: bool = True) -> tuple[Rig, dict]:
    """A rig whose sensors carry DLT estimates (distortion zero).

    Parameters
    ----------
    template : Rig
        Names, formats, free flags and the reference scanner; with
        ``keep_reference_external`` its reference camera's six external parameters are
        kept: they define the world frame (the gauge), and the control points are
        expressed in it.
    points_world, image_mm : dict sensor name -> (n, 3) world points, (n, 2) image mm
        (e.g. registered sphere centres and their image coordinates in that sensor).

    Returns
    -------
    rig, estimates : the start rig and each sensor's :class:`DLTEstimate`
    """
    params = template.params.copy()
    estimates = {}
    ref = template.scanner(template.reference).camera.name
    for i, sensor in enumerate(template.sensors):
        if sensor.name not in points_world:
            raise DLTError(f"sensor {sensor.name}: no control points for the DLT")
        try:
            est = DLTEstimate.from_estimate(points_world[sensor.name], image_mm[sensor.name],
                                            near_angles=sensor.angles)
        except DLTError as err:
            raise DLTError(f"sensor {sensor.name}: {err}") from None
        estimates[sensor.name] = est
        new = est.params14
        if keep_reference_external and sensor.name == ref:
            new[:6] = sensor.params[:6]
        params[i] = new
    return template.with_params(params), estimates
