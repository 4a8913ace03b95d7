"""Is the sensor model too simple? A statistic on the residuals binned over every image.

mrcal's ``mrcal-show-residuals`` shows a model that is too simple as residuals that
keep a pattern over the image: where a lens bends rays in a way the model cannot
follow, the residuals of every measurement that images there lean the same way. This
module turns that picture into one number per sensor and residual with a threshold.

Statistic
---------
The control points of each sensor's image are binned as the report bins them
(:func:`fringecal.calibration.results.binned_residuals`, ``IMAGE_BINS`` across) and the
measurements are split in two halves (alternating in table order). In each bin, each
half gives a mean residual (epsilon-1 or epsilon-2), ``m_A`` and ``m_B``. Noise is
independent between the halves, so ``m_A m_B`` has mean ``f^2`` where ``f`` is the
part of the residual fixed to that place of the image (the pattern) and mean 0 without
one. Over the bins::

    Z = sum_b m_A,b m_B,b / sqrt(sum_b var(m_A,b) var(m_B,b))

is about standard normal for a model that describes the images (the sum's standard
deviation is the denominator), and grows with the number of bins times the pattern's
square for one that does not. The variance of each bin's mean counts the sphere images
in the bin (one measurement, one sphere), not the points, as the independent units:
points of one sphere image share its form error, the pose's error and the phase errors
of that measurement, so counting points would call ordinary correlated noise a pattern
(the variances of the within- and between-image parts are pooled over the image, see
:func:`_pattern`). Bins need a sphere image in each half. ``systematic_um = 1000 sqrt(max(0, mean_b
m_A m_B))`` is the pattern's RMS over the bins.

Verdict: the model is "too simple" when the largest ``Z`` over sensors and residuals
exceeds ``Z_MAX = 5`` (one-sided normal tail 3e-7 per statistic; a run has 4 per scanner,
so a correct model is flagged far less than once in ten thousand runs). The statistic
sees any error fixed to the image, so a flag names the lens model first and says what
else it could be (projector non-linearity, an artefact sphere always imaged at the same
place): :mod:`.models` then lets held-out measurements decide whether a richer model helps.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fringecal.calibration.diagnostics import Diagnosis
from fringecal.calibration.model import BundleProblem

__all__ = ["Z_MAX", "PatternStatistic", "ModelAdequacy", "residual_pattern"]

#: largest pattern statistic Z of a model that describes the images
Z_MAX = 5.0
#: bins across each image (as the report's binned residuals)
BINS = 16


@dataclass(frozen=True)
class PatternStatistic:
    """The pattern statistic of one sensor's image and one residual."""

    scanner: str
    sensor: str
    role: str
    residual: str
    z: float
    systematic_um: float
    n_bins: int

    def to_dict(self) -> dict:
        return {"scanner": self.scanner, "sensor": self.sensor, "role": self.role, "residual": self.residual,
                "z": self.z, "systematic_um": self.systematic_um, "n_bins": self.n_bins}


@dataclass(frozen=True)
class ModelAdequacy:
    """Every :class:`PatternStatistic` of an adjustment and the verdict."""

    statistics: tuple
    threshold: float = Z_MAX
    model: str = "brown14"

    @property
    def worst(self) -> PatternStatistic | None:
        finite = [s for s in self.statistics if np.isfinite(s.z)]
        return max(finite, key=lambda s: s.z) if finite else None

    @property
    def z_max(self) -> float:
        w = self.worst
        return float(w.z) if w is not None else float("nan")

    @property
    def too_simple(self) -> bool:
        return bool(self.z_max > self.threshold)

    def message(self) -> str:
        w = self.worst
        if w is None:
            return "residual pattern: no image bin holds two sphere images in each half of the measurements"
        where = (f"{w.residual} over the image of {w.sensor} ({w.role} of {w.scanner}): Z = {w.z:.1f}, "
                 f"pattern RMS {w.systematic_um:.1f} um over {w.n_bins} bins")
        if self.too_simple:
            return (f"the lens model is too simple ({self.model}): the residuals keep a pattern over the images "
                    f"(largest Z = {w.z:.1f} > threshold {self.threshold:g}; {where}). A lens term the model "
                    "lacks is the usual cause; projector non-linearity or an artefact sphere always imaged at "
                    "the same place give the same sign")
        return (f"residual pattern: largest Z = {w.z:.1f} <= threshold {self.threshold:g} ({where}): the "
                f"{self.model} model describes the images")

    def diagnosis(self) -> Diagnosis | None:
        """The warning ``lens_model_too_simple`` when the verdict says so, else None."""
        if not self.too_simple:
            return None
        return Diagnosis("lens_model_too_simple", "warning", self.worst.sensor, self.message())

    def to_dict(self) -> dict:
        return {"model": self.model, "z_max": self.z_max, "threshold": self.threshold,
                "too_simple": self.too_simple, "message": self.message(),
                "statistics": [s.to_dict() for s in self.statistics]}


