"""The simulated data source, whole: the virtual scanner that renders the fringe frames
a scanner would record of a scene, with per-pixel ground truth (:mod:`.render`,
:mod:`.scene`, :mod:`.scenes`, :mod:`.kernel`), the simulated world and its unmodelled
errors (:mod:`.world`, :mod:`.errors`), the simulated rig and its priors
(:mod:`.source`, :mod:`.prior`, :mod:`.rigs`), the hexapod's moves and each simulated
measurement (:mod:`.moves`, :mod:`.measurement`), the rig written as a data set
(:mod:`.export`), objects to measure (:mod:`.objects`), and simulated control points
and sphere centres without images for tests and benchmarks (:mod:`.control_points`,
:mod:`.sphere_centres`, :mod:`.basin`). The ``simulate:`` section of a run
configuration is :mod:`.settings`.

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
