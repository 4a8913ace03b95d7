"""One simulated measurement: render the scanner's frames of the artefact where the
hexapod put it, decode them, and write the measurement store with the renderer's
ground truth beside the decoded maps.

Store contents (beyond the decoder's ``tau_x``, ``tau_y``, ``modulation_*``,
``phase_error_*``, ``texture``, ``valid``): the truth maps of
:class:`~fringecal.simulate.GroundTruth` prefixed ``truth_`` (see
:data:`TRUTH_VARIABLES`; the world point becomes ``truth_x``, ``truth_y``,
``truth_z``), and the attributes ``measurement``, ``pose``, ``scanner``,
``camera_format``, ``truth_sensors``, ``T_world_artefact`` (the reached pose the
frames were rendered at), ``T_world_artefact_planned``, ``config_digest``,
``object_names``, ``object_kinds``, ``sphere_ids``, ``render``, ``seed`` and
``source = "simulated"`` (the decoder adds ``sequence``, ``decoder``, ``summary``).
"""

from __future__ import annotations

import hashlib
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import xarray as xr

from ..fringe.decode import DecodedPhase
from ..fringe.measurement import decode_to_store
from ..frames import Frame
from ..sensor import Sensor
from ..simulate import GroundTruth, artefact_scene, backdrop, render_measurement, scaled_scanner
from ..simulate.evaluation import pure_mask
from .plan import POSE_COLUMNS, AcquisitionInputs, MeasurementPlan, measurement_digest

__all__ = ["AcquiredMeasurement", "acquire_measurement", "measurement_rng", "truth_variables", "truth_from_store",
           "store_summary", "TRUTH_VARIABLES"]

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
    """What :func:`acquire_measurement` did: the decoded maps and a small summary."""

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


def _pose_attr(T: Frame) -> dict[str, float]:
    return dict(zip(POSE_COLUMNS, map(float, T.params)))


def _sensor_attr(s: Sensor) -> dict:
    f = s.format
    return {"name": s.name, "role": s.role, "params": s.as_dict(),
            "format": {"width_px": f.width_px, "height_px": f.height_px, "width_mm": f.width_mm,
                       "height_mm": f.height_mm}}


def acquire_measurement(plan: MeasurementPlan, reached: Frame, run_config, out_path,
                        inputs: AcquisitionInputs | None = None) -> AcquiredMeasurement:
    """Render ``plan``'s scanner looking at the artefact at ``reached``, decode the
    frames and write the measurement store at ``out_path`` (atomically).

    The camera is resampled to ``acquisition.camera_width_px`` (same field of view);
    the scene is the artefact with rods and end caps (plus a backdrop plane
    ``acquisition.backdrop_mm`` in front of the camera, if set); the noise comes from
    :func:`measurement_rng` (``acquisition.seed``, measurement id).
    """
    acq = run_config.acquisition
    inputs = inputs or AcquisitionInputs.from_run_config(run_config)
    scanner = scaled_scanner(inputs.rig.scanner(plan.scanner), acq.camera_width_px)
    background = backdrop(scanner, acq.backdrop_mm) if acq.backdrop_mm is not None else None
    scene = artefact_scene(inputs.artefact, inputs.rods, reached, inputs.hardware, background)
    sequence = acq.sequence.build()
    t0 = time.perf_counter()
    rendered = render_measurement(scanner, scene, acq.render, measurement_rng(acq.seed, plan.measurement), sequence)
    t1 = time.perf_counter()
    truth = rendered.truth
    fmt = scanner.camera.format
    attrs = {
        "source": "simulated",
        "measurement": plan.measurement,
        "pose": plan.pose,
        "scanner": plan.scanner,
        "camera_format": {"width_px": fmt.width_px, "height_px": fmt.height_px, "width_mm": fmt.width_mm,
                          "height_mm": fmt.height_mm},
        "truth_sensors": {"camera": _sensor_attr(scanner.camera), "projector": _sensor_attr(scanner.projector)},
        "T_world_artefact": _pose_attr(reached),
        "T_world_artefact_planned": _pose_attr(plan.T_world_artefact),
        "config_digest": measurement_digest(run_config),
        "object_names": list(truth.object_names),
        "object_kinds": list(truth.object_kinds),
        "sphere_ids": list(truth.sphere_ids),
        "render": acq.render.model_dump(mode="json"),
        "seed": {"run": acq.seed, "measurement": plan.measurement},
        "bit_depth": acq.render.bit_depth,
    }
    decoded = decode_to_store(rendered.frames, sequence, Path(out_path), attrs, truth_variables(truth),
                              settings=run_config.decode, full_scale=acq.render.max_dn,
                              store_frames=acq.store_frames, source=f"measurement {plan.measurement}")
    t2 = time.perf_counter()
    spheres = pure_mask(truth, ("sphere",), decoded.valid)
    summary = {"measurement": plan.measurement, "pose": plan.pose, "scanner": plan.scanner, "store": str(out_path),
               "valid_fraction": float(decoded.valid.mean()), "sphere_pixels": int(spheres.sum()),
               "render_s": t1 - t0, "decode_store_s": t2 - t1}
    return AcquiredMeasurement(decoded, summary)


def store_summary(path) -> dict:
    """Measurement, pose, scanner, valid fraction and the number of valid pixels wholly
    on a lit sphere, read from a simulated measurement's store."""
    from types import SimpleNamespace

    from ..store import open_store

    with open_store(path) as ds:
        fields = ("object_index", "purity", "lit_fraction", "tau_x")
        truth = SimpleNamespace(object_kinds=tuple(ds.attrs["object_kinds"]),
                                **{f: ds[TRUTH_VARIABLES[f][0]].values for f in fields})
        valid = ds["valid"].values
        a = ds.attrs
        return {"measurement": a["measurement"], "pose": a["pose"], "scanner": a["scanner"],
                "valid_fraction": float(valid.mean()), "sphere_pixels": int(pure_mask(truth, ("sphere",), valid).sum())}
