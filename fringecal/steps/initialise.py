"""Start values: every scanner's prior calibration moved into the reference frame by
its link, a DLT per sensor in the global frame from the CMM centres at the linked
poses (thesis 6.3), one start pose per measurement; and the control points of all
measurements in one table. These are the bundle adjustment's inputs.
"""

from __future__ import annotations

import pandas as pd

from fringecal.calibration.initial import UnlinkedScanners, initial_calibration
from fringecal.rundir import RunDir
from fringecal.steps.base import DataProblem, Settings, Step
from fringecal.steps.spheres_first import modelled_items

__all__ = ["Initialise"]


class Initialise(Step):
    name = "initialise"
    title = "start values"
    settings = ("reference_scanner",)
    modules = ("fringecal.calibration.initial",)

    def reads(self, rd: RunDir, cfg: Settings, item: str):
        return [rd.sensors_prior, rd.sphere_centres, rd.poses, rd.scanner_links, rd.artefact] + \
            [rd.control_points_of(m) for m in modelled_items(rd)]

    def writes(self, rd: RunDir, cfg: Settings, item: str):
        return [rd.control_points, rd.poses_initial, rd.sensors_initial, rd.dlt]

    def run(self, rd: RunDir, cfg: Settings, item: str, **context) -> None:
        centres = rd.sphere_centres.load()
        try:
            init = initial_calibration(rd.sensors_prior.load(cfg.reference_scanner), centres,
                                       rd.poses.load(), rd.scanner_links.load(), rd.artefact.load())
        except UnlinkedScanners as err:
            raise DataProblem(unlinked_message(rd, err.scanners, cfg.reference_scanner, centres)) from None
        cps = [rd.control_points_of(m).load() for m in modelled_items(rd)]
        rd.control_points.save(pd.concat([c for c in cps if len(c)], ignore_index=True))
        rd.poses_initial.save(init.poses)
        rd.sensors_initial.save(init.rig)
        rd.dlt.save(init.dlt)


def unlinked_message(rd: RunDir, scanners: list[str], reference: str, centres: pd.DataFrame) -> str:
    """What a scanner without a link lacks: per scanner, its labelled spheres in each
    measurement (a pose needs three, and a link one pose shared with a linked scanner)."""
    per = centres.groupby(["scanner", "measurement"]).size() if len(centres) else pd.Series(dtype=int)
    parts = []
    for s in scanners:
        seen = per[s] if s in per.index.get_level_values(0) else pd.Series(dtype=int)
        best = ", ".join(f"{m}: {n}" for m, n in seen.sort_values(ascending=False).head(4).items()) or "none"
        parts.append(f"scanner {s} (labelled spheres per measurement, most first: {best})")
    return (f"{rd.root}: {'; '.join(parts)}: never sees three or more labelled artefact spheres in a measurement "
            f"whose pose the reference scanner {reference} (or a scanner linked to it) knows, so it cannot be placed "
            f"in the reference frame; why spheres were not labelled: {rd.label_outcomes.path}. Measure the artefact "
            "where every scanner sees at least three of its spheres in a pose another scanner sees too")
