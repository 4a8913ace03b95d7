"""The calibration file: sensor parameters per scanner as hierarchical XML (thesis
section 6.7) plus an equivalent JSON document.

Layout::

    <calibration software="fringecal" version=".." reference_scanner="scanner1">
      <scanner name="scanner1">
        <sensor name="C1" role="camera">
          <format width_px="2048" height_px="2048" width_mm="15.1" height_mm="15.1"/>
          <external>   x0 y0 z0 omega phi kappa </external>
          <internal>   xi_h eta_h c </internal>
          <distortion> k1 k2 k3 p1 p2 </distortion>
          <thin_prism> s1 s2 s3 s4 </thin_prism>   (only a model with thin-prism terms)
          <correction_field degree="4"> f01 .. f19 </correction_field>   (only a model with a field)
          <observed_region unit=".." format_mm="w h" cells="nx ny" min_points_per_cell="5"
                           fraction_observed="..">             (only where the calibration knows it)
            <vertex x_mm=".." y_mm=".."/> ...                  the hull, counter-clockwise
            <points_per_cell> ny lines of nx counts </points_per_cell>
          </observed_region>
        </sensor>
        ...
      </scanner>
      <metadata><item key="...">value</item></metadata>
    </calibration>

Each parameter is a leaf ``<x0 unit="mm" free="false" u="0.012">694.018</x0>``; values
are written with Python's shortest round-trip representation, so reading a file back
gives the same floats bit for bit.

The JSON document also carries, like mrcal's models, what a user of the calibration
needs to state uncertainties and to trace it (the XML keeps the thesis layout only):

* ``covariance`` -- the covariance of every sensor parameter (rig order, 14 per sensor,
  fixed parameters with zero rows; ``parameters`` names them ``<sensor>.<parameter>``),
  split as the length budget splits it (:class:`fringecal.calibration.propagation.ParameterCovariances`):
  ``adjustment`` (observation noise through the bundle adjustment), ``artefact_cmm``
  (the artefact table's CMM uncertainty scaled by ``artefact_u_factor``),
  ``artefact_scale`` (parameter change per unit relative scale of the artefact) with
  ``artefact_scale_u_rel`` (its relative standard uncertainty: CTE times the
  temperature uncertainty). :func:`read_calibration` gives them back.
* ``replicas`` -- the sensor parameters of the calibration's re-adjustments, each a row
  in ``covariance``'s parameter order: ``bootstrap`` (wild-bootstrap replicas,
  :mod:`fringecal.calibration.bootstrap`: a derived quantity's bias is the mean over
  them minus its value) and ``jackknife`` (one per measurement left out, named in
  ``left_out``, with the same jackknife of noise-only worlds as ``noise_params``
  (``noise_draws`` of them), :mod:`fringecal.calibration.jackknife`: a quantity's spread
  over them beyond the noise worlds' is its model error). ``fringecal measure`` states
  sphere distances with both, as the verification states the ball-bar's lengths.
* ``sensor_model`` -- the sensor model the run used and why (configured, or chosen by
  held-out measurements with every candidate's held-out error and the residual-pattern
  statistic; :mod:`fringecal.calibration.models`). Sensors with thin-prism terms carry
  them as ``thin_prism`` (s1..s4 with unit, free flag and u) beside ``parameters``,
  sensors with a correction field (:mod:`fringecal.lens.field`) as ``correction_field``
  (its ``degree``, the ``basis`` it is expressed in, and its ``coefficients`` f01.. in mm
  with free flag and u); without them the document is the 14-parameter one. The
  ``covariance`` block holds the 14 parameters' covariance (with a field: marginal over
  the field's coefficients, whose own u are in ``correction_field``).
* ``phase_ripple`` -- per scanner and orientation, the phase ripple its decoder
  corrected in its calibration stacks (only where it did): the mean of their fits,
  :func:`fringecal.fringe.ripple.ripple_document`. ``fringecal measure`` corrects a
  small object's stack with it when the calibration is read outside its run directory.
* ``observed_region`` (per sensor, beside ``parameters``) -- where on its image plane the
  adjustment's control points lay: their count on a grid over the format and the
  fraction of the format they cover (:class:`fringecal.lens.observed_region.ObservedRegion`);
  ``fringecal measure`` flags the points measured outside it. A file without it (one
  written before it existed, or by another program) reads as "not known":
  :attr:`Calibration.observed_regions` has no entry for that sensor. The XML carries it
  too (``<observed_region>``, the layout above; :func:`read_calibration` reads it back),
  and ``fringecal export opencv`` writes its hull in pixels
  (:mod:`fringecal.interop.opencv_storage`).
* ``provenance`` -- the digests of the adjustment's input files, its settings and their
  digest, the package versions. The run's whole configuration is in its
  ``manifest.json``; a calibration depends only on the settings listed here and on its
  inputs (whose digests tie it to the data it came from).
"""

from __future__ import annotations

