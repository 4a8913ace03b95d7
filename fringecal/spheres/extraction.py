"""Sphere extraction of one measurement, with no manual input (issue 4).

Two passes, as an operator would work but automatic:

1. :func:`fit_candidates` without labels: candidates by normal voting
   (:mod:`fringecal.spheres.candidates`), each region fitted robustly
   (:func:`fringecal.spheres.regions.fit_region`: edges, silhouettes, residual outliers
   and rods detected among the outliers are rejected with counts per reason).
2. After labelling and a pose per measurement (:func:`fringecal.spheres.poses_and_links.label_pose_link`),
   :func:`fit_candidates` again on the same regions with each sphere's rod directions
   from the artefact definition: a cone around every rod axis (end cap plus margin)
   is masked, so no rod or end-cap point survives into a fit, even where a cap meets
   the sphere and distances alone cannot tell them apart.

The pixels each fit keeps form the sphere's clean image region: the control points of
the bundle adjustment are chosen from them.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from fringecal.pointcloud import PointMaps
from fringecal.spheres.candidates import CandidateConfig, find_sphere_candidates
from fringecal.spheres.fit import FitError
from fringecal.spheres.regions import boundary_flags, fit_region
from fringecal.spheres.robust import RejectionConfig

__all__ = ["MeasurementFits", "fit_candidates"]


@dataclass
class MeasurementFits:
    """Sphere fits of one measurement.

    Attributes
    ----------
    rows : list of dict
        :class:`fringecal.schemas.SphereFitsTable` rows, one per fitted candidate.
    regions : ndarray of int16, shape (rows, cols)
        Candidate index of each pixel of a candidate region, -1 elsewhere.
    kept : ndarray of int16, shape (rows, cols)
        Candidate index of the pixels a fit kept, -1 elsewhere.
    failures : list of dict
        ``candidate, reason`` of candidates that could not be fitted.
    """

    rows: list = field(default_factory=list)
    regions: np.ndarray | None = None
    kept: np.ndarray | None = None
    failures: list = field(default_factory=list)


def fit_candidates(maps: PointMaps, valid, camera, projector, radius_mm: float, measurement: str, scanner: str,
                   *, regions: np.ndarray | None = None, rod_axes: dict | None = None,
                   sphere_ids: dict | None = None, fixed_radius: dict | None = None,
                   candidate_config: CandidateConfig | None = None,
                   rejection_config: RejectionConfig | None = None,
                   edge_width_px: int = 2) -> MeasurementFits:
    """Fit every sphere candidate of a measurement.

    Parameters
    ----------
    maps : PointMaps
        Triangulated maps (x, y, z in the scanner's frame).
    valid : bool array, shape (rows, cols)
        The decoder's validity mask (edges of it are flagged).
    camera, projector : Sensor
        Viewpoints for the silhouette test.
    radius_mm : float
        Expected sphere radius (the artefact's).
    measurement, scanner : str
    regions : int array, optional
        Candidate regions from a first pass; found by voting when omitted.
    rod_axes, sphere_ids, fixed_radius : dict candidate -> value, optional
        Second pass: rod directions (k, 3) in the scanner's frame, the label, and the
        CMM radius to fix (None keeps the radius free).
    """
    valid = np.asarray(valid, bool)
    if regions is None:
        cands = find_sphere_candidates(maps, radius_mm, camera.pinhole, candidate_config)
        regions = np.full(valid.shape, -1, np.int16)
        for i, c in enumerate(cands):
            regions[c.region] = i
    out = MeasurementFits(regions=regions, kept=np.full(valid.shape, -1, np.int16))
    flags = {"edge": boundary_flags(valid, edge_width_px)}
    viewpoints = [camera.pinhole, projector.pinhole]
    for cand in np.unique(regions[regions >= 0]):
        cand = int(cand)
        sid = (sphere_ids or {}).get(cand, "")
        radius = (fixed_radius or {}).get(cand)
        try:
            rf = fit_region(maps, regions == cand, radius, expected_radius=radius_mm, flag_maps=flags,
                            viewpoints=viewpoints, rod_axes=(rod_axes or {}).get(cand),
                            config=rejection_config)
        except FitError as err:
            out.failures.append({"measurement": measurement, "scanner": scanner, "candidate": str(cand),
                                 "sphere_id": sid, "reason": str(err)})
            continue
        out.rows.append(rf.row(measurement, scanner, cand, sphere_id=sid))
        r, c = rf.kept_pixels
        out.kept[r, c] = cand
    return out
