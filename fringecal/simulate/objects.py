"""Simulated objects to *measure* with a finished calibration (``simulate.objects``).

A calibration exists to measure: these are the objects a simulation puts in front of
the scanners after the calibration measurements, each at a pose of its own
(``T_world_object``), recorded by every scanner that sees enough of it:

* ``panel``: a free-form curved panel (:class:`~fringecal.simulate.scene.Panel`), the
  sheet ``z = x^2 / (2 Rx) + y^2 / (2 Ry) + cubic`` over |x| <= a, |y| <= b of its own
  frame, in the matt ``flat`` material of the acceptance test by default;
* ``artefact``: the calibration artefact itself (as built, with rods and end caps) at
  a pose that is none of the calibration poses.

``fringecal simulate`` writes each object as ``objects/<name>/<scanner>/`` image stacks
in the data set and its truth as ``objects/<name>.json`` in the truth folder
(:func:`object_truth`); :func:`render_object_stores` renders one object straight into
decoded stores ``DIR/<scanner>.zarr`` (the format of a run's ``measurements/*.zarr``)
for tests and benchmarks, without image files.

Which scanners record an object (:func:`plan_object`): a scanner records it when at
least ``min_view_fraction`` of the object's sample points lie in front of and inside
both its camera and its projector image, and (panel) the sheet there faces both
(same side). The samples are a 21 x 21 grid over the panel, or the artefact's sphere
centres. Occlusion is not considered. An object no scanner sees enough of is refused
(a configured object is never dropped silently); the others are reported as skipped.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Literal, Optional, Union

import numpy as np
from pydantic import Field, TypeAdapter, field_validator

from fringecal.atomic import write_json
from fringecal.config import StrictModel
from fringecal.frames import POSE_COLUMNS, Frame
from fringecal.fringe.decode import DecodeSettings
from fringecal.fringe.sequence import FringeSequence, SequenceConfig
from fringecal.rig import Rig, scaled_rig
from fringecal.simulate.config import AcquisitionConfig, RenderConfig
from fringecal.simulate.measurement import simulate_measurement
from fringecal.simulate.scene import Panel, Scene, SceneObject
from fringecal.simulate.scenes import artefact_scene
from fringecal.simulate.world import render_errors

__all__ = ["ObjectPose", "PanelObject", "ArtefactObject", "SimulatedObject", "ObjectPlan", "parse_object",
           "object_pose", "panel_of", "object_scene", "view_fractions", "plan_object", "object_truth",
           "truth_distance", "panel_from_truth", "render_object_stores", "PANEL_SAMPLES",
           "DEFAULT_MIN_VIEW_FRACTION", "OBJECT_SEED"]

#: The panel's visibility samples per side (a PANEL_SAMPLES^2 grid).
PANEL_SAMPLES = 21
#: A scanner that sees less than this fraction of an object's samples does not record it.
DEFAULT_MIN_VIEW_FRACTION = 0.05
#: Default noise seed of object measurements (the acceptance test uses 98, the ball-bar 99).
OBJECT_SEED = 97

_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.+-]*$")


class ObjectPose(StrictModel):
    """``T_world_object``: origin (mm) and thesis angles (rad, eq. 2-6), with
    ``x_world = R(omega, phi, kappa)^T x_local + t`` (the poses' convention)."""

    tx_mm: float
    ty_mm: float
    tz_mm: float
    omega_rad: float = 0.0
    phi_rad: float = 0.0
    kappa_rad: float = 0.0

    def frame(self) -> Frame:
        return Frame.from_params([getattr(self, c) for c in POSE_COLUMNS])

    @classmethod
    def of(cls, frame: Frame) -> "ObjectPose":
        return cls(**{c: float(v) for c, v in zip(POSE_COLUMNS, frame.params)})


class _Object(StrictModel):
    name: str
    pose: ObjectPose
    min_view_fraction: float = Field(DEFAULT_MIN_VIEW_FRACTION, ge=0, le=1)
    seed: int = OBJECT_SEED

    @field_validator("name")
    @classmethod
    def _folder_name(cls, v):
        if not _NAME.match(v):
            raise ValueError(f"object name {v!r} must be a folder name: letters, digits and _ . + - "
                             "(not starting with . + - or _)")
        return v


class PanelObject(_Object):
    """A free-form curved panel (:class:`~fringecal.simulate.scene.Panel`).

    ``size_mm`` is its full extent (2a, 2b) along its x and y axes; ``radius_x_mm``,
    ``radius_y_mm`` the radii of curvature at the vertex (None: straight; negative:
    bending towards -z); ``cubic_mm`` the heights at the edge of the cubic terms
    (u^3, u^2 v, u v^2, v^3; u = x/a, v = y/b); ``material`` a material of the render
    configuration. Its +z axis is the side it is meant to be measured from.
    """

    kind: Literal["panel"] = "panel"
    size_mm: tuple[float, float] = (600.0, 400.0)
    radius_x_mm: Optional[float] = 2000.0
    radius_y_mm: Optional[float] = 3000.0
    cubic_mm: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)
    material: str = "flat"

    @field_validator("size_mm")
    @classmethod
    def _size(cls, v):
        if min(v) <= 0:
            raise ValueError(f"size_mm {list(v)}: both sides must be positive")
        return v

    @field_validator("radius_x_mm", "radius_y_mm")
    @classmethod
    def _radius(cls, v):
        if v is not None and v == 0:
            raise ValueError("a radius of curvature cannot be 0 (None: straight)")
        return v

    @property
    def curvature(self) -> tuple[float, float]:
        """(kx, ky) in 1/mm."""
        return tuple(0.0 if r is None else 1.0 / r for r in (self.radius_x_mm, self.radius_y_mm))


