"""Kernel inputs of the unmodelled errors (:mod:`fringecal.simulate.errors`), one
measurement at a time: :class:`RenderErrors` and the arrays :func:`render_measurement
<fringecal.simulate.render.render_measurement>` hands to the kernel.

Projector gamma. The commanded grey level of a fringe is ``v = (A + B cos psi) /
(A + B)`` (1 at the brightest fringe), the projector emits ``v ** gamma``, and the
emitted pattern is rescaled so that its mean and fundamental stay ``A`` and ``B``
(the render configuration's light levels are those of the emitted fringes; gamma
only adds harmonics)::

    E(psi) = A + sum_h b_h cos(h psi),   b_h = B g_h / g_1,   g_h = Fourier cosine
                                                              coefficients of v^gamma

:func:`emitted_harmonics` keeps h = 1..H, the smallest H whose neglected tail sum
|b_h| is below 1e-6 of full scale (0.004 DN at 12 bits). Each sub-sample then adds
phasors of the counts h t (defocus factor of count h t), and frame k of count t is
``base + sum_h b_h Re(exp(i h delta_k) Z_ht)``. The N-step estimator
``arg sum_k I_k exp(-i delta_k)`` keeps harmonic h only if h = +-1 (mod N): for the
thesis's N = 7, harmonics 2..5 cancel exactly, 6 and 8 alias onto the fundamental,
giving the phase error ``arg(b_1 + b_6 exp(-7 i phi) + b_8 exp(7 i phi) + ...)``,
a ripple of 7 periods per fringe.

Drift during a scan shifts the pattern by ``psi_f = scan_drift f / (n_frames - 1)``
(rad of tau) at frame f of the sequence (both orientations), i.e. the phase
``t psi_f`` is added to every harmonic's step phase: :func:`frame_weights`.

A lens field (:func:`lens_field`) is a degree-6 :class:`~fringecal.lens.field.CorrectionField`
of a true camera or projector: :meth:`RenderErrors.sensors` attaches it to the scanner's
sensors, and the kernel honours any sensor's field through its pack
(:func:`fringecal.simulate.geometry.sensor_pack`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from fringecal.fringe.sequence import FringeSequence
from fringecal.lens.field import CorrectionField, field_terms
from fringecal.sensor import Sensor, SensorFormat
from fringecal.simulate import geometry as g

__all__ = ["HARMONIC_TAIL", "LENS_FIELD_DEGREE", "MAX_HARMONICS", "NO_FIELD", "RenderErrors", "emitted_harmonics",
           "form_array", "frame_weights", "lens_field", "phase_field", "thin_prism"]

#: Largest neglected tail sum |b_h| of the emitted pattern (fraction of full scale).
HARMONIC_TAIL = 1e-6
#: Most harmonics rendered; a gamma needing more is refused.
MAX_HARMONICS = 32
#: The kernel's "no phase field" (empty; no allocation per pixel).
NO_FIELD = np.zeros((2, 0, 0))
#: Degree of a true lens field: its first 19 terms are the calibration's degree-4 field,
#: the other 26 what that model cannot describe.
LENS_FIELD_DEGREE = 6


@dataclass(frozen=True)
class RenderErrors:
    """The unmodelled errors of one rendered measurement (defaults: none).

    Attributes
    ----------
    projector_gamma : float
    camera_linearity_error : float
        ``e`` of the response ``I + 4 e I (1 - I)`` applied to the mean signal.
    scan_drift_rad : float
        Pattern shift over the whole sequence (rad of tau).
    phase_field_rms_rad : float
        RMS of the smooth phase field, drawn from the measurement's generator.
    phase_field_modes : int
    sphere_form : dict sphere id -> ndarray (m, 5)
        Zonal form terms (ux, uy, uz, amplitude mm, degree) in the world frame.
    camera_prism, projector_prism : (s1, s2)
        Thin-prism coefficients (mm^-1) of the true camera and projector.
    camera_field, projector_field : CorrectionField or None
        Lens fields of the true camera and projector (:func:`lens_field`).
    """

    projector_gamma: float = 1.0
    camera_linearity_error: float = 0.0
    scan_drift_rad: float = 0.0
    phase_field_rms_rad: float = 0.0
    phase_field_modes: int = 4
    sphere_form: dict = field(default_factory=dict)
    camera_prism: tuple = (0.0, 0.0)
    projector_prism: tuple = (0.0, 0.0)
    camera_field: CorrectionField | None = None
    projector_field: CorrectionField | None = None

    def sensors(self, scanner) -> tuple[Sensor, Sensor]:
        """(camera, projector) of ``scanner`` with the lens fields attached (where given)."""
        cam, prj = scanner.camera, scanner.projector
        if self.camera_field is not None:
            cam = cam.with_field(self.camera_field)
        if self.projector_field is not None:
            prj = prj.with_field(self.projector_field)
        return cam, prj


def emitted_harmonics(offset: float, amplitude: float, gamma: float) -> np.ndarray:
    """``[A, b_1, ..., b_H]`` of the emitted pattern (module notes); ``[A, B]`` at gamma 1.

    >>> emitted_harmonics(0.4, 0.35, 1.0).tolist()
    [0.4, 0.35]
    >>> b = emitted_harmonics(0.4, 0.35, 2.2)
    >>> len(b) - 1, round(float(b[1]), 12), round(float(b[2] / b[1]), 4)
    (8, 0.35, 0.2532)
    """
    if gamma == 1.0 or amplitude == 0.0:
        return np.array([offset, amplitude], float)
    n = 4096
    psi = 2 * np.pi * np.arange(n) / n
    v = (offset + amplitude * np.cos(psi)) / (offset + amplitude)
    c = np.fft.rfft(v ** gamma).real * (2.0 / n)
    b = amplitude * c / c[1]
    tail = np.cumsum(np.abs(b[:0:-1]))[::-1]  # tail[h - 1] = sum_{j >= h} |b_j|
    order = next((h for h in range(1, len(tail)) if tail[h] <= HARMONIC_TAIL), None)
    if order is None or order > MAX_HARMONICS:
        raise ValueError(f"projector_gamma {gamma} with offset {offset} and amplitude {amplitude} needs more than "
                         f"{MAX_HARMONICS} harmonics (lower the amplitude relative to the offset)")
    out = np.concatenate([[offset], b[1:order + 1]])
    lowest = out[0] + np.cos(np.outer(psi, np.arange(1, order + 1))) @ out[1:]
    if lowest.min() < -HARMONIC_TAIL:
        raise ValueError(f"projector_gamma {gamma}: no non-negative pattern has mean {offset} and fundamental "
                         f"{amplitude} (use gamma >= 1 or a lower amplitude)")
    return out


def frame_weights(sequence: FringeSequence, harmonics: np.ndarray, scan_drift_rad: float = 0.0):
    """(counts (H n_t,), fcos (n_frames, H), fsin (n_frames, H)) for the kernel:
    the fringe counts followed by h t for h = 2..H, and per frame and harmonic
    ``b_h cos(h (delta_k + t psi_f))``, ``b_h sin(...)`` (module notes)."""
    b = np.asarray(harmonics, float)
    n_h = len(b) - 1
    counts = np.concatenate([h * np.asarray(sequence.fringe_counts, float) for h in range(1, n_h + 1)])
    frames = sequence.frames()
    phases = sequence.step_phases()
    if n_h == 1 and scan_drift_rad == 0.0:  # the linear pattern, exactly as without errors
        step_cos, step_sin = np.cos(phases), np.sin(phases)
        fcos = np.array([[b[1] * step_cos[k]] for _, _, k in frames])
        fsin = np.array([[b[1] * step_sin[k]] for _, _, k in frames])
        return counts, fcos, fsin
    f = np.arange(len(frames))
    psi = scan_drift_rad * f / max(len(frames) - 1, 1)
    t = np.array([tt for _, tt, _ in frames], float)
    k = np.array([kk for _, _, kk in frames])
    arg = np.outer(phases[k] + t * psi, np.arange(1, n_h + 1))
    return counts, b[1:] * np.cos(arg), b[1:] * np.sin(arg)


def phase_field(rng: np.random.Generator, shape: tuple[int, int], rms_rad: float, modes: int) -> np.ndarray:
    """(2, rows, cols): for tau_x and tau_y each, ``modes`` 2-D cosine modes
    ``a cos(pi (k_u u + k_v v) + phase)`` over the image (u, v in [0, 1] from the first
    to the last column/row, k_u, k_v integers 0..3 not both 0, a normal, phase
    uniform), scaled to exactly ``rms_rad`` over the image."""
    rows, cols = shape
    v = np.linspace(0.0, 1.0, rows)[:, None]
    u = np.linspace(0.0, 1.0, cols)[None, :]
    out = np.empty((2, rows, cols))
    for o in range(2):
        k = rng.integers(0, 4, size=(modes, 2))
        k[(k == 0).all(axis=1), 0] = 1
        a = rng.standard_normal(modes)
        ph = rng.uniform(0.0, 2 * np.pi, modes)
        f = sum(a[m] * np.cos(np.pi * (k[m, 0] * u + k[m, 1] * v) + ph[m]) for m in range(modes))
        out[o] = f * (rms_rad / np.sqrt(np.mean(f * f)))
    return out


def form_array(scene, kinds: np.ndarray, owner: np.ndarray, sphere_form: dict) -> np.ndarray:
    """(n_prim, m, 5) form terms of every sphere primitive of a scene object of kind
    ``sphere`` whose sphere id is in ``sphere_form``; (0, 1, 5) when there are none."""
    if not sphere_form:
        return np.zeros((0, 1, 5))
    m = max(len(v) for v in sphere_form.values())
    out = np.zeros((len(kinds), m, 5))
    for j, (kind, obj) in enumerate(zip(kinds, owner)):
        o = scene.objects[obj]
        if kind == g.SPHERE and o.kind == "sphere" and o.sphere_id in sphere_form:
            terms = np.asarray(sphere_form[o.sphere_id], float)
            out[j, :len(terms)] = terms
    return out


def thin_prism(native: SensorFormat, corner_px: float, angle_rad: float) -> tuple[float, float]:
    """(s1, s2) of a thin-prism term displacing the image by ``corner_px`` pixels of
    ``native`` (pitch ``width_mm / (width_px - 1)``, eq. 2-21) at the ideal radius of
    the format's corner, in the direction ``angle_rad``.

    >>> s = thin_prism(SensorFormat(2048, 2048, 15.1, 15.1), 0.2, 0.0)
    >>> round(s[0] * (15.1 ** 2 / 2) / (15.1 / 2047), 12), s[1]
    (0.2, 0.0)
    """
    pitch = native.width_mm / (native.width_px - 1)
    r2 = (native.width_mm ** 2 + native.height_mm ** 2) / 4
    size = corner_px * pitch / r2
    return float(size * np.cos(angle_rad)), float(size * np.sin(angle_rad))


def lens_field(fmt: SensorFormat, rms_um: float, rng: np.random.Generator) -> CorrectionField:
    """A degree-:data:`LENS_FIELD_DEGREE` correction field over ``fmt`` whose displacement
    has RMS ``rms_um`` micrometres over the format: all 45 coefficients drawn N(0, 1),
    then scaled (the basis fields have RMS length 1, so the RMS is their norm in mm).
    About 19/45 of its energy lies in the calibration's degree-4 ``field`` model.

    >>> from fringecal.lens.field import format_grid
    >>> f = lens_field(SensorFormat(2048, 2048, 15.1, 15.1), 3.0, np.random.default_rng(1))
    >>> f.degree, f.n_terms, round(float(np.sqrt(np.mean(np.sum(f.value(format_grid(15.1, 15.1)) ** 2, -1)))) * 1e3, 9)
    (6, 45, 3.0)
    """
    z = rng.standard_normal(field_terms(LENS_FIELD_DEGREE))
    a = z * (rms_um * 1e-3 / np.linalg.norm(z))
    return CorrectionField(float(fmt.width_mm), float(fmt.height_mm), LENS_FIELD_DEGREE, a)
