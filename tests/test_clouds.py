"""Black-box scanners' point clouds in a data set: a good one opens without a prior
calibration, each bad cloud stops ``fringecal run --dataset`` with one line naming the
file, status 2 and nothing written, and the spheres found in a cloud are where they are."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from fringecal.artefact import load_artefact
from fringecal.dataset import DataSet, DataSetError
from fringecal.flows.cli import app
from fringecal.rotation import rotation_matrix
from fringecal.scancloud import CloudFileError, read_scanner_cloud, write_scanner_cloud
from fringecal.spheres.cloud_spheres import cloud_sphere_fits

THESIS = Path(__file__).resolve().parents[1] / "configs" / "thesis"
ARTEFACT = load_artefact(THESIS / "artefact_cmm1.csv")
NOISE_MM = 0.05


def visible_caps(centres: np.ndarray, radius: float, rng, n_per: int = 1500, noise: float = NOISE_MM) -> np.ndarray:
    """Points on the caps of spheres that a scanner at the origin sees, with normal noise."""
    pts = []
    for c in centres:
        u = rng.normal(size=(4 * n_per, 3))
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        u = u[u @ (-c / np.linalg.norm(c)) > 0.2][:n_per]
        pts.append(c + (radius + rng.normal(0, noise, (len(u), 1))) * u)
    return np.concatenate(pts)


def scanner_view(T_scanner_artefact: tuple, ids: list[str]) -> np.ndarray:
    """Centres of the spheres ``ids`` in a scanner's frame."""
    R, t = T_scanner_artefact
    sel = [ARTEFACT.ids.index(i) for i in ids]
    return ARTEFACT.centres[sel] @ R.T + t


def black_box_dataset(root: Path, seed: int = 0) -> Path:
    """Two measurements, two black-box scanners (no sensors_prior.csv), 6 spheres each."""
    rng = np.random.default_rng(seed)
    root.mkdir(parents=True)
    (root / "dataset.yaml").write_text(yaml.safe_dump({"name": "bb", "reference_scanner": "bbA"}))
    shutil.copy(THESIS / "artefact_cmm1.csv", root / "artefact.csv")
    ids = list(ARTEFACT.ids)
    for m, angle in (("1", 0.0), ("2", 0.2)):
        for s, (view, dx) in {"bbA": (ids[:6], -300.0), "bbB": (ids[-6:], 300.0)}.items():
            R = rotation_matrix(0.1 + angle, -0.2, 0.3)
            c0 = ARTEFACT.centres.mean(axis=0)
            T = (R, np.array([dx, 0.0, 3600.0]) - R @ c0)
            folder = root / "measurements" / m
            folder.mkdir(parents=True, exist_ok=True)
            write_scanner_cloud(folder / f"{s}.ply", visible_caps(scanner_view(T, view), 25.0, rng))
    return root


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    return black_box_dataset(tmp_path_factory.mktemp("clouds") / "ds")


def test_a_black_box_data_set_opens_without_prior_calibrations(dataset):
    ds = DataSet.open(dataset)
    assert ds.sensors_prior is None and ds.scanners == ("bbA", "bbB") and ds.black_boxes == ("bbA", "bbB")
    assert [(s.id, s.format) for s in ds.measurements] == [("1-bbA", "cloud"), ("1-bbB", "cloud"),
                                                          ("2-bbA", "cloud"), ("2-bbB", "cloud")]
    ds.check_frames(threads=1)


def test_spheres_found_in_a_cloud_are_where_they_are():
    rng = np.random.default_rng(3)
    R = rotation_matrix(0.3, -0.2, 0.1)
    truth = (ARTEFACT.centres[:8] - ARTEFACT.centres.mean(axis=0)) @ R.T + [0, 0, 3600]
    backdrop = np.column_stack([rng.uniform(-1500, 1500, (50_000, 2)), rng.normal(4600, NOISE_MM, 50_000)])
    fits, failures = cloud_sphere_fits(np.concatenate([visible_caps(truth, 25.0, rng), backdrop]), "1", "s", 25.0)
    assert len(fits) == 8 and failures.empty
    found = fits[["x_mm", "y_mm", "z_mm"]].to_numpy()
    err = np.linalg.norm(found[:, None] - truth[None], axis=2).min(axis=1)
    # 1500 points at 0.05 mm noise on a cap: centre error ~ 0.05 / sqrt(1500) * a few
    assert err.max() < 0.02, err
    u = np.linalg.norm(fits[["u_x_mm", "u_y_mm", "u_z_mm"]].to_numpy(), axis=1)
    assert np.all(err < 5 * u), (err, u)  # the fit's uncertainty is the scatter's size
    assert np.allclose(fits["rms_mm"], NOISE_MM, rtol=0.15)


