"""Error sources the calibration model cannot absorb: switches of the simulation.

By default the simulated world is *ideal*: the rendered artefact is exactly its CMM
table, the scanners are exactly the 14-parameter sensors being estimated, the
projector and camera are linear and the only phase noise is white camera noise. A
:class:`SimulationErrors` block (``simulate.errors`` of a run config) switches on the
errors a real cell has and the calibration does not model; ``profile: realistic``
sets every switch not given explicitly to its documented realistic value
(:data:`REALISTIC`, sources below and in ``docs/simulator.md``)::

    simulate:
      errors:
        profile: realistic
        projector_gamma: 1.0      # explicit keys override the profile

Switches, realistic values and where the values come from (thesis = T. R. Tarvaz's
thesis, by section):

=========================  ================  ==============================================
switch                     realistic         source
=========================  ================  ==============================================
cmm_deviation, cmm_u_scale on, 1             the CMM table's own ``u_mm`` (0.010 mm); the
                                             thesis's CMM: 1 part in 500 000 (section 3.6.2)
sphere_diameter_sd_mm      0.003             assumed (touch-probe diameter uncertainty)
sphere_form_rms_mm         0.002             assumed: ISO 3290-1 G20-G40 balls are round to
                                             0.5-1 um, the matting dust adds more
artefact_temperature_c     20.5              thesis section 3.6.1: "temperature controlled to
                                             ~0.5 C"; CTE 1.9e-6 /K (same line)
artefact_use_gravity       pose-1 tilt       table 6-1 pose 1 with world +y up (the hexapod
                                             config): the platform is level to 1.5 mrad
ballbar_deviation          on                ball-bar certificate u 0.4 um (thesis 6.9.3)
projector_gamma            2.2               assumed: a projector without linearisation
camera_linearity_error     0.003             assumed, within EMVA 1288 datasheet values
                                             (~0.1-1 %)
phase_field_rms_rad        1e-4              assumed (air, projector: ~15 um at 2.5 m)
scan_drift_rad             5e-5              assumed (0.01 projector pixel in ~15 s,
                                             thesis 4.5.2's acquisition time)
session_drift_mm / _mrad   0.003 / 0.001     assumed per pose; thesis 4.5.2 sizes the
                                             hexapod's drift at ~7 um per acquisition
thin_prism_corner_px       0.2               assumed within the 0.1-0.3 px of systematic
                                             residual parametric models leave (mrcal docs;
                                             Schoeps et al., CVPR 2020)
lens_field_rms_um          0 (off)           lens manufacturing errors beyond Brown's
                                             radial/tangential terms (decentred or tilted
                                             elements, aspheric form errors), which mrcal's
                                             splined models exist to describe; no source
                                             sizes them for the thesis's optics
=========================  ================  ==============================================

Which step reads which switch (its cache key) is fixed by :data:`ARTEFACT_SWITCHES`,
:data:`RENDER_SWITCHES` and :data:`SESSION_SWITCHES`.
"""

from __future__ import annotations

import hashlib
from typing import Literal

import numpy as np
from pydantic import Field, model_validator

from fringecal.config import StrictModel

__all__ = ["ARTEFACT_SWITCHES", "REALISTIC", "RENDER_SWITCHES", "SESSION_SWITCHES", "SimulationErrors", "error_rng",
           "errors_subset", "switch_settings"]

#: Gravity in the artefact (CMM) frame for pose 1 of thesis table 6-1, world +y up.
_POSE1_GRAVITY = (-0.0007, 0.00136, -0.99999883)

