"""Simulated acquisition against truth: the decoder on rendered frames (noise-free and
default noise), the default noise's epsilon-1, the hexapod hook-up, the stores."""

import json
import os

import numpy as np
import pandas as pd
import pytest
import xarray as xr
import yaml
from typer.testing import CliRunner

from flows.cli import app
from fringecal.acquisition import (AcquisitionInputs, acquire_measurement, measurement_rng,
                                   move_hexapod, plan_acquisition, planned_poses, poses_table, truth_from_store)
from fringecal.frames import Frame
from fringecal.fringe.decode import decode
from fringecal.fringe.sequence import FringeSequence
from fringecal.pointcloud import triangulate_maps
from fringecal.runconfig import load_run_config
from fringecal.simulate import RenderConfig, artefact_scene, backdrop, phase_noise, render_measurement, scaled_scanner
from fringecal.simulate.evaluation import pure_mask, tau_error_summary, tau_residuals
from fringecal.store import is_complete, open_store

runner = CliRunner()
THESIS = FringeSequence()
SHORT = FringeSequence(fringe_counts=(16, 15, 14, 12, 8), n_steps=4)
POSE_COLS = ["tx_mm", "ty_mm", "tz_mm", "omega_rad", "phi_rad", "kappa_rad"]


def tiny_config(tmp_path, pose_rows=(0, 1), width=96, sequence=SHORT, url="hexsim://", shift_mm=0.0, **acq):
    """A run config over some rows of table 6-1 (the first row moved by ``shift_mm`` in x)."""
    from fringecal.config import thesis_dir

    d = thesis_dir()
    poses = pd.read_csv(d / "poses_scanner1_table6-1.csv", dtype={"measurement": str}).iloc[list(pose_rows)]
    poses.iloc[0, poses.columns.get_loc("tx_mm")] += shift_mm
    poses.to_csv(tmp_path / "poses.csv", index=False)
    rig = {"name": "tiny", "reference_scanner": "scanner1", "sensors": str(d / "sensors_refined_table6-8.csv"),
           "artefact": str(d / "artefact_cmm2.csv"), "rods": str(d / "rods.csv"), "artefact_poses": "poses.csv",
           "materials": str(d / "materials.yaml")}
    (tmp_path / "rig.yaml").write_text(yaml.safe_dump(rig))
    run = {"name": "tiny", "rig": "rig.yaml",
           "acquisition": {"camera_width_px": width, "hexapod": {"url": url},
                           "sequence": {"fringe_counts": list(sequence.fringe_counts), "n_steps": sequence.n_steps},
                           **acq}}
    path = tmp_path / "run.yaml"
    path.write_text(yaml.safe_dump(run))
    return path


@pytest.fixture(scope="module")
def thesis(thesis_dir, thesis_rig, thesis_artefact):
    from fringecal.artefact import load_rods

    poses = pd.read_csv(thesis_dir / "poses_scanner1_table6-1.csv")
    frames = [Frame.from_params(r) for r in poses[POSE_COLS].to_numpy(float)]
    return thesis_rig, thesis_artefact, load_rods(thesis_dir / "rods.csv", thesis_artefact), frames


def render_and_decode(thesis, scanner, pose, width, config, sequence=THESIS, backdrop_mm=None, seed=1):
    rig, artefact, rods, poses = thesis
    s = scaled_scanner(rig.scanner(scanner), width)
    scene = artefact_scene(artefact, rods, poses[pose],
                           background=backdrop(s, backdrop_mm) if backdrop_mm else None)
    m = render_measurement(s, scene, config, np.random.default_rng(seed), sequence)
    return s, m.truth, decode(m.frames, sequence, None, config.max_dn)


# -- the decoder on rendered frames -----------------------------------------------------------------