import json
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from fringecal import __version__
from fringecal.atomic import write_text
from fringecal.calibration.propagation import FieldCovariances, ParameterCovariances
from fringecal.lens.field import CorrectionField, field_names
from fringecal.lens.observed_region import ObservedRegion
from fringecal.names import UnsafeNameError, check_name
from fringecal.rig import Rig, Scanner
from fringecal.sensor import PARAM_NAMES, PRISM_NAMES, Sensor, SensorFormat

__all__ = ["write_calibration_xml", "xml_text", "document_xml", "calibration_texts", "read_calibration_xml", "write_calibration_json",
           "read_calibration_json", "rig_to_dict", "rig_from_dict", "CalibrationFileError", "Calibration",
           "read_calibration", "covariance_document", "parameter_names", "replicas_document", "REPLICA_KINDS"]

_GROUPS = {
    "external": ("x0", "y0", "z0", "omega", "phi", "kappa"),
    "internal": ("xi_h", "eta_h", "c"),
    "distortion": ("k1", "k2", "k3", "p1", "p2"),
}
_UNITS = {"x0": "mm", "y0": "mm", "z0": "mm", "omega": "rad", "phi": "rad", "kappa": "rad",
          "xi_h": "mm", "eta_h": "mm", "c": "mm", "k1": "mm^-2", "k2": "mm^-4", "k3": "mm^-6",
          "p1": "mm^-1", "p2": "mm^-1", "s1": "mm^-1", "s2": "mm^-3", "s3": "mm^-1", "s4": "mm^-3"}


class CalibrationFileError(ValueError):
    """A calibration file is malformed; the message names the file and element."""


def parameter_names(rig: Rig) -> list[str]:
    """``<sensor>.<parameter>`` of every sensor parameter in rig order (14 per sensor)."""
    return [f"{sensor.name}.{n}" for scanner in rig.scanners for sensor in scanner.sensors for n in PARAM_NAMES]


def covariance_document(rig: Rig, covariances) -> dict:
    """The ``covariance`` block of a calibration document from
    :class:`~fringecal.calibration.propagation.ParameterCovariances` (matrices (14 n, 14 n))."""
    n = 14 * sum(len(s.sensors) for s in rig.scanners)
    for name in ("calibration", "cmm"):
        if np.shape(getattr(covariances, name)) != (n, n):
            raise ValueError(f"covariance {name!r} has shape {np.shape(getattr(covariances, name))}, expected {(n, n)}")
    out = {"parameters": parameter_names(rig), **_covariance_arrays(covariances),
           "artefact_scale_u_rel": float(covariances.u_scale)}
    if covariances.field is not None:
        out["field"] = {"parameters": field_parameter_names(rig, covariances.field.n_terms),
                        **_covariance_arrays(covariances.field)}
    return out


def field_parameter_names(rig: Rig, n_terms: int) -> list[str]:
    """:func:`parameter_names`, then ``<sensor>.field.f01`` .. of every sensor (the
    extended vector of :class:`~fringecal.calibration.propagation.FieldCovariances`)."""
    names = field_names(next((s.field.degree for s in rig.sensors if s.field is not None
                              and len(s.field.coefficients) == n_terms), 4))
    return parameter_names(rig) + [f"{s.name}.field.{n}" for s in rig.sensors for n in names]


def _covariance_arrays(c) -> dict:
    return {"adjustment": np.asarray(c.calibration, float).tolist(), "artefact_cmm": np.asarray(c.cmm, float).tolist(),
            "artefact_scale": np.asarray(c.scale, float).tolist()}


#: the kinds of replicas a calibration document may carry
REPLICA_KINDS = ("bootstrap", "jackknife", "jackknife_noise")


def replicas_document(replicas: dict, left_out=None) -> dict:
    """The ``replicas`` block from kind -> sensor parameters: ``bootstrap`` and
    ``jackknife`` (n, n_sensors, 14), ``jackknife_noise`` (draws, n, n_sensors, 14); each
    replica a row of 14 n_sensors values. The jackknife's block carries ``left_out`` (its
    measurements) and its noise-only worlds as ``noise_params`` with ``noise_draws``."""
    unknown = sorted(set(replicas) - set(REPLICA_KINDS))
    if unknown:
        raise ValueError(f"unknown kind of replicas {unknown}; expected {REPLICA_KINDS}")
    out = {}
    for kind in ("bootstrap", "jackknife"):
        if kind in replicas:
            out[kind] = {"params": _replica_rows(replicas[kind]).tolist()}
    if "jackknife" in out:
        if left_out is not None:
            out["jackknife"]["left_out"] = [str(m) for m in left_out]
        if "jackknife_noise" in replicas:
            q = np.asarray(replicas["jackknife_noise"], float)
            out["jackknife"]["noise_draws"] = int(len(q))
            out["jackknife"]["noise_params"] = _replica_rows(q.reshape((-1,) + q.shape[-2:])).tolist()
    return out


def _replica_rows(p) -> np.ndarray:
    """Replicas (n, n_sensors, 14[+K]) as rows in the covariance's parameter order: every
    sensor's 14, then (with correction fields) every sensor's K coefficients."""
    p = np.asarray(p, float)
    return np.concatenate([p[..., :14].reshape(len(p), -1), p[..., 14:].reshape(len(p), -1)], axis=1)


