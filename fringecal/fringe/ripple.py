"""Phase ripple: the projector's and camera's phase errors that the N-step sequence does
not cancel, estimated from the frames themselves and corrected where the data show them.

Why there is a ripple
---------------------
The N-step estimator ``arg sum_k I_k exp(-i delta_k)`` is exact for a sinusoidal
pattern. A projector without linearisation (gamma), a camera whose response is not
linear, or anything else that bends the grey levels adds harmonics h to the pattern;
those with ``h = +-1 (mod N)`` alias onto the fundamental and leave a phase error that
is a periodic function of the true phase ``Phi``, with ``N`` periods per fringe::

    phi_measured = Phi + sum_m a_m cos(m N Phi) + b_m sin(m N Phi)

(for the thesis's N = 7 harmonics 6 and 8 alias, for a 4-step sequence harmonics 3 and
5: a gamma-2.2 projector then errs by tens of milliradians). Phase steps that are not
exactly ``2 pi k / N`` (a projector's timing, drift within a count's frames) give a
ripple with two periods per fringe. The ripple's size depends on the blur of the
pattern at that count's spatial frequency, so every fringe count gets its own
coefficients.

How it is seen without a reference
----------------------------------
The decoder's contract makes the unwrapped phases ``Phi_t = t w`` exactly linear in the
fringe count t, and ``tau`` is their least-squares slope (:mod:`.decode`). A ripple is
a function of ``t w`` *modulo 2 pi*, which differs from count to count, so it does not
fit a line through the origin: it stays in the slope's residuals. With ``P = I - t t^T
/ t^T t`` the projection onto those residuals and ``G_t(Phi_t)`` the ripple basis
(``cos, sin (f Phi_t)`` for f in :func:`ripple_frequencies`, count t only), every
decoded pixel gives ``r = P G c + noise``; the coefficients ``c`` of all counts follow
by linear least squares over an even sample of the valid pixels (:data:`MAX_PIXELS`),
beside a phase offset per count (drift between counts: neither evidence nor
corrected); their covariance is the sandwich over pixels (the noise differs from pixel
to pixel with the modulation). The evidence is ``Z = (chi^2 - dof) / sqrt(2 dof)``,
``chi^2 = c^T C^-1 c``, about standard normal without a ripple.

Correction (``DecodeSettings.phase_ripple``)
--------------------------------------------
``auto`` (default) corrects where ``Z > Z_APPLY`` (5, as the residual-pattern flag of
the calibration) *and* the ripple's RMS (less what the coefficients' own scatter gives
it) is at least ``MIN_RATIO`` (a tenth) of the phase noise left beside it: a smaller
ripple moves tau by less than a tenth of tau's own noise, and Z alone also grows with
structure that is no ripple (mixed pixels of a small stack, the renderer's
sub-sampling on a flat's 10,000 pixels). The fit leaves out pixels whose tau-fit
residual exceeds ``OUTLIER_FACTOR`` (3) times the median and needs
``MIN_PIXELS_PER_COEFFICIENT`` (40) pixels per coefficient; a smaller stack is decoded
without a fit. ``always`` corrects every stack with a fit; ``off`` is the decoder
without this step. Corrected, every count's unwrapped phase loses its fitted ripple at
its own measured phase and ``tau`` and the phase-error map are fitted again; the
validity mask follows the new phase errors. What the ripple could not move -- its part
along ``t`` itself, a bias of ``tau`` no residual can see -- stays; for a ripple at
``N`` or more periods per fringe that part averages out over a count's many fringes.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from fringecal.fringe.sequence import FringeSequence

__all__ = ["MAX_PIXELS", "Z_APPLY", "MIN_RATIO", "MIN_PIXELS_PER_COEFFICIENT", "OUTLIER_FACTOR", "PhaseRipple",
           "ripple_frequencies", "wrapped_phases", "unwrap_to", "estimate_ripple", "ripple_of", "correct_ripple",
           "scanner_ripple", "ripple_document"]

#: about as many valid pixels (every s-th pixel, kept where valid) the coefficients are fitted on
MAX_PIXELS = 10_000
#: evidence above which ``phase_ripple: auto`` corrects
Z_APPLY = 5.0
#: ... and only a ripple at least this fraction of the phase noise it was fitted under:
#: a smaller one moves tau by less than a tenth of tau's own noise
MIN_RATIO = 0.1
#: fewest pixels per coefficient for a fit (fewer: no fit of the stack's own; its
#: scanner's ripple where one is given, :func:`scanner_ripple`)
MIN_PIXELS_PER_COEFFICIENT = 40
#: pixels whose tau-fit residual exceeds this many times the median are left out of the
#: fit (mixed pixels at edges, wrong fringe orders): the ripple is a property of the
#: sequence and the sensors, seen best where the phases are clean
OUTLIER_FACTOR = 3.0


def ripple_frequencies(n_steps: int) -> tuple[int, ...]:
    """Ripple periods per fringe: 2 (phase-step errors), N, 2N and 3N (aliased harmonics;
    2N and 3N also carry the ripple's own distortion where it is large, since it is
    fitted as a function of the measured phase).

    >>> ripple_frequencies(7), ripple_frequencies(4), ripple_frequencies(3)
    ((2, 7, 14, 21), (2, 4, 8, 12), (2, 3, 6, 9))
    """
    return tuple(sorted({2, n_steps, 2 * n_steps, 3 * n_steps}))


@dataclass(frozen=True)
class PhaseRipple:
    """The fitted ripple of one orientation.

    Attributes
    ----------
    orientation : str
    frequencies : tuple of int
        Periods per fringe of the basis, f.
    coefficients : array (K, F, 2)
        ``a, b`` of ``a cos(f Phi) + b sin(f Phi)`` per fringe count (rad).
    covariance : array (2 K F, 2 K F)
        Sandwich covariance of the flattened coefficients.
    z : float
        Evidence of a ripple (module notes).
    n_pixels : int
    residual_rms_rad : float
        RMS residual of the tau fit over the fitted pixels, before the correction.
    noise_rms_rad : float
        RMS of what the ripple and the counts' offsets leave of those residuals: the
        phase noise of one count.
    applied : bool
    """

    orientation: str
    frequencies: tuple[int, ...]
    coefficients: np.ndarray
    covariance: np.ndarray
    z: float
    n_pixels: int
    residual_rms_rad: float
    noise_rms_rad: float
    applied: bool = False
    #: ``"stack"``: fitted on this stack; ``"scanner"``: the scanner's ripple from its
    #: calibration stacks (:func:`scanner_ripple`), for a stack too small for a fit
    source: str = "stack"

    @property
    def amplitude_rad(self) -> np.ndarray:
        """Peak amplitude per fringe count and frequency, (K, F)."""
        return np.hypot(self.coefficients[..., 0], self.coefficients[..., 1])

    @property
    def rms_rad(self) -> float:
        """RMS of the fitted ripple over the phase, mean over the fringe counts."""
        return float(np.sqrt(np.mean(np.sum(self.coefficients ** 2, axis=(1, 2)) / 2.0)))

    @property
    def excess_rms_rad(self) -> float:
        """:attr:`rms_rad` less what the coefficients' own scatter gives it (their variances
        subtracted from their squares): about zero without a ripple."""
        k = self.coefficients.shape[0]
        excess = np.sum(self.coefficients ** 2) - np.trace(self.covariance)
        return float(np.sqrt(max(excess, 0.0) / (2.0 * k)))

    @property
    def significant(self) -> bool:
        """Evidence above :data:`Z_APPLY` and a ripple (:attr:`excess_rms_rad`) of at least
        :data:`MIN_RATIO` of the phase noise: what ``phase_ripple: auto`` corrects."""
        return bool(self.z > Z_APPLY and self.excess_rms_rad >= MIN_RATIO * self.noise_rms_rad)

    def to_dict(self, sequence: FringeSequence) -> dict:
        u = np.sqrt(np.diag(self.covariance)).reshape(self.coefficients.shape)
        return {"orientation": self.orientation, "applied": bool(self.applied), "source": self.source,
                "z": float(self.z), "z_apply": Z_APPLY,
                "n_pixels": int(self.n_pixels), "rms_rad": self.rms_rad, "excess_rms_rad": self.excess_rms_rad,
                "residual_rms_rad": float(self.residual_rms_rad), "noise_rms_rad": float(self.noise_rms_rad),
                "min_ratio": MIN_RATIO, "significant": self.significant,
                "frequencies_per_fringe": list(self.frequencies),
                "counts": {str(t): {f"f{f}": {"cos_rad": float(self.coefficients[j, i, 0]),
                                              "sin_rad": float(self.coefficients[j, i, 1]),
                                              "u_cos_rad": float(u[j, i, 0]), "u_sin_rad": float(u[j, i, 1])}
                                    for i, f in enumerate(self.frequencies)}
                           for j, t in enumerate(sequence.fringe_counts)}}


def wrapped_phases(frames: np.ndarray, sequence: FringeSequence, orientation: str) -> np.ndarray:
    """The N-step phase of every fringe count, ``atan2(-sum I sin, sum I cos)`` as the
    decoder computes it: (K, ...) for frames (n_frames, ...)."""
    o = sequence.orientations.index(orientation)
    n, k = sequence.n_steps, len(sequence.fringe_counts)
    steps = sequence.step_phases()
    block = frames[o * k * n:(o + 1) * k * n]
    out = np.empty((k,) + frames.shape[1:])
    for j in range(k):
        f = block[j * n:(j + 1) * n].astype(np.float64)
        c = np.tensordot(np.cos(steps), f, axes=1)
        s = np.tensordot(np.sin(steps), f, axes=1)
        out[j] = np.arctan2(-s, c)
    return out


def unwrap_to(phases: np.ndarray, counts, tau: np.ndarray) -> np.ndarray:
    """Unwrapped phases (K, ...) nearest ``t tau`` (tau from the decoder)."""
    t = np.asarray(counts, float).reshape((-1,) + (1,) * tau.ndim)
    return phases + 2 * np.pi * np.round((t * tau - phases) / (2 * np.pi))


def _basis(unwrapped: np.ndarray, frequencies) -> np.ndarray:
    """cos, sin (f Phi): (..., F, 2); the multiples of a frequency by angle addition
    (one cosine and one sine per distinct base frequency instead of one per f)."""
    out = np.empty(unwrapped.shape + (len(frequencies), 2))
    cache = {}
    for i, f in enumerate(frequencies):
        base = next((b for b in cache if f % b == 0 and f // b <= 3), None)
        if base is None:
            c, s = np.cos(f * unwrapped), np.sin(f * unwrapped)
            cache[f] = (c, s)
        else:
            c1, s1 = cache[base]
            m = f // base
            c2, s2 = c1 * c1 - s1 * s1, 2 * c1 * s1
            c, s = (c2, s2) if m == 2 else (c2 * c1 - s2 * s1, s2 * c1 + c2 * s1)
        out[..., i, 0], out[..., i, 1] = c, s
    return out


def ripple_of(coefficients: np.ndarray, unwrapped: np.ndarray, frequencies) -> np.ndarray:
    """The ripple (K, ...) at unwrapped phases (K, ...)."""
    flat = unwrapped.reshape(unwrapped.shape[0], -1)
    out = np.einsum("knfc,kfc->kn", _basis(flat, frequencies), coefficients)
    return out.reshape(unwrapped.shape)


def _sample(valid: np.ndarray, max_pixels: int) -> tuple[np.ndarray, ...]:
    """Rows and columns of about ``max_pixels`` valid pixels: every s-th pixel of the
    image in memory order, kept where valid (no index of every valid pixel is built)."""
    step = max(1, -(-int(np.count_nonzero(valid)) // max_pixels))
    picked = np.arange(0, valid.size, step)
    idx = picked[valid.reshape(-1)[::step]]
    return np.unravel_index(idx, valid.shape)


def estimate_ripple(frames: np.ndarray, sequence: FringeSequence, orientation: str, tau: np.ndarray,
                    valid: np.ndarray, phase_error: np.ndarray | None = None,
                    max_pixels: int = MAX_PIXELS) -> PhaseRipple | None:
    """Fit the ripple of one orientation on valid pixels (module notes); None with fewer
    than :data:`MIN_PIXELS_PER_COEFFICIENT` pixels per coefficient.

    ``frames`` (n_frames, H, W) as decoded, ``tau`` (H, W) the decoder's, ``valid``
    (H, W) the pixels to fit on; with the decoder's ``phase_error`` (H, W), those of the
    sample whose error exceeds :data:`OUTLIER_FACTOR` times the sample's median are left out.
    """
    freqs = ripple_frequencies(sequence.n_steps)
    counts = np.asarray(sequence.fringe_counts, float)
    k, n_f = counts.size, len(freqs)
    n_coef = 2 * k * n_f
    rows, cols = _sample(valid, max_pixels)
    if phase_error is not None and rows.size:
        err = phase_error[rows, cols]
        clean = err <= OUTLIER_FACTOR * np.median(err)
        rows, cols = rows[clean], cols[clean]
    if rows.size < MIN_PIXELS_PER_COEFFICIENT * n_coef or k < 2:
        return None
    phi = unwrap_to(wrapped_phases(frames[:, rows, cols], sequence, orientation), counts, tau[rows, cols])
    slope = counts @ phi / (counts @ counts)
    resid = phi - counts[:, None] * slope  # (K, n), already in the range of P
    # every count's phase offset (drift between counts) is fitted beside its ripple, so
    # that it does not leak into it; it is neither evidence nor corrected (its part
    # orthogonal to t cannot move tau, its part along t no residual shows)
    g = np.concatenate([_basis(phi, freqs).reshape(k, -1, 2 * n_f), np.ones((k, rows.size, 1))], axis=2)
    width = 2 * n_f + 1
    # design A = P G, G block-diagonal (count j's columns act on count j's phase):
    # A^T A = G^T P G and A^T r = G^T r, since P r = r and P is a symmetric projection
    proj = np.eye(k) - np.outer(counts, counts) / (counts @ counts)
    normal = np.zeros((k, width, k, width))
    for j in range(k):  # count by count: no (K, n, K, width) intermediate
        for m in range(j, k):
            normal[j, :, m] = proj[j, m] * (g[j].T @ g[m])
            normal[m, :, j] = normal[j, :, m].T
    normal = normal.reshape(k * width, k * width)
    inv = np.linalg.pinv(normal)
    coef = inv @ np.einsum("jna,jn->ja", g, resid).reshape(-1)
    fitted = proj @ np.einsum("jna,ja->jn", g, coef.reshape(k, width))
    score = (g * (resid - fitted)[..., None]).transpose(1, 0, 2).reshape(rows.size, k * width)  # per pixel
    cov = inv @ (score.T @ score) @ inv
    left = resid - fitted
    keep = (np.arange(k * width) % width) < 2 * n_f
    coef, cov = coef[keep], cov[np.ix_(keep, keep)]
    chi2 = float(coef @ np.linalg.pinv(cov) @ coef)
    z = (chi2 - n_coef) / np.sqrt(2.0 * n_coef)
    dof = max(k - 1, 1)
    return PhaseRipple(orientation, freqs, coef.reshape(k, n_f, 2), cov, float(z), int(rows.size),
                       float(np.sqrt(np.sum(resid ** 2) / (rows.size * dof))),
                       float(np.sqrt(np.sum(left ** 2) / max(rows.size * dof - k * width, 1))))


def correct_ripple(frames: np.ndarray, sequence: FringeSequence, orientation: str, tau: np.ndarray,
                   phase_error: np.ndarray, ripple: PhaseRipple, where: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """tau and the phase-error map (H, W) refitted after the ripple is subtracted from
    every count's unwrapped phase, at the pixels ``where`` (H, W) is true (the others
    keep ``tau`` and ``phase_error``); float32, as the decoder's maps."""
    counts = np.asarray(sequence.fringe_counts, float)
    phi = unwrap_to(wrapped_phases(frames[:, where], sequence, orientation), counts, tau[where].astype(np.float64))
    phi -= ripple_of(ripple.coefficients, phi, ripple.frequencies)
    slope = counts @ phi / (counts @ counts)
    err = np.sqrt(np.sum((phi - counts[:, None] * slope) ** 2, axis=0) / max(counts.size - 1, 1))
    new_tau, new_err = tau.copy(), phase_error.copy()
    new_tau[where] = slope - 2 * np.pi * np.floor(slope / (2 * np.pi) + 0.5)
    new_err[where] = err
    return new_tau, new_err


