"""Spheres, first pass: triangulate each measurement with its scanner's prior
calibration, find sphere candidates by normal voting and fit them robustly.

Writes the point maps and candidate regions (``maps/<id>.zarr``) and the fits, with
an empty ``sphere_id`` until labelling (``tables/fits_first/<id>.csv``). Candidates
that could not be fitted are logged with their reason.

A black-box scanner's store is its cloud: its candidates come from normal voting in
the cloud, fitted by the same robust fit (:mod:`fringecal.spheres.cloud_spheres`);
there are no maps to write.
"""

from __future__ import annotations

import logging

import numpy as np

from fringecal.rundir import RunDir
from fringecal.scancloud import read_cloud_store
from fringecal.spheres.candidates import CandidateConfig
from fringecal.spheres.cloud_spheres import cloud_sphere_fits
from fringecal.spheres.passes import first_pass
from fringecal.spheres.robust import RejectionConfig
from fringecal.steps.base import (Settings, Step, black_box_scanners, store_fields, store_row, stores_of,
                                  stores_of_kind)

__all__ = ["SpheresFirst", "artefact_items", "modelled_items", "is_black_box"]

log = logging.getLogger(__name__)


def artefact_items(rd: RunDir) -> list[str]:
    """Ids of the calibration measurements' stores, in acquisition order."""
    return stores_of_kind(rd, "artefact")


def modelled_items(rd: RunDir) -> list[str]:
    """Ids of the modelled scanners' calibration stores (image stacks, not clouds)."""
    return stores_of(rd, "artefact", black_box=False)


def is_black_box(rd: RunDir, item: str) -> bool:
    return store_fields(rd, item)["scanner"] in black_box_scanners(rd)


class SpheresFirst(Step):
    name = "spheres-first"
    title = "spheres: first pass"
    settings = ("extraction.candidates", "extraction.rejection")
    modules = ("fringecal.spheres.passes",)

    def items(self, rd: RunDir, cfg: Settings) -> list[str]:
        return artefact_items(rd)

    def reads(self, rd: RunDir, cfg: Settings, item: str):
        if is_black_box(rd, item):
            return [store_row(rd, item), rd.store(item), rd.artefact, rd.acquisition]
        return [store_row(rd, item), rd.store(item), rd.sensors_prior, rd.artefact]

    def writes(self, rd: RunDir, cfg: Settings, item: str):
        if is_black_box(rd, item):
            return [rd.fits_first(item)]
        return [rd.maps(item), rd.fits_first(item)]

    def run(self, rd: RunDir, cfg: Settings, item: str, **context) -> None:
        row = store_fields(rd, item)
        if is_black_box(rd, item):
            self.run_cloud(rd, cfg, item, row)
            return
        scanner = rd.sensors_prior.load().scanner(row["scanner"])
        radius = float(np.median(rd.artefact.load().radii))
        rows, failures = first_pass(rd.store(item).path, scanner, radius, CandidateConfig(**cfg.extraction.candidates),
                                    RejectionConfig(**cfg.extraction.rejection), row["pose"], rd.maps(item).path)
        for f in failures.itertuples():
            log.warning("measurement %s, scanner %s, candidate %s: not fitted (%s)", row["pose"], row["scanner"],
                        f.candidate, f.reason)
        rd.fits_first(item).save(rows)

    def run_cloud(self, rd: RunDir, cfg: Settings, item: str, row: dict) -> None:
        points, normals = read_cloud_store(rd.store(item).path)
        radius = float(np.median(rd.artefact.load().radii))
        rows, failures = cloud_sphere_fits(points, row["pose"], row["scanner"], radius,
                                           rejection=RejectionConfig(**cfg.extraction.rejection), normals=normals)
        # normal voting proposes rods, end caps and sphere edges too: their refusals are expected
        for f in failures.itertuples():
            log.debug("measurement %s, black-box scanner %s, candidate %s: not fitted (%s)", row["pose"],
                      row["scanner"], f.candidate, f.reason)
        log.info("measurement %s, black-box scanner %s: %d sphere(s) fitted, %d candidate(s) refused", row["pose"],
                 row["scanner"], len(rows), len(failures))
        rd.fits_first(item).save(rows)
