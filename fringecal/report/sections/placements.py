"""Where the acceptance test's objects stood: their placements as world points, the
scanners' camera pinholes and the ball-bar positions, for the positions figure."""

from __future__ import annotations

import numpy as np

from fringecal.frames import POSE_COLUMNS, Frame
from fringecal.report.formatting import finite
from fringecal.report.rundata import Missing, RunData, numeric

__all__ = ["ballbar_segments", "pinholes", "placement"]


def placement(row: dict, standards: dict) -> dict | None:
    """One position as world points to draw.

    Parameters
    ----------
    row : a position of ``acceptance.json`` (``test`` and T_world_object as pose columns)
    standards : the objects' certificates (``acceptance_standards.json``)

    Returns
    -------
    ``test``, ``points`` (k, 3) and ``radius`` (spheres); an object of unknown size is a
    point at its frame's origin; None when the placement is not a valid pose.
    """
    try:
        T = Frame.from_params([float(row[c]) for c in POSE_COLUMNS])
    except (KeyError, TypeError, ValueError):
        return None
    if not np.all(np.isfinite(T.params)):
        return None
    test = str(row.get("test"))
    size = standards.get(test) if isinstance(standards.get(test), dict) else {}
    local = np.zeros((1, 3))
    radius = None
    if test == "sphere" and finite(size.get("diameter_mm")):
        radius = size["diameter_mm"] / 2
    elif test == "dumbbell" and finite(size.get("length_mm")):
        local = np.array([[0.0, 0.0, 0.0], [size["length_mm"], 0.0, 0.0]])
    elif test == "flat" and finite(size.get("length_mm")) and finite(size.get("width_mm")):
        u, v = size["length_mm"] / 2, size["width_mm"] / 2
        local = np.array([[-u, -v, 0.0], [u, -v, 0.0], [u, v, 0.0], [-u, v, 0.0], [-u, -v, 0.0]])
    return {"test": test, "points": T.to_world(local), "radius": radius}


def pinholes(run: RunData) -> list[tuple]:
    """(scanner, camera pinhole, reference scanner) of the calibration; none without one."""
    try:
        rig = run.load(run.rd.calibration)
    except (Missing, ValueError, KeyError, OSError):
        return []
    return [(sc.name, np.asarray(sc.camera.pinhole, float), rig.reference) for sc in rig.scanners]


def ballbar_segments(run: RunData) -> list[np.ndarray]:
    """The ball-bar (E) positions as their sphere centres (mean over the scanners)."""
    try:
        t = numeric(run.table(run.rd.ballbar_centres))
        mean = t.groupby(["position", "sphere_id"], sort=True)[["x_mm", "y_mm", "z_mm"]].mean()
    except (Missing, ValueError, KeyError, OSError):
        return []
    return [g.to_numpy(float) for _, g in mean.groupby(level="position", sort=False)]