#: The realistic profile: every switch's value (sources in the module notes).
REALISTIC: dict = {
    "cmm_deviation": True,
    "cmm_u_scale": 1.0,
    "sphere_diameter_sd_mm": 0.003,
    "sphere_form_rms_mm": 0.002,
    "artefact_temperature_c": 20.5,
    "artefact_cte_per_c": 1.9e-6,
    "artefact_use_gravity": _POSE1_GRAVITY,
    "artefact_use_supports": None,
    "ballbar_deviation": True,
    "projector_gamma": 2.2,
    "camera_linearity_error": 0.003,
    "phase_field_rms_rad": 1.0e-4,
    "phase_field_modes": 4,
    "scan_drift_rad": 5.0e-5,
    "session_drift_mm": 0.003,
    "session_drift_mrad": 0.001,
    "thin_prism_corner_px": 0.2,
    "lens_field_rms_um": 0.0,  # off: the preset's lens error is the thin prism (figures in docs)
}

#: Switches that decide the artefact and ball-bar as built (step ``simulate-prepare``).
ARTEFACT_SWITCHES = ("seed", "cmm_deviation", "cmm_u_scale", "sphere_diameter_sd_mm", "artefact_temperature_c",
                     "artefact_cte_per_c", "artefact_use_gravity", "artefact_use_supports", "ballbar_deviation")
#: Switches of the renderer (every rendered store).
RENDER_SWITCHES = ("seed", "sphere_form_rms_mm", "projector_gamma", "camera_linearity_error",
                   "phase_field_rms_rad", "phase_field_modes", "scan_drift_rad", "thin_prism_corner_px",
                   "lens_field_rms_um")
#: Switches of the scanners' drift over the calibration session (artefact stores only).
SESSION_SWITCHES = ("seed", "session_drift_mm", "session_drift_mrad")


