"""Start values: every scanner's prior calibration moved into the reference frame by
its link, a DLT per sensor in the global frame from the CMM centres at the linked
poses (thesis 6.3), one start pose per measurement; and the control points of all
measurements in one table. These are the bundle adjustment's inputs.
"""

from __future__ import annotations

import pandas as pd

from fringecal.calibration.initial import initial_calibration
from fringecal.rundir import RunDir
from fringecal.steps.base import Settings, Step
from fringecal.steps.spheres_first import artefact_items

__all__ = ["Initialise"]


class Initialise(Step):
    name = "initialise"
    title = "start values"
    settings = ("reference_scanner",)
    modules = ("fringecal.calibration.initial",)

    def reads(self, rd: RunDir, cfg: Settings, item: str):
        return [rd.sensors_prior, rd.sphere_centres, rd.poses, rd.scanner_links, rd.artefact] + \
            [rd.control_points_of(m) for m in artefact_items(rd)]

    def writes(self, rd: RunDir, cfg: Settings, item: str):
        return [rd.control_points, rd.poses_initial, rd.sensors_initial, rd.dlt]

    def run(self, rd: RunDir, cfg: Settings, item: str, **context) -> None:
        init = initial_calibration(rd.sensors_prior.load(cfg.reference_scanner), rd.sphere_centres.load(),
                                   rd.poses.load(), rd.scanner_links.load(), rd.artefact.load())
        cps = [rd.control_points_of(m).load() for m in artefact_items(rd)]
        rd.control_points.save(pd.concat([c for c in cps if len(c)], ignore_index=True))
        rd.poses_initial.save(init.poses)
        rd.sensors_initial.save(init.rig)
        rd.dlt.save(init.dlt)
