"""From sphere fits to linked scanner frames: the table-level steps of issue 4.

The image-space step fits one :class:`~fringecal.spheres.robust.RobustSphereFit`
per candidate region and turns each into a row with :func:`sphere_fit_row`;
:func:`label_pose_link` then labels every (measurement, scanner), estimates one
artefact pose each by SVD (:func:`fringecal.pose.estimate_poses`) and links the
scanners into the reference frame (:func:`fringecal.linking.link_scanners`).
Every table it returns satisfies its schema in :mod:`schemas`.
"""

from __future__ import annotations

from dataclasses import dataclass

import pandas as pd

from schemas import (LabelOutcomesTable, ScannerLinksTable, SphereCentresTable, SphereFitsTable,
                     validate_table)

from ..artefact import Artefact
from ..linking import LinkResult, link_scanners
from ..pose import PoseResult, estimate_poses
from .fit import SphereModel
from .labelling import LabellingConfig, label_sphere_fits
from .robust import RobustSphereFit

__all__ = ["sphere_fit_row", "centres_from_fits", "label_pose_link", "LabelPoseLink"]


def sphere_fit_row(measurement, scanner, candidate, fit: RobustSphereFit | SphereModel, bbox=None,
                   sphere_id: str = "") -> dict:
    """One :class:`schemas.SphereFitsTable` row.

    ``bbox`` is the candidate's image region ``(u_min, v_min, u_max, v_max)`` in
    camera pixels. Rejection counts come from a :class:`RobustSphereFit`.
    """
    model = fit.model if isinstance(fit, RobustSphereFit) else fit
    d = model.to_dict()
    row = {"measurement": str(measurement), "scanner": str(scanner), "candidate": str(candidate),
           "sphere_id": sphere_id, "x_mm": d["x_mm"], "y_mm": d["y_mm"], "z_mm": d["z_mm"],
           "radius_mm": d["radius_mm"], "radius_fixed": d["radius_fixed"], "rms_mm": d["rms_mm"],
           "n_points": d["n_points"], "u_x_mm": d["u_x_mm"], "u_y_mm": d["u_y_mm"], "u_z_mm": d["u_z_mm"],
           "cap_angle_deg": d["cap_angle_deg"], "coverage": d["coverage"]}
    if bbox is not None:
        row.update(zip(("u_min_px", "v_min_px", "u_max_px", "v_max_px"), map(float, bbox)))
    if isinstance(fit, RobustSphereFit):
        row["n_rejected"] = fit.n_rejected
        row.update({f"rejected_{k}": int(v) for k, v in fit.rejected.items()})
    else:
        row["n_rejected"] = 0
    return row


def centres_from_fits(fits: pd.DataFrame) -> pd.DataFrame:
    """The labelled rows of a sphere-fits table as a :class:`schemas.SphereCentresTable`."""
    labelled = fits[fits["sphere_id"].astype(str) != ""].reset_index(drop=True)
    return validate_table(labelled, SphereCentresTable, "labelled sphere fits")


@dataclass(frozen=True)
class LabelPoseLink:
    """Tables of :func:`label_pose_link`.

    ``fits``: the sphere-fits table with ``sphere_id`` filled; ``labels``: one
    outcome per (measurement, scanner); ``centres``: labelled centres;
    ``poses``: poses and the groups skipped with their reasons; ``links``:
    ``T_reference_scanner`` per scanner (``links.table()``) and the unlinked ones.
    """

    fits: pd.DataFrame
    labels: pd.DataFrame
    centres: pd.DataFrame
    poses: PoseResult
    links: LinkResult | None
    links_error: str = ""

    def links_table(self) -> pd.DataFrame:
        if self.links is None:
            return pd.DataFrame(columns=list(ScannerLinksTable.to_schema().columns))
        return validate_table(self.links.table(), ScannerLinksTable, "scanner links")


def label_pose_link(fits: pd.DataFrame, artefact: Artefact, reference: str,
                    config: LabellingConfig | None = None, allowed_ids: dict | None = None,
                    planned: dict | None = None, source: str = "<sphere fits>") -> LabelPoseLink:
    """Label, pose and link in one go; bad groups are reported, the others go on.

    Parameters
    ----------
    fits : DataFrame
        :class:`schemas.SphereFitsTable` rows (``sphere_id`` may be empty).
    artefact : Artefact
    reference : str
        Reference scanner of the global frame.
    config, allowed_ids, planned
        See :func:`fringecal.spheres.labelling.label_sphere_fits`.
    """
    fits = validate_table(fits, SphereFitsTable, source)
    labelled, outcomes = label_sphere_fits(fits, artefact, config, allowed_ids, planned)
    labelled = validate_table(labelled, SphereFitsTable, source)
    outcomes = validate_table(outcomes, LabelOutcomesTable, "label outcomes")
    centres = centres_from_fits(labelled)
    if len(centres):
        poses = estimate_poses(centres, artefact, source)
    else:
        poses = PoseResult(pd.DataFrame(columns=["measurement", "scanner"]),
                           pd.DataFrame(columns=["measurement", "scanner", "reason"]))
    # groups refused by labelling never reach the pose step: say so in its skip list
    refused = outcomes[outcomes["status"] == "refused"]
    if len(refused):
        extra = pd.DataFrame({"measurement": refused["measurement"], "scanner": refused["scanner"],
                              "reason": "labelling refused: " + refused["message"]})
        poses = PoseResult(poses.poses, pd.concat([poses.skipped, extra], ignore_index=True))
    links, links_error = None, ""
    if len(poses.poses):
        try:
            links = link_scanners(poses.poses, reference, source=source)
        except ValueError as err:
            links_error = str(err)
    else:
        links_error = "no poses to link"
    return LabelPoseLink(labelled, outcomes, centres, poses, links, links_error)
