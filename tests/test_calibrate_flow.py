"""`fringecal calibrate --run RUN_DIR`: the flow, its outputs and its refusals."""

import json

import numpy as np
import pandas as pd
import pytest
from typer.testing import CliRunner

from fringecal.calibration import results as results_module
from fringecal.calibration.results import OUTPUT_FILES
from fringecal.calibration.run import calibrate_run
from fringecal.calibration.synthetic import dlt_start, simulate_control_points, thesis_truth, write_run_inputs
from fringecal.calibration_file import read_calibration_json, read_calibration_xml
from flows.cli import app
from schemas import (CalibratedPosesTable, CalibratedSensorsTable, MeasurementResidualsTable,
                     SphereResidualsTable, read_table)

runner = CliRunner()


def _text(res):
    return res.output.replace("\n", "")  # rich wraps long paths


@pytest.fixture(scope="module")
def simulated():
    rig, art, poses = thesis_truth()
    sim = simulate_control_points(rig, art, poses, spacing_px=20, rng=31)
    start_rig, start_poses = dlt_start(sim, rng=31)
    return sim, start_rig, start_poses


def _run_dir(tmp_path, simulated, config=None):
    sim, start_rig, start_poses = simulated
    write_run_inputs(tmp_path, sim, start_rig, start_poses, config)
    return tmp_path


@pytest.mark.flow
def test_flow_writes_every_output_and_caches(prefect_harness, simulated, tmp_path):
    from flows.calibrate_flow import calibrate_flow

    run = _run_dir(tmp_path, simulated, {"volume_diagonal_mm": 2872.3, "start": "given"})
    out = calibrate_flow(str(run))
    assert set(out["outputs"]) == set(OUTPUT_FILES)
    assert out["converged"] and out["after"]["rms_eps1_mm"] == pytest.approx(0.045, rel=0.1)
    sensors = read_table(run / "tables/sensors_calibrated.csv", CalibratedSensorsTable)
    read_table(run / "tables/poses_calibrated.csv", CalibratedPosesTable)
    per_sphere = read_table(run / "tables/residuals_per_sphere.csv", SphereResidualsTable)
    per_meas = read_table(run / "tables/residuals_per_measurement.csv", MeasurementResidualsTable)
    assert per_sphere["n_points"].sum() == per_meas["n_points"].sum() == len(simulated[0].control_points)
    xml = read_calibration_xml(run / "calibration.xml")
    js = read_calibration_json(run / "calibration.json")
    np.testing.assert_array_equal(xml.params, js.params)
    np.testing.assert_allclose(xml.params[:, 0], sensors["x0_mm"], rtol=1e-9)
    np.testing.assert_allclose(xml.uncertainty[:, 8], sensors["u_c_mm"], rtol=1e-9)
    summary = json.loads((run / "bundle_summary.json").read_text())
    assert summary["volume_diagonal_source"] == "given"
    assert summary["one_part_in_1p96_sigma"] == pytest.approx(2872.3 / (1.96 * summary["after"]["rms_eps2_mm"]))
    assert len(summary["correlation"]["names"]) == summary["n_free_parameters"] == len(summary["parameters"])
    assert (run / "figures/eps1_hist.png").read_bytes()[:4] == b"\x89PNG"
    stamp = (run / "calibration.xml").stat().st_mtime_ns
    again = calibrate_flow(str(run))
    assert again["outputs"] == out["outputs"] and (run / "calibration.xml").stat().st_mtime_ns == stamp


@pytest.mark.flow
def test_cli_explains_a_floating_world_frame(prefect_harness, simulated, tmp_path):
    run = _run_dir(tmp_path, simulated, {"start": "given"})
    sensors = pd.read_csv(run / "tables/sensors_initial.csv")
    sensors.loc[0, ["free_x0", "free_y0", "free_z0", "free_omega", "free_phi", "free_kappa"]] = True
    sensors.to_csv(run / "tables/sensors_initial.csv", index=False)
    res = runner.invoke(app, ["calibrate", "--run", str(run)])
    assert res.exit_code == 2, res.output
    assert "world frame is not fixed" in _text(res)
    assert not (run / "calibration.xml").exists()


def test_cli_refuses_bad_tables_and_config_before_any_work(simulated, tmp_path):
    run = _run_dir(tmp_path / "a", simulated)
    cp = pd.read_csv(run / "tables/control_points.csv", dtype=str)
    cp.loc[4, "tau_y_rad"] = "x"
    cp.to_csv(run / "tables/control_points.csv", index=False)
    res = runner.invoke(app, ["calibrate", "--run", str(run)])
    assert res.exit_code == 2
    assert "control_points.csv" in _text(res) and "line 6, column 'tau_y_rad': value 'x' is not a number" in _text(res)
    run2 = _run_dir(tmp_path / "b", simulated, {"gamma3": 1.0})
    res = runner.invoke(app, ["calibrate", "--run", str(run2)])
    assert res.exit_code == 2 and "calibrate.yaml" in _text(res) and "gamma3: unknown key" in _text(res)
    (run2 / "calibrate.yaml").unlink()
    (run2 / "tables/poses_initial.csv").unlink()
    res = runner.invoke(app, ["calibrate", "--run", str(run2)])
    assert res.exit_code == 2 and "poses_initial.csv" in _text(res)
    for r in (run, run2):
        assert not any((r / rel).exists() for rel in OUTPUT_FILES.values())


def test_outputs_are_all_or_nothing(simulated, tmp_path, monkeypatch):
    run = _run_dir(tmp_path, simulated, {"start": "given"})

    def broken(*args, **kwargs):
        raise RuntimeError("disk full")

    monkeypatch.setattr(results_module, "plot_histograms", broken)
    with pytest.raises(RuntimeError, match="disk full"):
        calibrate_run(run)
    assert not any((run / rel).exists() for rel in OUTPUT_FILES.values())
    assert not [p for p in run.iterdir() if p.name.startswith(".calibrate-staging")]
    monkeypatch.undo()
    result, paths = calibrate_run(run)
    assert all(p.exists() for p in paths.values())
    assert result.after.rms_eps1_mm < result.before.rms_eps1_mm / 10