def _replica_params(rows: np.ndarray, n_sensors: int) -> np.ndarray:
    """Inverse of :func:`_replica_rows`: (n, n_sensors, 14[+K])."""
    K = rows.shape[1] // n_sensors - 14
    head = rows[:, :14 * n_sensors].reshape(len(rows), n_sensors, 14)
    return np.concatenate([head, rows[:, 14 * n_sensors:].reshape(len(rows), n_sensors, K)], axis=2)


def _parameter_entries(names, values, free, uncertainty, k: int) -> dict:
    """name -> {value, unit, free[, u]} of one sensor (row ``k`` of ``uncertainty``)."""
    out = {}
    for j, name in enumerate(names):
        out[name] = {"value": float(values[j]), "unit": _UNITS[name], "free": bool(free[j])}
        if uncertainty is not None:
            out[name]["u"] = float(uncertainty[k, j])
    return out


def rig_to_dict(rig: Rig, metadata: dict | None = None, covariances=None, provenance: dict | None = None,
                sensor_model: dict | None = None, replicas: dict | None = None,
                phase_ripple: dict | None = None, observed_regions: dict | None = None) -> dict:
    """The JSON document of ``rig``; ``covariances``
    (:class:`~fringecal.calibration.propagation.ParameterCovariances`), ``provenance``,
    ``sensor_model`` (the model's choice and its evidence,
    :func:`fringecal.calibration.models.choose_sensor_model`), ``replicas`` (a
    :func:`replicas_document`) and ``phase_ripple`` (scanner -> orientation -> its
    ripple, :func:`fringecal.fringe.ripple.ripple_document`) are added when given, and
    each sensor's ``observed_region`` from ``observed_regions`` (sensor name ->
    :class:`~fringecal.lens.observed_region.ObservedRegion`) where it names the sensor
    (see the module notes)."""

    out = {"software": "fringecal", "version": __version__, "reference_scanner": rig.reference,
           "scanners": [], "metadata": dict(metadata or {})}
    if sensor_model is not None:
        out["sensor_model"] = sensor_model
    if covariances is not None:
        out["covariance"] = covariance_document(rig, covariances)
    if provenance is not None:
        out["provenance"] = dict(provenance)
    if replicas:
        out["replicas"] = replicas
    if phase_ripple:
        out["phase_ripple"] = phase_ripple
    k = 0
    for scanner in rig.scanners:
        entry = {"name": scanner.name, "sensors": []}
        for sensor in scanner.sensors:
            f = sensor.format
            params = _parameter_entries(PARAM_NAMES, sensor.params, rig.free[k], rig.uncertainty, k)
            entry["sensors"].append({
                "name": sensor.name, "role": sensor.role,
                "format": {"width_px": f.width_px, "height_px": f.height_px,
                           "width_mm": f.width_mm, "height_mm": f.height_mm},
                "parameters": params,
            })
            if rig.has_prism:  # only then: a 14-parameter calibration's document is unchanged
                entry["sensors"][-1]["thin_prism"] = _parameter_entries(PRISM_NAMES, sensor.prism, rig.prism_free[k],
                                                                        rig.prism_uncertainty, k)
            if sensor.field is not None:
                entry["sensors"][-1]["correction_field"] = _field_entry(sensor.field, rig.field_free[k],
                                                                        rig.field_uncertainty, k)
            if sensor.name in (observed_regions or {}):
                entry["sensors"][-1]["observed_region"] = observed_regions[sensor.name].to_dict()
            k += 1
        out["scanners"].append(entry)
    return out


_FIELD_BASIS = ("fringecal.lens.field: vector polynomials of total degree 2..degree in m / R (m measured "
                "image-plane mm from the format's centre, R half its diagonal), orthonormal over the format and "
                "orthogonal to the fields the 14 parameters absorb; a measured point m stands for m - f(m)")


def _field_entry(f: CorrectionField, free: bool, uncertainty, k: int) -> dict:
    terms = {}
    for j, name in enumerate(field_names(f.degree)):
        terms[name] = {"value": float(f.coefficients[j]), "unit": "mm", "free": bool(free)}
        if uncertainty is not None and j < uncertainty.shape[1]:
            terms[name]["u"] = float(uncertainty[k, j])
    return {"degree": int(f.degree), "basis": _FIELD_BASIS, "coefficients": terms}


