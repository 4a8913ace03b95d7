"""`fringecal calibrate --run RUN_DIR` (the bundle step over a run directory): its
outputs, its record, and its refusals."""

import json

import numpy as np
import pandas as pd
import pytest
import yaml
from typer.testing import CliRunner

from fringecal.calibration.file import read_calibration_json, read_calibration_xml
from fringecal.flows.cli import app
from fringecal.run.config import RunConfig
from fringecal.rundir import RunDir
from fringecal.simulate.control_points import dlt_start, simulate_control_points, thesis_truth, write_run_inputs
from fringecal.steps import bundle as bundle_step_module
from fringecal.steps import get_step, run_step

pytestmark = pytest.mark.slow  # whole runs: the fast tier (-m "not slow") leaves this module out

BUNDLE = get_step("bundle")

runner = CliRunner()


def _text(res):
    return res.output.replace("\n", "")  # rich wraps long paths


@pytest.fixture(scope="module")
def simulated():
    rig, art, poses = thesis_truth()
    sim = simulate_control_points(rig, art, poses, spacing_px=20, rng=31)
    start_rig, start_poses = dlt_start(sim, rng=31)
    return sim, start_rig, start_poses


def _run_dir(tmp_path, simulated) -> RunDir:
    sim, start_rig, start_poses = simulated
    rd = RunDir(tmp_path).create()
    write_run_inputs(rd, sim, start_rig, start_poses)
    return rd


def _config(tmp_path, bundle: dict):
    path = tmp_path / "run.yaml"
    path.write_text(yaml.safe_dump({"bundle": bundle}))
    return path


def _outputs(rd):
    return BUNDLE.writes(rd, BUNDLE.view(RunConfig()), "")


def test_step_writes_every_output_and_is_current_on_a_second_call(simulated, tmp_path):
    rd = _run_dir(tmp_path, simulated)
    cfg = RunConfig(bundle={"volume_diagonal_mm": 2872.3, "start": "given"})
    out = run_step(BUNDLE, rd, cfg)
    assert set(out["outputs"]) == {f.rel for f in _outputs(rd)} and not out["reused"]
    summary = rd.bundle_summary.load()
    assert summary["converged"] and summary["after"]["rms_eps1_mm"] == pytest.approx(0.045, rel=0.1)
    sensors = rd.sensors_calibrated.load()
    rd.poses_calibrated.load()
    per_sphere = rd.residuals_per_sphere.load()
    per_meas = rd.residuals_per_measurement.load()
    assert per_sphere["n_points"].sum() == per_meas["n_points"].sum() == len(simulated[0].control_points)
    xml = read_calibration_xml(rd.calibration.xml.path)
    js = read_calibration_json(rd.calibration.path)
    np.testing.assert_array_equal(xml.params, js.params)
    np.testing.assert_allclose(xml.params[:, 0], sensors["x0_mm"], rtol=1e-9)
    np.testing.assert_allclose(xml.uncertainty[:, 8], sensors["u_c_mm"], rtol=1e-9)
    assert summary["volume_diagonal_source"] == "given" and summary["bundle_seconds"] > 0
    assert summary["one_part_in_1p96_sigma"] == pytest.approx(2872.3 / (1.96 * summary["after"]["rms_eps2_mm"]))
    assert len(summary["correlation"]["names"]) == summary["n_free_parameters"] == len(summary["parameters"])
    assert rd.histogram("eps1").load()[:4] == b"\x89PNG"
    stamp = rd.calibration.xml.path.stat().st_mtime_ns
    again = run_step(BUNDLE, rd, cfg)
    assert again["reused"] and again["outputs"] == out["outputs"]
    assert rd.calibration.xml.path.stat().st_mtime_ns == stamp
    changed = run_step(BUNDLE, rd, RunConfig(bundle={"volume_diagonal_mm": 2872.3, "start": "given", "gamma2": 0.5}))
    assert not changed["reused"] and changed["key"] != out["key"]


def test_cli_calibrate_json_with_a_config(simulated, tmp_path):
    rd = _run_dir(tmp_path / "run", simulated)
    cfg = _config(tmp_path, {"start": "given", "volume_diagonal_mm": 2872.3})
    res = runner.invoke(app, ["calibrate", "--run", str(rd.root), "--config", str(cfg), "--json"])
    assert res.exit_code == 0, res.output
    doc = json.loads(res.stdout)
    assert doc["converged"] and doc["volume_diagonal_mm"] == 2872.3 and not doc["reused"]
    assert sorted(doc["outputs"]) == sorted(f.rel for f in _outputs(rd))


def test_cli_explains_a_floating_world_frame(simulated, tmp_path):
    rd = _run_dir(tmp_path / "run", simulated)
    sensors = pd.read_csv(rd.sensors_initial.path)
    sensors.loc[0, ["free_x0", "free_y0", "free_z0", "free_omega", "free_phi", "free_kappa"]] = True
    sensors.to_csv(rd.sensors_initial.path, index=False)
    res = runner.invoke(app, ["calibrate", "--run", str(rd.root), "--config", str(_config(tmp_path, {"start": "given"}))])
    assert res.exit_code == 2, res.output
    assert "world frame is not fixed" in _text(res)
    assert not rd.calibration.xml.exists()


def test_cli_refuses_bad_tables_and_config_before_any_work(simulated, tmp_path):
    rd = _run_dir(tmp_path / "a", simulated)
    cp = pd.read_csv(rd.control_points.path, dtype=str)
    cp.loc[4, "tau_y_rad"] = "x"
    cp.to_csv(rd.control_points.path, index=False)
    res = runner.invoke(app, ["calibrate", "--run", str(rd.root)])
    assert res.exit_code == 2
    assert "control_points.csv" in _text(res) and "line 6, column 'tau_y_rad': value 'x' is not a number" in _text(res)
    rd2 = _run_dir(tmp_path / "b", simulated)
    bad = _config(tmp_path, {"gamma3": 1.0})
    res = runner.invoke(app, ["calibrate", "--run", str(rd2.root), "--config", str(bad)])
    assert res.exit_code == 2 and "run.yaml" in _text(res) and "bundle.gamma3: unknown key" in _text(res)
    rd2.poses_initial.path.unlink()
    res = runner.invoke(app, ["calibrate", "--run", str(rd2.root)])
    assert res.exit_code == 2 and "poses_initial.csv" in _text(res)
    for r in (rd, rd2):
        assert not any(f.exists() for f in _outputs(r))


def test_outputs_are_all_or_nothing(simulated, tmp_path, monkeypatch):
    rd = _run_dir(tmp_path, simulated)
    cfg = RunConfig(bundle={"start": "given"})

    def broken(*args, **kwargs):
        raise RuntimeError("disk full")

    monkeypatch.setattr(bundle_step_module, "residual_histograms_png", broken)
    with pytest.raises(RuntimeError, match="disk full"):
        run_step(BUNDLE, rd, cfg)
    assert not any(f.exists() for f in _outputs(rd))
    assert not [p for p in rd.root.rglob(".*") if p.is_file()]
    monkeypatch.undo()
    record = run_step(BUNDLE, rd, cfg)
    assert all(f.exists() for f in _outputs(rd)) and not record["reused"]
    summary = rd.bundle_summary.load()
    assert summary["after"]["rms_eps1_mm"] < summary["before"]["rms_eps1_mm"] / 10
