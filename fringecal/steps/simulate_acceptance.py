"""Simulated source, step 5: render, decode and store the acceptance test's objects.

One step per object (VDI/VDE 2634 parts 2 and 3): ``simulate-sphere`` (probing sphere,
P_F and P_S), ``simulate-dumbbell`` (sphere spacing SD) and ``simulate-flat`` (flatness
F). Each position of ``truth/acceptance_positions.csv`` is recorded by the scanner it
was planned for (the acquisition table lists the stores); the object is built exactly
to its certificate (``acceptance_standards.json``) and rendered with the acceptance's
camera resolution (``simulate.acceptance.camera_width_px``, else the verification's,
else the acquisition's) and noise seed (``simulate.acceptance.seed``), and stored like
a recorded stack in ``measurements/<position>-<scanner>.zarr``. The scanners record
at their session-start placement (no session drift), as for the ball-bar.
"""

from __future__ import annotations

from fringecal.acceptance.standards import AcceptanceStandards
from fringecal.rig import scaled_scanner
from fringecal.rundir import RunDir, TableFile
from fringecal.simulate.scenes import ArtefactHardware, Scene, acceptance_scene
from fringecal.simulate.source import acceptance_camera_width
from fringecal.steps.base import Settings
from fringecal.steps.simulate_render import RenderStores

__all__ = ["SimulateSphere", "SimulateDumbbell", "SimulateFlat"]


class _SimulateAcceptance(RenderStores):
    """Render the acceptance positions of one object (``kind`` = the test)."""

    settings = RenderStores.settings + ("simulate.acceptance.camera_width_px", "simulate.verification.camera_width_px",
                                        "simulate.acceptance.seed")
    modules = RenderStores.modules + ("fringecal.acceptance.standards",)

    def placements(self, rd: RunDir) -> TableFile:
        return rd.truth.acceptance_positions

    def objects(self, rd: RunDir) -> list:
        return [rd.acceptance_standards]

    def scene(self, rd: RunDir, T, hardware: ArtefactHardware) -> Scene:
        standards = AcceptanceStandards.model_validate(rd.acceptance_standards.load())
        return acceptance_scene(self.kind, standards, T, hardware)

    def recording(self, rd: RunDir, cfg: Settings, scanner: str, pose: str):
        true_scanner, acquisition = super().recording(rd, cfg, scanner, pose)
        width = acceptance_camera_width(cfg.simulate)
        if width is not None:
            true_scanner = scaled_scanner(true_scanner, width)
        return true_scanner, acquisition.model_copy(update={"seed": cfg.simulate.acceptance.seed})


class SimulateSphere(_SimulateAcceptance):
    name = "simulate-sphere"
    title = "render acceptance sphere"
    kind = "sphere"


class SimulateDumbbell(_SimulateAcceptance):
    name = "simulate-dumbbell"
    title = "render acceptance dumbbell"
    kind = "dumbbell"


class SimulateFlat(_SimulateAcceptance):
    name = "simulate-flat"
    title = "render acceptance flat"
    kind = "flat"
