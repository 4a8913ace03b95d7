"""One simulated measurement: render a scanner's frames of a scene, decode them into
the measurement store a real scanner's data would give, and keep the renderer's
ground truth in a store of its own (:func:`simulate_measurement`).

The acquisition store holds the decoder's ``tau_x``, ``tau_y``, ``modulation_*``,
``phase_error_*``, ``texture``, ``valid`` and provenance attributes
(``measurement``, ``scanner``, ``camera_format``, ``bit_depth``, ``seed``,
``source = "simulated"``; the decoder adds ``sequence``, ``decoder``, ``summary``).
The truth store holds the maps of :class:`~fringecal.simulate.GroundTruth` prefixed
``truth_`` (:data:`TRUTH_VARIABLES`; the world point becomes ``truth_x``,
``truth_y``, ``truth_z``) and the true sensors, object names, kinds and sphere ids.
"""

from __future__ import annotations

import hashlib
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import xarray as xr

from fringecal.fringe.decode import DecodedPhase
from fringecal.fringe.measurement import decode_to_store
from fringecal.rig import Scanner
from fringecal.sensor import Sensor
from fringecal.simulate import GroundTruth, Measurement, Scene, SceneObject, backdrop, render_measurement
from fringecal.simulate.evaluation import pure_mask
from fringecal.store import write_store

__all__ = ["AcquiredMeasurement", "simulate_measurement", "render_frames", "measurement_rng", "truth_variables",
           "truth_from_store", "camera_format_attr", "TRUTH_VARIABLES"]

#: GroundTruth field -> (store variable, dtype). Points and the averaged projector
#: coordinates stay float64: they are what tests compare decoded values against.
TRUTH_VARIABLES = {
    "tau_x": ("truth_tau_x", np.float64),
    "tau_y": ("truth_tau_y", np.float64),
    "tau_x_centre": ("truth_tau_x_centre", np.float32),
    "tau_y_centre": ("truth_tau_y_centre", np.float32),
    "object_index": ("truth_object_index", np.int16),
    "centre_object_index": ("truth_centre_object_index", np.int16),
    "sphere_index": ("truth_sphere_index", np.int16),
    "purity": ("truth_purity", np.float32),
    "lit_fraction": ("truth_lit_fraction", np.float32),
    "light": ("truth_light", np.int8),
    "irradiance": ("truth_irradiance", np.float32),
    "ambient_level": ("truth_ambient_level", np.float32),
}
_POINT = ("truth_x", "truth_y", "truth_z")


@dataclass(frozen=True)
class AcquiredMeasurement:
    """What :func:`simulate_measurement` did: the decoded maps and a small summary."""

    decoded: DecodedPhase
    summary: dict


def measurement_rng(seed: int, measurement: str) -> np.random.Generator:
    """A generator that depends on the run's seed and the measurement id only, so a
    measurement's noise is the same whatever else is acquired and in whatever order.

    >>> a = measurement_rng(1, "1-scanner1").integers(1 << 30)
    >>> b = measurement_rng(1, "1-scanner1").integers(1 << 30)
    >>> c = measurement_rng(1, "1-scanner2").integers(1 << 30)
    >>> bool(a == b), bool(a == c)
    (True, False)
    """
    word = int.from_bytes(hashlib.sha256(measurement.encode()).digest()[:8], "little")
    return np.random.default_rng(np.random.SeedSequence([int(seed), word]))


def truth_variables(truth: GroundTruth) -> dict[str, np.ndarray]:
    """Store variables (all (rows, cols)) of a rendered measurement's truth."""
    out = {name: np.asarray(getattr(truth, field), dtype) for field, (name, dtype) in TRUTH_VARIABLES.items()}
    for i, name in enumerate(_POINT):
        out[name] = np.ascontiguousarray(truth.point[..., i], np.float64)
    return out


def truth_from_store(ds: xr.Dataset) -> GroundTruth:
    """The :class:`GroundTruth` kept in a simulated measurement's store."""
    missing = [n for n in (*(v for v, _ in TRUTH_VARIABLES.values()), *_POINT) if n not in ds.variables]
    if missing:
        raise KeyError(f"store has no ground truth ({', '.join(missing)} missing): not a simulated measurement")
    kw = {field: ds[name].values for field, (name, _) in TRUTH_VARIABLES.items()}
    kw["point"] = np.stack([ds[n].values for n in _POINT], axis=-1)
    for k in ("object_names", "object_kinds", "sphere_ids"):
        kw[k] = tuple(str(x) for x in ds.attrs[k])
    return GroundTruth(**kw)


