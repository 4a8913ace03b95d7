"""Calibration file (XML + JSON) and the legacy artefact definition: lossless round trips."""

import numpy as np
import pytest

from fringecal.artefact import read_legacy_definition, write_legacy_definition
from fringecal.calibration.file import (
    CalibrationFileError,
    read_calibration_json,
    read_calibration_xml,
    write_calibration_json,
    write_calibration_xml,
)
from fringecal.rig import Rig
from fringecal.schemas import TableError


def perturbed_rig(rig: Rig, rng) -> Rig:
    params = rig.params * (1 + rng.normal(size=rig.params.shape) * 1e-7)  # full-precision floats
    unc = np.abs(rng.normal(size=rig.params.shape)) * 1e-3
    return rig.with_params(params, uncertainty=unc)


def test_xml_and_json_round_trip_bit_for_bit(tmp_path, thesis_rig, rng):
    rig = perturbed_rig(thesis_rig, rng)
    for write, read, name in [(write_calibration_xml, read_calibration_xml, "cal.xml"),
                              (write_calibration_json, read_calibration_json, "cal.json")]:
        write(rig, tmp_path / name, metadata={"rms_eps2_mm": 0.087})
        back = read(tmp_path / name)
        np.testing.assert_array_equal(back.params, rig.params)
        np.testing.assert_array_equal(back.uncertainty, rig.uncertainty)
        np.testing.assert_array_equal(back.free, rig.free)
        assert back.reference == rig.reference
        assert [(s.name, s.role, s.format) for s in back.sensors] == [(s.name, s.role, s.format) for s in rig.sensors]
    assert not list(tmp_path.glob(".*tmp"))


def test_replicas_round_trip_bit_for_bit_and_bad_ones_are_named(tmp_path, thesis_rig, rng):
    """The calibration's bootstrap and jackknife replicas travel in calibration.json (what
    `fringecal measure` states distances with) and come back as (n, n_sensors, 14), bit
    for bit; a wrong shape, a non-finite value or an unknown kind stops with the file,
    the block and the row or parameter."""
    import json

    from fringecal.calibration.file import read_calibration, replicas_document, rig_to_dict

    boot = thesis_rig.params * (1 + rng.normal(size=(5,) + thesis_rig.params.shape) * 1e-6)
    jack = thesis_rig.params * (1 + rng.normal(size=(4,) + thesis_rig.params.shape) * 1e-6)
    noise = thesis_rig.params * (1 + rng.normal(size=(2, 4) + thesis_rig.params.shape) * 1e-6)
    doc = rig_to_dict(thesis_rig, replicas=replicas_document({"bootstrap": boot, "jackknife": jack,
                                                              "jackknife_noise": noise}, "1234"))
    p = tmp_path / "cal.json"
    p.write_text(json.dumps(doc))
    back = read_calibration(p).replicas
    np.testing.assert_array_equal(back["bootstrap"], boot)
    np.testing.assert_array_equal(back["jackknife"], jack)
    np.testing.assert_array_equal(back["jackknife_noise"], noise)
    assert doc["replicas"]["jackknife"]["left_out"] == ["1", "2", "3", "4"]
    write_calibration_json(thesis_rig, tmp_path / "plain.json")
    assert read_calibration(tmp_path / "plain.json").replicas == {}

    bad = json.loads(json.dumps(doc))
    bad["replicas"]["jackknife"]["params"][2][14] = "nan"  # the first of P1
    p.write_text(json.dumps(bad).replace('"nan"', "NaN"))
    with pytest.raises(CalibrationFileError, match=r"cal.json: replicas 'jackknife': params row 2, P1.x0: not a finite"):
        read_calibration(p)
    bad = json.loads(json.dumps(doc))
    bad["replicas"]["bootstrap"]["params"][0] = bad["replicas"]["bootstrap"]["params"][0][:-1]
    p.write_text(json.dumps(bad))
    with pytest.raises(CalibrationFileError, match=r"replicas 'bootstrap': params row 0 has 55 values, expected 56"):
        read_calibration(p)
    bad = json.loads(json.dumps(doc))
    bad["replicas"]["jackknife"]["noise_params"].pop()
    p.write_text(json.dumps(bad))
    with pytest.raises(CalibrationFileError, match=r"noise_params has 7 rows, expected noise_draws \(2\) times the 4"):
        read_calibration(p)
    bad = json.loads(json.dumps(doc))
    bad["replicas"]["halves"] = bad["replicas"].pop("bootstrap")
    p.write_text(json.dumps(bad))
    with pytest.raises(CalibrationFileError, match="replicas 'halves': unknown kind"):
        read_calibration(p)


def test_xml_is_hierarchical_per_scanner(tmp_path, thesis_rig):
    import xml.etree.ElementTree as ET

    write_calibration_xml(thesis_rig, tmp_path / "cal.xml")
    root = ET.parse(tmp_path / "cal.xml").getroot()
    assert [s.get("name") for s in root.findall("scanner")] == ["scanner1", "scanner2"]
    c1 = root.find("scanner/sensor[@name='C1']")
    assert c1.get("role") == "camera"
    assert c1.find("external/x0").text == "694.018" and c1.find("external/x0").get("free") == "false"
    assert c1.find("distortion/k1").get("unit") == "mm^-2"


def test_malformed_calibration_files(tmp_path, thesis_rig):
    p = tmp_path / "cal.xml"
    write_calibration_xml(thesis_rig, p)
    p.write_text(p.read_text().replace(">52.701<", ">fifty<"))
    with pytest.raises(CalibrationFileError, match="sensor 'C1' <c>: not a number: 'fifty'"):
        read_calibration_xml(p)
    p.write_text("<calibration><scanner")
    with pytest.raises(CalibrationFileError, match="not well-formed"):
        read_calibration_xml(p)


def test_legacy_definition_round_trip(tmp_path, thesis_artefact):
    p = tmp_path / "artefact.def"
    write_legacy_definition(thesis_artefact, p)
    lines = p.read_text().splitlines()
    assert len(lines) == 60  # 15 spheres x 4 rows, as section 6.6
    assert lines[0].split() == ["x", "0", "0.0", "0.01"]
    assert lines[3].split()[:3] == ["r", "0", repr(49.998 / 2)]
    art, flags = read_legacy_definition(p, ids=thesis_artefact.ids)
    np.testing.assert_array_equal(art.centres, thesis_artefact.centres)
    np.testing.assert_array_equal(art.diameters, thesis_artefact.diameters)
    assert flags.shape == (15, 4) and not flags.any()


def test_legacy_definition_reads_thesis_example(tmp_path):
    p = tmp_path / "example.def"
    p.write_text("x\t1\t600\t0\ny\t1\t600\t0\nz\t1\t600\t0\nr\t1\t25\t0\n")
    art, flags = read_legacy_definition(p)
    assert art.ids == ("1",) and art.centres.tolist() == [[600, 600, 600]] and art.diameters.tolist() == [50]
    assert flags.all()


def test_legacy_definition_errors(tmp_path):
    p = tmp_path / "bad.def"
    p.write_text("x\t1\t600\t0\ny\t1\t600\t0\nq\t1\t600\t0\nr\t1\t25\t0\n")
    with pytest.raises(TableError, match=r"line 3, column 'description': expected 'z', found 'q'"):
        read_legacy_definition(p)
    p.write_text("x\t1\t600\t0\ny\t1\t600\n")
    with pytest.raises(TableError, match="line 2: expected 4 columns"):
        read_legacy_definition(p)
