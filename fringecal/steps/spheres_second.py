"""Spheres, second pass: refit each labelled sphere with cones around its rods (tube
and end cap) masked, label every pixel with its sphere, and select the clean pixels
as control points (thesis 6.4), leaving out the rim where pixel integration biases
the phase (chapter 5).

A measurement's key holds only its own rows of the labelled fits and poses, so a
label that changes elsewhere does not redo it.
"""

from __future__ import annotations

from fringecal.calibration.initial import poses_from_table
from fringecal.rundir import RunDir
from fringecal.spheres.passes import second_pass
from fringecal.spheres.robust import RejectionConfig
from fringecal.steps.base import Rows, Settings, Step, store_fields, store_row
from fringecal.steps.spheres_first import modelled_items

__all__ = ["SpheresSecond"]


class SpheresSecond(Step):
    name = "spheres-second"
    title = "spheres: second pass"
    settings = ("extraction.rejection", "extraction.second_pass_rod_cones", "control_points")
    modules = ("fringecal.spheres.passes",)

    def items(self, rd: RunDir, cfg: Settings) -> list[str]:
        return modelled_items(rd)

    def _own(self, rd: RunDir, item: str) -> dict:
        row = store_fields(rd, item)
        return {"measurement": row["pose"], "scanner": row["scanner"]}

    def reads(self, rd: RunDir, cfg: Settings, item: str):
        own = self._own(rd, item)
        return [store_row(rd, item), rd.store(item), rd.maps(item), rd.sensors_prior, rd.artefact, rd.rods,
                Rows(rd.sphere_fits_labelled, own), Rows(rd.poses, own)]

    def writes(self, rd: RunDir, cfg: Settings, item: str):
        return [rd.fits_final(item), rd.control_points_of(item), rd.sphere_labels(item)]

    def run(self, rd: RunDir, cfg: Settings, item: str, **context) -> None:
        own = self._own(rd, item)
        artefact = rd.artefact.load()
        rods = rd.rods.load(artefact) if rd.rods.exists() else None
        poses = Rows(rd.poses, own).load()
        T = poses_from_table(poses).get((own["measurement"], own["scanner"])) if len(poses) else None
        res = second_pass(rd.store(item).path, rd.maps(item).path, rd.sensors_prior.load().scanner(own["scanner"]),
                          artefact, rods, Rows(rd.sphere_fits_labelled, own).load(), T,
                          RejectionConfig(**cfg.extraction.rejection), cfg.control_points, own["measurement"],
                          rd.sphere_labels(item).path, rod_cones=cfg.extraction.second_pass_rod_cones)
        rd.fits_final(item).save(res.fits)
        rd.control_points_of(item).save(res.control_points)