class ArtefactObject(_Object):
    """The calibration artefact (as built: spheres, rods, end caps) at ``pose``
    (``T_world_artefact``, the artefact table's frame to the world)."""

    kind: Literal["artefact"] = "artefact"


#: One entry of ``simulate.objects`` (chosen by its ``kind``).
SimulatedObject = Annotated[Union[PanelObject, ArtefactObject], Field(discriminator="kind")]
_ADAPTER = TypeAdapter(SimulatedObject)


def parse_object(spec) -> PanelObject | ArtefactObject:
    """A :data:`SimulatedObject` from a model or a mapping (``simulate.objects`` entry)."""
    if isinstance(spec, (PanelObject, ArtefactObject)):
        return spec
    return _ADAPTER.validate_python(spec)


def object_pose(spec) -> Frame:
    """``T_world_object`` of an object."""
    return parse_object(spec).pose.frame()


def panel_of(spec: PanelObject) -> Panel:
    """The panel primitive of a panel object, placed at its pose."""
    T = spec.pose.frame()
    a, b = spec.size_mm[0] / 2, spec.size_mm[1] / 2
    return Panel(T.t, T.R, (a, b), spec.curvature, spec.cubic_mm)


def object_scene(spec, artefact=None, rods=None, hardware=None) -> Scene:
    """The scene of one object: a panel (object ``panel:<name>``, kind ``panel``), or
    :func:`~fringecal.simulate.scenes.artefact_scene` of ``artefact`` (needed then;
    ``rods`` and ``hardware`` optional) at the object's pose."""
    spec = parse_object(spec)
    if spec.kind == "panel":
        return Scene((SceneObject(f"panel:{spec.name}", "panel", spec.material, (panel_of(spec),)),))
    if artefact is None:
        raise ValueError(f"object {spec.name!r}: an artefact object needs the artefact definition")

    return artefact_scene(artefact, rods, spec.pose.frame(), hardware)


def _samples(spec, artefact) -> tuple[np.ndarray, np.ndarray | None]:
    """World sample points (n, 3) of an object and, for a panel, its normals (n, 3)."""
    if spec.kind == "panel":
        panel = panel_of(spec)
        u = np.linspace(-1.0, 1.0, PANEL_SAMPLES)
        x, y = np.meshgrid(u * panel.half_size[0], u * panel.half_size[1], indexing="ij")
        return panel.surface_points(x, y).reshape(-1, 3), panel.normals(x, y).reshape(-1, 3)
    if artefact is None:
        raise ValueError(f"object {spec.name!r}: an artefact object needs the artefact definition")
    return spec.pose.frame().to_world(artefact.centres), None


def view_fractions(spec, rig, artefact=None) -> dict[str, float]:
    """Per scanner of ``rig``, the fraction of the object's sample points (see the
    module notes) in view of both its camera and its projector."""
    spec = parse_object(spec)
    points, normals = _samples(spec, artefact)
    out = {}
    for s in rig.scanners:
        seen = s.camera.in_view(points) & s.projector.in_view(points)
        if normals is not None:
            to_cam = np.einsum("ij,ij->i", normals, s.camera.pinhole - points)
            to_prj = np.einsum("ij,ij->i", normals, s.projector.pinhole - points)
            seen &= (to_cam * to_prj) > 0
        out[s.name] = float(seen.mean())
    return out