def _field_of(entry: dict, fmt: SensorFormat, where: str) -> tuple[CorrectionField, bool, list]:
    """The correction field of a sensor's ``correction_field`` entry, its free flag and u."""
    degree = entry.get("degree")
    if not isinstance(degree, int) or not 2 <= degree <= 8:
        raise CalibrationFileError(f"{where}: correction_field degree {degree!r} must be a whole number from 2 to 8")
    names = field_names(degree)
    terms = entry.get("coefficients", {})
    missing = [n for n in names if n not in terms]
    if missing or len(terms) != len(names):
        raise CalibrationFileError(f"{where}: a degree-{degree} correction_field has coefficients "
                                   f"{names[0]}..{names[-1]}; missing {missing[:3]}" if missing else
                                   f"{where}: a degree-{degree} correction_field has {len(names)} coefficients, "
                                   f"found {len(terms)}")
    values = [float(terms[n]["value"]) for n in names]
    u = [float(terms[n]["u"]) if "u" in terms[n] else np.nan for n in names]
    for n, v, un in zip(names, values, u):
        if not np.isfinite(v) or ("u" in terms[n] and not un >= 0):
            raise CalibrationFileError(f"{where}: correction_field coefficient {n!r} = {v} (u {un}); each must be "
                                       "a finite number, its u finite and >= 0")
    free = any(bool(terms[n].get("free", False)) for n in names)
    return CorrectionField(fmt.width_mm, fmt.height_mm, degree, values), free, u


def rig_from_dict(d: dict, source: str = "<calibration>") -> Rig:
    """The rig of a calibration document; every name must be one safe path component
    and every parameter, format and uncertainty a finite number (a NaN parameter would
    drop its scanner's points from a cloud without a word)."""
    try:
        scanners, free, unc, prism_free, prism_u, field_free, field_u = [], [], [], [], [], [], []
        for i, sc in enumerate(d["scanners"]):
            check_name(sc["name"], f"scanners[{i}] name", source)
            pair = {}
            for se in sc["sensors"]:
                where = f"scanner {sc['name']!r} sensor {se['name']!r}"
                check_name(se["name"], f"scanner {sc['name']!r}: sensor", source)
                f = se["format"]
                fmt = SensorFormat(int(f["width_px"]), int(f["height_px"]), float(f["width_mm"]), float(f["height_mm"]))
                if not (fmt.width_px > 1 and fmt.height_px > 1 and fmt.width_mm > 0 and fmt.height_mm > 0):
                    raise CalibrationFileError(f"{source}: {where}: format {f} must be positive (width_px, height_px "
                                               "> 1, width_mm, height_mm > 0)")
                p = se["parameters"]
                vals = [float(p[n]["value"]) for n in PARAM_NAMES]
                u = [float(p[n]["u"]) if "u" in p[n] else np.nan for n in PARAM_NAMES]
                for n, v, un in zip(PARAM_NAMES, vals, u):
                    if not np.isfinite(v):
                        raise CalibrationFileError(f"{source}: {where}: parameter {n!r} is {v}; every parameter "
                                                   "must be a finite number")
                    if "u" in p[n] and not (un >= 0):  # NaN or negative
                        raise CalibrationFileError(f"{source}: {where}: parameter {n!r} has uncertainty u = {un}; "
                                                   "a standard uncertainty is a finite number >= 0")
                tp = se.get("thin_prism", {})
                prism = [float(tp[n]["value"]) if n in tp else 0.0 for n in PRISM_NAMES]
                if not np.all(np.isfinite(prism)):
                    raise CalibrationFileError(f"{source}: {where}: thin_prism {prism} must be finite numbers")
                pair[se["role"]] = Sensor(se["name"], se["role"], fmt, vals, prism)
                field_free.append(False)
                field_u.append(None)
                if "correction_field" in se:
                    f, field_free[-1], field_u[-1] = _field_of(se["correction_field"], fmt, f"{source}: {where}")
                    pair[se["role"]] = pair[se["role"]].with_field(f)
                free.append([bool(p[n]["free"]) for n in PARAM_NAMES])
                prism_free.append([bool(tp[n].get("free", False)) if n in tp else False for n in PRISM_NAMES])
                prism_u.append([float(tp[n]["u"]) if n in tp and "u" in tp[n] else np.nan for n in PRISM_NAMES])
                unc.append(u)
            scanners.append(Scanner(sc["name"], pair["camera"], pair["projector"]))
        u = np.array(unc)
        pu = np.array(prism_u)
        fu = None
        if any(x is not None and not np.isnan(x).all() for x in field_u):
            n = max(len(x) for x in field_u if x is not None)
            fu = np.array([x if x is not None and len(x) == n else np.full(n, np.nan) for x in field_u])
        return Rig(tuple(scanners), d["reference_scanner"], np.array(free),
                   None if np.isnan(u).all() else u, np.array(prism_free, bool).reshape(-1, 4),
                   None if np.isnan(pu).all() else pu, np.array(field_free, bool), fu)
    except UnsafeNameError as err:
        raise CalibrationFileError(str(err)) from None
    except (KeyError, TypeError, ValueError) as err:
        raise CalibrationFileError(f"{source}: malformed calibration ({type(err).__name__}: {err})") from None


def write_calibration_json(rig: Rig, path, metadata: dict | None = None, covariances=None,
                           provenance: dict | None = None) -> Path:
    return write_text(Path(path), json.dumps(rig_to_dict(rig, metadata, covariances, provenance), indent=2) + "\n")


