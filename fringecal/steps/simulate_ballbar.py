"""Simulated source, step 4: render, decode and store the ball-bar at every position.

Every scanner that sees a bar sphere records the position (the acquisition table
lists them); the bar is rendered at ``truth/ballbar_positions.csv`` with the
verification's own camera resolution and noise seed, and stored like a recorded
stack in ``measurements/<position>-<scanner>.zarr``.
"""

from __future__ import annotations

from ..acquisition import frames_from_rows, simulate_measurement
from ..ballbar import ballbar_rods
from ..rundir import RunDir
from ..simulate.resolution import scaled_scanner
from ..simulate.scenes import ArtefactHardware, artefact_scene
from .base import Rows, Settings, Step, store_fields, store_row, stores_of_kind
from .simulate_render import ACQUISITION_SETTINGS, hardware_file, log_summary

__all__ = ["SimulateBallbar"]


class SimulateBallbar(Step):
    name = "simulate-ballbar"
    title = "render ball-bar"
    settings = ACQUISITION_SETTINGS + ("simulate.verification.camera_width_px", "simulate.verification.seed")
    locations = ("simulate.rig",)
    modules = ("fringecal.acquisition.measure", "fringecal.simulate")

    def items(self, rd: RunDir, cfg: Settings) -> list[str]:
        return stores_of_kind(rd, "ballbar")

    def reads(self, rd: RunDir, cfg: Settings, item: str):
        row = store_fields(rd, item)
        return [store_row(rd, item), Rows(rd.truth.ballbar_positions, {"measurement": row["pose"]}),
                rd.truth.sensors, rd.ballbar, hardware_file(cfg)]

    def writes(self, rd: RunDir, cfg: Settings, item: str):
        return [rd.store(item), rd.truth.store(item)]

    def run(self, rd: RunDir, cfg: Settings, item: str, **context) -> None:
        row = store_fields(rd, item)
        T = frames_from_rows(Rows(rd.truth.ballbar_positions, {"measurement": row["pose"]}).load())[row["pose"]]
        bar = rd.ballbar.load()
        scene = artefact_scene(bar, ballbar_rods(bar), T, ArtefactHardware.from_materials(hardware_file(cfg)))
        scanner = rd.truth.sensors.load().scanner(row["scanner"])
        v = cfg.simulate.verification
        if v.camera_width_px is not None:
            scanner = scaled_scanner(scanner, v.camera_width_px)
        acq = cfg.simulate.acquisition
        settings = _Acquisition(acq, seed=v.seed)
        result = simulate_measurement(item, scanner, scene, settings, cfg.decode, rd.store(item).path,
                                      rd.truth.store(item).path, {"pose": row["pose"], "kind": "ballbar"})
        log_summary(result.summary)


class _Acquisition:
    """The acquisition settings with the verification's own noise seed."""

    def __init__(self, acq, seed: int):
        self.render, self.sequence, self.backdrop_mm = acq.render, acq.sequence, acq.backdrop_mm
        self.store_frames, self.seed = acq.store_frames, seed
