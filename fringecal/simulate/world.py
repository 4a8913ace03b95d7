"""The simulated world as it really is, when the error switches of
:class:`~fringecal.simulate.errors.SimulationErrors` are on: the artefact and the
ball-bar as built, the form of their spheres, the scanners as they drift over a
calibration session, and the per-measurement :class:`RenderErrors` of a scanner.

The run keeps fitting and adjusting against the CMM table (with the corrections it
is configured with); only the renderer sees what this module builds.

* Artefact as built: the CMM table's centres plus N(0, (cmm_u_scale u_mm)^2) per
  coordinate, its diameters plus N(0, sphere_diameter_sd_mm^2), then the corrections
  for the *true* state: the configured sag and thermal corrections, except that a
  true ``artefact_temperature_c`` scales about the centroid by
  ``artefact_cte_per_c (T - 20 C)`` and a true ``artefact_use_gravity`` /
  ``artefact_use_supports`` replaces the use condition of the sag correction
  (:func:`fringecal.engineering.corrections.apply_corrections`, the rig's rods).
* Ball-bar as built: its length differs from the certificate by
  N(0, (cmm_u_scale u)^2), u the certificate table's ``u_mm``; both spheres move
  along the bar by half of it.
* Sphere form: two degree-2 and two degree-3 zonal terms ``a P_l(u . n)`` per sphere
  with random body-fixed axes, scaled to exactly ``sphere_form_rms_mm`` RMS over the
  sphere (addition theorem: the mean of ``P_l(u . n) P_l(w . n)`` over the sphere is
  ``P_l(u . w) / (2 l + 1)``); they turn with the artefact's pose.
* Session drift: each scanner (camera and projector together) moves rigidly, about
  the midpoint of its two pinholes, by a random walk over the poses in acquisition
  order (zero at the first pose; per pose N(0, session_drift_mm^2) per axis and
  N(0, session_drift_mrad^2) per rotation axis).
* Lens field: every true camera and projector gets a degree-6 correction field of RMS
  ``lens_field_rms_um`` over its format (:func:`~fringecal.simulate.unmodelled.lens_field`),
  drawn from the seed and the sensor's name; the renderer gets it through
  :func:`render_errors`, the control-point simulator through :func:`with_lens_fields`.
  The run's rig never holds it.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
from numpy.polynomial import legendre

from fringecal.artefact import Artefact, load_artefact
from fringecal.config import ConfigError
from fringecal.engineering.corrections import ArtefactCorrections, SagSettings, ThermalSettings, apply_corrections
from fringecal.rig import Rig, Scanner, load_rig
from fringecal.rotation import angles_from_matrix
from fringecal.simulate.errors import SimulationErrors, error_rng
from fringecal.simulate.unmodelled import RenderErrors, lens_field, thin_prism

__all__ = ["FORM_DEGREES", "as_built_artefact", "as_built_ballbar", "drifted_scanner", "form_rms", "native_formats",
           "render_errors", "sensor_lens_field", "session_displacement", "sphere_form_terms", "with_lens_fields"]

#: Degrees of the zonal form terms of each sphere.
FORM_DEGREES = (2, 2, 3, 3)


def _true_corrections(sim, errors: SimulationErrors):
    """(corrections, temperature) of the artefact's true state."""

    corr = sim.artefact_corrections or ArtefactCorrections()
    temperature = sim.temperature_c
    if errors.artefact_temperature_c is not None:
        corr = corr.model_copy(update={"thermal": ThermalSettings(cte_per_c=errors.artefact_cte_per_c)})
        temperature = errors.artefact_temperature_c
    if errors.artefact_use_gravity is not None or errors.artefact_use_supports is not None:
        sag = corr.sag
        if sag is None:
            rods = sim.rig_config().rods
            if rods is None:
                raise ConfigError(f"{sim.rig}: simulate.errors.artefact_use_gravity/_supports need the rig's rods")
            sag = SagSettings(rods=rods)
        update = {}
        if errors.artefact_use_gravity is not None:
            update["use_gravity"] = tuple(errors.artefact_use_gravity)
        if errors.artefact_use_supports is not None:
            update["use_supports"] = errors.artefact_use_supports
        corr = corr.model_copy(update={"sag": sag.model_copy(update=update)})
    return corr, temperature


