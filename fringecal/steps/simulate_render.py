"""Simulated source, step 3: render, decode and store every calibration measurement.

Each (measurement, scanner) store is rendered with the true scanner looking at the
artefact as built where the hexapod put it (``truth/poses.csv``), decoded like any
recorded stack, and written to ``measurements/<id>.zarr``; the renderer's per-pixel
truth goes to ``truth/measurements/<id>.zarr``. The key of one store holds only its
own pose row, so adding a pose renders only the new measurements.
"""

from __future__ import annotations

import logging

from ..acquisition.measure import simulate_measurement
from ..frames import frames_from_rows
from ..rundir import RunDir, TableFile
from ..runconfig import AcquisitionConfig
from ..simulate.scenes import ArtefactHardware, Scene, artefact_scene
from .base import Rows, Settings, Step, store_fields, store_row, stores_of_kind

__all__ = ["SimulateRender", "RenderStores", "ACQUISITION_SETTINGS", "hardware_file"]

log = logging.getLogger(__name__)

#: What the rendering of a store depends on besides its scene and scanner.
ACQUISITION_SETTINGS = ("simulate.acquisition.render", "simulate.acquisition.sequence",
                        "simulate.acquisition.seed", "simulate.acquisition.backdrop_mm",
                        "simulate.acquisition.store_frames", "decode")


def hardware_file(cfg: Settings):
    """The materials file of the rig (tube and end-cap sizes; the thesis's by default)."""
    from ..config import RigConfig, load_yaml_model, thesis_dir

    return load_yaml_model(cfg.simulate.rig, RigConfig).materials or thesis_dir() / "materials.yaml"


class RenderStores(Step):
    """Render, decode and store the acquisition stores of one ``kind``; subclasses say
    where the scene stands, what it holds and how the scanner records it."""

    kind: str
    settings = ACQUISITION_SETTINGS
    locations = ("simulate.rig",)
    modules = ("fringecal.acquisition.measure", "fringecal.simulate")

    def placements(self, rd: RunDir) -> TableFile:
        """The table of ``T_world_<object>`` per measurement or position."""
        raise NotImplementedError

    def objects(self, rd: RunDir) -> list:
        """The files of the scene's objects."""
        raise NotImplementedError

    def scene(self, rd: RunDir, T, hardware: ArtefactHardware) -> Scene:
        raise NotImplementedError

    def recording(self, rd: RunDir, cfg: Settings, scanner: str):
        """The scanner (true sensors) and the acquisition settings it records with."""
        acq = cfg.simulate.acquisition
        return rd.truth.sensors.load().scanner(scanner), AcquisitionConfig(
            render=acq.render, sequence=acq.sequence, seed=acq.seed, backdrop_mm=acq.backdrop_mm,
            store_frames=acq.store_frames)

    def items(self, rd: RunDir, cfg: Settings) -> list[str]:
        return stores_of_kind(rd, self.kind)

    def _placement(self, rd: RunDir, item: str) -> Rows:
        return Rows(self.placements(rd), {"measurement": store_fields(rd, item)["pose"]})

    def reads(self, rd: RunDir, cfg: Settings, item: str):
        return [store_row(rd, item), self._placement(rd, item), rd.truth.sensors, *self.objects(rd),
                hardware_file(cfg)]

    def writes(self, rd: RunDir, cfg: Settings, item: str):
        return [rd.store(item), rd.truth.store(item)]

    def run(self, rd: RunDir, cfg: Settings, item: str, **context) -> None:
        row = store_fields(rd, item)
        T = frames_from_rows(self._placement(rd, item).load())[row["pose"]]
        scene = self.scene(rd, T, ArtefactHardware.from_materials(hardware_file(cfg)))
        scanner, acquisition = self.recording(rd, cfg, row["scanner"])
        s = simulate_measurement(item, scanner, scene, acquisition, cfg.decode, rd.store(item).path,
                                 rd.truth.store(item).path, {"pose": row["pose"], "kind": self.kind}).summary
        log.info("%s: render %.1f s, decode + store %.1f s, %.1f %% valid", item, s["render_s"], s["decode_store_s"],
                 100 * s["valid_fraction"])


class SimulateRender(RenderStores):
    name = "simulate-render"
    title = "render measurements"
    kind = "artefact"

    def placements(self, rd: RunDir) -> TableFile:
        return rd.truth.poses

    def objects(self, rd: RunDir) -> list:
        return [rd.truth.artefact, rd.rods]

    def scene(self, rd: RunDir, T, hardware: ArtefactHardware) -> Scene:
        artefact = rd.truth.artefact.load()
        return artefact_scene(artefact, rd.rods.load(artefact) if rd.rods.exists() else None, T, hardware)