def _json_document(path: Path) -> dict:
    try:
        d = json.loads(path.read_text(encoding="utf-8"))
    except UnicodeDecodeError as err:
        raise CalibrationFileError(f"{path}: not UTF-8 text ({err})") from None
    except json.JSONDecodeError as err:
        raise CalibrationFileError(f"{path}: not valid JSON ({err})") from None
    if not isinstance(d, dict):
        raise CalibrationFileError(f"{path}: a calibration is a JSON object, found {type(d).__name__}")
    return d


def read_calibration_json(path) -> Rig:
    path = Path(path)
    return rig_from_dict(_json_document(path), str(path))


@dataclass(frozen=True)
class Calibration:
    """A calibration file read whole: the rig, the covariance of its sensor parameters
    (:class:`~fringecal.calibration.propagation.ParameterCovariances`, None when the file has
    none, e.g. the XML), the provenance and the metadata."""

    rig: Rig
    covariances: object | None = None
    provenance: dict = field(default_factory=dict)
    metadata: dict = field(default_factory=dict)
    black_boxes: dict | None = None  # the black-box scanners (fringecal.calibration.blackbox), if any
    # kind -> re-adjusted sensor parameters: bootstrap, jackknife (n, n_sensors, 14); jackknife_noise
    # (draws, n, n_sensors, 14)
    replicas: dict = field(default_factory=dict)
    # scanner -> orientation -> the phase ripple its decoder corrects small stacks with
    # (fringecal.fringe.ripple.ripple_document records)
    phase_ripple: dict = field(default_factory=dict)
    # sensor name -> where its control points lay (fringecal.lens.observed_region); a sensor
    # without an entry: not known (a file without observed_region)
    observed_regions: dict = field(default_factory=dict)


def _rows(rows, names: list[str], where: str, key: str = "params") -> np.ndarray:
    """(n, len(names)) finite values of a list of rows; errors name the row and parameter."""
    if not isinstance(rows, list):
        raise CalibrationFileError(f"{where}: expected {key}, one row per replica")
    for r, row in enumerate(rows):
        if not isinstance(row, list) or len(row) != len(names):
            got = f"{len(row)} values" if isinstance(row, list) else type(row).__name__
            raise CalibrationFileError(f"{where}: {key} row {r} has {got}, expected {len(names)} (the "
                                       "covariance's parameters in order)")
    try:
        params = np.asarray(rows, float).reshape(len(rows), len(names))
    except (TypeError, ValueError) as err:
        raise CalibrationFileError(f"{where}: {key}: {type(err).__name__}: {err}") from None
    if not np.isfinite(params).all():
        r, c = np.argwhere(~np.isfinite(params))[0]
        raise CalibrationFileError(f"{where}: {key} row {r}, {names[c]}: not a finite number")
    return params


def _replicas(doc: dict, rig: Rig, source: str) -> dict:
    """kind -> arrays of a document's ``replicas`` block (:func:`replicas_document`)."""
    if not isinstance(doc, dict):
        raise CalibrationFileError(f"{source}: replicas: expected an object of bootstrap, jackknife")
    names = parameter_names(rig)
    first = next((b.get("params") for b in doc.values() if isinstance(b, dict)), None)
    width = len(first[0]) if isinstance(first, list) and first and isinstance(first[0], list) else len(names)
    if rig.has_field and width > len(names):  # a model with the fields: replicas carry their coefficients
        names = field_parameter_names(rig, len(rig.fields[0]))
    n_s = len(rig.sensors)
    out = {}
    for kind, block in doc.items():
        where = f"{source}: replicas {kind!r}"
        if kind not in ("bootstrap", "jackknife"):
            raise CalibrationFileError(f"{where}: unknown kind; expected bootstrap or jackknife")
        if not isinstance(block, dict):
            raise CalibrationFileError(f"{where}: expected an object with params")
        out[kind] = _replica_params(_rows(block.get("params"), names, where), n_s)
        if kind == "jackknife" and "noise_params" in block:
            draws = block.get("noise_draws")
            noise = _rows(block["noise_params"], names, where, "noise_params")
            n = len(out[kind])
            if not isinstance(draws, int) or draws < 1 or len(noise) != draws * n:
                raise CalibrationFileError(f"{where}: noise_params has {len(noise)} rows, expected noise_draws "
                                           f"({draws!r}) times the {n} replicas")
            out["jackknife_noise"] = _replica_params(noise, n_s).reshape((draws, n) + out[kind].shape[1:])
    return out


def _covariances(doc: dict, rig: Rig, source: str):
    try:
        u_scale = float(doc["artefact_scale_u_rel"])
    except (KeyError, TypeError, ValueError) as err:
        raise CalibrationFileError(f"{source}: covariance: {type(err).__name__}: {err}") from None
    arrays = _covariance_block(doc, parameter_names(rig), source, "covariance")
    if not np.isfinite(u_scale) or u_scale < 0:
        raise CalibrationFileError(f"{source}: covariance 'artefact_scale_u_rel' must be finite and >= 0, got {u_scale}")
    field = None
    if "field" in doc:
        n_terms = (len(doc["field"].get("parameters", [])) - len(parameter_names(rig))) // len(rig.sensors)
        f = _covariance_block(doc["field"], field_parameter_names(rig, n_terms), source, "covariance field")
        field = FieldCovariances(f["adjustment"], f["artefact_cmm"], f["artefact_scale"], n_terms)
    return ParameterCovariances(arrays["adjustment"], arrays["artefact_cmm"], arrays["artefact_scale"], u_scale, field)


