"""Frames -> decoded maps -> one measurement store.

:func:`decode_to_store` is the whole path for frames already in memory (a simulated
measurement is render -> ``decode_to_store``, :func:`fringecal.simulate.measurement.simulate_measurement`); :func:`decode_folder` reads a
frame folder first. Both refuse a measurement without fringes (zero modulation
everywhere) or without a single valid pixel, naming the source.
"""

from __future__ import annotations

import statistics
from pathlib import Path
from typing import Iterable, Mapping

import numpy as np
import xarray as xr

from fringecal import __version__
from fringecal.fringe.decode import DecodedPhase, DecodeSettings, decode
from fringecal.fringe.importer import FrameStackError, read_frames
from fringecal.fringe.sequence import FringeSequence
from fringecal.store import write_store

__all__ = ["NoFringesError", "check_decoded", "measurement_dataset", "decode_to_store", "decode_folder",
           "decoding_summary", "VARIABLE_ATTRS"]

VARIABLE_ATTRS = {
    "tau": {"units": "rad", "long_name": "temporal phase gradient = projector coordinate w of eq. 2-22 in [-pi, pi]"},
    "modulation": {"units": "DN", "long_name": "fringe modulation B, mean over the fringe counts"},
    "phase_error": {"units": "rad", "long_name": "RMS residual of the least-squares tau fit (K-1 dof)"},
    "texture": {"units": "DN", "long_name": "mean intensity of all frames (background A)"},
    "valid": {"long_name": "modulation and phase error within thresholds, no saturated frame"},
    "frames": {"units": "DN", "long_name": "raw fringe frames in acquisition order"},
}


class NoFringesError(FrameStackError):
    """Frames that decode to nothing usable (no modulation, no valid pixel)."""


def check_decoded(result: DecodedPhase, source: str) -> None:
    """Raise :class:`NoFringesError` naming ``source`` when an orientation has no
    modulation anywhere or no pixel is valid."""
    seq = result.sequence
    min_mod = result.settings.min_modulation * (result.full_scale if np.isfinite(result.full_scale) else 1.0)
    for o in seq.orientations:
        peak = float(np.max(result.modulation[o]))
        if peak < min_mod:
            first = seq.frame_name(o, seq.fringe_counts[0], 0).rsplit(".", 1)[0]
            last = seq.frame_name(o, seq.fringe_counts[-1], seq.n_steps - 1).rsplit(".", 1)[0]
            what = "zero modulation everywhere" if peak < 1e-6 * max(min_mod, 1.0) else "no fringes"
            raise NoFringesError(
                f"{source}: {what} in orientation {o}: frames {first}..{last} have modulation below the "
                f"threshold {min_mod:.3g} DN at every pixel (largest {peak:.3g} DN); was the projector on?")
    if not result.valid.any():
        reasons = [f"{np.mean(result.saturated):.0%} saturated"]
        for o in seq.orientations:
            reasons.append(f"median phase error {o} {np.median(result.phase_error[o]):.3g} rad "
                           f"(limit {result.settings.max_phase_error})")
        raise NoFringesError(f"{source}: no valid pixel ({'; '.join(reasons)}); frames out of order or a "
                             "different fringe sequence?")


def _summary(result: DecodedPhase) -> dict:
    out = {"valid_fraction": float(np.mean(result.valid)), "saturated_fraction": float(np.mean(result.saturated))}
    v = result.valid
    for o in result.sequence.orientations:
        if v.any():
            out[f"median_phase_error_{o}_rad"] = float(np.median(result.phase_error[o][v]))
            out[f"median_modulation_{o}_dn"] = float(np.median(result.modulation[o][v]))
            out[f"tau_{o}_range_rad"] = [float(result.tau[o][v].min()), float(result.tau[o][v].max())]
    if result.ripple:
        out["phase_ripple"] = {o: {"z": float(r.z), "applied": bool(r.applied), "excess_rms_rad": r.excess_rms_rad}
                               for o, r in result.ripple.items()}
    return out


