"""The virtual scanner: renders the fringe frames a scanner would record of a scene,
with per-pixel ground truth.

Typical use::

    scene = artefact_scene(artefact, rods, T_world_artefact)
    m = render_measurement(scaled_scanner(scanner, 512), scene, RenderConfig(), rng)
    m.frames      # uint16 (98, 512, 512), FringeSequence().frames() order
    m.truth       # GroundTruth: tau_x, tau_y, point, object_index, sphere_index, ...
"""

from fringecal.rig import scaled_rig, scaled_scanner
from fringecal.sensor import scaled_format
from fringecal.simulate.config import (
                     DEFAULT_MATERIALS,
                     Material,
                     RenderConfig,
                     excess_noise_for_tau_noise,
                     phase_noise,
                     surface_levels,
)
from fringecal.simulate.render import (
                     LIGHT_LIT,
                     LIGHT_NO_HIT,
                     LIGHT_OUTSIDE,
                     LIGHT_SHADOW,
                     GroundTruth,
                     Measurement,
                     render_measurement,
)
from fringecal.simulate.scene import Box, Cylinder, Hits, Panel, Plane, Scene, SceneObject, Sphere
from fringecal.simulate.scenes import (
                     SPHERE_PLATE_SEPARATION_MM,
                     ArtefactHardware,
                     artefact_scene,
                     backdrop,
                     sphere_plate_pose,
                     sphere_plate_scene,
)
from fringecal.simulate.visibility import pixel_centre_rays, sphere_visibility

__all__ = [
    "Material", "RenderConfig", "DEFAULT_MATERIALS", "surface_levels", "phase_noise", "excess_noise_for_tau_noise",
    "GroundTruth", "Measurement", "render_measurement",
    "LIGHT_NO_HIT", "LIGHT_LIT", "LIGHT_SHADOW", "LIGHT_OUTSIDE",
    "scaled_format", "scaled_scanner", "scaled_rig",
    "Sphere", "Cylinder", "Box", "Plane", "Panel", "SceneObject", "Scene", "Hits",
    "ArtefactHardware", "artefact_scene", "backdrop", "sphere_plate_scene", "sphere_plate_pose",
    "SPHERE_PLATE_SEPARATION_MM", "pixel_centre_rays", "sphere_visibility",
]