def _covariance_block(doc: dict, names: list[str], source: str, where: str) -> dict:
    """The three arrays of a covariance block, checked against ``names``."""
    n = len(names)
    try:
        if doc["parameters"] != names:
            raise ValueError(f"parameters do not name the sensors of the calibration in order ({n} expected)")
        arrays = {k: np.asarray(doc[k], float) for k in ("adjustment", "artefact_cmm", "artefact_scale")}
    except (KeyError, TypeError, ValueError) as err:
        raise CalibrationFileError(f"{source}: {where}: {type(err).__name__}: {err}") from None
    for key, shape in (("adjustment", (n, n)), ("artefact_cmm", (n, n)), ("artefact_scale", (n,))):
        if arrays[key].shape != shape:
            raise CalibrationFileError(f"{source}: {where} {key!r} has shape {arrays[key].shape}, expected {shape}")
        if not np.isfinite(arrays[key]).all():
            bad = np.argwhere(~np.isfinite(arrays[key]))[0]
            raise CalibrationFileError(f"{source}: {where} {key!r} holds non-finite values (first at "
                                       f"{_entry(names, bad)})")
        if arrays[key].ndim == 2:
            _check_covariance(arrays[key], names, key, source)
    return arrays


def _entry(names: list[str], index) -> str:
    return ", ".join(names[int(i)] for i in index) if len(index) else "?"


def _check_covariance(c: np.ndarray, names: list[str], key: str, source: str) -> None:
    """A covariance matrix: variances >= 0 on the diagonal, symmetric, every correlation
    within [-1, 1] (up to rounding): else it is not one, and an uncertainty drawn from it
    would be meaningless."""
    diag = np.diag(c)
    if (neg := np.flatnonzero(diag < 0)).size:
        i = int(neg[0])
        raise CalibrationFileError(f"{source}: covariance {key!r}: the variance of {names[i]} is {diag[i]:.6g}; "
                                   "a variance cannot be negative")
    scale = np.sqrt(np.outer(diag, diag))
    tol = 1e-9 * max(float(np.max(np.abs(c))), 1e-300)
    asym = np.abs(c - c.T) > tol + 1e-6 * scale
    if asym.any():
        i, j = np.argwhere(asym)[0]
        raise CalibrationFileError(f"{source}: covariance {key!r} is not symmetric ({names[i]}, {names[j]}: "
                                   f"{c[i, j]:.6g} against {c[j, i]:.6g})")
    beyond = np.abs(c) > scale * (1 + 1e-6) + tol
    if beyond.any():
        i, j = np.argwhere(beyond)[0]
        raise CalibrationFileError(f"{source}: covariance {key!r}: |cov({names[i]}, {names[j]})| = "
                                   f"{abs(c[i, j]):.6g} exceeds the product of their standard deviations; "
                                   "not a covariance matrix")


_RIPPLE_TERMS = ("cos_rad", "sin_rad", "u_cos_rad", "u_sin_rad")


def _phase_ripple(doc, rig: Rig, source: str) -> dict:
    """The ``phase_ripple`` block (scanner -> orientation -> ripple record), checked:
    scanners of the calibration, orientations x and y, every coefficient and its u a
    finite number; errors name the scanner, orientation, count and term."""
    where = f"{source}: phase_ripple"
    names = [s.name for s in rig.scanners]
    if not isinstance(doc, dict):
        raise CalibrationFileError(f"{where}: expected an object keyed by scanner")
    for scanner, per in doc.items():
        if scanner not in names:
            raise CalibrationFileError(f"{where}: unknown scanner {scanner!r}; the calibration has {', '.join(names)}")
        if not isinstance(per, dict):
            raise CalibrationFileError(f"{where} {scanner}: expected an object keyed by orientation (x, y)")
        for o, rec in per.items():
            at = f"{where} {scanner} {o}"
            if o not in ("x", "y"):
                raise CalibrationFileError(f"{at}: unknown orientation; expected x or y")
            freqs = rec.get("frequencies_per_fringe") if isinstance(rec, dict) else None
            counts = rec.get("counts") if isinstance(rec, dict) else None
            if not isinstance(freqs, list) or len(freqs) < 2 or not isinstance(counts, dict) or not counts:
                raise CalibrationFileError(f"{at}: expected frequencies_per_fringe and counts")
            for t, terms in counts.items():
                for f in freqs:
                    entry = terms.get(f"f{f}") if isinstance(terms, dict) else None
                    for key in _RIPPLE_TERMS:
                        v = entry.get(key) if isinstance(entry, dict) else None
                        if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v):
                            raise CalibrationFileError(f"{at}: count {t}, f{f} {key}: not a finite number")
            rec.setdefault("orientation", o)
    return doc