def _bad(dataset: Path, tmp: Path, edit) -> tuple[Path, Path]:
    ds = tmp / "ds"
    shutil.copytree(dataset, ds)
    return ds, edit(ds / "measurements" / "2" / "bbB.ply")


def _metres(path):
    write_scanner_cloud(path, read_scanner_cloud(path).points / 1000.0)


def _nan(path):
    pts = read_scanner_cloud(path).points
    pts[7] = np.nan
    write_scanner_cloud(path, pts)


def _empty(path):
    write_scanner_cloud(path, np.zeros((0, 3)))


def _units_m(path):
    write_scanner_cloud(path, read_scanner_cloud(path).points, comments=("units: m",))


def _not_ply(path):
    path.write_text("x y z\n1 2 3\n")


@pytest.mark.parametrize("edit, message", [
    (_metres, "in metres?"), (_nan, "have a NaN or infinite coordinate (the first is vertex 7)"),
    (_empty, "empty cloud"), (_units_m, "the header says 'units: m'"), (_not_ply, "not a PLY file"),
], ids=["metres", "nan", "empty", "units-m", "not-ply"])
def test_a_bad_cloud_stops_the_run_with_one_line_naming_it(dataset, tmp_path, edit, message):
    ds, _ = _bad(dataset, tmp_path, lambda p: (edit(p), p)[1])
    before = sorted(tmp_path.rglob("*"))
    res = CliRunner().invoke(app, ["run", "--dataset", str(ds), "--out", str(tmp_path / "run")])
    assert res.exit_code == 2, res.output
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: "), res.output
    assert str(ds / "measurements" / "2" / "bbB.ply") in lines[0] and message in lines[0], lines[0]
    assert sorted(tmp_path.rglob("*")) == before


def test_a_cloud_beyond_the_points_bound_is_refused_from_its_header(dataset, tmp_path, monkeypatch):
    """2**24 points (every pixel of a 4096 x 4096 camera) is every points input's bound;
    shown with a small one: refused before a point is read, one line, nothing written."""
    import fringecal.scancloud as scancloud

    ds, path = _bad(dataset, tmp_path, lambda p: p)
    points = read_scanner_cloud(path).points
    write_scanner_cloud(path, np.concatenate([points, points[:10]]))  # 10 points more than the others
    n = len(points) + 10
    monkeypatch.setattr(scancloud, "MAX_POINTS", n - 1)
    before = sorted(tmp_path.rglob("*"))
    res = CliRunner().invoke(app, ["run", "--dataset", str(ds), "--out", str(tmp_path / "run")])
    assert res.exit_code == 2, res.output
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and f"{path}: {n} points; at most {n - 1} can be used" in lines[0], res.output
    assert sorted(tmp_path.rglob("*")) == before


def test_a_scanner_gives_clouds_or_stacks_not_both(dataset, tmp_path):
    ds, _ = _bad(dataset, tmp_path, lambda p: p)
    (ds / "measurements" / "2" / "bbB.zarr").mkdir()
    with pytest.raises(DataSetError, match="which gives point clouds elsewhere"):
        DataSet.open(ds)


def test_cloud_file_errors_name_the_file(tmp_path):
    path = write_scanner_cloud(tmp_path / "s.ply", np.array([[0.0, 0, 3000], [1, 0, 3000]]))
    with pytest.raises(CloudFileError, match=r"s\.ply: the cloud spans 1 units, less than half"):
        read_scanner_cloud(path, 25.0)


def test_an_e57_cloud_is_read_in_mm(tmp_path):
    pye57 = pytest.importorskip("pye57", reason="E57 needs the optional extra fringecal[e57] (pye57)")
    rng = np.random.default_rng(5)
    metres = rng.normal([0.1, -0.2, 3.6], 0.05, (500, 3))
    path = tmp_path / "s.e57"
    e57 = pye57.E57(str(path), mode="w")
    e57.write_scan_raw({"cartesianX": metres[:, 0], "cartesianY": metres[:, 1], "cartesianZ": metres[:, 2]})
    e57.close()
    cloud = read_scanner_cloud(path, 25.0)
    assert np.allclose(cloud.points, 1000 * metres, atol=1e-6)


def test_measure_takes_a_black_box_s_cloud_beside_the_stacks(tmp_path):
    """fringecal measure's folder: a black box's <scanner>.ply is its entry; a cloud of
    a scanner the calibration does not hold as a black box is refused naming it."""
    from fringecal.config import thesis_dir
    from fringecal.measure.sources import MeasurementSourceError, measurement_entries
    from fringecal.rig import load_rig

    rig = load_rig(thesis_dir() / "sensors_refined_table6-8.csv")
    folder = tmp_path / "m1"
    folder.mkdir()
    path = write_scanner_cloud(folder / "box.ply", np.array([[0.0, 0, 3000], [100, 0, 3000]]))
    assert measurement_entries(folder, rig, "frames", ("box",)) == {"box": path}
    with pytest.raises(MeasurementSourceError, match=r"box\.ply: a point cloud, but scanner 'box' is not a black-box"):
        measurement_entries(folder, rig, "frames")


