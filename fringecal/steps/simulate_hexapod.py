"""Simulated source, step 2: move the (simulated) hexapod through the planned poses.

The pose each move reached, read back from the platform's encoders, is where the
artefact really is, so the renderer uses it (``truth/poses.csv``); the moves table
(planned and reached pose, encoder counts) is the acquisition log a live cell keeps
too. Without the hexapod every pose is reached exactly.
"""

from __future__ import annotations

import logging

from fringecal.frames import frame_rows, frames_from_rows
from fringecal.hexapod.config import default_hexapod_config_path
from fringecal.rundir import RunDir
from fringecal.simulate.config import HexapodStepConfig
from fringecal.simulate.moves import move_hexapod, poses_table
from fringecal.steps.base import Settings, Step

__all__ = ["SimulateHexapod"]

log = logging.getLogger(__name__)


def _hexapod_config_file(hexapod):
    return hexapod.config or default_hexapod_config_path()


class SimulateHexapod(Step):
    name = "simulate-hexapod"
    title = "hexapod moves"
    settings = ("simulate.acquisition.hexapod.enabled", "simulate.acquisition.hexapod.url")
    locations = ("simulate.acquisition.hexapod.config",)
    modules = ("fringecal.hexapod",)

    def reads(self, rd: RunDir, cfg: Settings, item: str):
        hx = cfg.simulate.acquisition.hexapod
        return [rd.poses_planned] + ([_hexapod_config_file(hx)] if hx.enabled else [])

    def writes(self, rd: RunDir, cfg: Settings, item: str):
        return [rd.hexapod_moves, rd.truth.poses]

    def run(self, rd: RunDir, cfg: Settings, item: str, **context) -> None:
        hx = cfg.simulate.acquisition.hexapod
        moves = move_hexapod(frames_from_rows(rd.poses_planned.load()),
                             HexapodStepConfig(enabled=hx.enabled, url=hx.url, config=hx.config))
        for m in moves:
            log.info("pose %s: reached %.4f mm / %.1f urad from plan", m.pose, m.translation_error_mm,
                     1e6 * m.rotation_error_rad)
        rd.hexapod_moves.save(poses_table(moves))
        rd.truth.poses.save(frame_rows({m.pose: m.reached for m in moves}))
