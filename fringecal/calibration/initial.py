"""Start values of the bundle adjustment: every sensor by the DLT (section 6.3)."""

from __future__ import annotations

from ..rig import Rig
from .dlt import DLTError, DLTEstimate

__all__ = ["initial_rig_from_dlt"]


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
