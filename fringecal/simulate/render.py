"""Render one measurement of a scanner: camera frames plus per-pixel ground truth.

For each camera pixel an n x n grid of sub-samples over the pixel footprint (eq. 2-21
pixel centres, sub-sample rays through the full camera model) is cast into the
scene. At each hit the projector coordinate (tau_x, tau_y) follows from the full
projector model; a ray from the projector pinhole decides whether the projector
lights the point (shadows, back faces, outside the SLM). Shading, ambient light and
projector defocus are described in :mod:`fringecal.simulate.config`.

Speed: per pixel, orientation and fringe count t the sub-samples reduce to one
phasor ``Z_t = sum_s w_s P_s m_t,s exp(i t tau_s)``; every phase step is then
``I_k = ambient + A S + B Re(exp(i 2 pi k/N) Z_t)`` with ``S = sum_s w_s P_s``.
Candidate primitives are culled per image tile with bounding cones. The whole
pipeline, noise included, is one parallel numba kernel over tiles
(:mod:`fringecal.simulate.kernel`). Errors outside the calibration model (sphere form,
projector gamma, camera response, a phase field, drift during the scan, a thin-prism
lens term, a lens correction field) come in as
:class:`~fringecal.simulate.unmodelled.RenderErrors`; without them the frames are bit
for bit those of the ideal renderer. A sensor's own correction field
(:attr:`fringecal.sensor.Sensor.field`) is honoured too: camera pixels are corrected to
``m - f(m)`` before their rays are cast, and projector coordinates are the measured
ones (:mod:`.geometry`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np

from fringecal.atomic import atomic_path
from fringecal.fringe.sequence import FringeSequence
from fringecal.rig import Scanner
from fringecal.simulate import geometry as g
from fringecal.simulate.config import RenderConfig
from fringecal.simulate.kernel import LIGHT_LIT, LIGHT_NO_HIT, LIGHT_OUTSIDE, LIGHT_SHADOW, render_tiles
from fringecal.simulate.scene import Scene
from fringecal.simulate.unmodelled import (
    NO_FIELD,
    RenderErrors,
    emitted_harmonics,
    form_array,
    frame_weights,
    phase_field,
)

__all__ = ["GroundTruth", "Measurement", "render_measurement", "LIGHT_NO_HIT", "LIGHT_LIT",
           "LIGHT_SHADOW", "LIGHT_OUTSIDE"]



@dataclass(frozen=True)
class GroundTruth:
    """Per-pixel truth of one rendered measurement; maps have shape (rows, cols).

    Attributes
    ----------
    tau_x, tau_y : float64
        Projector coordinates (rad, eq. 2-22) averaged over the lit sub-samples that
        hit :attr:`object_index` (area-weighted); NaN where none is lit.
    tau_x_centre, tau_y_centre : float64
        Projector coordinates of the pixel-centre ray's hit; NaN unless it is lit.
    point : float64, shape (rows, cols, 3)
        World point (mm) hit by the pixel-centre ray; NaN where it hits nothing.
    object_index : int16
        Dominant object (most sub-samples) as an index into :attr:`object_names`;
        -1 = most sub-samples hit nothing.
    centre_object_index : int16
        Object hit by the pixel-centre ray (-1 none).
    sphere_index : int16
        Index into :attr:`sphere_ids` where the dominant object is a sphere, else -1.
    purity : float32
        Fraction of the pixel footprint (sub-samples) on the dominant object.
    lit_fraction : float32
        Fraction of the footprint that receives projector light.
    light : int8
        Pixel-centre ray: 0 no hit, 1 lit, 2 shadow (the projector's view of the point
        is blocked, by another object or by the object itself), 3 outside the SLM.
    irradiance : float64
        ``S = sum_s w_s P_s``: the frames are ``ambient_level + A S + B Re(...)``.
    ambient_level : float64
        Ambient contribution (fraction of full scale).
    object_names, object_kinds : tuple of str
        Per object index.
    sphere_ids : tuple of str
        Per sphere index.
    """

    tau_x: np.ndarray
    tau_y: np.ndarray
    tau_x_centre: np.ndarray
    tau_y_centre: np.ndarray
    point: np.ndarray
    object_index: np.ndarray
    centre_object_index: np.ndarray
    sphere_index: np.ndarray
    purity: np.ndarray
    lit_fraction: np.ndarray
    light: np.ndarray
    irradiance: np.ndarray
    ambient_level: np.ndarray
    object_names: tuple[str, ...]
    object_kinds: tuple[str, ...]
    sphere_ids: tuple[str, ...]

    _LABELS = ("object_names", "object_kinds", "sphere_ids")

    @property
    def shape(self) -> tuple[int, int]:
        return self.tau_x.shape

    def objects_of_kind(self, kind: str) -> np.ndarray:
        """Object indices of ``kind``."""
        return np.array([i for i, k in enumerate(self.object_kinds) if k == kind], int)

    def sphere_mask(self, sphere_id: str | None = None, min_purity: float = 1.0) -> np.ndarray:
        """Pixels whose dominant object is a sphere (``sphere_id`` or any), at least
        ``min_purity`` of the footprint on it and lit by the projector."""
        if sphere_id is None:
            m = self.sphere_index >= 0
        else:
            m = self.sphere_index == self.sphere_ids.index(str(sphere_id))
        return m & (self.purity >= min_purity) & np.isfinite(self.tau_x)

    def to_dict(self) -> dict:
        return {f.name: getattr(self, f.name) for f in fields(self)}

    def save(self, path) -> Path:
        """Write to ``path`` (.npz), atomically."""
        path = Path(path)
        arrays = {k: v for k, v in self.to_dict().items() if k not in self._LABELS}
        labels = {k: np.array(getattr(self, k), dtype=str) for k in self._LABELS}
        with atomic_path(path) as tmp, open(tmp, "wb") as f:
            np.savez_compressed(f, **arrays, **labels)
        return path

    @classmethod
    def load(cls, path) -> "GroundTruth":
        with np.load(Path(path)) as z:
            kw = {k: (tuple(str(x) for x in z[k]) if k in cls._LABELS else z[k]) for k in z.files}
        return cls(**kw)


@dataclass(frozen=True)
class Measurement:
    """Frames (n_frames, rows, cols) uint16 in ``sequence.frames()`` order, and truth;
    ``phase_field`` (2, rows, cols) is the phase added to tau_x, tau_y (rad) when a
    phase-field error was rendered (the truth's tau excludes it)."""

    frames: np.ndarray
    truth: GroundTruth
    sequence: FringeSequence
    scanner: str
    phase_field: np.ndarray | None = None


def render_measurement(scanner: Scanner, scene: Scene, config: RenderConfig, rng: np.random.Generator,
                       sequence: FringeSequence | None = None, errors: RenderErrors | None = None) -> Measurement:
    """Render the fringe sequence of ``scanner`` looking at ``scene``.

    Parameters
    ----------
    scanner : Scanner
        Camera and projector with their 14-parameter models and formats.
    scene : Scene
        Objects in world coordinates; every material must be in ``config.materials``.
    config : RenderConfig
    rng : numpy.random.Generator
        Source of the noise key; the same generator state gives the same frames.
    sequence : FringeSequence, default the thesis's 2 x 7 x 7
    errors : RenderErrors, optional
        Unmodelled errors (:mod:`fringecal.simulate.unmodelled`); the phase field is
        drawn from ``rng`` after the noise key, so without one the frames are unchanged.

    Returns
    -------
    Measurement
        ``frames`` uint16 (n_frames, rows, cols) and ``truth``.
    """
    seq = sequence or FringeSequence()
    missing = sorted({o.material for o in scene.objects} - set(config.materials))
    if missing:
        raise ValueError(f"scene materials {missing} are not in the render configuration "
                         f"(have {sorted(config.materials)})")
    err = errors or RenderErrors()
    cam, prj = err.sensors(scanner)
    H, W = cam.format.shape
    prims, kinds, owner = scene.packed()
    mats = np.array([[config.materials[o.material].albedo, config.materials[o.material].specular,
                      config.materials[o.material].shininess] for o in scene.objects], float).reshape(-1, 3)
    obj_sphere = scene.object_sphere_index()
    orient = np.array([0 if o == "x" else 1 for o in seq.orientations], np.int64)
    counts, fcos, fsin = frame_weights(seq, emitted_harmonics(config.offset, config.amplitude, err.projector_gamma),
                                       err.scan_drift_rad)
    optics = np.array([config.offset, config.amplitude, config.ambient, config.reference_distance_mm,
                       config.focus_distance_mm, config.blur_at_focus_mm, config.blur_per_mm])
    sigma_e = math.hypot(config.read_noise_e, config.excess_noise * config.full_well_e)
    noise = np.array([config.full_well_e, sigma_e, 1.0 / config.gain_e_per_dn, float(config.max_dn),
                      1.0 if config.shot_noise else 0.0, err.camera_linearity_error])
    key = np.uint64(rng.integers(0, 2**63, dtype=np.int64))
    field = phase_field(rng, (H, W), err.phase_field_rms_rad, err.phase_field_modes) \
        if err.phase_field_rms_rad > 0 else NO_FIELD
    cam_fmt = np.array([W, H, cam.format.width_mm, cam.format.height_mm], float)
    prj_fmt = np.array([prj.format.width_mm, prj.format.height_mm], float)

    frames = np.empty((seq.n_frames, H, W), np.uint16)
    tau = np.empty((2, H, W))
    tau_c = np.empty((2, H, W))
    point = np.empty((H, W, 3))
    ints = np.empty((3, H, W), np.int16)  # dominant object, centre object, sphere index
    fracs = np.empty((2, H, W), np.float32)  # purity, lit fraction
    light = np.empty((H, W), np.int8)
    levels = np.empty((2, H, W))  # irradiance, ambient
    render_tiles(g.sensor_pack(cam, err.camera_prism), cam_fmt, g.sensor_pack(prj, err.projector_prism), prj_fmt,
                 prims, kinds, owner, mats, obj_sphere, form_array(scene, kinds, owner, err.sphere_form),
                 config.supersampling, orient, counts, fcos, fsin, optics, noise, field, key,
                 config.tile_px, frames, tau, tau_c, point, ints, fracs, light, levels)
    truth = GroundTruth(
        tau_x=tau[0], tau_y=tau[1], tau_x_centre=tau_c[0], tau_y_centre=tau_c[1], point=point,
        object_index=ints[0], centre_object_index=ints[1], sphere_index=ints[2],
        purity=fracs[0], lit_fraction=fracs[1], light=light, irradiance=levels[0], ambient_level=levels[1],
        object_names=scene.names, object_kinds=tuple(o.kind for o in scene.objects),
        sphere_ids=scene.sphere_ids,
    )
    return Measurement(frames, truth, seq, scanner.name, None if field is NO_FIELD else field)
