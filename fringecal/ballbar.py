"""The ball-bar verification of a calibrated rig (thesis section 6.9.3, VDI/VDE 2634).

A ball-bar (two spheres, certified centre distance) is placed so that one sphere is
seen by one scanner and the other by the next: its measured length then tests the
link between the scanners' frames that the calibration made. This module places the
bar (:func:`thesis_positions`, :func:`vdi7_positions`), builds its scene for the
virtual scanner, and measures the sphere a scanner sees in its maps
(:func:`measure_sphere`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from .artefact import Artefact
from .frames import Frame
from .pointcloud import PointMaps
from .spheres.candidates import find_sphere_candidates
from .spheres.fit import FitError
from .spheres.regions import boundary_flags, fit_region
from .spheres.robust import RejectionConfig

__all__ = ["BallBarPosition", "frame_along", "thesis_positions", "vdi7_positions", "ballbar_rods",
           "measure_sphere", "SphereMeasurement"]


@dataclass(frozen=True)
class BallBarPosition:
    """One placement of the bar: ``T_world_ballbar`` (sphere A at the local origin,
    B on the local +x axis) and which scanner sees which sphere."""

    name: str
    T_world_ballbar: Frame
    scanner_of: dict  # sphere id -> scanner name


def frame_along(a, b) -> Frame:
    """``T_world_bar`` with its origin at ``a`` and local +x towards ``b``.

    >>> T = frame_along([0, 0, 0], [0, 10, 0])
    >>> T.to_world([[5.0, 0, 0]]).round(12).tolist()
    [[0.0, 5.0, 0.0]]
    """
    a = np.asarray(a, float)
    u = np.asarray(b, float) - a
    u /= np.linalg.norm(u)
    helper = np.array([0.0, 0.0, 1.0]) if abs(u[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    v = np.cross(helper, u)
    v /= np.linalg.norm(v)
    w = np.cross(u, v)
    R = np.stack([u, v, w])  # rows: local axes in world; x_local = R (x_world - a)
    return Frame.from_matrix(R, a)


def thesis_positions(table_6_9: pd.DataFrame, scanners=("scanner1", "scanner2")) -> list[BallBarPosition]:
    """The nine positions of thesis table 6-9 (centres of A and B per measurement).

    The thesis's measured centres fix where the bar was; its direction and midpoint
    are kept and the bar is placed with its certified length by the artefact itself.
    """
    out = []
    for meas, g in table_6_9.groupby("measurement", sort=False):
        a = g[g.sphere_id == "A"][["x_mm", "y_mm", "z_mm"]].to_numpy(float)[0]
        b = g[g.sphere_id == "B"][["x_mm", "y_mm", "z_mm"]].to_numpy(float)[0]
        out.append(BallBarPosition(f"bb{int(meas):02d}" if str(meas).isdigit() else f"bb{meas}",
                                   frame_along(a, b), {"A": scanners[0], "B": scanners[1]}))
    return out


def vdi7_positions(reference: list[BallBarPosition], length_mm: float) -> list[BallBarPosition]:
    """Seven positions after VDI/VDE 2634's scheme, spanning two volumes side by side.

    The guideline puts the bar along the four space diagonals and three directions
    parallel to the axes of the measurement volume. With two scanners side by side
    and a bar longer than one scanner's field, every position spans both volumes:
    four join opposite corners (in height and depth) of the regions where the
    ``reference`` positions put spheres A and B, and three run level across the
    middle and at the lowest and highest heights. Sphere B is then placed at the
    bar's length from A.
    """
    A = np.array([p.T_world_ballbar.t for p in reference])
    B = np.array([p.T_world_ballbar.to_world([[length_mm, 0, 0]])[0] for p in reference])
    lo_a, hi_a = A.min(0), A.max(0)
    lo_b, hi_b = B.min(0), B.max(0)
    mid_a, mid_b = (lo_a + hi_a) / 2, (lo_b + hi_b) / 2
    pick = lambda lo, hi, sy, sz, mid: np.array([mid[0], (lo if sy < 0 else hi)[1] if sy else mid[1],  # noqa: E731
                                                 (lo if sz < 0 else hi)[2] if sz else mid[2]])
    pairs = [(pick(lo_a, hi_a, -1, -1, mid_a), pick(lo_b, hi_b, 1, 1, mid_b)),
             (pick(lo_a, hi_a, 1, -1, mid_a), pick(lo_b, hi_b, -1, 1, mid_b)),
             (pick(lo_a, hi_a, -1, 1, mid_a), pick(lo_b, hi_b, 1, -1, mid_b)),
             (pick(lo_a, hi_a, 1, 1, mid_a), pick(lo_b, hi_b, -1, -1, mid_b)),
             (mid_a, mid_b),
             (pick(lo_a, hi_a, -1, 0, mid_a), pick(lo_b, hi_b, -1, 0, mid_b)),
             (pick(lo_a, hi_a, 1, 0, mid_a), pick(lo_b, hi_b, 1, 0, mid_b))]
    scanners = reference[0].scanner_of
    return [BallBarPosition(f"vdi{i + 1}", frame_along(a, b), dict(scanners)) for i, (a, b) in enumerate(pairs)]


def ballbar_rods(artefact: Artefact) -> pd.DataFrame:
    """The bar's tube as a rods table (one rod joining its two spheres)."""
    a, b = artefact.ids[:2]
    return pd.DataFrame({"rod_id": ["bar"], "sphere_a": [a], "sphere_b": [b], "length_mm": [0.0]})


@dataclass(frozen=True)
class SphereMeasurement:
    """The centre of the one bar sphere a scanner saw, with its fit statistics."""

    centre: np.ndarray
    radius_mm: float
    rms_mm: float
    n_points: int
    rejected: dict


def measure_sphere(maps: PointMaps, valid, camera, projector, radius_mm: float, rod_axis=None,
                   rejection_config: RejectionConfig | None = None, fixed_radius: bool = True) -> SphereMeasurement:
    """Find and fit the (single) bar sphere in a measurement's maps.

    The strongest sphere candidate of the bar's radius is fitted robustly; with
    ``rod_axis`` (unit direction from this sphere to the other, in the maps' frame)
    the tube and its end cap are masked by a cone, as for the artefact.

    Raises
    ------
    FitError
        No sphere of that radius in the measurement, or too few clean points.
    """
    cands = find_sphere_candidates(maps, radius_mm, camera.pinhole)
    if not cands:
        raise FitError(f"no sphere of radius {radius_mm:.3f} mm found")
    best = max(cands, key=lambda c: c.votes)
    axes = None if rod_axis is None else np.asarray(rod_axis, float).reshape(1, 3)
    rf = fit_region(maps, best.region, radius_mm if fixed_radius else None, expected_radius=radius_mm,
                    flag_maps={"edge": boundary_flags(valid)}, viewpoints=[camera.pinhole, projector.pinhole],
                    rod_axes=axes, config=rejection_config)
    m = rf.fit.model
    return SphereMeasurement(np.asarray(m.centre, float), float(m.radius), float(m.rms), int(m.n_points),
                             dict(rf.fit.rejected))
