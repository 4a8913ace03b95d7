"""Spheres, second pass: refit each labelled sphere with cones around its rods (tube
and end cap) masked, label every pixel with its sphere, and select the clean pixels
as control points (thesis 6.4), leaving out the rim where pixel integration biases
the phase (chapter 5).

A measurement's key holds only its own rows of the labelled fits and poses, so a
label that changes elsewhere does not redo it.

A black-box scanner's labelled spheres are refitted in its cloud the same way
(certified radius, rod cones, the rim beyond ``control_points.max_incidence_deg``
left out: :func:`fringecal.spheres.cloud_spheres.refit_cloud_sphere`); its fits are
its observations in the adjustment.
"""

from __future__ import annotations

import logging

import numpy as np
import pandas as pd

from fringecal.calibration.initial import poses_from_table
from fringecal.rundir import RunDir
from fringecal.scancloud import read_cloud_store
from fringecal.spheres.cloud_spheres import near_any, refit_cloud_sphere
from fringecal.spheres.fit import FitError
from fringecal.spheres.passes import second_pass
from fringecal.spheres.poses_and_links import sphere_fit_row
from fringecal.spheres.robust import RejectionConfig, rod_directions
from fringecal.steps.base import Rows, Settings, Step, store_fields, store_row
from fringecal.steps.spheres_first import artefact_items, is_black_box

__all__ = ["SpheresSecond"]

log = logging.getLogger(__name__)


class SpheresSecond(Step):
    name = "spheres-second"
    title = "spheres: second pass"
    settings = ("extraction.rejection", "extraction.second_pass_rod_cones", "control_points")
    modules = ("fringecal.spheres.passes",)

    def items(self, rd: RunDir, cfg: Settings) -> list[str]:
        return artefact_items(rd)

    def _own(self, rd: RunDir, item: str) -> dict:
        row = store_fields(rd, item)
        return {"measurement": row["pose"], "scanner": row["scanner"]}

    def reads(self, rd: RunDir, cfg: Settings, item: str):
        own = self._own(rd, item)
        if is_black_box(rd, item):
            return [store_row(rd, item), rd.store(item), rd.artefact, rd.rods, rd.acquisition,
                    Rows(rd.sphere_fits_labelled, own), Rows(rd.poses, own)]
        return [store_row(rd, item), rd.store(item), rd.maps(item), rd.sensors_prior, rd.artefact, rd.rods,
                Rows(rd.sphere_fits_labelled, own), Rows(rd.poses, own)]

    def writes(self, rd: RunDir, cfg: Settings, item: str):
        if is_black_box(rd, item):
            return [rd.fits_final(item)]
        return [rd.fits_final(item), rd.control_points_of(item), rd.sphere_labels(item)]

    def run(self, rd: RunDir, cfg: Settings, item: str, **context) -> None:
        own = self._own(rd, item)
        if is_black_box(rd, item):
            self.run_cloud(rd, cfg, item, own)
            return
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

    def run_cloud(self, rd: RunDir, cfg: Settings, item: str, own: dict) -> None:
        artefact = rd.artefact.load()
        rods = rd.rods.load(artefact) if rd.rods.exists() else None
        poses = Rows(rd.poses, own).load()
        T = poses_from_table(poses).get((own["measurement"], own["scanner"])) if len(poses) else None
        fits = Rows(rd.sphere_fits_labelled, own).load()
        fits = fits[fits["sphere_id"].astype(str) != ""]
        points, _ = read_cloud_store(rd.store(item).path)
        radii = {str(i): float(artefact.radii[artefact.ids.index(str(i))]) for i in fits["sphere_id"]}
        if len(fits):  # every sphere's neighbourhood in one pass over the cloud
            points = near_any(points, fits[["x_mm", "y_mm", "z_mm"]].to_numpy(float), max(radii.values()))
        rows = []
        cones = rods is not None and cfg.extraction.second_pass_rod_cones
        for f in fits.itertuples():
            axes = rod_directions(artefact, rods, f.sphere_id, T) if cones else None
            radius = radii[str(f.sphere_id)]
            try:
                fit = refit_cloud_sphere(points, np.array([f.x_mm, f.y_mm, f.z_mm]), radius, axes,
                                         RejectionConfig(**cfg.extraction.rejection),
                                         cfg.control_points.max_incidence_deg)
            except (FitError, ValueError) as err:
                log.warning("measurement %s, black-box scanner %s, sphere %s: not refitted (%s)", own["measurement"],
                            own["scanner"], f.sphere_id, err)
                continue
            rows.append(sphere_fit_row(own["measurement"], own["scanner"], f.candidate, fit,
                                       sphere_id=str(f.sphere_id)))
        rd.fits_final(item).save(pd.DataFrame(rows) if rows else pd.DataFrame(columns=list(fits.columns)))