def as_built_artefact(sim, errors: SimulationErrors) -> Artefact:
    """The artefact the renderer places (module notes); ``sim.artefact()`` itself
    when no artefact switch is on."""

    if not (errors.cmm_deviation or errors.sphere_diameter_sd_mm or errors.artefact_temperature_c is not None
            or errors.artefact_use_gravity is not None or errors.artefact_use_supports is not None):
        return sim.artefact()
    table = load_artefact(sim.rig_config().artefact)
    centres, diameters = table.centres, table.diameters
    if errors.cmm_deviation:
        z = error_rng(errors.seed, "cmm-centres").standard_normal(centres.shape)
        centres = centres + (errors.cmm_u_scale * table.u)[:, None] * z
    if errors.sphere_diameter_sd_mm:
        z = error_rng(errors.seed, "diameters").standard_normal(len(table))
        diameters = diameters + errors.sphere_diameter_sd_mm * z
    built = Artefact(table.ids, centres, diameters, table.u, table.name)
    corrections, temperature = _true_corrections(sim, errors)
    return apply_corrections(built, corrections, temperature)


def as_built_ballbar(certificate: Artefact, errors: SimulationErrors) -> Artefact:
    """The ball-bar the renderer places: the certificate's, or with the length
    deviation of the module notes when ``ballbar_deviation`` is on."""
    if not errors.ballbar_deviation:
        return certificate
    c = certificate.centres
    axis = (c[1] - c[0]) / np.linalg.norm(c[1] - c[0])
    u = errors.cmm_u_scale * float(np.sqrt(np.mean(certificate.u ** 2)))
    delta = u * error_rng(errors.seed, "ballbar-length").standard_normal()
    moved = c.copy()
    moved[0] -= delta / 2 * axis
    moved[1] += delta / 2 * axis
    return Artefact(certificate.ids, moved, certificate.diameters, certificate.u, certificate.name)


def form_rms(terms: np.ndarray) -> float:
    """RMS over the sphere of the radial deviation ``sum a P_l(u . n)`` of ``terms``
    (rows ux, uy, uz, a, l), exactly, by the addition theorem."""
    terms = np.asarray(terms, float)
    total = 0.0
    for i in range(len(terms)):
        for j in range(len(terms)):
            if terms[i, 4] == terms[j, 4]:
                degree = int(terms[i, 4])
                cos = float(np.clip(terms[i, :3] @ terms[j, :3], -1.0, 1.0))
                total += terms[i, 3] * terms[j, 3] * legendre.legval(cos, [0] * degree + [1]) / (2 * degree + 1)
    return float(np.sqrt(total))


