"""The acceptance test states, per object position, the share of its fits' pixels
outside the calibration's observed region (``acceptance.json`` ``observed_region``,
:mod:`fringecal.acceptance.observed`), counted as the ball-bar's is.

The world: the small thesis rig's acceptance objects (one sphere, dumbbell and flat per
scanner, noise-free at 300 px, where a dumbbell sphere keeps enough pixels to be found;
as tests/test_simulate_acceptance.py renders them at 200 px),
measured with the true sensors. The region is built here: scanner1's camera observed
only the part of its format left of its sphere's middle column, so part of that sphere
lies outside and the counts are known by a plain comparison of image-plane x with the
cut; nothing else has a region (a sensor without one flags nothing).
"""

import numpy as np
import pytest
import yaml

from fringecal.acceptance.document import measure_acceptance
from fringecal.acceptance.observed import objects_outside, partly_outside
from fringecal.acceptance.standards import AcceptanceStandards
from fringecal.lens.observed_region import ObservedRegion
from fringecal.report.sections.acceptance import _values
from fringecal.run.config import load_run_config
from fringecal.rundir import RunDir
from fringecal.simulate.small_thesis import write_small_thesis_config
from fringecal.steps.acceptance import acceptance_stores
from fringecal.store import open_store
from fringecal.verification.measure import store_scanner


@pytest.fixture(scope="module")
def measured(tmp_path_factory):
    """The stores, the true rig and the acceptance values with the pixels each fit kept."""
    from fringecal.steps import run_pipeline

    d = tmp_path_factory.mktemp("acceptance-region")
    path = write_small_thesis_config(d, width=64, poses=(1,), positions=(1,))
    raw = yaml.safe_load(path.read_text())
    raw["simulate"]["acquisition"]["render"] = {"shot_noise": False, "read_noise_e": 0.0, "excess_noise": 0.0}
    raw["simulate"]["acceptance"] = {"sphere": 1, "dumbbell": 1, "flat": 1, "camera_width_px": 300}
    path.write_text(yaml.safe_dump(raw))
    cfg = load_run_config(path)
    rd = RunDir(d / "run").create()
    run_pipeline(rd, cfg, until="simulate-flat")
    stores = acceptance_stores(rd)
    rig = rd.truth.sensors.load()
    values, failures, kept = measure_acceptance(stores, rig, AcceptanceStandards(**rd.acceptance_standards.load()),
                                                cfg.acceptance, cfg.extraction.rejection,
                                                cfg.verification.uncertainty, None, pixels=True)
    assert not failures
    return stores, rig, values, kept


def image_x(stores, rig, kind, position, scanner, rows, cols):
    """Image-plane x (mm) of camera pixels of a store (its camera at the store's size)."""
    with open_store(stores[kind][position][scanner]) as ds:
        camera = store_scanner(ds, rig.scanner(scanner)).camera
    return camera.image_mm(np.stack([cols, rows], axis=-1).astype(float))[:, 0]


def left_of(camera, x_cut: float) -> ObservedRegion:
    """A region of ``camera``: the part of its format left of image-plane x = ``x_cut``."""
    w, h = camera.format.width_mm, camera.format.height_mm
    hull = np.array([[-w / 2, -h / 2], [x_cut, -h / 2], [x_cut, h / 2], [-w / 2, h / 2]])
    return ObservedRegion(w, h, np.zeros((16, 16)), hull)


def test_each_object_s_share_outside_equals_a_recount_of_its_pixels(measured):
    """Every object's count equals the number of its scanner1 pixels right of the cut
    (the other sensors have no region); the sphere of scanner1 is partly outside (about
    half of it, 20-80 %), and each sphere's and flat's pixels are the points its fit kept."""
    stores, rig, values, kept = measured
    (pos, sc, _), (rows, cols) = next((k, v) for k, v in kept["sphere"].items() if k[1] == "scanner1")
    x_cut = float(np.median(image_x(stores, rig, "sphere", pos, sc, rows, cols)))
    camera = rig.scanner("scanner1").camera
    doc = objects_outside(stores, rig, kept, {camera.name: left_of(camera, x_cut)})
    assert doc["known"] is True
    assert {(o["test"], o["position"]) for o in doc["objects"]} == \
        {(kind, k[0]) for kind, px in kept.items() for k in px}
    for o in doc["objects"]:
        recount = {s: [0, 0] for s in o["scanners"]}
        for (p, s, _), (r, c) in kept[o["test"]].items():
            if p == o["position"]:
                recount[s][0] += len(r)
                if s == "scanner1":
                    recount[s][1] += int(np.sum(image_x(stores, rig, o["test"], p, s, r, c) > x_cut))
        assert {s: [e["points"], e["outside"]] for s, e in o["scanners"].items()} == recount
        assert o["points"] == sum(n for n, _ in recount.values()) and o["outside"] == sum(k for _, k in
                                                                                           recount.values())
        assert o["fraction"] == pytest.approx(o["outside"] / o["points"], abs=1e-12)
    sphere1 = next(o for o in doc["objects"] if o["test"] == "sphere" and "scanner1" in o["scanners"])
    assert 0.2 < sphere1["fraction"] < 0.8
    n_spheres = sum(o["test"] == "sphere" for o in doc["objects"])
    assert partly_outside(doc)[0] == f"sphere: 1 of {n_spheres} positions, up to {100 * sphere1['fraction']:.0f} %"
    for kind, parameter in (("sphere", "P_F"), ("flat", "F")):
        for (p, s, _), (r, _c) in kept[kind].items():
            row = values[(values.parameter == parameter) & (values.position == p) & (values.scanner == s)]
            assert len(r) == int(row.n_points.iloc[0]) > 100


