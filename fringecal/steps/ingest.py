"""Recorded data set, step 1: take the data set's tables into the run directory.

The run keeps its own copy of every input table, so it can be reproduced and
reported on without the data set: the artefact (the CMM table with the corrections
of ``dataset.yaml``, if any), its rods, each scanner's prior calibration, the
planned poses, the ball-bar, the acceptance objects' certificates
(``verification/acceptance/standards.yaml`` as ``acceptance_standards.json``) and the
list of stacks to decode with their kinds (``artefact``, ``ballbar``, ``sphere``,
``dumbbell``, ``flat``) (:class:`~fringecal.dataset.DataSet` validates all of it first).
An optional input the data set lacks removes the run's copy, so no earlier run's file
is left behind.

The reference scanner's frame is the world (the data-set contract), so its camera's
six external parameters are fixed whatever ``sensors_prior.csv`` says.
"""

from __future__ import annotations

from dataclasses import replace

import pandas as pd

from fringecal.acceptance.standards import load_standards
from fringecal.artefact import load_artefact, load_rods
from fringecal.dataset import DataSet
from fringecal.engineering.corrections import apply_corrections
from fringecal.rig import load_rig
from fringecal.rundir import RunDir
from fringecal.schemas import PosePlanTable, read_table
from fringecal.steps.base import Settings, Step, Value, save_or_remove

__all__ = ["Ingest"]


def _stacks(ds: DataSet) -> list[dict]:
    return [{"measurement": s.id, "kind": s.kind, "pose": s.group, "scanner": s.scanner,
             "source": str(s.path.relative_to(ds.root)), "format": s.format}
            for s in ds.stacks()]


def modelled_prior(path, reference: str):
    """The modelled scanners' prior calibrations, the reference camera's exterior fixed."""
    prior = load_rig(path, reference=reference)
    free = prior.free.copy()
    free[[s.name for s in prior.sensors].index(prior.scanner(prior.reference).camera.name), :6] = False
    return replace(prior, free=free)


class Ingest(Step):
    name = "ingest"
    title = "data set"
    settings = ("reference_scanner",)
    locations = ("dataset",)
    modules = ("fringecal.dataset", "fringecal.engineering.corrections")

    def reads(self, rd: RunDir, cfg: Settings, item: str):
        ds = DataSet.open(cfg.dataset)
        files = [ds.root / "dataset.yaml", ds.artefact, ds.rods, ds.sensors_prior, ds.poses_planned, ds.ballbar,
                 ds.acceptance_standards]
        sag = ds.config.artefact_corrections.sag if ds.config.artefact_corrections else None
        if sag is not None:
            files += [p for p in (sag.rods, sag.materials) if p is not None]
        return [f for f in files if f is not None] + [Value("stacks", _stacks(ds))]

    def writes(self, rd: RunDir, cfg: Settings, item: str):
        return [rd.artefact, rd.rods, rd.ballbar, rd.acceptance_standards, rd.sensors_prior, rd.poses_planned,
                rd.acquisition]

    def run(self, rd: RunDir, cfg: Settings, item: str, **context) -> None:
        ds = DataSet.open(cfg.dataset)
        artefact = apply_corrections(load_artefact(ds.artefact), ds.config.artefact_corrections,
                                     ds.config.temperature_c)
        rd.artefact.save(artefact)
        save_or_remove(rd.rods, ds.rods and load_rods(ds.rods, artefact))
        save_or_remove(rd.ballbar, ds.ballbar and load_artefact(ds.ballbar))
        save_or_remove(rd.acceptance_standards,
                       ds.acceptance_standards and load_standards(ds.acceptance_standards).model_dump(mode="json"))
        save_or_remove(rd.poses_planned, ds.poses_planned and read_table(ds.poses_planned, PosePlanTable))
        if ds.sensors_prior is None:  # black boxes only
            rd.sensors_prior.remove()
        else:
            rd.sensors_prior.save(modelled_prior(ds.sensors_prior, cfg.reference_scanner))
        table = pd.DataFrame(_stacks(ds)).drop(columns="format")
        table.insert(4, "store", [rd.store(m).rel for m in table["measurement"]])
        rd.acquisition.save(table)
