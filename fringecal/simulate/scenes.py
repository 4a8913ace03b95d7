"""Scene builders: the large-volume artefact, the chapter-5 sphere-plate artefact, the
acceptance test's objects (sphere, dumbbell, flat; :func:`acceptance_scene`) and a
backdrop.

The artefact (thesis chapter 3): chrome-steel spheres (diameters from the artefact
definition), carbon-fibre tubes of 21.8 mm between them, and a mild-steel end cap
where each tube meets a sphere. ``configs/thesis/materials.yaml`` gives the cap as a
21.8 mm cylinder reaching 25 mm out from the sphere surface along the rod axis
(section 3.5.1 prints no drawing: 25 mm follows from (600 - 50 - 500)/2, the
diameter is taken flush with the tube). The cap is modelled as a solid cylinder
starting where its rim meets the sphere, so it hides the spherical cap of surface it
encloses, as the real cap does; the tube runs between the two caps' outer ends.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from fringecal.artefact import Artefact
from fringecal.config import StrictModel, read_yaml_mapping, thesis_dir
from fringecal.frames import Frame
from fringecal.rig import Scanner
from fringecal.simulate.scene import Box, Cylinder, Plane, Scene, SceneObject, Sphere
from fringecal.verification.ballbar import ballbar_rods

__all__ = [
    "ArtefactHardware",
    "artefact_scene",
    "backdrop",
    "sphere_plate_scene",
    "sphere_plate_pose",
    "sphere_scene",
    "dumbbell_scene",
    "flat_scene",
    "acceptance_scene",
    "SPHERE_PLATE_SEPARATION_MM",
]

#: Sphere centre to plate surface, CMM (thesis table 5-1).
SPHERE_PLATE_SEPARATION_MM = 50.645


class ArtefactHardware(StrictModel):
    """Tube and end-cap dimensions (mm)."""

    tube_diameter_mm: float = 21.8
    end_cap_diameter_mm: float = 21.8
    end_cap_length_mm: float = 25.0

    @classmethod
    def from_materials(cls, path=None) -> "ArtefactHardware":
        """Read ``tube.outer_diameter_mm`` and ``end_cap.outer_diameter_mm, length_mm``
        from a materials file (default: the thesis's ``materials.yaml``)."""
        path = Path(path) if path is not None else thesis_dir() / "materials.yaml"
        data = read_yaml_mapping(path)
        try:
            return cls(tube_diameter_mm=data["tube"]["outer_diameter_mm"],
                       end_cap_diameter_mm=data["end_cap"]["outer_diameter_mm"],
                       end_cap_length_mm=data["end_cap"]["length_mm"])
        except (KeyError, TypeError) as err:
            raise ValueError(f"{path}: missing {err} (need tube.outer_diameter_mm, "
                             "end_cap.outer_diameter_mm, end_cap.length_mm)") from None


def artefact_scene(artefact: Artefact, rods: pd.DataFrame | None, T_world_artefact: Frame,
                   hardware: ArtefactHardware | None = None, background: Plane | None = None) -> Scene:
    """Spheres, end caps and tubes of ``artefact`` placed by ``T_world_artefact``.

    Objects are named ``sphere:<id>`` (kind ``sphere``), ``end_cap:<rod>:<sphere>``
    (kind ``end_cap``, ``sphere_id`` = the sphere it sits on) and ``rod:<rod>`` (kind
    ``rod``); materials ``sphere``, ``end_cap``, ``rod``; the optional backdrop is
    ``background``. ``rods`` needs ``rod_id, sphere_a, sphere_b``; None gives bare
    spheres.
    """
    hw = hardware or ArtefactHardware()
    centres = T_world_artefact.to_world(artefact.centres)
    objects = [SceneObject(f"sphere:{sid}", "sphere", "sphere", (Sphere(c, r),), sid)
               for sid, c, r in zip(artefact.ids, centres, artefact.radii)]
    rc, rt = hw.end_cap_diameter_mm / 2, hw.tube_diameter_mm / 2
    for rod in ([] if rods is None else rods.itertuples(index=False)):
        ia, ib = artefact.index([rod.sphere_a, rod.sphere_b])
        ca, cb = centres[ia], centres[ib]
        span = float(np.linalg.norm(cb - ca))
        u = (cb - ca) / span
        outer = []
        for end, (i, c, sign) in enumerate(((ia, ca, 1.0), (ib, cb, -1.0))):
            r = artefact.radii[i]
            seat = np.sqrt(r * r - rc * rc) if rc < r else 0.0
            reach = r + hw.end_cap_length_mm
            outer.append(c + sign * reach * u)
            cap = Cylinder(c + sign * seat * u, c + sign * reach * u, rc)
            sid = artefact.ids[i]
            objects.append(SceneObject(f"end_cap:{rod.rod_id}:{sid}", "end_cap", "end_cap", (cap,), sid))
        if np.dot(outer[1] - outer[0], u) > 0:
            objects.append(SceneObject(f"rod:{rod.rod_id}", "rod", "rod", (Cylinder(outer[0], outer[1], rt),)))
    if background is not None:
        objects.append(SceneObject("background", "background", "background", (background,)))
    return Scene(tuple(objects))


def backdrop(scanner: Scanner, distance_mm: float) -> Plane:
    """A plane perpendicular to the camera's optical axis, ``distance_mm`` in front of it."""
    cam = scanner.camera
    axis = cam.R[2]  # sensor z' in world: points in front have z' > 0
    return Plane(cam.pinhole + distance_mm * axis, axis)


def sphere_plate_scene(T_world_plate: Frame, sphere_diameter_mm: float = 20.0,
                       separation_mm: float = SPHERE_PLATE_SEPARATION_MM,
                       plate_size_mm: tuple[float, float] = (160.0, 80.0), plate_thickness_mm: float = 10.0,
                       stalk_diameter_mm: float = 8.0, sphere_id: str = "S",
                       background: Plane | None = None) -> Scene:
    """The sphere-plate artefact of thesis chapter 5.

    In the plate frame the plate's front face is z = 0 (normal +z, the plate occupies
    -thickness <= z <= 0, |x| <= 80, |y| <= 40 mm) and the sphere centre is at
    (0, 0, ``separation_mm``), on a stalk along +z. Objects: ``sphere:<id>`` (kind and
    material ``sphere``), ``plate`` (kind and material ``plate``), ``stalk`` (kind and
    material ``stalk``). Thickness and stalk diameter are not in the thesis
    (assumptions; neither affects the sphere or the plate face).
    """
    R = T_world_plate.R  # rows: plate axes in world
    centre = T_world_plate.to_world([0.0, 0.0, separation_mm])
    w, h = plate_size_mm
    plate = Box(T_world_plate.to_world([0.0, 0.0, -plate_thickness_mm / 2]), R,
                (w / 2, h / 2, plate_thickness_mm / 2))
    stalk = Cylinder(T_world_plate.to_world([0.0, 0.0, 0.0]), centre, stalk_diameter_mm / 2)
    objects = [
        SceneObject(f"sphere:{sphere_id}", "sphere", "sphere", (Sphere(centre, sphere_diameter_mm / 2),), sphere_id),
        SceneObject("plate", "plate", "plate", (plate,)),
        SceneObject("stalk", "stalk", "stalk", (stalk,)),
    ]
    if background is not None:
        objects.append(SceneObject("background", "background", "background", (background,)))
    return Scene(tuple(objects))


def sphere_plate_pose(scanner: Scanner, sphere_centre, tilt_rad: float, rotation_rad: float,
                      separation_mm: float = SPHERE_PLATE_SEPARATION_MM) -> Frame:
    """T_world_plate for the chapter-5 experiment (figures 5-3, 5-4).

    At tilt = rotation = 0 the plate normal points from the sphere towards the
    scanner (the bisector of the directions to camera and projector pinholes). The
    rotation turns the normal within the plane through both pinholes and the sphere;
    the tilt then turns it out of that plane (tilt 0: the normal lies in the plane of
    the optical axes, as in the thesis). The sphere centre stays at ``sphere_centre``.
    """
    s = np.asarray(sphere_centre, float).reshape(3)
    to_cam = scanner.camera.pinhole - s
    to_prj = scanner.projector.pinhole - s
    w = to_cam / np.linalg.norm(to_cam) + to_prj / np.linalg.norm(to_prj)
    w /= np.linalg.norm(w)
    base = scanner.projector.pinhole - scanner.camera.pinhole
    e_b = base - np.dot(base, w) * w
    e_b /= np.linalg.norm(e_b)
    e_n = np.cross(w, e_b)
    ct, st = np.cos(tilt_rad), np.sin(tilt_rad)
    cr, sr = np.cos(rotation_rad), np.sin(rotation_rad)
    z = ct * (cr * w + sr * e_b) + st * e_n
    x = cr * e_b - sr * w  # the rotated baseline direction
    x = x - np.dot(x, z) * z
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    return Frame.from_matrix(R, s - separation_mm * z)



# -- the acceptance test's objects (VDI/VDE 2634 parts 2 and 3) -------------------------

def sphere_scene(standard, T_world_sphere: Frame, background: Plane | None = None) -> Scene:
    """The probing sphere (:class:`~fringecal.acceptance.standards.SphereStandard`) of
    its calibrated diameter, centred at ``T_world_sphere``'s origin (no stand): one
    object ``sphere:S`` (kind and material ``sphere``, sphere id ``S``)."""
    objects = [SceneObject("sphere:S", "sphere", "sphere", (Sphere(T_world_sphere.t, standard.diameter_mm / 2),), "S")]
    if background is not None:
        objects.append(SceneObject("background", "background", "background", (background,)))
    return Scene(tuple(objects))


def dumbbell_scene(standard, T_world_dumbbell: Frame, hardware: ArtefactHardware | None = None,
                   background: Plane | None = None) -> Scene:
    """The dumbbell (:class:`~fringecal.acceptance.standards.DumbbellStandard`): spheres
    ``A`` at ``T_world_dumbbell``'s origin and ``B`` at (length_mm, 0, 0), joined like
    the ball-bar (:func:`artefact_scene`) by a rod of the dumbbell's rod diameter with
    end caps of that diameter and ``hardware``'s end-cap length."""

    hw = (hardware or ArtefactHardware()).model_copy(update={"tube_diameter_mm": standard.rod_diameter_mm,
                                                             "end_cap_diameter_mm": standard.rod_diameter_mm})
    bar = standard.artefact()
    return artefact_scene(bar, ballbar_rods(bar), T_world_dumbbell, hw, background)


def flat_scene(standard, T_world_flat: Frame, background: Plane | None = None) -> Scene:
    """The flat (:class:`~fringecal.acceptance.standards.FlatStandard`) as a box: its
    measured face is z = 0 of ``T_world_flat`` (normal +z, |x| <= length/2 along its
    length, |y| <= width/2), the body -thickness <= z <= 0. One object ``flat`` (kind
    and material ``flat``), perfectly flat (built to its certificate)."""
    R = T_world_flat.R  # rows: the flat's axes in the world
    box = Box(T_world_flat.to_world([0.0, 0.0, -standard.thickness_mm / 2]), R,
              (standard.length_mm / 2, standard.width_mm / 2, standard.thickness_mm / 2))
    objects = [SceneObject("flat", "flat", "flat", (box,))]
    if background is not None:
        objects.append(SceneObject("background", "background", "background", (background,)))
    return Scene(tuple(objects))


def acceptance_scene(test: str, standards, T_world_object: Frame, hardware: ArtefactHardware | None = None,
                     background: Plane | None = None) -> Scene:
    """The scene of one acceptance position: ``test`` is ``sphere``, ``dumbbell`` or
    ``flat``, ``standards`` the :class:`~fringecal.acceptance.standards.AcceptanceStandards`
    whose object is placed by ``T_world_object``."""
    standard = getattr(standards, test, None) if test in ("sphere", "dumbbell", "flat") else None
    if standard is None:
        raise ValueError(f"no acceptance object {test!r} in the standards (have "
                         f"{', '.join(t for t in ('sphere', 'dumbbell', 'flat') if getattr(standards, t, None))})")
    if test == "sphere":
        return sphere_scene(standard, T_world_object, background)
    if test == "dumbbell":
        return dumbbell_scene(standard, T_world_object, hardware, background)
    return flat_scene(standard, T_world_object, background)
