"""The observed region of a sensor (fringecal.lens.observed_region): the grid, its covered
fraction and ``contains`` against regions known by construction, and its round trip
through calibration.json."""

import json

import numpy as np
import pytest

from fringecal.lens.observed_region import MIN_POINTS_PER_CELL, ObservedRegion, grid_shape

#: the thesis projector's format (mm): 4:3, a 16 x 12 grid
W, H = 19.0, 14.3


def _uniform(x0, x1, y0, y1, n=200, seed=0):
    rng = np.random.default_rng(seed)
    return np.stack([rng.uniform(x0, x1, n * n), rng.uniform(y0, y1, n * n)], axis=-1)


def test_observations_over_the_left_half_cover_half_the_format_and_contain_exactly_it():
    """40,000 points uniform over x < 0: every left cell holds ~312 points, no right cell
    one; the hull covers half the format (within 0.1 %: the hull of uniform points falls
    short of their rectangle by about its perimeter over sqrt(n)) and ``contains`` is
    x < 0 but within 0.05 mm of the rectangle's edges."""
    obs = _uniform(-W / 2, 0.0, -H / 2, H / 2)
    region = ObservedRegion.from_observations(obs, W, H)
    assert region.shape == grid_shape(W, H) == (12, 16)
    assert abs(region.fraction - 0.5) < 1e-3 and region.fraction_of_cells == 0.5
    assert region.observed[:, :8].all() and not region.observed[:, 8:].any()
    assert region.counts.sum() == len(obs)
    probe = _uniform(-W / 2, W / 2, -H / 2, H / 2, n=100, seed=1)
    inside = region.contains(probe)
    clear = (np.abs(probe[:, 0]) > 0.05) & (np.abs(probe[:, 0]) < W / 2 - 0.05) & (np.abs(probe[:, 1]) < H / 2 - 0.05)
    np.testing.assert_array_equal(inside[clear], probe[clear, 0] < 0)
    assert not inside[probe[:, 0] >= 0].any()
    # off the format, NaN: never inside; shapes (..., 2) -> (...)
    with np.errstate(all="raise"):
        assert region.contains(np.array([[-W, 0.0], [-1.0, H], [np.nan, 0.0], [-np.inf, 0.0], [-1.0, 0.0]])).tolist() \
            == [False, False, False, False, True]
    assert region.contains(np.zeros((3, 4, 2))).shape == (3, 4)


def test_the_hull_bridges_the_gaps_between_sphere_images_but_not_a_stray_point():
    """Two blobs in opposite corners (the images of two spheres): the hull holds the
    line between them, where no control point lies; three stray points alone in a far
    cell (fewer than MIN_POINTS_PER_CELL) do not stretch it."""
    a = _uniform(-W / 2 + 1, -W / 2 + 3, -H / 2 + 1, -H / 2 + 3, n=30)
    b = _uniform(W / 2 - 3, W / 2 - 1, H / 2 - 3, H / 2 - 1, n=30, seed=1)
    stray = np.array([[W / 2 - 0.3, -H / 2 + 0.3]] * 3)
    region = ObservedRegion.from_observations(np.concatenate([a, b, stray]), W, H)
    assert region.contains([[0.0, 0.0], [-2.0, -1.5]]).all()           # between the blobs
    assert not region.contains([[W / 2 - 0.3, -H / 2 + 0.3], [-W / 2 + 1, H / 2 - 1]]).any()
    assert region.fraction_of_cells < region.fraction < 0.3