def scanner_ripple(fits: list[dict], sequence: FringeSequence) -> dict[str, PhaseRipple]:
    """A scanner's ripple per orientation from the fits of its calibration stacks
    (:meth:`PhaseRipple.to_dict` records, as the stores keep them), for its stacks too
    small for a fit of their own (a ball-bar's two spheres span less than two fringes,
    too few to tell a ripple from smooth errors across a sphere).

    An orientation gets one where more than half of its fits were corrected: the
    inverse-variance mean of their coefficients, with the variance of that mean, the
    median of their phase noise and the evidence of the mean. The ripple depends a
    little on the pattern's defocus, so stacks at other distances are corrected by an
    average; records of another sequence are ignored. A record may itself be such a mean
    (``source`` ``"scanner"``, as ``calibration.json`` carries it): it counts as one fit
    with its own u.
    """
    freqs = ripple_frequencies(sequence.n_steps)
    counts = [str(t) for t in sequence.fringe_counts]
    out = {}
    for o in sequence.orientations:
        mine = [f for f in fits if f.get("orientation") == o and f.get("frequencies_per_fringe") == list(freqs)
                and sorted(f.get("counts", {})) == sorted(counts)]
        used = [f for f in mine if f["applied"]]
        if not used or 2 * len(used) <= len(mine):
            continue
        c = np.array([[[[f["counts"][t][f"f{q}"][k] for k in ("cos_rad", "sin_rad")] for q in freqs] for t in counts]
                      for f in used])
        u = np.array([[[[f["counts"][t][f"f{q}"][k] for k in ("u_cos_rad", "u_sin_rad")] for q in freqs]
                       for t in counts] for f in used])
        w = 1.0 / np.maximum(u, 1e-12) ** 2
        var = 1.0 / w.sum(axis=0)
        mean = (w * c).sum(axis=0) * var
        chi2 = float(np.sum(mean ** 2 / var))
        z = (chi2 - mean.size) / np.sqrt(2.0 * mean.size)
        out[o] = PhaseRipple(o, freqs, mean, np.diag(var.reshape(-1)), float(z),
                             int(sum(f["n_pixels"] for f in used)),
                             float(np.median([f["residual_rms_rad"] for f in used])),
                             float(np.median([f["noise_rms_rad"] for f in used])), source="scanner")
    return out


def ripple_document(fits: list[dict]) -> dict:
    """orientation -> :meth:`PhaseRipple.to_dict` record of the scanner's ripple
    (:func:`scanner_ripple`) from its calibration stacks' fits, the sequence read off the
    fits themselves (their fringe counts and their second frequency, N); empty where
    there is none. What ``calibration.json`` carries for stacks decoded without the run."""
    if not fits:
        return {}
    first = fits[0]
    sequence = FringeSequence(tuple(sorted((int(t) for t in first["counts"]), reverse=True)),
                              int(first["frequencies_per_fringe"][1]))
    # applied: what the decoder corrects the scanner's small stacks with
    return {o: replace(r, applied=True).to_dict(sequence) for o, r in sorted(scanner_ripple(fits, sequence).items())}
