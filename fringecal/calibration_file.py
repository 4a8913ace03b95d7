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
        </sensor>
        ...
      </scanner>
      <metadata><item key="...">value</item></metadata>
    </calibration>

Each parameter is a leaf ``<x0 unit="mm" free="false" u="0.012">694.018</x0>``; values
are written with Python's shortest round-trip representation, so reading a file back
gives the same floats bit for bit.
"""

from __future__ import annotations

import json
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from .atomic import write_text
from .rig import Rig, Scanner
from .sensor import PARAM_NAMES, Sensor, SensorFormat

__all__ = ["write_calibration_xml", "xml_text", "read_calibration_xml", "write_calibration_json",
           "read_calibration_json", "rig_to_dict", "rig_from_dict", "CalibrationFileError"]

_GROUPS = {
    "external": ("x0", "y0", "z0", "omega", "phi", "kappa"),
    "internal": ("xi_h", "eta_h", "c"),
    "distortion": ("k1", "k2", "k3", "p1", "p2"),
}
_UNITS = {"x0": "mm", "y0": "mm", "z0": "mm", "omega": "rad", "phi": "rad", "kappa": "rad",
          "xi_h": "mm", "eta_h": "mm", "c": "mm", "k1": "mm^-2", "k2": "mm^-4", "k3": "mm^-6",
          "p1": "mm^-1", "p2": "mm^-1"}


class CalibrationFileError(ValueError):
    """A calibration file is malformed; the message names the file and element."""


def rig_to_dict(rig: Rig, metadata: dict | None = None) -> dict:
    from . import __version__

    out = {"software": "fringecal", "version": __version__, "reference_scanner": rig.reference,
           "scanners": [], "metadata": dict(metadata or {})}
    k = 0
    for scanner in rig.scanners:
        entry = {"name": scanner.name, "sensors": []}
        for sensor in scanner.sensors:
            f = sensor.format
            params = {}
            for j, name in enumerate(PARAM_NAMES):
                p = {"value": float(sensor.params[j]), "unit": _UNITS[name], "free": bool(rig.free[k, j])}
                if rig.uncertainty is not None:
                    p["u"] = float(rig.uncertainty[k, j])
                params[name] = p
            entry["sensors"].append({
                "name": sensor.name, "role": sensor.role,
                "format": {"width_px": f.width_px, "height_px": f.height_px,
                           "width_mm": f.width_mm, "height_mm": f.height_mm},
                "parameters": params,
            })
            k += 1
        out["scanners"].append(entry)
    return out


def rig_from_dict(d: dict, source: str = "<calibration>") -> Rig:
    try:
        scanners, free, unc = [], [], []
        for sc in d["scanners"]:
            pair = {}
            for se in sc["sensors"]:
                f = se["format"]
                fmt = SensorFormat(int(f["width_px"]), int(f["height_px"]), float(f["width_mm"]), float(f["height_mm"]))
                p = se["parameters"]
                vals = [float(p[n]["value"]) for n in PARAM_NAMES]
                pair[se["role"]] = Sensor(se["name"], se["role"], fmt, vals)
                free.append([bool(p[n]["free"]) for n in PARAM_NAMES])
                unc.append([float(p[n]["u"]) if "u" in p[n] else np.nan for n in PARAM_NAMES])
            scanners.append(Scanner(sc["name"], pair["camera"], pair["projector"]))
        u = np.array(unc)
        return Rig(tuple(scanners), d["reference_scanner"], np.array(free),
                   None if np.isnan(u).all() else u)
    except (KeyError, TypeError, ValueError) as err:
        raise CalibrationFileError(f"{source}: malformed calibration ({type(err).__name__}: {err})") from None


def write_calibration_json(rig: Rig, path, metadata: dict | None = None) -> Path:
    return write_text(Path(path), json.dumps(rig_to_dict(rig, metadata), indent=2) + "\n")


def read_calibration_json(path) -> Rig:
    path = Path(path)
    try:
        d = json.loads(path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as err:
        raise CalibrationFileError(f"{path}: not valid JSON ({err})") from None
    return rig_from_dict(d, str(path))


def write_calibration_xml(rig: Rig, path, metadata: dict | None = None) -> Path:
    return write_text(Path(path), xml_text(rig, metadata))


def xml_text(rig: Rig, metadata: dict | None = None) -> str:
    """The XML calibration document of ``rig`` (see the module's layout)."""
    d = rig_to_dict(rig, metadata)
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
    meta = ET.SubElement(root, "metadata")
    for k, v in d["metadata"].items():
        ET.SubElement(meta, "item", key=str(k)).text = json.dumps(v)
    ET.indent(root)
    return '<?xml version="1.0" encoding="utf-8"?>\n' + ET.tostring(root, encoding="unicode") + "\n"


def read_calibration_xml(path) -> Rig:
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
            sc["sensors"].append({"name": e_se.get("name"), "role": e_se.get("role"),
                                  "format": dict(fmt.attrib), "parameters": params})
        d["scanners"].append(sc)
    return rig_from_dict(d, str(path))
