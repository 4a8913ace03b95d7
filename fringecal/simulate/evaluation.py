"""Decoded maps against the renderer's ground truth: phase errors, unwrapping errors,
epsilon-1. What the tests, the noise calibration and a run's report measure.

A pixel counts only where the truth is unambiguous: its whole footprint lies on one
object (``purity == 1``) and is lit by the projector (``lit_fraction == 1``), so its
true projector coordinate is the mean over one smooth surface. An *unwrapping error*
is a decoded tau more than half a fringe period of the densest pattern,
``pi / max(fringe_counts)``, from the truth: the fringe order of some count was wrong.
The difference is taken as it is, not on the circle: tau and tau +- 2 pi give the same
frames, but they triangulate to different points, so a decoded tau that lands on the
far edge of the projector counts as an error.
"""

from __future__ import annotations

import numpy as np

from fringecal.fringe.sequence import FringeSequence
from fringecal.sensor import Sensor
from fringecal.simulate.render import GroundTruth

__all__ = ["pure_mask", "unwrap_threshold", "tau_residuals", "tau_error_summary", "projector_pixel_rad"]


def pure_mask(truth: GroundTruth, kinds: tuple[str, ...] | None = ("sphere",), valid: np.ndarray | None = None
              ) -> np.ndarray:
    """Pixels (rows, cols) wholly on one fully lit object of ``kinds`` (None: any
    object), and ``valid`` where given."""
    m = (truth.object_index >= 0) & (truth.purity >= 1.0) & (truth.lit_fraction >= 1.0) & np.isfinite(truth.tau_x)
    if kinds is not None:
        m &= np.isin(np.asarray(truth.object_kinds + ("",))[truth.object_index], kinds)
    return m if valid is None else m & np.asarray(valid, bool)


def unwrap_threshold(sequence: FringeSequence) -> float:
    """Half a fringe period of the densest count in tau units (rad): ``pi / max(t)``.

    >>> round(unwrap_threshold(FringeSequence()), 5)
    0.04909
    """
    return float(np.pi / max(sequence.fringe_counts))


def tau_residuals(tau: np.ndarray, truth_tau: np.ndarray) -> np.ndarray:
    """``tau - truth`` (rad), in float64."""
    return np.asarray(tau, float) - np.asarray(truth_tau, float)


def projector_pixel_rad(projector: Sensor, orientation: str) -> float:
    """One projector pixel in tau units: ``2 pi / N`` with N the projector's pixel
    count across (x: width, y: height) (eq. 2-22)."""
    n = projector.format.width_px if orientation == "x" else projector.format.height_px
    return 2 * np.pi / n


def tau_error_summary(tau: dict[str, np.ndarray], truth: GroundTruth, mask: np.ndarray, sequence: FringeSequence,
                      projector: Sensor) -> dict:
    """Per orientation over ``mask``: pixel count, RMS and mean of tau - truth (rad and
    projector pixels), RMS without unwrapping errors, and the number of unwrapping errors."""
    limit = unwrap_threshold(sequence)
    out = {"n_pixels": int(np.count_nonzero(mask)), "unwrap_threshold_rad": limit}
    for o in sequence.orientations:
        d = tau_residuals(tau[o][mask], getattr(truth, f"tau_{o}")[mask])
        bad = np.abs(d) > limit
        good = d[~bad]
        px = projector_pixel_rad(projector, o)
        rms = float(np.sqrt(np.mean(good**2))) if good.size else float("nan")
        out[o] = {"unwrap_errors": int(np.count_nonzero(bad)), "rms_rad": rms, "rms_projector_px": rms / px,
                  "mean_rad": float(np.mean(good)) if good.size else float("nan")}
    return out