def read_calibration(path) -> Calibration:
    """A calibration file (``.json`` with covariance and provenance, or the ``.xml``)."""
    path = Path(path)
    if not path.is_file():
        raise CalibrationFileError(f"{path}: no such file" if not path.exists() else f"{path}: not a file")
    if path.suffix.lower() == ".xml":  # the thesis layout: sensors and their observed regions only
        rig, regions = _read_xml(path)
        return Calibration(rig, observed_regions=regions)
    d = _json_document(path)
    rig = rig_from_dict(d, str(path))
    cov = _covariances(d["covariance"], rig, str(path)) if "covariance" in d else None
    replicas = _replicas(d["replicas"], rig, str(path)) if "replicas" in d else {}
    ripple = _phase_ripple(d["phase_ripple"], rig, str(path)) if "phase_ripple" in d else {}
    return Calibration(rig, cov, dict(d.get("provenance") or {}), dict(d.get("metadata") or {}), d.get("black_boxes"),
                       replicas, ripple, _observed_regions(d, rig, str(path)))


def _observed_regions(d: dict, rig: Rig, source: str) -> dict:
    """sensor name -> :class:`~fringecal.lens.observed_region.ObservedRegion` of every
    sensor entry that has an ``observed_region`` (checked: its grid, and its format the
    sensor's)."""
    out = {}
    formats = {s.name: s.format for s in rig.sensors}
    for sc in d["scanners"]:
        for se in sc["sensors"]:
            if "observed_region" not in se:
                continue
            where = f"{source}: scanner {sc['name']!r} sensor {se['name']!r}: observed_region"
            try:
                region = ObservedRegion.from_dict(se["observed_region"])
            except ValueError as err:
                raise CalibrationFileError(f"{where}: {err}") from None
            fmt = formats[se["name"]]
            if not np.allclose([region.width_mm, region.height_mm], fmt.size_mm, rtol=1e-9):
                raise CalibrationFileError(f"{where}: format_mm {[region.width_mm, region.height_mm]} is not the "
                                           f"sensor's format ({fmt.width_mm} x {fmt.height_mm} mm)")
            out[se["name"]] = region
    return out


def write_calibration_xml(rig: Rig, path, metadata: dict | None = None, observed_regions: dict | None = None) -> Path:
    return write_text(Path(path), xml_text(rig, metadata, observed_regions))


def _xml_region(parent, region: dict) -> None:
    """An ``observed_region`` entry (:meth:`ObservedRegion.to_dict`) as XML under ``parent``."""
    e = ET.SubElement(parent, "observed_region", {
        "unit": region["unit"], "format_mm": " ".join(map(repr, region["format_mm"])),
        "cells": " ".join(map(str, region["cells"])), "min_points_per_cell": str(region["min_points_per_cell"]),
        "fraction_observed": repr(region["fraction_observed"])})
    for x, y in region["hull_mm"]:
        ET.SubElement(e, "vertex", x_mm=repr(x), y_mm=repr(y))
    ET.SubElement(e, "points_per_cell").text = "\n".join(" ".join(map(str, row)) for row in region["points_per_cell"])


def _xml_region_entry(e, where: str) -> dict:
    """The ``observed_region`` entry of an ``<observed_region>`` element (checked by
    :func:`_observed_regions` as the JSON's)."""
    try:
        counts = [[int(v) for v in line.split()] for line in (e.findtext("points_per_cell") or "").split("\n")
                  if line.strip()]
        return {"format_mm": [float(v) for v in e.get("format_mm", "").split()],
                "cells": [int(v) for v in e.get("cells", "").split()],
                "min_points_per_cell": int(e.get("min_points_per_cell", "")),
                "hull_mm": [[float(v.get("x_mm")), float(v.get("y_mm"))] for v in e.findall("vertex")],
                "points_per_cell": counts}
    except (TypeError, ValueError) as err:
        raise CalibrationFileError(f"{where} <observed_region>: not numbers where numbers belong ({err})") from None


def xml_text(rig: Rig, metadata: dict | None = None, observed_regions: dict | None = None) -> str:
    """The XML calibration document of ``rig`` (see the module's layout), with each
    sensor's ``observed_regions`` entry where it has one (sensor name ->
    :class:`~fringecal.lens.observed_region.ObservedRegion`)."""
    return document_xml(rig_to_dict(rig, metadata, observed_regions=observed_regions))


def calibration_texts(doc: dict) -> tuple[str, str]:
    """The JSON and the XML text of one calibration document (:func:`rig_to_dict`): the
    XML made from the same document, so it carries every sensor's observed region the
    JSON does (and the thesis layout's parameters; the other blocks are the JSON's)."""
    return json.dumps(doc, indent=2) + "\n", document_xml(doc)