def _cluster_means(cell, half, cluster, e):
    """Per sphere image of each (bin, half): bin index, half, point count, mean and
    within sum of squares."""
    key = (cell.astype(np.int64) * 2 + half) * (int(cluster.max()) + 1) + cluster
    uniq, inv = np.unique(key, return_inverse=True)
    n = np.bincount(inv).astype(float)
    mean = np.bincount(inv, e) / n
    within = np.bincount(inv, e * e) - n * mean * mean
    bh = uniq // (int(cluster.max()) + 1)
    return bh, n, mean, np.clip(within, 0, None)


def _pattern(cell, half, cluster, e, n_cells):
    """(Z, systematic RMS mm, bins used) of one residual over one image (module notes).

    Each (bin, half) mean is the unweighted mean of its sphere images' means; its
    variance ``(tau^2 C + sigma^2 sum 1/n_c) / C^2`` uses the within-image variance
    ``sigma^2`` and the between-image variance ``tau^2`` (form, pose and phase errors
    shared by one sphere image), both pooled over the image's bins by the method of
    moments, so that bins of one or two sphere images get a stable variance."""
    bh, n, mean, within = _cluster_means(cell, half, cluster, e)
    k = len(n)
    sigma2 = float(np.sum(within) / max(np.sum(n) - k, 1.0))
    C = np.bincount(bh, minlength=2 * n_cells).astype(float)
    inv_n = np.bincount(bh, 1.0 / n, minlength=2 * n_cells)
    with np.errstate(invalid="ignore", divide="ignore"):
        m = np.bincount(bh, mean, minlength=2 * n_cells) / C
        ss = np.bincount(bh, (mean - m[bh]) ** 2, minlength=2 * n_cells)
        multi = C >= 2
        excess = np.sum(ss[multi]) - sigma2 * np.sum((1 - 1 / C[multi]) * inv_n[multi])
        tau2 = max(0.0, float(excess / max(np.sum(C[multi] - 1), 1.0)))
        var = (tau2 * C + sigma2 * inv_n) / (C * C)
    mA, mB = m[0::2], m[1::2]
    vA, vB = var[0::2], var[1::2]
    use = (C[0::2] > 0) & (C[1::2] > 0)
    if not use.any():
        return float("nan"), float("nan"), 0
    prod = mA[use] * mB[use]
    den = float(np.sqrt(np.sum(vA[use] * vB[use])))
    z = float(np.sum(prod) / den) if den > 0 else float("nan")
    return z, float(np.sqrt(max(0.0, float(np.mean(prod))))), int(use.sum())


def residual_pattern(problem: BundleProblem, residuals: np.ndarray, model: str = "brown14",
                     nx: int = BINS) -> ModelAdequacy:
    """The pattern statistic of every sensor's image and both residuals (see the module notes).

    Parameters
    ----------
    problem : BundleProblem
        The adjusted problem (its rig gives the formats).
    residuals : (n, 2)
        epsilon-1, epsilon-2 after the adjustment, in problem order (mm).
    model : str
        Name of the sensor model that was adjusted (for the message).
    """
    res = np.asarray(residuals, float)
    half = problem.meas_idx % 2
    cluster = problem.meas_idx * len(problem.artefact.ids) + problem.sphere_idx
    out = []
    for k, scanner in enumerate(problem.rig.scanners):
        mine = (problem.scanner_idx == k) & np.all(np.isfinite(res), axis=1)
        for sensor, image_mm in ((scanner.camera, problem.cam_mm), (scanner.projector, problem.prj_mm)):
            fmt = sensor.format
            ny = max(1, int(round(nx * fmt.height_px / fmt.width_px)))
            uv = fmt.mm_to_pixel(image_mm[mine])
            ix = np.clip(np.floor((uv[:, 0] + 0.5) / fmt.width_px * nx), 0, nx - 1).astype(int)
            iy = np.clip(np.floor((uv[:, 1] + 0.5) / fmt.height_px * ny), 0, ny - 1).astype(int)
            cell = iy * nx + ix
            for col, name in ((0, "eps1"), (1, "eps2")):
                z, sys_mm, used = _pattern(cell, half[mine], cluster[mine], res[mine, col], nx * ny)
                out.append(PatternStatistic(scanner.name, sensor.name, sensor.role, name, z, 1000 * sys_mm, used))
    return ModelAdequacy(tuple(out), Z_MAX, model)
