"""Spheres, first pass: triangulate each measurement with its scanner's prior
calibration, find sphere candidates by normal voting and fit them robustly.

Writes the point maps and candidate regions (``maps/<id>.zarr``) and the fits, with
an empty ``sphere_id`` until labelling (``tables/fits_first/<id>.csv``). Candidates
that could not be fitted are logged with their reason.
"""

from __future__ import annotations

import logging

import numpy as np

from fringecal.rundir import RunDir
from fringecal.spheres.candidates import CandidateConfig
from fringecal.spheres.passes import first_pass
from fringecal.spheres.robust import RejectionConfig
from fringecal.steps.base import Settings, Step, store_fields, store_row, stores_of_kind

__all__ = ["SpheresFirst", "artefact_items"]

log = logging.getLogger(__name__)


def artefact_items(rd: RunDir) -> list[str]:
    """Ids of the calibration measurements' stores, in acquisition order."""
    return stores_of_kind(rd, "artefact")


class SpheresFirst(Step):
    name = "spheres-first"
    title = "spheres: first pass"
    settings = ("extraction.candidates", "extraction.rejection")
    modules = ("fringecal.spheres.passes",)

    def items(self, rd: RunDir, cfg: Settings) -> list[str]:
        return artefact_items(rd)

    def reads(self, rd: RunDir, cfg: Settings, item: str):
        return [store_row(rd, item), rd.store(item), rd.sensors_prior, rd.artefact]

    def writes(self, rd: RunDir, cfg: Settings, item: str):
        return [rd.maps(item), rd.fits_first(item)]

    def run(self, rd: RunDir, cfg: Settings, item: str, **context) -> None:
        row = store_fields(rd, item)
        scanner = rd.sensors_prior.load().scanner(row["scanner"])
        radius = float(np.median(rd.artefact.load().radii))
        rows, failures = first_pass(rd.store(item).path, scanner, radius, CandidateConfig(**cfg.extraction.candidates),
                                    RejectionConfig(**cfg.extraction.rejection), row["pose"], rd.maps(item).path)
        for f in failures.itertuples():
            log.warning("measurement %s, scanner %s, candidate %s: not fitted (%s)", row["pose"], row["scanner"],
                        f.candidate, f.reason)
        rd.fits_first(item).save(rows)