def test_a_quarter_and_the_threshold():
    """The top-left quarter (x < 0, y < 0) is 1/4 of the format; a cell with fewer than
    MIN_POINTS_PER_CELL points is not observed, one with exactly that many is."""
    region = ObservedRegion.from_observations(_uniform(-W / 2, 0.0, -H / 2, 0.0), W, H)
    assert abs(region.fraction - 0.25) < 1e-3 and region.fraction_of_cells == 0.25
    centre = np.array([(0.5 - 8) * W / 16, (0.5 - 6) * H / 12])   # the middle of cell (0, 0)
    corners = centre + 0.2 * np.array([[-1, -1], [1, -1], [1, 1], [-1, 1], [0, 0]])  # a 0.4 mm square
    few = ObservedRegion.from_observations(corners[:MIN_POINTS_PER_CELL - 1], W, H)
    enough = ObservedRegion.from_observations(corners[:MIN_POINTS_PER_CELL], W, H)
    assert few.fraction == 0.0 and not few.contains(centre)
    assert enough.observed[0, 0] and enough.fraction_of_cells == 1 / 192 and enough.contains(centre)
    assert abs(enough.fraction - 0.16 / (W * H)) < 1e-12


def test_bad_regions_are_refused():
    ok = ObservedRegion.from_observations(_uniform(-1, 1, -1, 1, n=20), W, H)
    with pytest.raises(ValueError, match="whole numbers"):
        ObservedRegion(W, H, np.array([[1.5, 2.0]]), ok.hull)
    with pytest.raises(ValueError, match="cells says"):
        ObservedRegion.from_dict({**ok.to_dict(), "cells": [2, 3]})
    with pytest.raises(ValueError, match="hull_mm"):
        ObservedRegion.from_dict({k: v for k, v in ok.to_dict().items() if k != "hull_mm"})
    with pytest.raises(ValueError, match="counter-clockwise"):
        ObservedRegion.from_dict({**ok.to_dict(), "hull_mm": ok.hull[::-1].tolist()})
    with pytest.raises(ValueError, match="off the format"):
        ObservedRegion.from_dict({**ok.to_dict(), "hull_mm": (ok.hull * 20).tolist()})
    with pytest.raises(ValueError, match="format_mm"):
        ObservedRegion.from_dict({"cells": [1, 1]})


def test_regions_round_trip_through_calibration_json(thesis_rig, tmp_path):
    """Every sensor's region written by rig_to_dict is read back equal by read_calibration;
    a file without regions reads as 'unknown' (no entry), as files before them do."""
    from fringecal.calibration.file import read_calibration, rig_to_dict

    regions = {s.name: ObservedRegion.from_observations(_uniform(-1.0, s.format.width_mm / 2, -2.0, 3.0, n=60,
                                                                 seed=k), s.format.width_mm, s.format.height_mm)
               for k, s in enumerate(thesis_rig.sensors)}
    path = tmp_path / "calibration.json"
    path.write_text(json.dumps(rig_to_dict(thesis_rig, observed_regions=regions)))
    back = read_calibration(path).observed_regions
    assert set(back) == {s.name for s in thesis_rig.sensors}
    for name, r in regions.items():
        assert back[name] == r and 0 < back[name].fraction < 1
    plain = tmp_path / "plain.json"
    plain.write_text(json.dumps(rig_to_dict(thesis_rig)))
    assert read_calibration(plain).observed_regions == {}
    doc = rig_to_dict(thesis_rig, observed_regions=regions)
    doc["scanners"][0]["sensors"][0]["observed_region"]["points_per_cell"] = [[1, 2]]
    path.write_text(json.dumps(doc))
    with pytest.raises(ValueError, match="observed_region"):
        read_calibration(path)


def test_a_cloud_written_before_the_flag_reads_with_nothing_flagged(tmp_path):
    """A PLY of the ten fields before ``outside_observed_region`` reads whole, the flag 0."""
    from plyfile import PlyData, PlyElement

    from fringecal.measure import POINT_DTYPE, read_cloud

    old = np.dtype([(n, POINT_DTYPE[n]) for n in POINT_DTYPE.names if n != "outside_observed_region"])
    pts = np.zeros(3, old)
    pts["x"], pts["u"] = [1.0, 2.0, 3.0], [4, 5, 6]
    PlyData([PlyElement.describe(pts, "vertex")], text=False, byte_order="<",
            comments=['scanners: ["s1"]', 'measurements: ["m"]']).write(str(tmp_path / "old.ply"))
    cloud = read_cloud(tmp_path / "old.ply")
    assert cloud.points["x"].tolist() == [1.0, 2.0, 3.0] and cloud.points["u"].tolist() == [4, 5, 6]
    assert cloud.points["outside_observed_region"].tolist() == [0, 0, 0] and cloud.scanners == ("s1",)