def test_without_regions_every_share_is_not_known(measured):
    """A calibration without observed regions (None or empty, as read_calibration gives
    for an older file): ``known`` false and every share null, not 0; E copies the
    verification's count, or is not known when the verification has none."""
    stores, rig, _, kept = measured
    for regions in (None, {}):
        doc = objects_outside(stores, rig, kept, regions, {"calibrated": {"positions": [{"measurement": "bb01"}]}})
        assert doc["known"] is False
        assert len(doc["objects"]) == len({(kind, k[0]) for kind, px in kept.items() for k in px}) + 1  # and E's
        assert all(o["outside"] is None and o["fraction"] is None for o in doc["objects"])
        assert partly_outside(doc) == []
    counted = {"bb01": {"points": 40, "outside": 10, "fraction": 0.25, "scanners": {"scanner1": {"points": 40,
                                                                                                 "outside": 10}}}}
    e = objects_outside(stores, rig, kept, None, {"calibrated": {"positions": [], "observed_region": counted}})
    assert e["objects"][-1] == {"test": "ballbar", "position": "bb01", **counted["bb01"]}
    assert partly_outside(e) == []  # the verification step warns about the ball-bar's positions


def test_the_report_s_values_table_shows_each_share_or_not_known():
    """A sphere's row shows its scanner's share, a length's its position's, an object
    without a count (a black box's cloud, a calibration without regions) "not known";
    an acceptance.json written before the count has no such column."""
    values = [{"test": "sphere", "parameter": "P_F", "position": "s1", "scanner": "scanner1", "value_mm": 0.01,
               "U_mm": 0.002, "n_points": 300, "n_excluded": 1},
              {"test": "dumbbell", "parameter": "SD", "position": "d1", "scanner": "scanner1/scanner2",
               "value_mm": 0.02, "U_mm": 0.03, "n_points": 0, "n_excluded": 0},
              {"test": "flat", "parameter": "F", "position": "f1", "scanner": "scanner2", "value_mm": 0.01,
               "U_mm": 0.002, "n_points": 900, "n_excluded": 2}]
    region = {"known": True, "objects": [
        {"test": "sphere", "position": "s1", "points": 400, "outside": 100, "fraction": 0.25,
         "scanners": {"scanner1": {"points": 300, "outside": 30}, "scanner2": {"points": 100, "outside": 70}}},
        {"test": "dumbbell", "position": "d1", "points": 1000, "outside": 125, "fraction": 0.125, "scanners": {}}]}
    table = _values({"values": values, "observed_region": region})
    assert table.head[-1].text == "Outside observed region"
    assert [row[-1].text for row in table.rows] == ["10 %", "12 %", "not known"]
    unknown = {"known": False, "objects": [{**o, "outside": None, "fraction": None} for o in region["objects"]]}
    assert [row[-1].text for row in _values({"values": values, "observed_region": unknown}).rows] == \
        ["not known"] * 3
    assert "Outside observed region" not in [c.text for c in _values({"values": values}).head]


def test_summary_json_counts_per_test_the_positions_outside(small_run, small_config, tmp_path):
    """``summary.json``'s acceptance block counts, per test, the positions partly and
    wholly outside the observed region and the largest share, as ``acceptance.json``
    states them; a calibration without regions: ``known`` false and every count None
    (not known, never 0). The run directory is the session's small run (read through
    links) with an ``acceptance.json`` written here."""
    import pandas as pd

    from fringecal.acceptance.evaluate import VALUE_COLUMNS, certificate
    from fringecal.acceptance.standards import AcceptanceLimits
    from fringecal.run.summary import run_summary

    rd = RunDir(tmp_path / "run")
    rd.root.mkdir()
    for entry in small_run[0].root.iterdir():
        (rd.root / entry.name).symlink_to(entry, entry.is_dir())
    values = pd.DataFrame([("sphere", "P_S", f"sphere-1-0{i}", "scanner1", 0.01, 0.002, 900, 3) for i in (1, 2, 3)]
                          + [("flat", "F", "flat-2-01", "scanner2", 0.02, 0.002, 900, 3)], columns=VALUE_COLUMNS)
    doc = certificate(values, AcceptanceLimits(), 2.0, 0.003, ["scanner1", "scanner2"])

    def obj(test, position, points, outside):
        return {"test": test, "position": position, "points": points, "outside": outside,
                "fraction": outside / points, "scanners": {}}

    doc["observed_region"] = {"known": True, "objects": [
        obj("sphere", "sphere-1-01", 500, 500), obj("sphere", "sphere-1-02", 400, 100),
        obj("sphere", "sphere-1-03", 300, 0), obj("flat", "flat-2-01", 800, 0), obj("ballbar", "bb01", 250, 50)]}
    rd.acceptance.save(doc)
    cfg = load_run_config(small_config)
    counts = run_summary(rd, cfg)["acceptance"]["outside_observed_region"]
    assert counts == {"known": True, "tests": {
        "sphere": {"positions": 3, "partly_outside": 2, "wholly_outside": 1, "max_fraction": 1.0},
        "flat": {"positions": 1, "partly_outside": 0, "wholly_outside": 0, "max_fraction": 0.0},
        "ballbar": {"positions": 1, "partly_outside": 1, "wholly_outside": 0, "max_fraction": 0.2}}}
    doc["observed_region"] = {"known": False, "objects": [{**o, "outside": None, "fraction": None}
                                                          for o in doc["observed_region"]["objects"]]}
    rd.acceptance.save(doc)
    unknown = run_summary(rd, cfg)["acceptance"]["outside_observed_region"]
    assert unknown["known"] is False and {t: c["positions"] for t, c in unknown["tests"].items()} == \
        {"sphere": 3, "flat": 1, "ballbar": 1}
    assert all(v is None for c in unknown["tests"].values() for k, v in c.items() if k != "positions")
