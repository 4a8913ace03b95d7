"""A simulated black-box scanner: a scanner that delivers its points, not its images.

The black box records like any simulated scanner (rendered fringe frames, decoded as a
recorded stack is decoded) and then triangulates every valid pixel with its own true
sensors, as a commercial head does inside: its cloud holds the triangulated points with
the noise of its phases, in its own frame (its camera's: ``x_local = R (x_world - t)``
of :func:`fringecal.simulate.prior.scanner_frames`), rounded to float32 as a PLY file
holds them. Both doors compute it with :func:`black_box_points` from the same decoded
maps, so a simulated run's cloud store and ``fringecal simulate``'s ``.ply`` hold the
same numbers.
"""

from __future__ import annotations

import numpy as np

from fringecal.frames import Frame
from fringecal.pointcloud import triangulate_maps
from fringecal.config import ConfigError
from fringecal.rig import Rig, Scanner
from fringecal.scancloud import write_scanner_cloud
from fringecal.store import open_store

__all__ = ["black_box_points", "own_frame", "without_black_boxes", "write_black_box_ply",
           "store_points"]


def own_frame(scanner: Scanner) -> Frame:
    """``T_world_scanner`` of a black box's own frame: its camera's."""
    return Frame.from_matrix(scanner.camera.R, scanner.camera.pinhole)


def black_box_points(scanner: Scanner, tau_x, tau_y, valid) -> np.ndarray:
    """The black box's cloud (n, 3) float32, mm in its own frame, from decoded maps."""
    xyz = triangulate_maps(scanner.camera, scanner.projector, tau_x, tau_y, valid).points()
    return own_frame(scanner).to_local(xyz).astype(np.float32)


def without_black_boxes(rig: Rig, outputs: dict) -> Rig | None:
    """The prior calibrations of the scanners that deliver images: a black box
    (``simulate.outputs``: ``cloud``) has none (None: every scanner is a black box)."""
    keep = [i for i, s in enumerate(rig.scanners) if outputs.get(s.name) != "cloud"]
    if not keep:
        return None
    if rig.reference not in [rig.scanners[i].name for i in keep]:
        raise ConfigError(f"simulate.outputs: the reference scanner {rig.reference!r} delivers a cloud; a rig with "
                          "modelled scanners needs one of them as its reference")
    rows = [2 * i + k for i in keep for k in (0, 1)]
    return Rig(tuple(rig.scanners[i] for i in keep), rig.reference, rig.free[rows])


def store_points(store, scanner: Scanner) -> np.ndarray:
    """The black box's cloud from a decoded measurement store."""
    with open_store(store) as ds:
        return black_box_points(scanner, ds["tau_x"].values, ds["tau_y"].values, ds["valid"].values)


def write_black_box_ply(store, scanner: Scanner, path) -> None:
    """The black box's cloud of a decoded store as the data set's ``<scanner>.ply``."""
    write_scanner_cloud(path, store_points(store, scanner))