@dataclass(frozen=True)
class ObjectPlan:
    """What is recorded of one object: its spec, ``T_world_object``, scene, the view
    fraction of every scanner, and the scanners that record it (rig order)."""

    spec: PanelObject | ArtefactObject
    T_world_object: Frame
    scene: Scene
    fractions: dict
    recorders: tuple[str, ...]
    skipped: dict = field(default_factory=dict)

    def describe_skipped(self) -> list[str]:
        """One line per scanner that does not record the object."""
        return [f"object {self.spec.name}: {s} sees {100 * f:.0f} % of it (< {100 * self.spec.min_view_fraction:g} %): "
                "not recorded" for s, f in self.skipped.items()]


def plan_object(spec, rig, artefact=None, rods=None, hardware=None) -> ObjectPlan:
    """The :class:`ObjectPlan` of ``spec`` in front of ``rig`` (the true sensors).

    Raises
    ------
    ValueError
        When no scanner sees ``min_view_fraction`` of the object; the message names it
        and every scanner's fraction.
    """
    spec = parse_object(spec)
    fractions = view_fractions(spec, rig, artefact)
    recorders = tuple(s for s, f in fractions.items() if f >= spec.min_view_fraction and f > 0)
    if not recorders:
        seen = ", ".join(f"{s} {100 * f:.0f} %" for s, f in fractions.items())
        raise ValueError(f"simulate.objects: object {spec.name!r} ({spec.kind}) at {spec.pose.frame().params.round(4).tolist()} "
                         f"is seen by no scanner (view fractions: {seen}; need {100 * spec.min_view_fraction:g} %); move it "
                         "into a scanner's measurement volume")
    skipped = {s: f for s, f in fractions.items() if s not in recorders}
    return ObjectPlan(spec, spec.pose.frame(), object_scene(spec, artefact, rods, hardware), fractions, recorders,
                      skipped)


def object_truth(plan: ObjectPlan, artefact=None, camera_width_px: int | None = None) -> dict:
    """The truth document of an object (JSON-native; ``objects/<name>.json`` of a truth
    folder): ``name``, ``kind``, ``T_world_object`` (the six pose columns), the
    convention, ``scanners`` (view fraction, recorded or not), ``seed``,
    ``min_view_fraction``, ``camera_width_px`` and, per kind, ``panel`` (its
    parameters, the surface formula) or ``spheres`` (every sphere's id, world centre
    ``x_mm, y_mm, z_mm`` and ``diameter_mm``, of the artefact as built)."""
    spec = plan.spec
    doc = {"name": spec.name, "kind": spec.kind,
           "T_world_object": {c: float(v) for c, v in zip(POSE_COLUMNS, plan.T_world_object.params)},
           "convention": "x_world = R(omega, phi, kappa)^T x_object + t (thesis eq. 2-6)",
           "scanners": {s: {"view_fraction": f, "recorded": s in plan.recorders} for s, f in plan.fractions.items()},
           "min_view_fraction": spec.min_view_fraction, "seed": spec.seed, "camera_width_px": camera_width_px}
    if spec.kind == "panel":
        panel = panel_of(spec)
        doc["panel"] = {"size_mm": list(spec.size_mm), "half_size_mm": panel.half_size.tolist(),
                        "radius_x_mm": spec.radius_x_mm, "radius_y_mm": spec.radius_y_mm,
                        "curvature_per_mm": panel.curvature.tolist(), "cubic_mm": list(spec.cubic_mm),
                        "material": spec.material,
                        "surface": "z = kx x^2/2 + ky y^2/2 + c30 u^3 + c21 u^2 v + c12 u v^2 + c03 v^3, u = x/a, "
                                   "v = y/b, |x| <= a, |y| <= b (object frame; (kx, ky) = curvature_per_mm, "
                                   "(a, b) = half_size_mm, (c30, c21, c12, c03) = cubic_mm)"}
    else:
        centres = plan.T_world_object.to_world(artefact.centres)
        doc["spheres"] = [{"sphere_id": str(i), "x_mm": float(c[0]), "y_mm": float(c[1]), "z_mm": float(c[2]),
                           "diameter_mm": float(2 * r)} for i, c, r in zip(artefact.ids, centres, artefact.radii)]
    return doc


def panel_from_truth(doc: dict) -> Panel:
    """The :class:`~fringecal.simulate.scene.Panel` of a panel's truth document."""
    T = Frame.from_params([doc["T_world_object"][c] for c in POSE_COLUMNS])
    p = doc["panel"]
    return Panel(T.t, T.R, p["half_size_mm"], p["curvature_per_mm"], p["cubic_mm"])


