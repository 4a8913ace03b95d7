"""Phase decoding: N-step phase estimation, reverse-exponential temporal unwrapping
and the least-squares temporal phase gradient (thesis sections 2.3.7, 6.8).

For every camera pixel and orientation the frames of each fringe count ``t`` give a
wrapped phase ``phi_t`` (the N-step estimator, any N >= 3), a modulation ``B_t`` and a
background ``A``. The contract of :mod:`fringecal.fringe.sequence` makes the true
unwrapped phase ``Phi_t = t * w`` exactly, with ``w = tau`` the projector coordinate of
eq. 2-22 in [-pi, pi], so:

1. The beat chain finds the fringe orders. The beat ``phi_s - phi_(s-1)`` is ``w``
   itself (no wrapping possible); the beats ``phi_s - phi_(s-d)`` for d = 2, 4, ...
   are ``d * w`` and are each unwrapped with the previous estimate. The last one,
   ``w_beat = Phi_(d_max) / d_max``, predicts every ``t * w`` well enough to round
   each density's phase to its fringe order.
2. ``tau`` is the least-squares slope, through the origin, of the unwrapped phases
   ``Phi_t`` against ``t``: ``tau = sum(t Phi_t) / sum(t^2)``. With independent phase
   noise sigma_phi its standard deviation is ``sigma_phi / sqrt(sum t^2)``, against
   ``sqrt(2) sigma_phi / d_max`` for ``w_beat`` (6.6 times more for the thesis's
   64..32 schedule).
3. The phase-error map is the RMS residual of that fit with K - 1 degrees of freedom
   (K fringe counts, one parameter), an estimate of sigma_phi; the modulation map
   is the mean of ``B_t`` over the counts; the texture is the mean intensity of all
   frames (the background ``A``).

One fused numba kernel does all of it, row by row in parallel with per-row scratch
space only, so memory is the frames plus the output maps.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Literal, Sequence

import numba as nb
import numpy as np
from pydantic import Field

from fringecal.config import StrictModel
from fringecal.fringe.ripple import PhaseRipple, correct_ripple, estimate_ripple, scanner_ripple
from fringecal.fringe.sequence import FringeSequence

__all__ = ["DecodeSettings", "DecodedPhase", "decode", "tau_noise_theory"]


class DecodeSettings(StrictModel):
    """Validity thresholds of the decoder.

    ``min_modulation`` is a fraction of the full scale (the saturation level, e.g.
    4095 for 12-bit frames; 1.0 for float frames decoded without one); ``max_phase_error`` is the largest accepted RMS residual
    of the tau fit in radians. A pixel is valid when, in every orientation, its
    modulation reaches the threshold and its phase error does not exceed it, and no
    frame is saturated there.
    """

    min_modulation: float = Field(0.02, ge=0.0, le=1.0)
    max_phase_error: float = Field(0.3, gt=0.0)
    #: ``auto``: estimate the phase ripple of every orientation and correct it where it
    #: is significant (evidence Z above 5, RMS at least a tenth of the phase noise);
    #: ``always``: correct it whatever Z; ``off``: the decoder without the ripple step
    #: (:mod:`fringecal.fringe.ripple`)
    phase_ripple: Literal["auto", "always", "off"] = "auto"


@dataclass
class DecodedPhase:
    """Decoded maps of one measurement, each of shape (H, W).

    ``tau``, ``modulation``, ``phase_error`` (and ``tau_beat`` if requested) are keyed
    by orientation. ``modulation`` and ``texture`` are in the frames' intensity
    units; ``tau``, ``phase_error`` in radians.
    """

    sequence: FringeSequence
    full_scale: float
    settings: DecodeSettings
    tau: dict[str, np.ndarray]
    modulation: dict[str, np.ndarray]
    phase_error: dict[str, np.ndarray]
    texture: np.ndarray
    saturated: np.ndarray
    valid: np.ndarray
    tau_beat: dict[str, np.ndarray] = field(default_factory=dict)
    #: the fitted phase ripple per orientation (none where ``phase_ripple: off`` or too
    #: few valid pixels); ``applied`` says whether tau was corrected
    ripple: dict[str, PhaseRipple] = field(default_factory=dict)

    @property
    def shape(self) -> tuple[int, int]:
        return self.texture.shape

    def maps(self) -> dict[str, np.ndarray]:
        """The store variables: ``tau_x``, ``modulation_x``, ``phase_error_x``, (same
        for y), ``texture``, ``valid``."""
        out = {}
        for o in self.sequence.orientations:
            out[f"tau_{o}"] = self.tau[o]
            out[f"modulation_{o}"] = self.modulation[o]
            out[f"phase_error_{o}"] = self.phase_error[o]
        out["texture"] = self.texture
        out["valid"] = self.valid
        return out


def tau_noise_theory(sequence: FringeSequence, sigma_intensity: float, modulation: float) -> dict[str, float]:
    """Standard deviation of tau for additive intensity noise (rad).

    The N-step estimator gives ``sigma_phi = sigma_I / B * sqrt(2 / N)`` for each
    fringe count; the least-squares slope divides it by ``sqrt(sum t^2)``, the beat
    estimate ``(phi_s - phi_(s-d_max)) / d_max`` multiplies it by ``sqrt(2) / d_max``.

    >>> th = tau_noise_theory(FringeSequence(), sigma_intensity=1.0, modulation=100.0)
    >>> round(th["beat"] / th["least_squares"], 2)
    6.55
    """
    counts = np.asarray(sequence.fringe_counts, float)
    sigma_phi = sigma_intensity / modulation * np.sqrt(2.0 / sequence.n_steps)
    d_max = counts[0] - counts[-1]
    return {
        "phase": float(sigma_phi),
        "least_squares": float(sigma_phi / np.sqrt(np.sum(counts**2))),
        "beat": float(np.sqrt(2.0) * sigma_phi / d_max),
    }


def decode(frames: np.ndarray, sequence: FringeSequence, settings: DecodeSettings | None = None,
           full_scale: float | None = None, beat_estimate: bool = False,
           scanner_fits: Sequence[dict] = ()) -> DecodedPhase:
    """Decode one measurement's frames into phase-gradient, modulation and error maps.

    Parameters
    ----------
    frames : array (n_frames, H, W), any integer or float dtype
        In the order of ``sequence.frames()`` (orientation, fringe count, step).
        uint8, uint16 and float32 are read in place; other types are converted to
        float32 first (a copy).
    sequence : FringeSequence
    settings : DecodeSettings, optional
    full_scale : float, optional
        Saturation level: samples at or above it mark the pixel saturated (invalid).
        Defaults to the dtype's maximum for integer frames and to no check for floats.
    beat_estimate : bool
        Also return ``tau_beat``, the beat-chain estimate (for noise comparisons).
    scanner_fits : sequence of dict
        The ripple fits of the scanner's calibration stacks (their stores'
        ``decoder.phase_ripple_fit`` records): where this stack is too small for a fit
        of its own, the scanner's ripple from them
        (:func:`fringecal.fringe.ripple.scanner_ripple`) is corrected (unless
        ``phase_ripple: off``).

    Examples
    --------
    >>> seq = FringeSequence(fringe_counts=(8, 7, 6, 4), n_steps=4, orientations=("x",))
    >>> w = np.linspace(-3, 3, 5)[None, :]
    >>> frames = np.stack([seq.pattern(w, t, k, A=100, B=50) for _, t, k in seq.frames()])
    >>> res = decode(frames, seq, full_scale=255)
    >>> np.round(res.tau["x"], 6), np.round(res.modulation["x"], 3)
    (array([[-3. , -1.5,  0. ,  1.5,  3. ]], dtype=float32), array([[50., 50., 50., 50., 50.]], dtype=float32))
    """
    settings = settings or DecodeSettings()
    frames = np.asarray(frames)
    if frames.ndim != 3 or frames.shape[0] != sequence.n_frames:
        raise ValueError(f"expected frames of shape ({sequence.n_frames}, H, W) for {sequence.n_frames} frames, "
                         f"got {frames.shape}")
    if frames.dtype.kind not in "uif":
        raise ValueError(f"frames must be integer or float, got {frames.dtype}")
    if full_scale is None:
        full_scale = float(np.iinfo(frames.dtype).max) if frames.dtype.kind in "ui" else np.inf
    # uint8 and uint16 (camera data) are decoded as they are; anything else as float32,
    # so the kernel is compiled for three types only
    if frames.dtype not in (np.uint8, np.uint16, np.float32):
        frames = frames.astype(np.float32)
    frames = np.ascontiguousarray(frames)
    n_o, (h, w) = len(sequence.orientations), frames.shape[1:]
    counts = np.asarray(sequence.fringe_counts, np.int64)
    steps = sequence.step_phases()

    tau = np.empty((n_o, h, w), np.float32)
    mod = np.empty((n_o, h, w), np.float32)
    err = np.empty((n_o, h, w), np.float32)
    beat = np.empty((n_o, h, w) if beat_estimate else (n_o, 0, 0), np.float32)
    texture = np.empty((h, w), np.float32)
    saturated = np.empty((h, w), np.bool_)
    valid = np.empty((h, w), np.bool_)
    min_mod = settings.min_modulation * (full_scale if np.isfinite(full_scale) else 1.0)
    _decode_rows(frames, counts, np.cos(steps).astype(np.float32), np.sin(steps).astype(np.float32),
                 np.float32(full_scale), min_mod, settings.max_phase_error,
                 tau, mod, err, beat, texture, saturated, valid)
    orients = sequence.orientations
    ripple = {}
    if settings.phase_ripple != "off":
        ripple = _ripple_step(frames, sequence, settings, min_mod, tau, mod, err, saturated, valid, scanner_fits)
    return DecodedPhase(
        sequence=sequence, full_scale=float(full_scale), settings=settings,
        tau=dict(zip(orients, tau)), modulation=dict(zip(orients, mod)), phase_error=dict(zip(orients, err)),
        texture=texture, saturated=saturated, valid=valid,
        tau_beat=dict(zip(orients, beat)) if beat_estimate else {}, ripple=ripple,
    )


def _ripple_step(frames, sequence, settings, min_mod, tau, mod, err, saturated, valid,
                 scanner_fits: Sequence[dict]) -> dict[str, PhaseRipple]:
    """Estimate every orientation's ripple on the valid pixels and correct where asked
    (the scanner's where the stack is too small for a fit); ``tau``, ``err`` and
    ``valid`` are updated in place."""
    out = {}
    scanner = None  # the scanner's ripple, computed when an orientation first needs it
    for i, o in enumerate(sequence.orientations):
        found = estimate_ripple(frames, sequence, o, tau[i], valid, err[i])
        if found is None:
            if scanner is None:
                scanner = scanner_ripple(scanner_fits, sequence) if scanner_fits else {}
            found = scanner.get(o)
            if found is None:
                continue
        if settings.phase_ripple == "always" or found.significant or found.source == "scanner":
            lit = ~saturated & (mod[i] >= min_mod)  # the pixels whose tau can become valid
            tau[i], err[i] = correct_ripple(frames, sequence, o, tau[i], err[i], found, lit)
            found = replace(found, applied=True)
        out[o] = found
    if any(r.applied for r in out.values()):
        ok = ~saturated
        for i in range(len(sequence.orientations)):
            ok &= (err[i] <= settings.max_phase_error) & (mod[i] >= min_mod)
        valid[...] = ok
    return out


_TWO_PI = 2.0 * np.pi
_INV_TWO_PI = 1.0 / _TWO_PI
_TAN_PI_8 = float(np.tan(np.pi / 8))


def _atan_coefficients(n_terms: int = 7) -> tuple[float, ...]:
    """Least-squares odd polynomial for atan on [0, tan(pi/8)] (max error 4e-12 rad)."""
    x = np.cos(np.linspace(0.0, np.pi / 2, 4000)) * _TAN_PI_8
    basis = np.stack([x ** (2 * i + 1) for i in range(n_terms)], axis=1)
    return tuple(float(c) for c in np.linalg.lstsq(basis, np.arctan(x), rcond=None)[0])


_ATAN = _atan_coefficients()


@nb.njit(inline="always", cache=True, error_model="numpy")
def _atan2(y, x):  # pragma: no cover - numba
    """Branch-free atan2 (vectorises where libm's does not); |error| < 1e-11 rad."""
    ax = abs(x)
    ay = abs(y)
    hi = max(ax, ay)
    lo = min(ax, ay)
    a = lo / hi if hi > 0.0 else 0.0
    big = a > _TAN_PI_8
    z = (a - 1.0) / (a + 1.0) if big else a
    z2 = z * z
    p = _ATAN[6]
    p = p * z2 + _ATAN[5]
    p = p * z2 + _ATAN[4]
    p = p * z2 + _ATAN[3]
    p = p * z2 + _ATAN[2]
    p = p * z2 + _ATAN[1]
    p = p * z2 + _ATAN[0]
    r = z * p
    r = r + 0.25 * np.pi if big else r
    r = 0.5 * np.pi - r if ay > ax else r
    r = np.pi - r if x < 0.0 else r
    return -r if y < 0.0 else r


@nb.njit(parallel=True, cache=True, error_model="numpy")
def _decode_rows(frames, counts, cos_k, sin_k, full_scale, min_mod, max_err,
                 tau, mod, err, beat, texture, saturated, valid):  # pragma: no cover - numba
    """Everything in column loops over per-row scratch rows so LLVM vectorises them."""
    n_o, h, w = tau.shape
    n_k = counts.shape[0]
    n_steps = cos_k.shape[0]
    want_beat = beat.shape[1] > 0
    sum_t2 = 0.0
    for j in range(n_k):
        sum_t2 += counts[j] * counts[j]
    inv_sum_t2 = 1.0 / sum_t2
    scale_b = 2.0 / n_steps / n_k
    inv_dof = 1.0 / (n_k - 1)
    inv_frames = np.float32(1.0 / frames.shape[0])
    for r in nb.prange(h):
        acc_c = np.empty((n_k, w), np.float32)
        acc_s = np.empty((n_k, w), np.float32)
        phi = np.empty((n_k, w))
        est = np.empty(w)
        work = np.empty(w)
        total = np.zeros(w, np.float32)
        top = np.full(w, -np.inf, np.float32)
        ok = np.ones(w, np.bool_)
        for o in range(n_o):
            # N-step sums: the only pass over the frames
            for j in range(n_k):
                ac = acc_c[j]
                as_ = acc_s[j]
                ac[:] = 0.0
                as_[:] = 0.0
                for k in range(n_steps):
                    row = frames[(o * n_k + j) * n_steps + k, r]
                    ck = cos_k[k]
                    sk = sin_k[k]
                    for c in range(w):
                        v = np.float32(row[c])
                        ac[c] += v * ck
                        as_[c] += v * sk
                        total[c] += v
                        top[c] = max(top[c], v)
            # wrapped phases and mean modulation
            work[:] = 0.0
            for j in range(n_k):
                ac = acc_c[j]
                as_ = acc_s[j]
                ph = phi[j]
                for c in range(w):
                    cc = np.float64(ac[c])
                    ss = np.float64(as_[c])
                    ph[c] = _atan2(-ss, cc)
                    work[c] += np.sqrt(cc * cc + ss * ss)
            for c in range(w):
                mod[o, r, c] = scale_b * work[c]
            # beat chain, used only to find the fringe orders
            p0 = phi[0]
            p1 = phi[1]
            for c in range(w):
                e = p0[c] - p1[c]
                est[c] = e - _TWO_PI * np.floor(e * _INV_TWO_PI + 0.5)
            for j in range(2, n_k):
                d = np.float64(counts[0] - counts[j])
                inv_d = 1.0 / d
                pj = phi[j]
                for c in range(w):
                    bt = p0[c] - pj[c]
                    est[c] = (bt + _TWO_PI * np.floor((d * est[c] - bt) * _INV_TWO_PI + 0.5)) * inv_d
            if want_beat:
                for c in range(w):
                    beat[o, r, c] = est[c]
            # unwrap every density and fit tau through the origin
            work[:] = 0.0
            for j in range(n_k):
                t = np.float64(counts[j])
                pj = phi[j]
                for c in range(w):
                    u = pj[c] + _TWO_PI * np.floor((t * est[c] - pj[c]) * _INV_TWO_PI + 0.5)
                    pj[c] = u
                    work[c] += t * u
            for c in range(w):
                est[c] = work[c] * inv_sum_t2
            work[:] = 0.0
            for j in range(n_k):
                t = np.float64(counts[j])
                pj = phi[j]
                for c in range(w):
                    e = pj[c] - t * est[c]
                    work[c] += e * e
            for c in range(w):
                e = np.sqrt(work[c] * inv_dof)
                # tau and tau + 2 pi give identical frames for integer counts; when noise
                # wraps the first beat the chain lands on the twin outside [-pi, pi]
                tau[o, r, c] = est[c] - _TWO_PI * np.floor(est[c] * _INV_TWO_PI + 0.5)
                err[o, r, c] = e
                ok[c] &= (e <= max_err) & (mod[o, r, c] >= min_mod)
        for c in range(w):
            texture[r, c] = total[c] * inv_frames
            sat = top[c] >= full_scale
            saturated[r, c] = sat
            valid[r, c] = ok[c] & ~sat
