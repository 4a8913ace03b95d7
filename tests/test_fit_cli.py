"""`fringecal fit sphere|plane`: the pipeline's fits on exported points, clear errors."""

import json

import numpy as np
import pandas as pd
import pytest
from typer.testing import CliRunner

from fringecal.flows.cli import app
from fringecal.spheres.reference_data import plane_reference_data, sphere_reference_data

runner = CliRunner()


def write_points(path, points, extra=False):
    df = pd.DataFrame(points, columns=["x_mm", "y_mm", "z_mm"])
    if extra:
        df.insert(0, "label", "sphere")
    df.to_csv(path, index=False, float_format="%.12f")
    return path


def test_sphere_free_and_fixed_radius(tmp_path):
    ds = sphere_reference_data([120.0, -40.0, 2500.0], 25.0, 500, 70.0, (0.2, 0.1, 1), 0.02, seed=4)
    path = write_points(tmp_path / "sphere.csv", ds.points, extra=True)
    res = runner.invoke(app, ["fit", "sphere", "--points", str(path), "--json"])
    assert res.exit_code == 0, res.output
    out = json.loads(res.output)
    np.testing.assert_allclose([out["x_mm"], out["y_mm"], out["z_mm"]], ds.centre, atol=1e-6)
    assert out["radius_mm"] == pytest.approx(25.0, abs=1e-6) and out["n_points"] == 500
    assert out["rms_mm"] == pytest.approx(0.02, abs=1e-6) and not out["radius_fixed"]
    res = runner.invoke(app, ["fit", "sphere", "--points", str(path), "--radius-mm", "25", "--json"])
    out = json.loads(res.output)
    assert out["radius_fixed"] and out["radius_mm"] == 25.0
    np.testing.assert_allclose([out["x_mm"], out["y_mm"], out["z_mm"]], ds.centre, atol=1e-6)
    res = runner.invoke(app, ["fit", "sphere", "--points", str(path)])
    assert res.exit_code == 0 and "radius_mm" in res.output


def test_robust_sphere_reports_rejections(tmp_path):
    ds = sphere_reference_data([0.0, 0.0, 0.0], 25.0, 800, 70.0, (0, 0, 1), 0.0, seed=2)
    rng = np.random.default_rng(0)
    pts = ds.points + rng.normal(0, 0.01, ds.points.shape)
    pts[:30] += [0.0, 0.0, 3.0]
    res = runner.invoke(app, ["fit", "sphere", "--points", str(write_points(tmp_path / "p.csv", pts)),
                              "--robust", "--noise-mm", "0.01", "--json"])
    out = json.loads(res.output)
    assert out["rejected_residual"] >= 30 and out["n_points"] + out["n_rejected"] == 800
    assert abs(out["z_mm"]) < 0.005


def test_plane(tmp_path):
    ds = plane_reference_data([0.0, 0.0, 1e4], [0.1, 0.0, 1.0], 300, noise_rms_mm=0.003, seed=1)
    res = runner.invoke(app, ["fit", "plane", "--points", str(write_points(tmp_path / "pl.csv", ds.points)),
                              "--json"])
    out = json.loads(res.output)
    n = np.array([out["nx"], out["ny"], out["nz"]])
    assert np.linalg.norm(np.cross(n, ds.normal)) < 1e-7
    assert out["rms_mm"] == pytest.approx(0.003, abs=1e-9) and out["flatness_mm"] > 0.01


def test_bad_input_gives_one_message_and_status_2(tmp_path):
    bad = tmp_path / "bad.csv"
    bad.write_text("x_mm,y_mm,z_mm\n1,2,3\n4,five,6\n7,8\n")
    res = runner.invoke(app, ["fit", "sphere", "--points", str(bad)])
    assert res.exit_code == 2
    assert "bad.csv" in res.output and "line 3, column 'y_mm'" in res.output and "not a number" in res.output
    missing = tmp_path / "cols.csv"
    missing.write_text("x,y,z\n1,2,3\n")
    res = runner.invoke(app, ["fit", "plane", "--points", str(missing)])
    assert res.exit_code == 2 and "missing required column" in res.output
    flat = write_points(tmp_path / "flat.csv", np.c_[np.arange(10.0), np.arange(10.0) ** 2 % 7, np.zeros(10)])
    res = runner.invoke(app, ["fit", "sphere", "--points", str(flat)])
    assert res.exit_code == 2 and "flat.csv" in res.output and "sphere" in res.output
    res = runner.invoke(app, ["fit", "sphere", "--points", str(tmp_path / "nowhere.csv")])
    assert res.exit_code == 2 and "file not found" in res.output
