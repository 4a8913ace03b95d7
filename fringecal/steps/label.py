"""Label, pose, link: which artefact sphere each fitted candidate is (inter-sphere
distances, and where distances alone are ambiguous the planned poses or, without a
plan, all scanners' views together through the links their measurements agree on), one artefact
pose per (measurement, scanner) by SVD, and each scanner's frame linked to the
reference scanner's through the measurements they share (thesis 6.2-6.3).

The labelling estimates each scanner's scale and centre uncertainty from all its
measurements, and its frame by consensus with the planned poses; a labelling that the
scanner's other measurements or the other scanners' poses contradict is refused
(``fringecal.spheres.label_scanners``). Groups that cannot be labelled or posed are
reported in ``label_outcomes`` and ``poses_skipped`` (and logged, with what was
estimated per scanner and any refused link); the others go on.
"""

from __future__ import annotations

import logging

import pandas as pd

from fringecal.frames import frames_from_rows
from fringecal.rundir import RunDir
from fringecal.spheres.labelling import LabellingConfig
from fringecal.spheres.poses_and_links import label_pose_link
from fringecal.steps.base import Settings, Step
from fringecal.steps.spheres_first import artefact_items

__all__ = ["Label"]

log = logging.getLogger(__name__)


class Label(Step):
    name = "label"
    title = "label, pose, link"
    settings = ("extraction.labelling", "extraction.use_planned_poses", "reference_scanner")
    modules = ("fringecal.spheres.poses_and_links",)

    def reads(self, rd: RunDir, cfg: Settings, item: str):
        planned = [rd.poses_planned] if cfg.extraction.use_planned_poses else []
        return [rd.fits_first(m) for m in artefact_items(rd)] + [rd.artefact] + planned

    def writes(self, rd: RunDir, cfg: Settings, item: str):
        return [rd.sphere_fits_labelled, rd.label_outcomes, rd.sphere_centres, rd.poses, rd.poses_skipped,
                rd.scanner_links]

    def run(self, rd: RunDir, cfg: Settings, item: str, **context) -> None:
        fits = [rd.fits_first(m).load() for m in artefact_items(rd)]
        table = pd.concat([f for f in fits if len(f)], ignore_index=True)
        # a cloud's fits (black boxes) have no image-space rejection counts: none rejected
        counts = [c for c in table.columns if c.startswith("rejected_")]
        table[counts] = table[counts].fillna(0).astype(int)
        planned = None
        if cfg.extraction.use_planned_poses and rd.poses_planned.exists():
            planned = frames_from_rows(rd.poses_planned.load())
        res = label_pose_link(table, rd.artefact.load(), cfg.reference_scanner,
                              LabellingConfig(**cfg.extraction.labelling), planned=planned)
        for scanner, est in res.estimates.items():
            log.info("labelling, scanner %s: %s", scanner, est.note)
        for r in res.poses.skipped.itertuples():
            log.warning("measurement %s, scanner %s: no pose (%s)", r.measurement, r.scanner, r.reason)
        if res.links_error:
            log.warning("scanner links: %s", res.links_error)
        if res.links is not None:
            for scanner, why in res.links.unlinked.items():
                log.warning("scanner %s not linked: %s", scanner, why)
            for scanner, link in res.links.links.items():
                if link.rejected:
                    log.warning("scanner %s: measurement(s) %s left out of its link as outliers", scanner,
                                ", ".join(link.rejected))
        rd.sphere_fits_labelled.save(res.fits)
        rd.label_outcomes.save(res.labels)
        rd.sphere_centres.save(res.centres)
        rd.poses.save(res.poses.poses)
        rd.poses_skipped.save(res.poses.skipped)
        rd.scanner_links.save(res.links_table())
