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

from fringecal.flows.cli import app
from fringecal.frames import Frame
from fringecal.fringe.decode import decode
from fringecal.fringe.sequence import FringeSequence
from fringecal.pointcloud import triangulate_maps
from fringecal.run.config import load_run_config
from fringecal.simulate import RenderConfig, artefact_scene, backdrop, phase_noise, render_measurement, scaled_scanner
from fringecal.simulate.evaluation import pure_mask, tau_error_summary, tau_residuals
from fringecal.simulate.measurement import measurement_rng, simulate_measurement, truth_from_store
from fringecal.simulate.moves import move_hexapod, poses_table
from fringecal.simulate.source import acquisition_table, load_simulated_rig
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
    run = {"name": "tiny", "simulate": {
        "rig": "rig.yaml",
        "acquisition": {"camera_width_px": width, "hexapod": {"url": url},
                        "sequence": {"fringe_counts": list(sequence.fringe_counts), "n_steps": sequence.n_steps},
                        **acq}}}
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

def _sim(path, overrides=None):
    return load_run_config(path, overrides).simulate


def test_plan_lists_every_pose_and_scanner_in_order(tmp_path):
    sr = load_simulated_rig(_sim(tiny_config(tmp_path, pose_rows=(2, 0))))
    table = acquisition_table(sr)
    artefact = table[table.kind == "artefact"]
    assert list(artefact.measurement) == ["3-scanner1", "3-scanner2", "1-scanner1", "1-scanner2"]
    assert list(sr.planned) == ["3", "1"] and sr.planned["1"].params[0] == pytest.approx(200.048)
    # thesis table 6-9: sphere A in scanner one's view, B in scanner two's
    assert all(p.scanner_of == {"A": "scanner1", "B": "scanner2"} for p in sr.positions)
    assert list(table[table.kind == "ballbar"].measurement[:2]) == ["bb01-scanner1", "bb01-scanner2"]


def test_hexapod_moves_reach_the_plan_to_encoder_quantisation(tmp_path):
    from fringecal.hexapod import HexapodRig, load_hexapod_config
    from fringecal.hexapod.planning import quantisation_bound

    sim = _sim(tiny_config(tmp_path, pose_rows=range(12)))
    moves = move_hexapod(load_simulated_rig(sim).planned, sim.acquisition.hexapod)
    rig = HexapodRig.from_config(load_hexapod_config())
    for m in moves:
        planned, reached = rig.platform_pose_for(m.planned), rig.platform_pose_for(m.reached)
        bound = quantisation_bound(rig.config, planned)
        assert np.all(np.abs(reached - planned) <= 1.01 * bound)
        assert 1e-4 < m.translation_error_mm < 0.1 and m.rotation_error_rad < 1e-4
    table = poses_table(moves)
    assert table["hexapod"].all() and table["counts_1"].notna().all()
    off = _sim(tiny_config(tmp_path, pose_rows=(0,)), {"simulate": {"acquisition": {"hexapod": {"enabled": False}}}})
    still = move_hexapod(load_simulated_rig(off).planned, off.acquisition.hexapod)
    assert still[0].reached is still[0].planned and poses_table(still)["counts_1"].isna().all()


def test_hexapod_faults_and_unreachable_poses_name_the_pose(tmp_path):
    from fringecal.hexapod import HexapodFault, TargetRejected
    from fringecal.hexapod.simulator import get_controller

    def move(sim):
        return move_hexapod(load_simulated_rig(sim).planned, sim.acquisition.hexapod)

    move(_sim(tiny_config(tmp_path, pose_rows=(0,), url="hexsim://acq-count")))
    n = get_controller("acq-count").n_received  # commands to open the box and reach pose 1
    with pytest.raises(HexapodFault, match="artefact pose 2: hexapod stopped: no reply"):
        move(_sim(tiny_config(tmp_path, pose_rows=(0, 1, 2), url=f"hexsim://acq-fault?fault=timeout&after={n + 1}")))
    box = get_controller("acq-fault")
    assert [c.split()[0] for c in box.motion_log()] == ["MOVEALL", "MOVEALL"]  # pose 3 never commanded
    assert box.log[-1][1].startswith("STOP")
    with pytest.raises(TargetRejected, match="artefact pose 1: .*outside the workspace"):
        move(_sim(tiny_config(tmp_path, pose_rows=(0, 1), shift_mm=2000.0)))