@pytest.mark.parametrize("scanner", ["scanner1", "scanner2"])
def test_noise_free_tau_is_the_true_projector_coordinate(thesis, scanner):
    """Full thesis sequence (64..32 x 7 steps), no noise, defocus kept, one sample per
    pixel: tau within 0.01 projector pixel RMS, no unwrapping error."""
    cfg = RenderConfig().noise_free().model_copy(update={"supersampling": 1})
    s, truth, res = render_and_decode(thesis, scanner, 0, 160, cfg)
    mask = pure_mask(truth, ("sphere",), res.valid)
    summary = tau_error_summary(res.tau, truth, mask, THESIS, s.projector)
    assert summary["n_pixels"] > 200
    for o in "xy":
        assert summary[o]["unwrap_errors"] == 0
        # 12-bit rounding alone gives ~1e-6 rad = 3e-4 projector pixel
        assert summary[o]["rms_projector_px"] < 0.01, summary
    everywhere = tau_error_summary(res.tau, truth, pure_mask(truth, None, res.valid), THESIS, s.projector)
    assert everywhere["x"]["unwrap_errors"] == everywhere["y"]["unwrap_errors"] == 0  # end caps and rods too


def test_default_noise_unwrapping_errors_below_one_in_100000(thesis):
    """Default noise, a dim backdrop 3.5 m away behind the artefact (so most pixels are
    the worst case), the nearest and the farthest pose of table 6-1, both scanners."""
    cfg = RenderConfig()
    n = errors = 0
    for scanner in ("scanner1", "scanner2"):
        for pose in (0, 11):
            s, truth, res = render_and_decode(thesis, scanner, pose, 384, cfg, backdrop_mm=3500.0, seed=pose)
            summary = tau_error_summary(res.tau, truth, pure_mask(truth, None, res.valid), THESIS, s.projector)
            n += summary["n_pixels"]
            errors += summary["x"]["unwrap_errors"] + summary["y"]["unwrap_errors"]
    # 0 errors in more than 300,000 pixels bounds the rate below 1e-5 at 95 % confidence
    assert n > 300_000
    assert errors < n * 1e-5, (errors, n)


@pytest.fixture(scope="module")
def noise_pairs(thesis):
    """Pose 1, both scanners, 384 px: the default noise and noise-free renders of the same scene."""
    out = []
    for scanner in ("scanner1", "scanner2"):
        noisy = render_and_decode(thesis, scanner, 0, 384, RenderConfig(), seed=3)
        clean = render_and_decode(thesis, scanner, 0, 384, RenderConfig().noise_free())
        out.append((noisy, clean))
    return out


def test_tau_noise_follows_the_renderer_phase_noise_model(noise_pairs):
    """Per pixel, (tau_noisy - tau_noise_free) / sigma_tau(theory) has unit spread;
    theory: config.phase_noise at the pixel's true level and decoded modulation."""
    cfg = RenderConfig()
    for (s, truth, res), (_, _, clean) in noise_pairs:
        mask = pure_mask(truth, ("sphere",), res.valid & clean.valid)
        level = (truth.ambient_level + cfg.offset * truth.irradiance)[mask]
        for o in "xy":
            modulation = clean.modulation[o][mask] / cfg.max_dn
            sigma = np.array([phase_noise(cfg, a, b)["sigma_tau"] for a, b in zip(level, modulation)])
            z = tau_residuals(res.tau[o][mask], clean.tau[o][mask]) / sigma
            assert np.std(z) == pytest.approx(1.0, abs=0.12), (s.name, o)


def test_default_noise_gives_the_thesis_epsilon_one(noise_pairs):
    """epsilon-1 from noise (noisy minus noise-free, true sensor parameters) on valid
    sphere pixels: 45 um RMS at 2048 px (benchmarks/noise_calibration.py); at 384 px
    the pure pixels reach less far towards the grazing rim, so 41-43 um. Band: 45 um +- 20 %."""
    for (s, truth, res), (_, _, clean) in noise_pairs:
        mask = pure_mask(truth, ("sphere",), res.valid & clean.valid)
        eps = [triangulate_maps(s.camera, s.projector, r.tau["x"], r.tau["y"], r.valid).eps1[mask]
               for r in (res, clean)]
        noise_um = 1e3 * np.sqrt(np.mean((eps[0] - eps[1]) ** 2))
        assert 36.0 < noise_um < 54.0, (s.name, noise_um, mask.sum())


