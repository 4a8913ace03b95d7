"""Task adapter: sphere fits -> labels, poses and scanner links (sections 6.2-6.3)."""

from __future__ import annotations

import logging
from pathlib import Path

from prefect import get_run_logger, task
from prefect.exceptions import MissingContextError

from fringecal.artefact import load_artefact
from fringecal.frames import Frame
from fringecal.spheres.labelling import LabellingConfig
from fringecal.spheres.steps import label_pose_link
from schemas import (LabelOutcomesTable, PosePlanTable, PosesTable, ScannerLinksTable, SphereCentresTable,
                     SphereFitsTable, read_table, write_table)

from .refs import Ref, cache_key, ref_for

#: file names written in ``out_dir`` (the run's ``tables/``)
OUTPUTS = {"fits": "sphere_fits_labelled.csv", "labels": "labels.csv", "centres": "sphere_centres.csv",
           "poses": "poses.csv", "links": "scanner_links.csv"}


def _logger():
    """The run logger inside Prefect, a plain logger when called as ``task.fn``."""
    try:
        return get_run_logger()
    except MissingContextError:
        return logging.getLogger(__name__)


def _key(context, parameters) -> str:
    return cache_key("label-pose-link", parameters)


@task(name="label-pose-link", cache_key_fn=_key, persist_result=True)
def label_pose_link_task(artefact: Ref, fits: Ref, out_dir: str, reference: str, planned: Ref | None = None,
                         centre_u_mm: float = 0.02) -> dict:
    """Label every (measurement, scanner) of a sphere-fits table, pose it, link the scanners.

    Writes the five tables of :data:`OUTPUTS` into ``out_dir`` (each atomically) and
    returns their refs plus the refused, skipped and unlinked groups with reasons,
    which are also logged; one bad measurement never stops the others.
    """
    logger = _logger()
    art = load_artefact(artefact.path)
    table = read_table(fits.path, SphereFitsTable)
    plan = None
    if planned is not None:
        p = read_table(planned.path, PosePlanTable)
        plan = {r.measurement: Frame([r.tx_mm, r.ty_mm, r.tz_mm], [r.omega_rad, r.phi_rad, r.kappa_rad])
                for r in p.itertuples()}
    res = label_pose_link(table, art, reference, LabellingConfig(centre_u_mm=centre_u_mm), planned=plan,
                          source=fits.path)
    for r in res.labels[res.labels.status == "refused"].itertuples():
        logger.warning("measurement %s, scanner %s: labelling refused (%s)", r.measurement, r.scanner, r.message)
    for r in res.poses.skipped.itertuples():
        logger.warning("measurement %s, scanner %s: no pose (%s)", r.measurement, r.scanner, r.reason)
    unlinked = {} if res.links is None else res.links.unlinked
    for s, why in unlinked.items():
        logger.warning("scanner %s not linked: %s", s, why)
    if res.links_error:
        logger.warning("no scanner links: %s", res.links_error)
    out = Path(out_dir)
    write_table(res.fits, out / OUTPUTS["fits"], SphereFitsTable)
    write_table(res.labels, out / OUTPUTS["labels"], LabelOutcomesTable)
    write_table(res.centres, out / OUTPUTS["centres"], SphereCentresTable if len(res.centres) else None)
    write_table(res.poses.poses, out / OUTPUTS["poses"], PosesTable if len(res.poses.poses) else None)
    write_table(res.links_table(), out / OUTPUTS["links"], ScannerLinksTable if res.links is not None else None)
    refs = {k: ref_for(out / name, "table") for k, name in OUTPUTS.items()}
    return {**refs, "refused": res.labels[res.labels.status == "refused"].to_dict("records"),
            "skipped": res.poses.skipped.to_dict("records"), "unlinked": unlinked, "links_error": res.links_error}