def test_measurement_noise_depends_on_seed_and_id_only(tmp_path, thesis):
    cfg = load_run_config(tiny_config(tmp_path, width=48, store_frames=True))
    sim = cfg.simulate
    sr = load_simulated_rig(sim)
    T = sr.planned["1"]
    scene = artefact_scene(sr.artefact, sr.rods, T, sr.hardware)
    s1, s2 = sr.truth.scanners

    def acquire(mid, scanner, out, acq=sim.acquisition):
        simulate_measurement(mid, scanner, scene, acq, cfg.decode, tmp_path / out, tmp_path / f"truth-{out}")

    acquire("1-scanner1", s1, "a1.zarr")
    acquire("1-scanner2", s2, "b.zarr")
    acquire("1-scanner1", s1, "a2.zarr")  # after another measurement
    f1, f2 = (open_store(tmp_path / n).frames.values for n in ("a1.zarr", "a2.zarr"))
    np.testing.assert_array_equal(f1, f2)
    # the same id under another seed differs; the truth store holds the renderer's truth
    acquire("1-scanner1", s1, "a3.zarr", sim.acquisition.model_copy(update={"seed": 1}))
    assert np.mean(open_store(tmp_path / "a3.zarr").frames.values != f1) > 0.3
    rig, artefact, rods, _ = thesis
    scanner = scaled_scanner(rig.scanner("scanner1"), 48)
    m = render_measurement(scanner, artefact_scene(artefact, rods, T, sr.hardware), sim.acquisition.render,
                           measurement_rng(sim.acquisition.seed, "1-scanner1"), SHORT)
    np.testing.assert_array_equal(m.frames, f1)
    assert not [v for v in open_store(tmp_path / "a1.zarr").variables if v.startswith("truth")]
    truth = truth_from_store(xr.open_zarr(tmp_path / "truth-a1.zarr"))
    np.testing.assert_array_equal(truth.point, m.truth.point)
    np.testing.assert_array_equal(truth.tau_y, m.truth.tau_y)
    np.testing.assert_array_equal(truth.object_index, m.truth.object_index)
    assert truth.object_kinds == m.truth.object_kinds


# -- the simulated source's steps in the flow, and the command line -------------------------------

def _stamp(path):
    return os.stat(path).st_ino, os.stat(path / "zarr.json").st_mtime_ns


@pytest.mark.flow
@pytest.mark.slow
def test_simulated_acquisition_two_poses_two_scanners(prefect_harness, tmp_path, thesis):
    from fringecal.flows.run_flow import run_flow
    from fringecal.rundir import RunDir

    cfg = tiny_config(tmp_path, width=128, url="hexsim://flowtest")
    rd = RunDir(tmp_path / "run")
    summary = run_flow(str(cfg), str(rd.root), until="simulate-render")
    ids = ["1-scanner1", "1-scanner2", "2-scanner1", "2-scanner2"]
    assert [t.split(":")[1] for t in summary["tasks"]["ran"] if t.startswith("simulate-render")] == ids
    _, artefact, _, _ = thesis
    reached = rd.truth.poses.load().set_index("measurement")
    moves = rd.hexapod_moves.load().set_index("measurement")
    for mid in ids:
        path = rd.store(mid).path
        assert is_complete(path)
        ds = xr.open_zarr(path)  # plain xarray reads the store
        assert {"tau_x", "valid"} <= set(ds.data_vars) and not [v for v in ds.data_vars if v.startswith("truth")]
        a = ds.attrs
        assert (a["measurement"], a["scanner"], a["camera_format"]["width_px"]) == (mid, mid[2:], 128)
        pose = a["pose"]
        T_reached = Frame.from_params(reached.loc[pose, POSE_COLS].to_numpy(float))
        T_planned = Frame.from_params(moves.loc[pose, [f"planned_{c}" for c in POSE_COLS]].to_numpy(float))
        np.testing.assert_allclose(T_reached.params, moves.loc[pose, POSE_COLS].to_numpy(float), atol=1e-6)
        assert 1e-4 < np.linalg.norm(T_reached.t - T_planned.t) < 0.1  # rounding to whole encoder counts
        # the rendered truth follows the reached pose, not the planned one
        truth = truth_from_store(xr.open_zarr(rd.truth.store(mid).path))
        on = truth.centre_object_index >= 0
        kinds = np.array(truth.object_kinds)[truth.centre_object_index[on]]
        names = np.array(truth.object_names)[truth.centre_object_index[on]]
        sid = [n.split(":")[1] for n in names[kinds == "sphere"]]
        points = truth.point[on][kinds == "sphere"]
        assert len(sid) > 50
        radii = artefact.radii[artefact.index(sid)]
        off = [np.abs(np.linalg.norm(points - T.to_world(artefact.centres_of(sid)), axis=1) - radii).max()
               for T in (T_reached, T_planned)]
        assert off[0] < 1e-5 and off[1] > 1e-3, off
        assert np.mean(ds.valid.values[truth.sphere_mask()]) > 0.9

    stamps = {m: _stamp(rd.store(m).path) for m in ids}
    table_stamp = os.stat(rd.hexapod_moves.path).st_mtime_ns
    again = run_flow(str(cfg), str(rd.root), until="simulate-render")  # all cache hits: nothing rewritten
    assert again["tasks"]["ran"] == [] and {m: _stamp(rd.store(m).path) for m in ids} == stamps
    assert os.stat(rd.hexapod_moves.path).st_mtime_ns == table_stamp

    import shutil

    shutil.rmtree(rd.store("2-scanner1").path)  # only the deleted store is made again
    third = run_flow(str(cfg), str(rd.root), until="simulate-render")
    assert third["tasks"]["ran"] == ["simulate-render:2-scanner1"] and is_complete(rd.store("2-scanner1").path)
    assert {m: _stamp(rd.store(m).path) for m in ids if m != "2-scanner1"} == \
        {m: s for m, s in stamps.items() if m != "2-scanner1"}