def document_xml(d: dict) -> str:
    """The XML text of a calibration document (:func:`rig_to_dict`): sensors, their
    thin-prism terms, correction fields and observed regions where it has them, and the
    metadata."""
    root = ET.Element("calibration", software=d["software"], version=d["version"],
                      reference_scanner=d["reference_scanner"])
    for sc in d["scanners"]:
        e_sc = ET.SubElement(root, "scanner", name=sc["name"])
        for se in sc["sensors"]:
            e_se = ET.SubElement(e_sc, "sensor", name=se["name"], role=se["role"])
            ET.SubElement(e_se, "format", {k: repr(v) if isinstance(v, float) else str(v)
                                           for k, v in se["format"].items()})
            for group, names in _GROUPS.items():
                e_g = ET.SubElement(e_se, group)
                for n in names:
                    p = se["parameters"][n]
                    attrs = {"unit": p["unit"], "free": "true" if p["free"] else "false"}
                    if "u" in p:
                        attrs["u"] = repr(p["u"])
                    ET.SubElement(e_g, n, attrs).text = repr(p["value"])
            extra = [("thin_prism", se.get("thin_prism"), {})]
            if "correction_field" in se:
                cf = se["correction_field"]
                extra.append(("correction_field", cf["coefficients"], {"degree": str(cf["degree"])}))
            for tag, entries, head in extra:  # beyond the thesis's layout, only where the model has them
                if entries is None:
                    continue
                e_g = ET.SubElement(e_se, tag, head)
                for n, p in entries.items():
                    attrs = {"unit": p["unit"], "free": "true" if p["free"] else "false"}
                    if "u" in p:
                        attrs["u"] = repr(p["u"])
                    ET.SubElement(e_g, n, attrs).text = repr(p["value"])
            if "observed_region" in se:
                _xml_region(e_se, se["observed_region"])
    meta = ET.SubElement(root, "metadata")
    for k, v in d["metadata"].items():
        ET.SubElement(meta, "item", key=str(k)).text = json.dumps(v)
    ET.indent(root)
    return '<?xml version="1.0" encoding="utf-8"?>\n' + ET.tostring(root, encoding="unicode") + "\n"


def _xml_leaves(element, where: str) -> dict:
    """name -> {value, free[, u]} of an element's parameter leaves (beyond the thesis's layout)."""
    out = {}
    for e_p in element:
        try:
            out[e_p.tag] = {"value": float(e_p.text), "free": e_p.get("free", "false") == "true",
                            **({"u": float(e_p.get("u"))} if e_p.get("u") is not None else {})}
        except (TypeError, ValueError):
            raise CalibrationFileError(f"{where} <{element.tag}><{e_p.tag}>: not a number: {e_p.text!r}") from None
    return out


def read_calibration_xml(path) -> Rig:
    return _read_xml(path)[0]


def _read_xml(path) -> tuple[Rig, dict]:
    """The rig of an XML calibration file and its sensors' observed regions."""
    path = Path(path)
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as err:
        raise CalibrationFileError(f"{path}: not well-formed XML ({err})") from None
    if root.tag != "calibration":
        raise CalibrationFileError(f"{path}: root element is <{root.tag}>, expected <calibration>")
    d = {"reference_scanner": root.get("reference_scanner"), "scanners": []}
    for e_sc in root.findall("scanner"):
        sc = {"name": e_sc.get("name"), "sensors": []}
        for e_se in e_sc.findall("sensor"):
            where = f"scanner {sc['name']!r} sensor {e_se.get('name')!r}"
            fmt = e_se.find("format")
            if fmt is None:
                raise CalibrationFileError(f"{path}: {where} has no <format>")
            params = {}
            for group, names in _GROUPS.items():
                e_g = e_se.find(group)
                if e_g is None:
                    raise CalibrationFileError(f"{path}: {where} has no <{group}>")
                for n in names:
                    e_p = e_g.find(n)
                    if e_p is None or e_p.text is None:
                        raise CalibrationFileError(f"{path}: {where} <{group}> has no <{n}> value")
                    try:
                        p = {"value": float(e_p.text), "free": e_p.get("free", "true") == "true"}
                        if e_p.get("u") is not None:
                            p["u"] = float(e_p.get("u"))
                    except ValueError:
                        raise CalibrationFileError(f"{path}: {where} <{n}>: not a number: {e_p.text!r}") from None
                    params[n] = p
            entry = {"name": e_se.get("name"), "role": e_se.get("role"), "format": dict(fmt.attrib),
                     "parameters": params}
            e_tp = e_se.find("thin_prism")
            if e_tp is not None:
                entry["thin_prism"] = _xml_leaves(e_tp, f"{path}: {where}")
            e_cf = e_se.find("correction_field")
            if e_cf is not None:
                terms = _xml_leaves(e_cf, f"{path}: {where}")
                try:
                    degree = int(e_cf.get("degree", ""))
                except ValueError:
                    raise CalibrationFileError(f"{path}: {where} <correction_field degree={e_cf.get('degree')!r}>: "
                                               "not a whole number") from None
                entry["correction_field"] = {"degree": degree, "coefficients": terms}
            e_or = e_se.find("observed_region")
            if e_or is not None:
                entry["observed_region"] = _xml_region_entry(e_or, f"{path}: {where}")
            sc["sensors"].append(entry)
        d["scanners"].append(sc)
    rig = rig_from_dict(d, str(path))
    return rig, _observed_regions(d, rig, str(path))
