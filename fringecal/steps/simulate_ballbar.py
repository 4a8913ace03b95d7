"""Simulated source, step 4: render, decode and store the ball-bar at every position.

Every scanner that sees a bar sphere records the position (the acquisition table
lists them); the bar as built (``truth/ballbar.csv``; the run's ``ballbar.csv`` is its
certificate) is rendered at ``truth/ballbar_positions.csv`` with the verification's
own camera resolution and noise seed, and stored like a recorded stack in
``measurements/<position>-<scanner>.zarr``. The scanners record the verification at
their session-start placement (no session drift).
"""

from __future__ import annotations

from fringecal.rig import scaled_scanner
from fringecal.rundir import RunDir, TableFile
from fringecal.simulate.scenes import ArtefactHardware, Scene, artefact_scene
from fringecal.steps.base import Settings
from fringecal.steps.simulate_render import RenderStores
from fringecal.verification.ballbar import ballbar_rods

__all__ = ["SimulateBallbar"]


class SimulateBallbar(RenderStores):
    name = "simulate-ballbar"
    title = "render ball-bar"
    kind = "ballbar"
    settings = RenderStores.settings + ("simulate.verification.camera_width_px", "simulate.verification.seed")

    def placements(self, rd: RunDir) -> TableFile:
        return rd.truth.ballbar_positions

    def objects(self, rd: RunDir) -> list:
        return [rd.truth.ballbar]

    def scene(self, rd: RunDir, T, hardware: ArtefactHardware) -> Scene:
        bar = rd.truth.ballbar.load()
        return artefact_scene(bar, ballbar_rods(bar), T, hardware)

    def recording(self, rd: RunDir, cfg: Settings, scanner: str, pose: str):
        true_scanner, acquisition = super().recording(rd, cfg, scanner, pose)
        v = cfg.simulate.verification
        if v.camera_width_px is not None:
            true_scanner = scaled_scanner(true_scanner, v.camera_width_px)
        return true_scanner, acquisition.model_copy(update={"seed": v.seed})