@pytest.mark.flow
@pytest.mark.slow
def test_cli_run_until_the_acquisition_json(prefect_harness, tmp_path):
    cfg = tiny_config(tmp_path, pose_rows=(0,), width=64, url="hexsim://clitest", hexapod={"enabled": False})
    res = runner.invoke(app, ["run", "--config", str(cfg), "--out", str(tmp_path / "run"), "--until", "simulate-render",
                              "--json"])
    assert res.exit_code == 0, res.output
    doc = json.loads(res.stdout[res.stdout.index("{"):])
    assert doc["tasks"]["ran"] == ["simulate-prepare", "simulate-hexapod", "simulate-render:1-scanner1",
                                   "simulate-render:1-scanner2"]
    moves = pd.read_csv(tmp_path / "run" / "tables" / "hexapod_moves.csv")
    assert not moves["hexapod"][0] and moves["translation_error_mm"][0] == 0
    assert (tmp_path / "run" / "measurements" / "1-scanner2.zarr").is_dir()


@pytest.mark.flow
@pytest.mark.slow
def test_cli_run_controller_fault_exits_1(prefect_harness, tmp_path):
    cfg = tiny_config(tmp_path, pose_rows=(0,), url="hexsim://?fault=garbled")
    res = runner.invoke(app, ["run", "--config", str(cfg), "--out", str(tmp_path / "run")])
    assert res.exit_code == 1, res.output
    assert "hexapod: opening the hexapod at hexsim://?fault=garbled: hexapod stopped: bad reply" in res.output
    cfg = tiny_config(tmp_path, pose_rows=(0,), url="hexsim://?fault=garbled&after=1")
    res = runner.invoke(app, ["run", "--config", str(cfg), "--out", str(tmp_path / "run")])
    assert res.exit_code == 1 and "hexapod: artefact pose 1: hexapod stopped: bad reply" in res.output
    assert not list((tmp_path / "run" / "measurements").glob("*.zarr"))


def test_cli_bad_simulation_configs_fail_before_prefect(tmp_path):
    def run(path):
        return runner.invoke(app, ["run", "--config", str(path), "--out", str(tmp_path / "run")])

    good = tiny_config(tmp_path)
    doc = yaml.safe_load(good.read_text())
    doc["simulate"]["acquisition"]["camera_widht_px"] = 10
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump(doc))
    res = run(bad)
    assert res.exit_code == 2 and "simulate.acquisition.camera_widht_px: unknown key" in res.output

    rig = yaml.safe_load((tmp_path / "rig.yaml").read_text())
    del rig["artefact_poses"]
    (tmp_path / "rig.yaml").write_text(yaml.safe_dump(rig))
    res = run(good)
    assert res.exit_code == 2 and "artefact_poses is not set" in res.output

    far = tiny_config(tmp_path, shift_mm=2000.0)
    res = run(far)
    assert res.exit_code == 2 and "artefact pose 1 is out of the hexapod's reach" in res.output
    assert not (tmp_path / "run").exists()