def camera_format_attr(fmt) -> dict:
    return {"width_px": fmt.width_px, "height_px": fmt.height_px, "width_mm": fmt.width_mm, "height_mm": fmt.height_mm}


def _sensor_attr(s: Sensor) -> dict:
    return {"name": s.name, "role": s.role, "params": s.as_dict(), "format": camera_format_attr(s.format)}


def render_frames(measurement: str, scanner: Scanner, scene: Scene, acquisition, errors=None) -> Measurement:
    """The fringe frames ``scanner`` records of ``scene`` (and the renderer's truth).

    ``acquisition`` is an :class:`~fringecal.simulate.config.AcquisitionConfig` (render
    settings, sequence, seed, optional backdrop ``backdrop_mm`` in front of the
    camera); the noise comes from :func:`measurement_rng` (seed, measurement id), so a
    measurement renders the same whatever else is rendered and in whatever order.
    ``errors`` (:class:`~fringecal.simulate.unmodelled.RenderErrors`, optional) are
    the unmodelled errors of this measurement (:func:`fringecal.simulate.world.render_errors`).
    """
    if acquisition.backdrop_mm is not None:
        bg = SceneObject("background", "background", "background", (backdrop(scanner, acquisition.backdrop_mm),))
        scene = Scene(scene.objects + (bg,))
    return render_measurement(scanner, scene, acquisition.render, measurement_rng(acquisition.seed, measurement),
                              acquisition.sequence.build(), errors)


def simulate_measurement(measurement: str, scanner: Scanner, scene: Scene, acquisition, decode_settings, out,
                         truth_out=None, attrs: dict | None = None, errors=None,
                         scanner_fits=()) -> AcquiredMeasurement:
    """Render, decode and write one measurement store at ``out`` (atomically), and its
    ground truth as a separate store at ``truth_out`` (if given).

    The acquisition store holds what a real scanner would deliver (decoded maps and
    provenance: ``measurement``, ``scanner``, ``camera_format``, ``bit_depth``,
    ``source = "simulated"`` plus ``attrs``); the truth store holds the renderer's
    per-pixel truth (:data:`TRUTH_VARIABLES`; the world point as ``truth_x``,
    ``truth_y``, ``truth_z``) and, as attributes, the true sensors and the scene's
    object names, kinds and sphere ids. ``errors``: as :func:`render_frames`;
    ``scanner_fits``: as :func:`fringecal.fringe.decode.decode`.
    """
    t0 = time.perf_counter()
    rendered = render_frames(measurement, scanner, scene, acquisition, errors)
    t1 = time.perf_counter()
    truth = rendered.truth
    fmt = scanner.camera.format
    base = {"source": "simulated", "measurement": measurement, "scanner": scanner.name,
            "camera_format": camera_format_attr(fmt), "bit_depth": acquisition.render.bit_depth,
            "seed": {"run": acquisition.seed, "measurement": measurement}, **(attrs or {})}
    decoded = decode_to_store(rendered.frames, rendered.sequence, Path(out), base, settings=decode_settings,
                              full_scale=acquisition.render.max_dn, store_frames=acquisition.store_frames,
                              source=f"measurement {measurement}", scanner_fits=scanner_fits)
    if truth_out is not None:
        cam, prj = errors.sensors(scanner) if errors is not None else scanner.sensors  # with any lens field
        truth_attrs = {"measurement": measurement, "truth_sensors": {"camera": _sensor_attr(cam),
                                                                     "projector": _sensor_attr(prj)},
                       "object_names": list(truth.object_names), "object_kinds": list(truth.object_kinds),
                       "sphere_ids": list(truth.sphere_ids), "render": acquisition.render.model_dump(mode="json")}
        ds = xr.Dataset({k: (("v", "u"), v) for k, v in truth_variables(truth).items()}, attrs=truth_attrs)
        write_store(truth_out, ds)
    t2 = time.perf_counter()
    spheres = pure_mask(truth, ("sphere",), decoded.valid)
    summary = {"measurement": measurement, "scanner": scanner.name, "store": str(out),
               "valid_fraction": float(decoded.valid.mean()), "sphere_pixels": int(spheres.sum()),
               "render_s": t1 - t0, "decode_store_s": t2 - t1}
    return AcquiredMeasurement(decoded, summary)