def test_the_verification_states_how_much_of_each_ballbar_position_lies_outside(small_run, small_config):
    """verification.json's ``observed_region``: per position the sphere fits' pixels
    outside the calibration's regions, as counted again from those pixels; a region that
    excludes scanner2's camera wholly puts all its pixels outside and none of scanner1's,
    and no regions none."""
    from fringecal.calibration.file import read_calibration
    from fringecal.run.config import load_run_config
    from fringecal.spheres.robust import RejectionConfig
    from fringecal.steps.verify import ballbar_stores
    from fringecal.verification.measure import measure_positions, positions_outside

    rd = small_run[0]
    cal = read_calibration(rd.calibration.path)
    stated = rd.verification.load()["calibrated"]["observed_region"]
    assert set(stated) == {str(p["measurement"]) for p in rd.verification.load()["calibrated"]["positions"]}
    stores = ballbar_stores(rd)
    _, _, pixels = measure_positions(stores, cal.rig, rd.ballbar.load(),
                                     RejectionConfig(**load_run_config(small_config).extraction.rejection), pixels=True)
    assert positions_outside(stores, cal.rig, pixels, cal.observed_regions) == stated
    cam2 = cal.rig.scanner("scanner2").camera
    nowhere = {cam2.name: ObservedRegion(cam2.format.width_mm, cam2.format.height_mm, np.zeros((16, 16)),
                                         np.zeros((0, 2)))}
    excluded = positions_outside(stores, cal.rig, pixels, nowhere)
    seen_by_2 = 0
    for position, e in excluded.items():
        by = e["scanners"]
        assert by.get("scanner1", {"outside": 0})["outside"] == 0
        if "scanner2" in by:
            seen_by_2 += 1
            assert by["scanner2"]["outside"] == by["scanner2"]["points"] > 0
        assert e["outside"] == sum(s["outside"] for s in by.values()) and e["points"] == sum(s["points"] for s in by.values())
    assert seen_by_2 > 0
    assert all(e["outside"] == 0 for e in positions_outside(stores, cal.rig, pixels, {}).values())


def test_contains_agrees_with_every_edges_test_on_random_hulls():
    """The fan search (one edge per point) against the test of every edge, on 50 random
    hulls of 3-60 points: random points, the vertices, the edges' midpoints and points
    1 nm either side of them."""
    from fringecal.lens.observed_region import _convex_hull

    rng = np.random.default_rng(7)
    tol = 1e-12 * W * W
    for _ in range(50):
        hull = _convex_hull(rng.uniform([-W / 2, -H / 2], [W / 2, H / 2], (rng.integers(3, 60), 2))
                            * rng.uniform(0.05, 1))
        region = ObservedRegion(W, H, np.zeros((12, 16)), hull)
        edge = np.roll(hull, -1, axis=0) - hull
        normal = np.stack([edge[:, 1], -edge[:, 0]], axis=1) / np.linalg.norm(edge, axis=1)[:, None]
        mid = hull + edge / 2
        probe = np.concatenate([rng.uniform([-W / 2, -H / 2], [W / 2, H / 2], (5000, 2)), hull, mid,
                                mid + 1e-6 * normal, mid - 1e-6 * normal])
        side = edge[None, :, 0] * (probe[:, None, 1] - hull[None, :, 1]) \
            - edge[None, :, 1] * (probe[:, None, 0] - hull[None, :, 0])
        np.testing.assert_array_equal(region.contains(probe), np.all(side >= -tol, axis=1))
        assert not region.contains(mid + 1e-6 * normal).any() and region.contains(mid - 1e-6 * normal).all()
