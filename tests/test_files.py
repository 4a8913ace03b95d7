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


def test_phase_ripple_travels_in_the_calibration_and_bad_entries_are_named(tmp_path, thesis_rig):
    """A scanner's phase ripple (what its decoder corrects small stacks with) travels in
    calibration.json for `fringecal measure` away from the run; a wrong scanner,
    orientation or value stops with the file, the block and the entry."""
    import json

    from fringecal.calibration.file import read_calibration, rig_to_dict
    from fringecal.fringe.ripple import PhaseRipple, ripple_document, scanner_ripple
    from fringecal.fringe.sequence import FringeSequence

    seq = FringeSequence(n_steps=3)
    k, n_f = len(seq.fringe_counts), 4
    coef = np.linspace(-0.1, 0.2, k * n_f * 2).reshape(k, n_f, 2)
    fit = PhaseRipple("x", (2, 3, 6, 9), coef, np.diag(np.full(coef.size, 1e-6)), 1e4, 5000, 0.2, 0.1,
                      applied=True).to_dict(seq)
    block = {"scanner1": ripple_document([fit, fit])}
    assert block["scanner1"]["x"]["applied"] and block["scanner1"]["x"]["source"] == "scanner"
    p = tmp_path / "cal.json"
    p.write_text(json.dumps(rig_to_dict(thesis_rig, phase_ripple=block)))
    back = read_calibration(p).phase_ripple
    assert back == block
    # read back, it corrects as the run's own fits did: their mean, with its u
    again = scanner_ripple(list(back["scanner1"].values()), seq)["x"]
    np.testing.assert_allclose(again.coefficients, coef, rtol=1e-12)
    np.testing.assert_allclose(np.diag(again.covariance), 5e-7, rtol=1e-9)
    # what fringecal measure corrects a scanner's small stacks with, the file read away from its run
    from fringecal.measure.run import _ripple_fits

    assert _ripple_fits(read_calibration(p), p) == {"scanner1": [block["scanner1"]["x"]], "scanner2": []}
    write_calibration_json(thesis_rig, tmp_path / "plain.json")
    assert read_calibration(tmp_path / "plain.json").phase_ripple == {}
    for change, message in (
            (lambda d: d.update(scanner9=d.pop("scanner1")), r"cal.json: phase_ripple: unknown scanner 'scanner9'"),
            (lambda d: d["scanner1"].update(z=d["scanner1"].pop("x")), r"phase_ripple scanner1 z: unknown orientation"),
            (lambda d: d["scanner1"]["x"]["counts"]["48"]["f6"].update(u_sin_rad="n/a"),
             r"phase_ripple scanner1 x: count 48, f6 u_sin_rad: not a finite number"),
            (lambda d: d["scanner1"]["x"].pop("counts"), r"phase_ripple scanner1 x: expected frequencies_per_fringe")):
        bad = json.loads(json.dumps(block))
        change(bad)
        p.write_text(json.dumps(rig_to_dict(thesis_rig, phase_ripple=bad)))
        with pytest.raises(CalibrationFileError, match=message):
            read_calibration(p)


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
