"""Simulated ball-bar verification of a calibration (thesis 6.9.3, VDI/VDE 2634).

The bar is rendered at each position by every scanner that sees one of its spheres
(:func:`fringecal.ballbar.thesis_positions` or :func:`fringecal.ballbar.vdi7_positions`);
each store is triangulated twice, with the calibrated sensors and with the true ones,
and the sphere is fitted with its certified radius. The true-parameter lengths give
the floor set by noise, against which the calibration is judged.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pandas as pd

from ..ballbar import BallBarPosition, measure_sphere
from ..rig import Rig
from ..spheres.fit import FitError
from .extract import measurement_maps

__all__ = ["measure_ballbar_store", "ballbar_centres"]


def measure_ballbar_store(store, scanner, radius_mm: float, rod_axis, rejection_config) -> dict:
    """Centre of the bar sphere in one store, triangulated with ``scanner``."""
    ds, maps, valid = measurement_maps(store, scanner)
    ds.close()
    m = measure_sphere(maps, valid, scanner.camera, scanner.projector, radius_mm, rod_axis, rejection_config)
    return {"x_mm": m.centre[0], "y_mm": m.centre[1], "z_mm": m.centre[2], "radius_mm": m.radius_mm,
            "rms_mm": m.rms_mm, "n_points": m.n_points}


def ballbar_centres(stores: dict, positions: list[BallBarPosition], ballbar, rigs: dict[str, Rig],
                    rejection_config, workers: int = 2) -> tuple[dict[str, pd.DataFrame], pd.DataFrame]:
    """Sphere centres of every position, once per rig (e.g. ``calibrated``, ``true``).

    Parameters
    ----------
    stores : dict (position name, sphere id) -> store path
    rigs : dict label -> Rig whose sensors triangulate the stores (world frame)

    Returns
    -------
    centres : dict label -> SphereCentresTable frame (measurement = position name,
        sphere ids ``A``/``B``)
    failures : DataFrame ``rig, measurement, sphere_id, reason``
    """
    radius = float(ballbar.radii[0])
    a_id = ballbar.ids[0]
    jobs = []
    for pos in positions:
        ends = pos.T_world_ballbar.to_world(ballbar.centres[:2])
        for sid, scanner_name in pos.scanner_of.items():
            here, there = (ends[0], ends[1]) if sid == a_id else (ends[1], ends[0])
            jobs += [(label, pos.name, sid, scanner_name, (there - here) / np.linalg.norm(there - here))
                     for label in rigs]

    def measure(job):
        label, name, sid, scanner_name, axis = job
        try:
            row = measure_ballbar_store(stores[(name, sid)], rigs[label].scanner(scanner_name), radius, axis,
                                        rejection_config)
        except FitError as err:
            return label, None, {"rig": label, "measurement": name, "sphere_id": sid, "reason": str(err)}
        return label, {"measurement": name, "scanner": scanner_name, "sphere_id": sid, **row}, None

    out = {label: [] for label in rigs}
    failures = []
    with ThreadPoolExecutor(max_workers=workers) as pool:  # numpy and zarr release the GIL
        for label, row, failure in pool.map(measure, jobs):
            if row is not None:
                out[label].append(row)
            else:
                failures.append(failure)
    frames = {label: pd.DataFrame(rows) for label, rows in out.items()}
    return frames, pd.DataFrame(failures, columns=["rig", "measurement", "sphere_id", "reason"])
