"""Which artefact spheres a camera sees, and how much of each the hardware hides.

Counts pixel-centre rays only (no rendering): for each sphere, its image in a scene
of bare spheres, and what of that image end caps, and caps plus rods, cover.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from fringecal.artefact import Artefact
from fringecal.frames import Frame
from fringecal.rig import Scanner, scaled_scanner
from fringecal.simulate.scene import Scene
from fringecal.simulate.scenes import ArtefactHardware, artefact_scene

__all__ = ["pixel_centre_rays", "sphere_visibility"]


def pixel_centre_rays(scanner: Scanner) -> tuple[np.ndarray, np.ndarray]:
    """Camera pinhole (3,) and unit rays (rows * cols, 3) through every pixel centre,
    row by row (eq. 2-21, full camera model)."""
    f = scanner.camera.format
    v, u = np.mgrid[0:f.height_px, 0:f.width_px]
    uv = np.stack([u.ravel(), v.ravel()], axis=1).astype(float)
    return scanner.camera.rays(scanner.camera.image_mm(uv))


def _lit(scanner: Scanner, scene: Scene, hits) -> np.ndarray:
    """Which hit points the projector lights (in its frame, front-facing, unshadowed)."""
    prj = scanner.projector
    ok = hits.object_index >= 0
    lit = np.zeros(len(ok), bool)
    pts = hits.point[ok]
    to_prj = prj.pinhole - pts
    dist = np.linalg.norm(to_prj, axis=1)
    facing = np.einsum("ij,ij->i", hits.normal[ok], to_prj) > 0
    inside = prj.format.contains_mm(prj.project(pts))
    first = scene.cast(prj.pinhole, -to_prj / dist[:, None])
    lit[ok] = facing & inside & (first.t >= dist * (1 - 1e-9) - 1e-7)
    return lit


def sphere_visibility(scanner: Scanner, artefact: Artefact, rods: pd.DataFrame, T_world_artefact: Frame,
                      width_px: int = 512, hardware: ArtefactHardware | None = None) -> pd.DataFrame:
    """Per sphere in the camera's view (pixel centres at ``width_px`` resolution):

    ``pixels_bare`` (image of the sphere with no caps or rods), ``pixels`` (visible
    with everything), ``hidden_by_end_caps`` (fraction of the bare image covered by
    end caps when only caps are added), ``hidden_by_hardware`` (covered by caps and
    rods), ``lit_fraction`` (of the visible pixels, lit by the projector).
    """
    small = scaled_scanner(scanner, width_px)
    origin, rays = pixel_centre_rays(small)
    full = artefact_scene(artefact, rods, T_world_artefact, hardware)
    bare = full.without("end_cap", "rod")
    caps = full.without("rod")

    def sphere_of(scene: Scene):
        hits = scene.cast(origin, rays)
        label = np.array([o.sphere_id if o.kind == "sphere" else "" for o in scene.objects] + [""], object)
        return label[hits.object_index], hits

    s_bare, _ = sphere_of(bare)
    s_caps, _ = sphere_of(caps)
    s_full, hits = sphere_of(full)
    lit = _lit(small, full, hits)
    rows = []
    for sid in artefact.ids:
        n_bare = int(np.sum(s_bare == sid))
        if n_bare == 0:
            continue
        vis = s_full == sid
        rows.append({
            "sphere_id": sid, "pixels_bare": n_bare, "pixels": int(vis.sum()),
            "hidden_by_end_caps": 1 - np.sum((s_caps == sid) & (s_bare == sid)) / n_bare,
            "hidden_by_hardware": 1 - np.sum(vis & (s_bare == sid)) / n_bare,
            "lit_fraction": float(lit[vis].mean()) if vis.any() else 0.0,
        })
    return pd.DataFrame(rows, columns=["sphere_id", "pixels_bare", "pixels", "hidden_by_end_caps",
                                       "hidden_by_hardware", "lit_fraction"])