def measurement_dataset(result: DecodedPhase, attrs: Mapping | None = None, frames: np.ndarray | None = None,
                        extra_vars: Mapping | None = None) -> xr.Dataset:
    """The store's dataset: the decoded maps on dims ("v", "u"), provenance attributes.

    ``extra_vars`` maps names to arrays of shape (H, W) or to ``(dims, array)`` pairs
    (e.g. a renderer's ground truth); ``frames`` (n_frames, H, W) is stored as
    ``frames`` with per-frame coordinates orientation, fringes, step.
    """
    h, w = result.shape
    data = {}
    for name, arr in result.maps().items():
        kind = name.rsplit("_", 1)[0] if name.endswith(("_x", "_y")) else name
        data[name] = xr.DataArray(arr, dims=("v", "u"), attrs=VARIABLE_ATTRS[kind])
    for name, value in (extra_vars or {}).items():
        dims, arr = value if isinstance(value, tuple) else (("v", "u"), value)
        data[name] = xr.DataArray(np.asarray(arr), dims=dims)
    seq = result.sequence
    coords = {"v": np.arange(h, dtype=np.int32), "u": np.arange(w, dtype=np.int32)}
    if frames is not None:
        data["frames"] = xr.DataArray(frames, dims=("frame", "v", "u"), attrs=VARIABLE_ATTRS["frames"])
        o, t, k = zip(*seq.frames())
        # object strings become zarr v3 variable-length strings (fixed-width ones have no v3 spec)
        coords.update(orientation=("frame", np.array(o, dtype=object)), fringes=("frame", np.array(t, np.int32)),
                      step=("frame", np.array(k, np.int32)))
    base = {
        "software": "fringecal",
        "software_version": __version__,
        "sequence": seq.to_dict(),
        "contract": "I = A + B cos(t * w + 2 pi k / N); tau = w (eq. 2-22 projector coordinate, rad)",
        "decoder": {**result.settings.model_dump(), "full_scale_dn": _finite_or_none(result.full_scale),
                    "method": "N-step phases, reverse-exponential beat chain for fringe orders, "
                              "least-squares slope through the origin"
                              + (", phase ripple corrected" if any(r.applied for r in result.ripple.values()) else ""),
                    "phase_ripple_fit": {o: r.to_dict(seq) for o, r in result.ripple.items()}},
        "summary": _summary(result),
    }
    return xr.Dataset(data, coords=coords, attrs={**base, **dict(attrs or {})})


def _finite_or_none(x: float):
    return float(x) if np.isfinite(x) else None


def decode_to_store(frames: np.ndarray, sequence: FringeSequence, out_path, attrs: Mapping | None = None,
                    extra_vars: Mapping | None = None, settings: DecodeSettings | None = None,
                    full_scale: float | None = None, store_frames: bool = False,
                    source: str | None = None, scanner_fits=()) -> DecodedPhase:
    """Decode frames (n_frames, H, W) and write the measurement store at ``out_path``.

    ``attrs`` (JSON-native: scanner, measurement, config_digest, ...) are merged
    into the provenance attributes; ``source`` names the frames in error messages;
    ``scanner_fits``: as :func:`~fringecal.fringe.decode.decode`.
    """
    result = decode(frames, sequence, settings, full_scale, scanner_fits=scanner_fits)
    check_decoded(result, source or str(out_path))
    ds = measurement_dataset(result, attrs, frames if store_frames else None, extra_vars)
    write_store(out_path, ds)
    return result


def decode_folder(folder, out_path, settings: DecodeSettings | None = None, attrs: Mapping | None = None,
                  store_frames: bool = False, threads: int | None = None, scanner_fits=()) -> DecodedPhase:
    """Read a frame folder (see :mod:`fringecal.fringe.importer`) and write its store
    (``scanner_fits``: as :func:`~fringecal.fringe.decode.decode`)."""
    stack = read_frames(folder, threads=threads)
    spec = stack.spec
    base = {"source": str(Path(folder).resolve()), "frame_format": stack.format, "bit_depth": spec.bit_depth}
    base.update({k: v for k, v in (("scanner", spec.scanner), ("measurement", spec.measurement)) if v is not None})
    return decode_to_store(stack.frames, stack.sequence, out_path, {**base, **dict(attrs or {})},
                           settings=settings, full_scale=stack.full_scale, store_frames=store_frames,
                           source=str(folder), scanner_fits=scanner_fits)


def decoding_summary(entries: Iterable[tuple[str, str, dict]]) -> list[dict] | None:
    """Per scanner, over decoded stacks given as ``(measurement, scanner, summary)``
    (each store's ``summary`` attribute as this module writes it; others are skipped):
    stacks, median valid fraction, median phase noise per orientation, and the phase
    ripple (fits, which stacks and orientations were corrected, the largest evidence Z,
    the largest corrected ripple). None without a decoded stack."""
    per: dict[str, dict] = {}
    for measurement, scanner, summary in entries:
        if "valid_fraction" not in summary:
            continue
        d = per.setdefault(scanner, {"stacks": 0, "valid": [], "noise": {}, "fits": 0, "corrected": [], "z": [],
                                     "ripple": []})
        d["stacks"] += 1
        d["valid"].append(summary["valid_fraction"])
        for o in ("x", "y"):
            if f"median_phase_error_{o}_rad" in summary:
                d["noise"].setdefault(o, []).append(summary[f"median_phase_error_{o}_rad"])
        for o, r in (summary.get("phase_ripple") or {}).items():
            d["fits"] += 1
            d["z"].append(r["z"])
            if r["applied"]:
                d["corrected"].append(f"{measurement} {o}")
                d["ripple"].append(r["excess_rms_rad"])
    if not per:
        return None
    return [{"scanner": scanner, "stacks": d["stacks"], "valid_fraction_median": statistics.median(d["valid"]),
             "phase_noise_median_rad": {o: statistics.median(v) for o, v in d["noise"].items()},
             "phase_ripple": {"fits": d["fits"], "corrected": d["corrected"],
                              "largest_z": max(d["z"]) if d["z"] else None,
                              "largest_corrected_rms_rad": max(d["ripple"]) if d["ripple"] else None}}
            for scanner, d in per.items()]