# -- acquisition pieces ------------------------------------------------------------------------------

def test_plan_lists_every_pose_and_scanner_in_order(tmp_path):
    cfg = load_run_config(tiny_config(tmp_path, pose_rows=(2, 0)))
    plans = plan_acquisition(cfg)
    assert [p.measurement for p in plans] == ["3-scanner1", "3-scanner2", "1-scanner1", "1-scanner2"]
    assert list(planned_poses(plans)) == ["3", "1"]
    assert plans[2].T_world_artefact.params[0] == pytest.approx(200.048)


def test_hexapod_moves_reach_the_plan_to_encoder_quantisation(tmp_path):
    from fringecal.hexapod import HexapodRig, load_hexapod_config
    from fringecal.hexapod.planning import quantisation_bound

    cfg = load_run_config(tiny_config(tmp_path, pose_rows=range(12)))
    moves = move_hexapod(planned_poses(plan_acquisition(cfg)), cfg)
    rig = HexapodRig.from_config(load_hexapod_config())
    for m in moves:
        planned, reached = rig.platform_pose_for(m.planned), rig.platform_pose_for(m.reached)
        bound = quantisation_bound(rig.config, planned)
        assert np.all(np.abs(reached - planned) <= 1.01 * bound)
        assert 1e-4 < m.translation_error_mm < 0.1 and m.rotation_error_rad < 1e-4
    table = poses_table(moves)
    assert table["hexapod"].all() and table["counts_1"].notna().all()
    off = load_run_config(tiny_config(tmp_path, pose_rows=(0,)), {"acquisition": {"hexapod": {"enabled": False}}})
    still = move_hexapod(planned_poses(plan_acquisition(off)), off)
    assert still[0].reached is still[0].planned and poses_table(still)["counts_1"].isna().all()


def test_hexapod_faults_and_unreachable_poses_name_the_pose(tmp_path):
    from fringecal.hexapod import HexapodFault, TargetRejected

    from fringecal.hexapod.simulator import get_controller

    one = load_run_config(tiny_config(tmp_path, pose_rows=(0,), url="hexsim://acq-count"))
    move_hexapod(planned_poses(plan_acquisition(one)), one)
    n = get_controller("acq-count").n_received  # commands to open the box and reach pose 1
    cfg = load_run_config(tiny_config(tmp_path, pose_rows=(0, 1, 2), url=f"hexsim://acq-fault?fault=timeout&after={n + 1}"))
    with pytest.raises(HexapodFault, match="artefact pose 2: hexapod stopped: no reply"):
        move_hexapod(planned_poses(plan_acquisition(cfg)), cfg)
    box = get_controller("acq-fault")
    assert [c.split()[0] for c in box.motion_log()] == ["MOVEALL", "MOVEALL"]  # pose 3 never commanded
    assert box.log[-1][1].startswith("STOP")
    far = load_run_config(tiny_config(tmp_path, pose_rows=(0, 1), shift_mm=2000.0))
    with pytest.raises(TargetRejected, match="artefact pose 1: .*outside the workspace"):
        move_hexapod(planned_poses(plan_acquisition(far)), far)