def truth_distance(doc: dict, points_world) -> np.ndarray:
    """Distance (n,) mm of world points (n, 3) from an object's true surface: signed
    from the panel's unbounded surface (+ on its +z side; :meth:`Panel.distance`), or
    from the nearest sphere surface of the artefact (+ outside; points on rods or end
    caps are not on any sphere and get their distance to the nearest one)."""
    p = np.asarray(points_world, float).reshape(-1, 3)
    if doc["kind"] == "panel":
        return panel_from_truth(doc).distance(p)[0]
    c = np.array([[s["x_mm"], s["y_mm"], s["z_mm"]] for s in doc["spheres"]])
    r = np.array([s["diameter_mm"] / 2 for s in doc["spheres"]])
    d = np.linalg.norm(p[:, None, :] - c[None], axis=-1) - r[None]
    return d[np.arange(len(p)), np.argmin(np.abs(d), axis=1)]


def render_object_stores(rig_true, object_spec, out_dir, render_config: RenderConfig | None = None,
                         seed: int | None = None, camera_width_px: int | None = None, *, sequence=None,
                         decode=None, artefact=None, rods=None, hardware=None, errors=None,
                         truth_dir=None) -> dict[str, Path]:
    """Render one object's measurement straight into decoded stores ``out_dir/<scanner>.zarr``.

    The stores are those of a run's ``measurements/*.zarr`` (decoded ``tau_x``,
    ``tau_y``, ``modulation_*``, ``phase_error_*``, ``texture``, ``valid``, provenance
    attributes plus ``object`` and ``kind``), written atomically; no image file is
    written. Scanners that see too little of the object are skipped (see the module
    notes); an object no scanner sees raises ValueError.

    Parameters
    ----------
    rig_true : Rig
        The true sensors in the world frame (e.g. a data set's truth ``sensors.csv``);
        scanners record at these placements.
    object_spec : PanelObject, ArtefactObject or mapping
        One ``simulate.objects`` entry.
    out_dir : path
        Folder of the stores (created).
    render_config : RenderConfig, optional
        Optics and noise (default :class:`RenderConfig`).
    seed : int, optional
        Noise seed (default the object's ``seed``); each scanner's noise is drawn from
        (seed, ``"<name>-<scanner>"``).
    camera_width_px : int, optional
        Resample the cameras to this width (default: as in ``rig_true``).
    sequence : SequenceConfig or FringeSequence, optional
        Fringe sequence (default the thesis's 2 x 7 x 7).
    decode : DecodeSettings, optional
    artefact, rods, hardware : optional
        The artefact (as built), its rods table and :class:`ArtefactHardware`; the
        artefact is required for an artefact object (default rods: none).
    errors : SimulationErrors, optional
        Unmodelled errors (:mod:`fringecal.simulate.errors`); the artefact's sphere form
        is drawn as for its calibration measurements (the same spheres).
    truth_dir : path, optional
        Also write the renderer's per-pixel truth stores ``truth_dir/<scanner>.zarr``
        and the truth document ``truth_dir/<name>.json`` (:func:`object_truth`).

    Returns
    -------
    dict
        scanner name -> store path, for the scanners that recorded the object.
    """

    spec = parse_object(object_spec)
    rig: Rig = scaled_rig(rig_true, camera_width_px) if camera_width_px is not None else rig_true
    plan = plan_object(spec, rig, artefact, rods, hardware)
    if isinstance(sequence, FringeSequence):
        sequence = SequenceConfig(fringe_counts=list(sequence.fringe_counts), n_steps=sequence.n_steps,
                                  orientations=list(sequence.orientations))
    acquisition = AcquisitionConfig(render=render_config or RenderConfig(), sequence=sequence or SequenceConfig(),
                                    seed=spec.seed if seed is None else seed)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    if truth_dir is not None:
        truth_dir = Path(truth_dir)
        truth_dir.mkdir(parents=True, exist_ok=True)
        write_json(truth_dir / f"{spec.name}.json", object_truth(plan, artefact, rig.scanners[0].camera.format.width_px))
    stores = {}
    for name in plan.recorders:
        scanner = rig.scanner(name)
        errs = None
        if errors is not None:
            errs = render_errors(errors, scanner, plan.T_world_object, "artefact" if spec.kind == "artefact"
                                 else spec.kind, plan.scene.sphere_ids)
        path = out_dir / f"{name}.zarr"
        simulate_measurement(f"{spec.name}-{name}", scanner, plan.scene, acquisition, decode or DecodeSettings(),
                             path, None if truth_dir is None else truth_dir / f"{name}.zarr",
                             {"object": spec.name, "kind": spec.kind}, errs)
        stores[name] = path
    return stores