def test_the_compiled_cube_passes_are_numpy_s_arithmetic():
    """The cubes' keys, order and sums of a cloud (fringecal.spheres.cloud_kernels) are
    numpy's step-by-step formulation's: keys and counts exactly, sums to rounding (1e-9
    of their size), the neighbourhoods' sums bit for bit, on 60 000 points of caps and a
    backdrop, coordinates near 3.6 m."""
    from fringecal.spheres.cloud_kernels import neighbourhood_sums
    from fringecal.spheres.cloud_spheres import _NEIGHBOUR_OFFSETS, _PAIRS, _Cubes

    rng = np.random.default_rng(5)
    caps = visible_caps(scanner_view((np.eye(3), np.array([0.0, 0.0, 3600.0])), list(ARTEFACT.ids)), 25.0, rng, 2000)
    backdrop = np.column_stack([rng.uniform(-600, 600, (30_000, 2)), 4300 + rng.normal(0, 0.05, 30_000)])
    points = np.concatenate([caps, backdrop])
    cell = 6.25
    cubes = _Cubes(points, cell)
    q = (np.floor(points / cell) - (np.floor(points.min(axis=0) / cell) - 1)).astype(np.int64)
    keys = (q[:, 0] << 42) | (q[:, 1] << 21) | q[:, 2]
    order = np.argsort(keys, kind="stable")
    start = np.flatnonzero(np.r_[True, np.diff(keys[order]) != 0])
    centred = points[order] - cubes.shift
    s1 = np.add.reduceat(centred, start, axis=0)
    s2 = np.add.reduceat(np.column_stack([centred[:, a] * centred[:, b] for a, b in _PAIRS]), start, axis=0)
    np.testing.assert_array_equal(cubes.keys, keys[order][start])
    np.testing.assert_array_equal(cubes.count, np.diff(np.r_[start, len(points)]))
    np.testing.assert_allclose(cubes.s1, s1, rtol=0, atol=1e-9 * np.abs(s1).max())
    np.testing.assert_allclose(cubes.s2, s2, rtol=0, atol=1e-9 * np.abs(s2).max())
    # the 26 neighbours' sums added as numpy adds them, cube by cube: the same bits
    n, t1, t2 = cubes.count.astype(float), cubes.s1.copy(), cubes.s2.copy()
    for off in _NEIGHBOUR_OFFSETS:
        i = np.minimum(np.searchsorted(cubes.keys, cubes.keys + off), len(cubes.keys) - 1)
        ok = cubes.keys[i] == cubes.keys + off
        n[ok] += cubes.count[i[ok]]
        t1[ok] += cubes.s1[i[ok]]
        t2[ok] += cubes.s2[i[ok]]
    for ours, numpy_s in zip(neighbourhood_sums(cubes.keys, cubes.count, cubes.s1, cubes.s2, _NEIGHBOUR_OFFSETS),
                             (n, t1, t2)):
        np.testing.assert_array_equal(ours, numpy_s)
    assert (n > cubes.count).mean() > 0.9  # neighbours were found and added


def test_one_pass_neighbourhoods_are_each_sphere_s_own():
    """near_any's one pass over a cloud keeps, for each centre, exactly the points (same
    order) the whole cloud gives within 1.25 radii of it, so refitting from it changes
    nothing: numpy's distance test as the reference, three centres (two overlapping)."""
    from fringecal.spheres.cloud_kernels import within_reach
    from fringecal.spheres.cloud_spheres import near_any, refit_cloud_sphere

    rng = np.random.default_rng(6)
    centres = np.array([[0.0, 0.0, 3600.0], [45.0, 0.0, 3600.0], [300.0, 200.0, 3500.0]])
    points = np.concatenate([visible_caps(centres, 25.0, rng, 3000),
                             rng.uniform([-400, -300, 3400], [400, 300, 3700], (50_000, 3))])
    near = near_any(points, centres, 25.0)
    assert len(near) < len(points) // 5
    for c in centres:
        expected = points[np.linalg.norm(points - c, axis=1) <= 1.25 * 25.0]
        np.testing.assert_array_equal(points[within_reach(points, c, 1.25 * 25.0)], expected)
        np.testing.assert_array_equal(near[within_reach(near, c, 1.25 * 25.0)], expected)
    whole = refit_cloud_sphere(points, centres[2], 25.0).model.centre
    np.testing.assert_array_equal(refit_cloud_sphere(near, centres[2], 25.0).model.centre, whole)
    assert np.linalg.norm(np.asarray(whole) - centres[2]) < 0.01