def test_measurement_noise_depends_on_seed_and_id_only(tmp_path, thesis):
    cfg = load_run_config(tiny_config(tmp_path, width=48, store_frames=True))
    inputs = AcquisitionInputs.from_run_config(cfg)
    a, b = plan_acquisition(cfg, inputs)[:2]
    T = a.T_world_artefact
    acquire_measurement(a, T, cfg, tmp_path / "a1.zarr", inputs)
    acquire_measurement(b, T, cfg, tmp_path / "b.zarr", inputs)
    acquire_measurement(a, T, cfg, tmp_path / "a2.zarr", inputs)  # after another measurement
    f1, f2 = (open_store(tmp_path / n).frames.values for n in ("a1.zarr", "a2.zarr"))
    np.testing.assert_array_equal(f1, f2)
    # the same id under another seed differs; the store's truth is the renderer's
    other = cfg.model_copy(update={"acquisition": cfg.acquisition.model_copy(update={"seed": 1})})
    acquire_measurement(a, T, other, tmp_path / "a3.zarr", inputs)
    assert np.mean(open_store(tmp_path / "a3.zarr").frames.values != f1) > 0.3
    rig, artefact, rods, _ = thesis
    scanner = scaled_scanner(rig.scanner(a.scanner), 48)
    m = render_measurement(scanner, artefact_scene(artefact, rods, T, inputs.hardware), cfg.acquisition.render,
                           measurement_rng(cfg.acquisition.seed, a.measurement), SHORT)
    np.testing.assert_array_equal(m.frames, f1)
    truth = truth_from_store(xr.open_zarr(tmp_path / "a1.zarr"))
    np.testing.assert_array_equal(truth.point, m.truth.point)
    np.testing.assert_array_equal(truth.tau_y, m.truth.tau_y)
    np.testing.assert_array_equal(truth.object_index, m.truth.object_index)
    assert truth.object_kinds == m.truth.object_kinds


# -- flow and CLI ------------------------------------------------------------------------------------

def _stamp(path):
    return os.stat(path).st_ino, os.stat(path / "zarr.json").st_mtime_ns


@pytest.mark.flow
def test_acquire_flow_two_poses_two_scanners(prefect_harness, tmp_path, thesis):
    from flows.acquire_flow import acquire_flow
    from fringecal.rundir import RunDir

    cfg = load_run_config(tiny_config(tmp_path, width=128, url="hexsim://flowtest"))
    rd = RunDir(tmp_path / "run")
    result = acquire_flow(cfg, str(rd.root))
    ids = ["1-scanner1", "1-scanner2", "2-scanner1", "2-scanner2"]
    assert list(result["stores"]) == ids
    _, artefact, _, _ = thesis
    poses = pd.read_csv(result["poses"].path, dtype={"measurement": str}).set_index("measurement")
    for mid in ids:
        path = rd.store(mid)
        assert is_complete(path) and result["stores"][mid].path == str(path)
        ds = xr.open_zarr(path)  # plain xarray reads the store
        assert {"tau_x", "valid", "truth_tau_x", "truth_x", "truth_sphere_index"} <= set(ds.data_vars)
        a = ds.attrs
        assert (a["measurement"], a["scanner"], a["camera_format"]["width_px"]) == (mid, mid[2:], 128)
        reached = Frame.from_params([a["T_world_artefact"][c] for c in POSE_COLS])
        planned = Frame.from_params([a["T_world_artefact_planned"][c] for c in POSE_COLS])
        np.testing.assert_allclose(reached.params, poses.loc[a["pose"], POSE_COLS].to_numpy(float), atol=1e-6)
        assert 1e-4 < np.linalg.norm(reached.t - planned.t) < 0.1  # rounding to whole encoder counts
        # the rendered truth follows the reached pose, not the planned one
        truth = truth_from_store(ds)
        on = truth.centre_object_index >= 0
        kinds = np.array(truth.object_kinds)[truth.centre_object_index[on]]
        names = np.array(truth.object_names)[truth.centre_object_index[on]]
        sid = [n.split(":")[1] for n in names[kinds == "sphere"]]
        points = truth.point[on][kinds == "sphere"]
        assert len(sid) > 50
        radii = artefact.radii[artefact.index(sid)]
        off = [np.abs(np.linalg.norm(points - T.to_world(artefact.centres_of(sid)), axis=1) - radii).max()
               for T in (reached, planned)]
        assert off[0] < 1e-6 and off[1] > 1e-3, off
        assert np.mean(ds.valid.values[truth.sphere_mask()]) > 0.9
    table = pd.read_csv(result["measurements"].path)
    assert list(table["measurement"]) == ids and (table["sphere_pixels"] > 20).all()

    stamps = {m: _stamp(rd.store(m)) for m in ids}
    table_stamp = os.stat(result["poses"].path).st_mtime_ns
    again = acquire_flow(cfg, str(rd.root))  # all cache hits: nothing rewritten
    assert again["stores"] == result["stores"] and {m: _stamp(rd.store(m)) for m in ids} == stamps
    assert os.stat(result["poses"].path).st_mtime_ns == table_stamp

    import shutil

    shutil.rmtree(rd.store("2-scanner1"))  # only the deleted store is made again
    acquire_flow(cfg, str(rd.root))
    assert is_complete(rd.store("2-scanner1"))
    assert {m: _stamp(rd.store(m)) for m in ids if m != "2-scanner1"} == \
        {m: s for m, s in stamps.items() if m != "2-scanner1"}


