"""Simulated source, step 1: the run's inputs and the simulator's truth.

Writes what a recorded data set would bring (the artefact with its corrections, its
rods, each scanner's prior calibration, the planned poses, the ball-bar, the list of
measurements) and, apart in ``truth/``, what only the simulator knows (the true
sensors at the simulated resolution, each scanner frame's true placement, the
ball-bar positions, the artefact and ball-bar as built, which differ from the CMM
table and the certificate when ``simulate.errors`` says so). See
:mod:`fringecal.simulate.source`.

The acceptance test (``simulate.acceptance``): the objects' certificates go to
``acceptance_standards.json`` (what a recorded data set's
``verification/acceptance/standards.yaml`` brings; removed when no acceptance
position is simulated), the planned positions to ``truth/acceptance_positions.csv``
(empty when none) and their stores to the acquisition table.

Fixed ball-bar positions (``verification.scheme`` ``thesis9`` or ``vdi7``) are checked
against the region of each image the planned poses will let the calibration observe
(:func:`fringecal.simulate.source.predicted_regions`): a sphere whose image leaves it is
named with its numbers in the run's log (``fringecal.log``; the ``planned`` scheme places
them inside). Not a warning on the terminal: the verification step warns of the
positions it measured outside the calibration's own regions, and the demo's thesis
positions would otherwise print the same news twice on every run.
"""

from __future__ import annotations

import logging

import pandas as pd

from fringecal.acceptance.plan import PLAN_COLUMNS
from fringecal.frames import frame_rows
from fringecal.rundir import RunDir
from fringecal.simulate.black_box import without_black_boxes
from fringecal.simulate.config import AcquisitionConfig
from fringecal.simulate.errors import ARTEFACT_SWITCHES, errors_subset, switch_settings
from fringecal.simulate.settings import SimulatedAcceptanceConfig, SimulatedVerificationConfig, SimulationConfig
from fringecal.simulate.source import (acquisition_table, input_files, load_simulated_rig, positions_outside,
                                       predicted_regions)
from fringecal.steps.base import Settings, Step, save_or_remove

__all__ = ["SimulatePrepare", "simulation_of"]

log = logging.getLogger(__name__)


def simulation_of(cfg: Settings) -> SimulationConfig:
    """The simulation config rebuilt from what :class:`SimulatePrepare` declares (render
    and decoding settings, the render-time error switches and the verification's and
    acceptance's camera widths, which it does not use, at their defaults)."""
    s = cfg.simulate
    v, a = s.verification, s.acceptance
    return SimulationConfig(rig=s.rig, artefact_corrections=s.artefact_corrections, temperature_c=s.temperature_c,
                            prior=s.prior, acquisition=AcquisitionConfig(camera_width_px=s.acquisition.camera_width_px),
                            verification=SimulatedVerificationConfig(ballbar=v.ballbar, positions=v.positions,
                                                                     scheme=v.scheme, per_pair=v.per_pair,
                                                                     per_scanner=v.per_scanner, seed=v.seed),
                            errors=errors_subset(s.errors, ARTEFACT_SWITCHES),
                            acceptance=SimulatedAcceptanceConfig(enabled=a.enabled, standards=a.standards,
                                                                 sphere=a.sphere, dumbbell=a.dumbbell, flat=a.flat,
                                                                 seed=a.seed))


class SimulatePrepare(Step):
    name = "simulate-prepare"
    title = "simulated rig"
    settings = ("simulate.artefact_corrections", "simulate.temperature_c", "simulate.prior",
                "simulate.acquisition.camera_width_px", "simulate.verification.scheme",
                "simulate.verification.per_pair", "simulate.verification.per_scanner", "simulate.verification.seed",
                "simulate.acceptance.enabled", "simulate.acceptance.sphere", "simulate.acceptance.dumbbell",
                "simulate.acceptance.flat", "simulate.acceptance.seed", "acceptance.specification.depth_range_mm",
                "simulate.outputs") \
        + switch_settings(ARTEFACT_SWITCHES)
    locations = ("simulate.rig", "simulate.verification.ballbar", "simulate.verification.positions",
                 "simulate.acceptance.standards")
    modules = ("fringecal.simulate.source", "fringecal.simulate.world", "fringecal.acceptance.plan",
               "fringecal.acceptance.standards")

    def reads(self, rd: RunDir, cfg: Settings, item: str):
        return input_files(simulation_of(cfg))

    def writes(self, rd: RunDir, cfg: Settings, item: str):
        return [rd.artefact, rd.rods, rd.ballbar, rd.sensors_prior, rd.poses_planned, rd.acquisition,
                rd.truth.sensors, rd.truth.artefact, rd.truth.ballbar, rd.truth.scanner_frames,
                rd.truth.ballbar_positions, rd.truth.acceptance_positions, rd.acceptance_standards]

    def run(self, rd: RunDir, cfg: Settings, item: str, **context) -> None:
        sr = load_simulated_rig(simulation_of(cfg), cfg.acceptance.specification.depth_range_mm)
        if cfg.simulate.verification.scheme != "planned":  # fixed positions: say where they leave the region
            outside = positions_outside(sr.truth, sr.positions, sr.ballbar,
                                        predicted_regions(sr.truth, sr.artefact, sr.planned))
            if outside:
                log.info("the ball-bar positions of verification.scheme %s put %d sphere image(s) outside the "
                         "region of the images the artefact's poses will let the calibration observe (predicted "
                         "from the planned poses; there its model extrapolates): %s. 'scheme: planned' places "
                         "them inside", cfg.simulate.verification.scheme, len(outside), "; ".join(outside))
        rd.artefact.save(sr.artefact)
        save_or_remove(rd.rods, sr.rods)
        rd.ballbar.save(sr.ballbar)
        modelled = without_black_boxes(sr.prior, cfg.simulate.outputs)
        if modelled is None:  # every scanner a black box: no prior calibration (docs/blackbox.md)
            rd.sensors_prior.remove()
        else:
            rd.sensors_prior.save(modelled)
        rd.poses_planned.save(frame_rows(sr.planned))
        table = acquisition_table(sr)
        table.insert(4, "store", [rd.store(m).rel for m in table["measurement"]])
        rd.acquisition.save(table)
        rd.truth.sensors.save(sr.truth)
        rd.truth.artefact.save(sr.built)
        rd.truth.ballbar.save(sr.ballbar_built)
        rd.truth.scanner_frames.save(frame_rows(sr.scanner_frames, key="scanner"))
        rd.truth.ballbar_positions.save(frame_rows({p.name: p.T_world_ballbar for p in sr.positions}))
        acceptance = sr.acceptance if sr.acceptance is not None else pd.DataFrame(columns=list(PLAN_COLUMNS))
        rd.truth.acceptance_positions.save(acceptance)
        save_or_remove(rd.acceptance_standards, None if acceptance.empty else
                       sr.acceptance_standards.model_dump(mode="json"))