def sphere_form_terms(seed: int, label: str, sphere_id: str, rms_mm: float) -> np.ndarray:
    """(len(FORM_DEGREES), 5) body-frame form terms of one sphere (module notes)."""
    rng = error_rng(seed, "form", label, sphere_id)
    axes = rng.standard_normal((len(FORM_DEGREES), 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    terms = np.column_stack([axes, rng.standard_normal(len(FORM_DEGREES)), FORM_DEGREES])
    terms[:, 3] *= rms_mm / form_rms(terms)
    return terms


def session_displacement(errors: SimulationErrors, scanner: str, poses: list[str]) -> np.ndarray:
    """(6,) walk of ``scanner`` at the last of ``poses`` (acquisition order up to the
    measurement's pose): translation mm, then rotation vector rad."""
    sd = np.array([errors.session_drift_mm] * 3 + [errors.session_drift_mrad * 1e-3] * 3)
    steps = [error_rng(errors.seed, "session", scanner, p).standard_normal(6) for p in poses[1:]]
    return sd * np.sum(steps, axis=0) if steps else np.zeros(6)


def _rotation(w) -> np.ndarray:
    """Rodrigues: the rotation by the rotation vector ``w`` (acting on world points)."""
    angle = float(np.linalg.norm(w))
    if angle == 0.0:
        return np.eye(3)
    k = np.asarray(w, float) / angle
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


def drifted_scanner(scanner: Scanner, displacement) -> Scanner:
    """``scanner`` moved rigidly by ``displacement`` (translation mm, rotation vector
    rad about the midpoint of its pinholes): a world point x goes to
    ``Rd (x - m) + m + t``, each sensor's pinhole likewise, its rotation to ``R Rd^T``."""
    d = np.asarray(displacement, float)
    if not d.any():
        return scanner
    Rd = _rotation(d[3:])
    mid = (scanner.camera.pinhole + scanner.projector.pinhole) / 2

    def move(sensor):
        p = sensor.params.copy()
        p[0:3] = Rd @ (sensor.pinhole - mid) + mid + d[:3]
        p[3:6] = angles_from_matrix(sensor.R @ Rd.T, near=sensor.angles)
        return sensor.with_params(p)

    return replace(scanner, camera=move(scanner.camera), projector=move(scanner.projector))


def native_formats(sensors_path) -> dict:
    """Sensor name -> format as the rig's sensors file gives it (before any resampling)."""
    return {s.name: s.format for s in load_rig(Path(sensors_path)).sensors}


def sensor_lens_field(errors: SimulationErrors, sensor):
    """The true lens field of ``sensor`` (None when ``lens_field_rms_um`` is off): the
    same for a sensor of any pixel count (the field lives on the format's mm)."""
    if not errors.lens_field_rms_um:
        return None
    return lens_field(sensor.format, errors.lens_field_rms_um, error_rng(errors.seed, "lens-field", sensor.name))


def with_lens_fields(rig: Rig, errors: SimulationErrors) -> Rig:
    """``rig`` (a truth rig) with every sensor's true lens field attached, for simulators
    that observe through :class:`~fringecal.sensor.Sensor` (e.g. the control points)."""
    if not errors.lens_field_rms_um:
        return rig

    def attach(s):
        return s.with_field(sensor_lens_field(errors, s))

    return replace(rig, scanners=tuple(replace(sc, camera=attach(sc.camera), projector=attach(sc.projector))
                                       for sc in rig.scanners))


def render_errors(errors: SimulationErrors, scanner: Scanner, T_world_object=None, label: str = "artefact",
                  sphere_ids=(), native: dict | None = None) -> RenderErrors | None:
    """The :class:`RenderErrors` of one measurement of ``scanner``; None when no
    render switch is on (the renderer's ideal path).

    ``T_world_object`` places the object whose spheres ``sphere_ids`` get form errors
    (``label`` keeps the artefact's and the ball-bar's draws apart); ``native`` maps
    sensor names to the formats the thin prism's pixels refer to (default the
    sensors' own).
    """
    if not (errors.sphere_form_rms_mm or errors.projector_gamma != 1.0 or errors.camera_linearity_error
            or errors.phase_field_rms_rad or errors.scan_drift_rad or errors.thin_prism_corner_px
            or errors.lens_field_rms_um):
        return None
    form = {}
    if errors.sphere_form_rms_mm and T_world_object is not None:
        R = T_world_object.R
        for sid in sphere_ids:
            terms = sphere_form_terms(errors.seed, label, str(sid), errors.sphere_form_rms_mm)
            terms[:, :3] = terms[:, :3] @ R  # body-fixed axes to the world (x_world = R^T x_local)
            form[str(sid)] = terms
    prisms = []
    for sensor in scanner.sensors:
        fmt = (native or {}).get(sensor.name, sensor.format)
        angle = error_rng(errors.seed, "prism", sensor.name).uniform(0.0, 2 * np.pi)
        prisms.append(thin_prism(fmt, errors.thin_prism_corner_px, angle) if errors.thin_prism_corner_px
                      else (0.0, 0.0))
    return RenderErrors(projector_gamma=errors.projector_gamma, camera_linearity_error=errors.camera_linearity_error,
                        scan_drift_rad=errors.scan_drift_rad, phase_field_rms_rad=errors.phase_field_rms_rad,
                        phase_field_modes=errors.phase_field_modes, sphere_form=form, camera_prism=prisms[0],
                        projector_prism=prisms[1], camera_field=sensor_lens_field(errors, scanner.camera),
                        projector_field=sensor_lens_field(errors, scanner.projector))