@pytest.mark.flow
def test_cli_acquire_json(prefect_harness, tmp_path):
    cfg = tiny_config(tmp_path, pose_rows=(0,), width=64, url="hexsim://clitest", hexapod={"enabled": False})
    res = runner.invoke(app, ["acquire", "--config", str(cfg), "--out", str(tmp_path / "run"), "--json"])
    assert res.exit_code == 0, res.output
    doc = json.loads(res.stdout[res.stdout.index("{"):])
    assert [m["measurement"] for m in doc["measurements"]] == ["1-scanner1", "1-scanner2"]
    assert doc["poses"][0]["hexapod"] is False and doc["poses"][0]["translation_error_mm"] == 0
    assert (tmp_path / "run" / "measurements" / "1-scanner2.zarr").is_dir()


@pytest.mark.flow
def test_cli_acquire_controller_fault_exits_1(prefect_harness, tmp_path):
    cfg = tiny_config(tmp_path, pose_rows=(0,), url="hexsim://?fault=garbled")
    res = runner.invoke(app, ["acquire", "--config", str(cfg), "--out", str(tmp_path / "run")])
    assert res.exit_code == 1, res.output
    assert "hexapod: opening the hexapod at hexsim://?fault=garbled: hexapod stopped: bad reply" in res.output
    cfg = tiny_config(tmp_path, pose_rows=(0,), url="hexsim://?fault=garbled&after=1")
    res = runner.invoke(app, ["acquire", "--config", str(cfg), "--out", str(tmp_path / "run")])
    assert res.exit_code == 1 and "hexapod: artefact pose 1: hexapod stopped: bad reply" in res.output
    assert not list((tmp_path / "run" / "measurements").glob("*.zarr"))


def test_cli_acquire_bad_configs_fail_before_prefect(tmp_path):
    def run(path):
        return runner.invoke(app, ["acquire", "--config", str(path), "--out", str(tmp_path / "run")])

    good = tiny_config(tmp_path)
    doc = yaml.safe_load(good.read_text())
    doc["acquisition"]["camera_widht_px"] = 10
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump(doc))
    res = run(bad)
    assert res.exit_code == 2 and "acquisition.camera_widht_px: unknown key" in res.output

    rig = yaml.safe_load((tmp_path / "rig.yaml").read_text())
    del rig["artefact_poses"]
    (tmp_path / "rig.yaml").write_text(yaml.safe_dump(rig))
    res = run(good)
    assert res.exit_code == 2 and "artefact_poses is not set" in res.output

    far = tiny_config(tmp_path, shift_mm=2000.0)
    res = run(far)
    assert res.exit_code == 2 and "artefact pose 1 is out of the hexapod's reach" in res.output
    assert not (tmp_path / "run").exists()
