"""The observed region (:mod:`fringecal.lens.observed_region`) in the calibration's other
files: the XML calibration file (image-plane mm, as ``calibration.json``) and the OpenCV
FileStorage export (the hull's vertices in each sensor's OpenCV pixels), both read back
by fringecal.

The regions are built on the thesis rig's four sensors (2048 x 2048 cameras, 1400 x
1050 projectors) from uniform observations over a different part of each format, so
every hull has a few dozen vertices off any grid."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from fringecal.calibration.file import CalibrationFileError, read_calibration, rig_to_dict, xml_text
from fringecal.flows.cli import app
from fringecal.interop.opencv_storage import read_stereo, stereo_text, write_rig
from fringecal.lens.observed_region import ObservedRegion


def _regions(rig) -> dict:
    out = {}
    for k, s in enumerate(rig.sensors):
        rng = np.random.default_rng(k)
        w, h = s.format.width_mm, s.format.height_mm
        obs = np.stack([rng.uniform(-w / 2 + 0.3 * k, w / 4, 4000), rng.uniform(-h / 3, h / 2, 4000)], axis=-1)
        out[s.name] = ObservedRegion.from_observations(obs, w, h)
    return out


def _pixels(sensor, image_mm):
    """fringecal's image (mm) -> the OpenCV pixel of its own definitions (as
    tests/test_opencv_interop.py): eq. 2-21 for a camera, eq. 2-22 over the SLM's pixels
    for a projector (tau = +-pi at the outer edges, pixel centres at integers)."""
    if sensor.role == "camera":
        return sensor.format.mm_to_pixel(image_mm)
    n = np.array([sensor.format.width_px, sensor.format.height_px], float)
    return (sensor.format.mm_to_phase(image_mm) / (2 * np.pi) + 0.5) * n - 0.5


def test_regions_round_trip_through_the_xml_calibration_file(thesis_rig, tmp_path):
    """Every sensor's region written into the XML reads back equal (hull bit for bit,
    counts, threshold); an XML without regions reads as not known ({}) with the same rig;
    a broken region is one CalibrationFileError naming it."""
    regions = _regions(thesis_rig)
    path = tmp_path / "calibration.xml"
    path.write_text(xml_text(thesis_rig, {"note": 1}, regions))
    cal = read_calibration(path)
    assert set(cal.observed_regions) == {s.name for s in thesis_rig.sensors}
    for name, r in regions.items():
        assert cal.observed_regions[name] == r and len(r.hull) >= 8 and 0.2 < r.fraction < 0.8
    plain = tmp_path / "plain.xml"
    plain.write_text(xml_text(thesis_rig, {"note": 1}))
    assert read_calibration(plain).observed_regions == {}
    np.testing.assert_array_equal(read_calibration(plain).rig.params, cal.rig.params)
    broken = path.read_text().replace("<points_per_cell>", "<points_per_cell>1 2\n", 1)
    path.write_text(broken)
    with pytest.raises(CalibrationFileError, match="observed_region"):
        read_calibration(path)


def test_opencv_export_carries_each_hull_in_pixels_and_reads_back(thesis_rig, tmp_path):
    """``observedHullPx1/2`` are the hull's vertices in OpenCV pixels: equal (1e-9 px) to
    the mm hull converted by the pixel definitions themselves, and read back by
    read_stereo to the mm hull (1e-12 mm); ``observedFraction`` is the region's. A
    scanner exported without regions has neither key, its text unchanged; a region that
    observed nothing is a 0 x 2 matrix and reads back empty."""
    regions = _regions(thesis_rig)
    written = write_rig(thesis_rig, tmp_path, grid=9, regions=regions)
    for scanner in thesis_rig.scanners:
        path = written[scanner.name][0]
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
        st = read_stereo(path)
        for i, sensor in ((1, scanner.camera), (2, scanner.projector)):
            hull = regions[sensor.name].hull
            px = fs.getNode(f"observedHullPx{i}").mat()
            assert px.shape == hull.shape
            np.testing.assert_allclose(px, _pixels(sensor, hull), rtol=0, atol=1e-9)
            assert fs.getNode(f"observedFraction{i}").real() == pytest.approx(regions[sensor.name].fraction, rel=1e-15)
            np.testing.assert_array_equal(st.hull_px1 if i == 1 else st.hull_px2, px)
            np.testing.assert_allclose(st.hull_mm(i), hull, rtol=0, atol=1e-12)
        fs.release()
        text = path.read_text()
        assert "PIXELS" in text and "observed" in text
        plain = stereo_text(scanner, grid=9)[0]
        assert "observed" not in plain and plain == stereo_text(scanner, grid=9, regions={})[0]
    plain_path = tmp_path / "plain.yml"
    plain_path.write_text(stereo_text(thesis_rig.scanners[0], grid=9)[0])
    assert read_stereo(plain_path).hull_px1 is None and read_stereo(plain_path).hull_mm(1) is None
    cam = thesis_rig.scanners[0].camera
    empty = {cam.name: ObservedRegion.from_observations(np.zeros((0, 2)), cam.format.width_mm, cam.format.height_mm)}
    plain_path.write_text(stereo_text(thesis_rig.scanners[0], grid=9, regions=empty)[0])
    back = read_stereo(plain_path)
    assert back.hull_px1.shape == (0, 2) and back.hull_px2 is None


def test_cli_export_of_a_run_calibration_writes_its_regions(thesis_rig, tmp_path):
    """``fringecal export opencv --calibration calibration.json`` (and the XML) exports
    the regions the file holds; a sensor table has none."""
    regions = _regions(thesis_rig)
    (tmp_path / "calibration.json").write_text(json.dumps(rig_to_dict(thesis_rig, observed_regions=regions)))
    (tmp_path / "calibration.xml").write_text(xml_text(thesis_rig, None, regions))
    runner = CliRunner()
    for name in ("calibration.json", "calibration.xml"):
        out = tmp_path / f"cv-{name}"
        res = runner.invoke(app, ["export", "opencv", "--calibration", str(tmp_path / name), "--out", str(out),
                                  "--json"])
        assert res.exit_code == 0, res.output
        st = read_stereo(out / "scanner1.yml")
        np.testing.assert_allclose(st.hull_mm(2), regions[thesis_rig.scanners[0].projector.name].hull, atol=1e-12)


def test_the_run_directory_s_one_save_path_keeps_the_regions(thesis_rig, small_run, tmp_path):
    """``RunDir.calibration.save`` writes each sensor's region into the JSON and the XML
    (both read back equal, hull bit for bit) and none when given none; the bundle step
    writes through the same path (the session's small run: its XML's regions equal its
    JSON's), and no other module makes a calibration's XML text."""
    import re
    from pathlib import Path

    from fringecal.rundir import RunDir

    regions = _regions(thesis_rig)
    rd = RunDir(tmp_path / "run").create()
    rd.calibration.save(thesis_rig, {"note": 1}, observed_regions=regions)
    for path in (rd.calibration.path, rd.calibration.xml.path):
        back = read_calibration(path)
        assert back.observed_regions == regions
        np.testing.assert_array_equal(back.rig.params, thesis_rig.params)
    assert read_calibration(rd.calibration.path).metadata == {"note": 1}
    rd.calibration.save(thesis_rig)
    assert read_calibration(rd.calibration.path).observed_regions == {}
    assert read_calibration(rd.calibration.xml.path).observed_regions == {}
    run = small_run[0]
    from_json = read_calibration(run.calibration.path).observed_regions
    assert len(from_json) == 4 and read_calibration(run.calibration.xml.path).observed_regions == from_json
    root = Path(__file__).resolve().parents[1]
    makers = sorted(str(p.relative_to(root)) for folder in ("fringecal", "flows", "tasks") for p in
                    (root / folder).rglob("*.py")
                    if re.search(r"\b(xml_text|document_xml|calibration_texts|write_calibration_xml)\(", p.read_text())
                    and p.name != "file.py")
    assert makers == ["fringecal/rundir.py"]


def test_import_opencv_keeps_each_sensor_s_region(thesis_rig, tmp_path):
    """Export -> ``fringecal import opencv --out prior.json``: every sensor's region comes
    back (hull within 1e-12 mm of the exported one, grid counts and threshold equal) in
    the JSON and its XML twin; a sensor table cannot hold them and says so; a grid that
    does not fit its hull's format is one message naming the file and key."""
    regions = _regions(thesis_rig)
    written = write_rig(thesis_rig, tmp_path / "cv", grid=9, regions=regions)
    stereo = [str(written[s.name][0]) for s in thesis_rig.scanners]
    args = ["import", "opencv", *[a for p in stereo for a in ("--stereo", p)]]
    runner = CliRunner()
    res = runner.invoke(app, [*args, "--out", str(tmp_path / "prior.json"), "--json"])
    assert res.exit_code == 0, res.output
    assert json.loads(res.stdout)["regions"] == "kept"
    for path in (tmp_path / "prior.json", tmp_path / "prior.xml"):
        back = read_calibration(path).observed_regions
        assert set(back) == set(regions)
        for name, r in regions.items():
            np.testing.assert_allclose(back[name].hull, r.hull, rtol=0, atol=1e-12)
            np.testing.assert_array_equal(back[name].counts, r.counts)
            assert back[name].min_points == r.min_points
            assert back[name].fraction == pytest.approx(r.fraction, rel=1e-12)
    res = runner.invoke(app, [*args, "--out", str(tmp_path / "prior.csv"), "--json"])
    assert res.exit_code == 0 and json.loads(res.stdout)["regions"].startswith("not kept: a sensor table")
    bad = tmp_path / "bad.yml"
    bad.write_text(open(stereo[0]).read().replace("observedMinPoints1: 5", "observedMinPoints1: 0"))
    res = runner.invoke(app, ["import", "opencv", "--stereo", str(bad), "--out", str(tmp_path / "bad.json")])
    assert res.exit_code == 2 and f"{bad}: key 'observedMinPoints1' must be a whole number >= 1" in res.output
    assert not (tmp_path / "bad.json").exists()