class SimulationErrors(StrictModel):
    """Unmodelled error sources of the simulation; all off by default (the ideal world).

    Attributes
    ----------
    profile : {"ideal", "realistic"}
        ``realistic`` fills every switch not given with :data:`REALISTIC`.
    seed : int
        Seed of every draw below (per quantity and object, see :func:`error_rng`).
    cmm_deviation : bool
        Sphere centres as built = CMM table + N(0, (cmm_u_scale * u_mm)^2) per coordinate.
    cmm_u_scale : float
        Factor on the table's ``u_mm`` (also on the ball-bar's).
    sphere_diameter_sd_mm : float
        Standard deviation of each sphere's true diameter about its table value.
    sphere_form_rms_mm : float
        RMS over the sphere of its radial form error (degree-2 and -3 zonal terms).
    artefact_temperature_c : float or None
        True artefact temperature: the as-built artefact is the CMM table scaled by
        ``artefact_cte_per_c (T - 20 C)`` about its centroid, whatever thermal
        correction the run applies (that is the run's model). None: the run's model.
    artefact_cte_per_c : float
        True effective CTE of the artefact.
    artefact_use_gravity : (3,) or None
        Gravity in the artefact frame during acquisition (None: as on the CMM).
    artefact_use_supports : str or None
        Supports during acquisition (``"5:xyz,1:yz,14:z"`` form; None: the CMM's).
    ballbar_deviation : bool
        Ball-bar length as built = certificate + N(0, (cmm_u_scale * u_mm)^2).
    projector_gamma : float
        Emitted intensity ~ commanded grey level ** gamma (1: linear).
    camera_linearity_error : float
        ``e`` of the camera response ``I + 4 e I (1 - I)`` (fractions of full scale).
    phase_field_rms_rad : float
        RMS of a smooth random field added to tau_x and tau_y per measurement.
    phase_field_modes : int
        Number of 2-D cosine modes of that field (per orientation).
    scan_drift_rad : float
        Pattern shift (rad of tau) from the first to the last frame of a sequence.
    session_drift_mm, session_drift_mrad : float
        Per-pose step of each scanner's random walk (per axis) over the session.
    thin_prism_corner_px : float
        Thin-prism lens term of every camera and projector, sized by its image
        displacement at the corner in pixels of the sensor file's native format.
    lens_field_rms_um : float
        A smooth degree-6 correction field (:mod:`fringecal.lens.field`) of every true
        camera and projector, 45 coefficients drawn with equal variance per sensor,
        scaled to this RMS displacement (micrometres on the image plane) over the
        format: what a real lens adds beyond Brown's radial and tangential terms
        (manufacturing errors; cf. mrcal's splined models). About 19/45 of it is what
        the calibration's degree-4 ``field`` model can absorb.
    """

    profile: Literal["ideal", "realistic"] = "ideal"
    seed: int = 1
    cmm_deviation: bool = False
    cmm_u_scale: float = Field(1.0, ge=0)
    sphere_diameter_sd_mm: float = Field(0.0, ge=0)
    sphere_form_rms_mm: float = Field(0.0, ge=0, le=0.1)
    artefact_temperature_c: float | None = None
    artefact_cte_per_c: float = 1.9e-6
    artefact_use_gravity: tuple[float, float, float] | None = None
    artefact_use_supports: str | None = None
    ballbar_deviation: bool = False
    projector_gamma: float = Field(1.0, ge=0.25, le=4.0)
    camera_linearity_error: float = Field(0.0, ge=-0.25, le=0.25)
    phase_field_rms_rad: float = Field(0.0, ge=0)
    phase_field_modes: int = Field(4, ge=1, le=32)
    scan_drift_rad: float = 0.0
    session_drift_mm: float = Field(0.0, ge=0)
    session_drift_mrad: float = Field(0.0, ge=0)
    thin_prism_corner_px: float = Field(0.0, ge=0)
    lens_field_rms_um: float = Field(0.0, ge=0)

    @model_validator(mode="before")
    @classmethod
    def _fill_profile(cls, data):
        if isinstance(data, dict) and data.get("profile") == "realistic":
            return {**REALISTIC, **data}
        return data

    def switches(self) -> dict:
        """Every switch's value (JSON types), without ``profile`` and ``seed``."""
        return self.model_dump(mode="json", exclude={"profile", "seed"})

    @property
    def is_ideal(self) -> bool:
        """True when no switch is on (the rendered world is the model's)."""
        return not (self.cmm_deviation or self.ballbar_deviation or self.sphere_diameter_sd_mm
                    or self.sphere_form_rms_mm or self.artefact_temperature_c is not None
                    or self.artefact_use_gravity is not None or self.artefact_use_supports is not None
                    or self.projector_gamma != 1.0 or self.camera_linearity_error or self.phase_field_rms_rad
                    or self.scan_drift_rad or self.session_drift_mm or self.session_drift_mrad
                    or self.thin_prism_corner_px or self.lens_field_rms_um)

    @property
    def profile_name(self) -> str:
        """The profile to quote with a result: ``ideal`` (no switch on), ``realistic``
        (exactly the preset, any seed), ``realistic+custom`` (the preset with changes)
        or ``custom``."""
        if self.is_ideal:
            return "ideal"
        if self.switches() == SimulationErrors(profile="realistic").switches():
            return "realistic"
        return "realistic+custom" if self.profile == "realistic" else "custom"


def error_rng(seed: int, *labels: str) -> np.random.Generator:
    """An independent generator per (seed, labels), e.g. ``("form", "artefact", "7")``:
    switching one error source on or off never changes another's draws.

    >>> a = error_rng(1, "centres").normal()
    >>> bool(a == error_rng(1, "centres").normal()), bool(a == error_rng(1, "diameters").normal())
    (True, False)
    """
    words = [int.from_bytes(hashlib.sha256(str(s).encode()).digest()[:8], "little") for s in labels]
    return np.random.default_rng(np.random.SeedSequence([int(seed), *words]))


def switch_settings(fields) -> tuple[str, ...]:
    """Dotted run-config paths of ``fields`` (a step's cache-key settings)."""
    return tuple(f"simulate.errors.{f}" for f in fields)


def errors_subset(view, fields) -> SimulationErrors:
    """A :class:`SimulationErrors` with ``fields`` taken from ``view`` (a step's
    settings view of ``simulate.errors`` or a full model) and the rest off."""
    return SimulationErrors(**{f: getattr(view, f) for f in fields})
