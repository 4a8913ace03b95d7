"""The acceptance test's objects rendered by the simulated source's steps
(``simulate-sphere``, ``simulate-dumbbell``, ``simulate-flat``) and by ``fringecal
simulate``: the stores' ground truth and the points triangulated with the true
sensors against the certificates and the planned positions.

The small thesis rig (two poses, one ball-bar position, 64 px calibration images),
one position per object and scanner at 200 px, noise-free rendering: what is left is
the renderer and decoder's own bias at that resolution (a camera pixel covers ~5 mm
of the object), not noise.
"""

import numpy as np
import pytest
import yaml

from fringecal.acceptance.standards import AcceptanceStandards, load_standards
from fringecal.frames import frames_from_rows
from fringecal.pointcloud import triangulate_maps
from fringecal.rig import scaled_scanner
from fringecal.run.config import load_run_config
from fringecal.rundir import RunDir
from fringecal.simulate.measurement import truth_from_store
from fringecal.simulate.small_thesis import write_small_thesis_config
from fringecal.spheres.fit import SphereModel
from fringecal.store import is_complete, open_store

WIDTH = 200
TESTS = ("sphere", "dumbbell", "flat")


def small_acceptance_config(d, **acceptance):
    path = write_small_thesis_config(d, width=64, poses=(1, 5), positions=(1,))
    cfg = yaml.safe_load(path.read_text())
    cfg["simulate"]["acquisition"]["render"] = {"shot_noise": False, "read_noise_e": 0.0, "excess_noise": 0.0}
    cfg["simulate"]["acquisition"]["store_frames"] = True
    cfg["simulate"]["acceptance"] = {"sphere": 1, "dumbbell": 1, "flat": 1, "camera_width_px": WIDTH, **acceptance}
    path.write_text(yaml.safe_dump(cfg))
    return load_run_config(path)


@pytest.fixture(scope="module")
def config(tmp_path_factory):
    return small_acceptance_config(tmp_path_factory.mktemp("acceptance-config"))


@pytest.fixture(scope="module")
def run(config, tmp_path_factory):
    from fringecal.steps import run_pipeline

    rd = RunDir(tmp_path_factory.mktemp("acceptance-run") / "run").create()
    return rd, run_pipeline(rd, config, until="simulate-flat")


def measured(rd, item):
    """(store, truth, points (rows, cols, 3) triangulated with the true sensors, T_world_object)."""
    ds, tr = open_store(rd.store(item).path), truth_from_store(open_store(rd.truth.store(item).path))
    scanner = scaled_scanner(rd.truth.sensors.load().scanner(ds.attrs["scanner"]), ds["tau_x"].shape[1])
    m = triangulate_maps(scanner.camera, scanner.projector, ds["tau_x"].values, ds["tau_y"].values,
                         ds["valid"].values)
    T = frames_from_rows(rd.truth.acceptance_positions.load())[ds.attrs["pose"]]
    return ds, tr, np.stack([m.x, m.y, m.z], axis=-1), T


def object_pixels(ds, tr, P, kind, sphere_id=None):
    """Pure pixels of one object kind (and sphere), and those of them with a valid point."""
    kinds = np.array(tr.object_kinds + ("none",))[tr.object_index]
    sel = (kinds == kind) & (tr.purity == 1)
    if sphere_id is not None:
        sel &= np.array(tr.sphere_ids + ("",))[tr.sphere_index] == sphere_id
    return sel, sel & ds["valid"].values.astype(bool) & np.isfinite(P).all(axis=-1)


def test_each_position_is_rendered_once_by_its_scanner(run, config):
    from fringecal.steps import run_pipeline

    rd, records = run
    plan = rd.truth.acceptance_positions.load()
    assert list(plan["measurement"]) == [f"{t}-{k}-01" for k in (1, 2) for t in TESTS]
    for test in TESTS:
        expected = {f"{test}-{k}-01-scanner{k}" for k in (1, 2)}
        assert set(records[f"simulate-{test}"]) == expected
        for item in expected:
            ds = open_store(rd.store(item).path)
            assert is_complete(rd.store(item).path) and is_complete(rd.truth.store(item).path)
            assert ds.attrs["kind"] == test and ds.attrs["pose"] == item.rsplit("-", 1)[0]
            assert ds["tau_x"].shape == (WIDTH, WIDTH) and ds.attrs["seed"]["run"] == config.simulate.acceptance.seed
    assert AcceptanceStandards.model_validate(rd.acceptance_standards.load()) == \
        load_standards(config.simulate.acceptance.standards_path())
    again = run_pipeline(rd, config, until="simulate-flat")
    assert all(r["reused"] for items in again.values() for r in items.values())


def test_the_sphere_has_its_certified_radius_at_the_planned_centre(run):
    rd, _ = run
    radius = AcceptanceStandards.model_validate(rd.acceptance_standards.load()).sphere.diameter_mm / 2
    for item in ("sphere-1-01-scanner1", "sphere-2-01-scanner2"):
        ds, tr, P, T = measured(rd, item)
        truth, valid = object_pixels(ds, tr, P, "sphere")
        assert truth.sum() > 500  # the 127 mm sphere is ~30 px across at 200 px and ~3 m
        exact = SphereModel.from_estimate(tr.point[truth])
        assert exact.radius == pytest.approx(radius, abs=1e-9)
        np.testing.assert_allclose(exact.centre, T.t, atol=1e-9)
        fit = SphereModel.from_estimate(P[valid])
        assert valid.sum() > 0.85 * truth.sum()
        # noise-free at 200 px: radius -0.045 mm, centre 0.10-0.12 mm off, RMS 0.015 mm (the
        # pixel-footprint bias of a curved surface; a quarter of that at 400 px)
        assert fit.radius == pytest.approx(radius, abs=0.1)
        assert np.linalg.norm(fit.centre - T.t) < 0.25 and fit.rms < 0.05


def test_the_dumbbell_spheres_are_their_certified_length_apart(run):
    rd, _ = run
    bell = AcceptanceStandards.model_validate(rd.acceptance_standards.load()).dumbbell
    for item in ("dumbbell-1-01-scanner1", "dumbbell-2-01-scanner2"):
        ds, tr, P, T = measured(rd, item)
        kinds = set(np.array(tr.object_kinds + ("none",))[tr.object_index].ravel())
        assert {"sphere", "rod", "end_cap"} <= kinds
        centres, fitted = [], []
        for sid, local in (("A", [0.0, 0, 0]), ("B", [bell.length_mm, 0, 0])):
            truth, valid = object_pixels(ds, tr, P, "sphere", sid)
            assert truth.sum() > 50
            exact = SphereModel.from_estimate(tr.point[truth])
            assert exact.radius == pytest.approx(bell.diameter_mm / 2, abs=1e-9)
            np.testing.assert_allclose(exact.centre, T.to_world([local])[0], atol=1e-9)
            centres.append(exact.centre)
            fitted.append(SphereModel.from_estimate(P[valid], radius=bell.diameter_mm / 2).centre)
        assert np.linalg.norm(centres[1] - centres[0]) == pytest.approx(bell.length_mm, abs=1e-9)
        # both centres share the resolution bias (~0.3 mm at 200 px): their distance is 0.035 mm long
        assert np.linalg.norm(fitted[1] - fitted[0]) == pytest.approx(bell.length_mm, abs=0.1)


def test_the_flat_lies_on_its_planned_plane(run):
    rd, _ = run
    flat = AcceptanceStandards.model_validate(rd.acceptance_standards.load()).flat
    for item in ("flat-1-01-scanner1", "flat-2-01-scanner2"):
        ds, tr, P, T = measured(rd, item)
        truth, valid = object_pixels(ds, tr, P, "flat")
        local = T.to_local(tr.point[truth])
        # every truth point on the box (the face z = 0 or a side face), nearly all on the face
        on_face = np.abs(local[:, 2]) < 1e-6
        side = ~on_face
        assert np.all((local[:, 2] > -flat.thickness_mm - 1e-6) & (local[:, 2] < 1e-6))
        assert np.all(np.isclose(np.abs(local[side, 0]), flat.length_mm / 2) |
                      np.isclose(np.abs(local[side, 1]), flat.width_mm / 2))
        assert on_face.mean() > 0.97 and on_face.sum() > 5000
        assert np.all(np.abs(local[on_face, :2]) <= [flat.length_mm / 2 + 1e-6, flat.width_mm / 2 + 1e-6])
        # triangulated with the true sensors, the face's points at least 10 mm from its edges (the
        # projector's blur mixes the edges with the side faces and the dark beyond) lie on the plane
        face = np.zeros(truth.shape, bool)
        face[truth] = on_face & np.all(np.abs(local[:, :2]) < [flat.length_mm / 2 - 10, flat.width_mm / 2 - 10],
                                       axis=1)
        z = T.to_local(P[face & valid])[:, 2]
        assert (face & valid).sum() > 0.95 * face.sum()
        assert abs(z.mean()) < 0.005 and np.abs(z).max() < 0.02  # mm; noise-free: -1 um, 1.8 um RMS, 7 um max


def test_fringecal_simulate_writes_the_same_acceptance_stacks(run, config, tmp_path):
    """The data-set door: certificates as YAML, each stack in
    verification/acceptance/<test>/<position>/<scanner>/ with the very frames the run
    stored, and the positions in the truth folder."""
    from fringecal.fringe.importer import read_frames
    from fringecal.rundir import TruthDir
    from fringecal.simulate.export import write_dataset

    rd, _ = run
    out, truth = tmp_path / "data", tmp_path / "truth"
    write_dataset(config, out, truth, "png")
    folder = out / "verification" / "acceptance"
    assert load_standards(folder / "standards.yaml") == AcceptanceStandards.model_validate(
        rd.acceptance_standards.load())
    stacks = sorted(str(p.relative_to(folder)) for p in folder.glob("*/*/*") if p.is_dir())
    table = rd.acquisition.load()
    table = table[table["kind"].isin(TESTS)]
    assert len(table) == 6 and stacks == sorted(f"{r.kind}/{r.pose}/{r.scanner}" for r in table.itertuples())
    for r in table.itertuples():
        np.testing.assert_array_equal(read_frames(folder / r.kind / r.pose / r.scanner).frames,
                                      open_store(rd.store(r.measurement).path)["frames"].values)
    np.testing.assert_array_equal(TruthDir(truth, prefix="").acceptance_positions.load().to_numpy(),
                                  rd.truth.acceptance_positions.load().to_numpy())
    assert "acceptance" not in yaml.safe_load((out / "dataset.yaml").read_text()).get("processing", {})


def test_prepare_keys_the_acceptance_and_removes_it_when_switched_off(tmp_path):
    from fringecal.steps import get_step
    from fringecal.steps.keys import run_step, step_key

    rd = RunDir(tmp_path / "run").create()
    prepare, sphere, flat = get_step("simulate-prepare"), get_step("simulate-sphere"), get_step("simulate-flat")

    def prepared(name, **acceptance):
        (tmp_path / name).mkdir()
        cfg = small_acceptance_config(tmp_path / name, **acceptance)
        run_step(prepare, rd, cfg)
        return {s.name: {i: step_key(s, rd, s.view(cfg), i) for i in s.items(rd, s.view(cfg))}
                for s in (prepare, sphere, flat)}

    keys_one = prepared("one")
    cfg = small_acceptance_config(tmp_path / "one")
    assert cfg.simulate.acceptance.standards_path().resolve() in prepare.reads(rd, prepare.view(cfg), "")
    keys_two = prepared("two", flat=2)
    # a second flat position: prepare reruns and one more flat store per scanner; no sphere rerenders
    assert keys_two["simulate-prepare"] != keys_one["simulate-prepare"]
    assert keys_two["simulate-sphere"] == keys_one["simulate-sphere"]
    assert set(keys_two["simulate-flat"]) == {"flat-1-01-scanner1", "flat-1-02-scanner1", "flat-2-01-scanner2",
                                              "flat-2-02-scanner2"}
    assert keys_two["simulate-flat"]["flat-1-01-scanner1"] == keys_one["simulate-flat"]["flat-1-01-scanner1"]
    # switched off: no positions, no certificates, no acceptance stores
    keys_off = prepared("off", enabled=False)
    assert rd.truth.acceptance_positions.load().empty and not rd.acceptance_standards.exists()
    assert not rd.acquisition.load()["kind"].isin(TESTS).any()
    assert keys_off["simulate-sphere"] == {} and keys_off["simulate-flat"] == {}


def test_a_black_box_s_acceptance_clouds_are_the_same_through_both_doors(run, tmp_path):
    """A black box's acceptance sphere and flat (here scanner2's stores): the simulated
    run's cloud store (``store_black_box_cloud``) and ``fringecal simulate``'s
    ``<scanner>.ply`` read back by the decode step (``cloud_store_from_file``) hold the
    same points, so the acceptance test measures the same P_F, P_S and F in both; with
    the true transform the sphere is its certified size within the renderer's bias at
    200 px."""
    import shutil

    from fringecal.acceptance.cloud import cloud_acceptance_values
    from fringecal.acceptance.standards import AcceptanceConfig
    from fringecal.calibration.blackbox import BlackBoxScanner
    from fringecal.scancloud import cloud_store_from_file, read_cloud_store
    from fringecal.simulate.black_box import own_frame, write_black_box_ply
    from fringecal.steps.simulate_render import store_black_box_cloud

    rd, _ = run
    table = rd.acquisition.load()
    mine = table[table["kind"].isin(("sphere", "flat")) & (table["scanner"] == "scanner2")]
    scanner = scaled_scanner(rd.truth.sensors.load().scanner("scanner2"), WIDTH)
    doors = {"run": {}, "dataset": {}}
    for r in mine.itertuples():
        stored = shutil.copytree(rd.store(r.measurement).path, tmp_path / f"{r.measurement}.zarr")
        store_black_box_cloud(stored, scanner)                                  # fringecal run -c
        ply = tmp_path / r.measurement / "scanner2.ply"
        ply.parent.mkdir()
        write_black_box_ply(rd.store(r.measurement).path, scanner, ply)        # fringecal simulate
        read = cloud_store_from_file(ply, tmp_path / f"{r.measurement}-ds.zarr")  # then run --dataset
        np.testing.assert_array_equal(read_cloud_store(read)[0], read_cloud_store(stored)[0])
        doors["run"].setdefault(r.kind, {})[r.pose] = {"scanner2": str(stored)}
        doors["dataset"].setdefault(r.kind, {})[r.pose] = {"scanner2": str(read)}
    box = BlackBoxScanner("scanner2", np.r_[own_frame(scanner).params, 1.0], np.zeros((7, 7)), 0.0, 0)
    doc = {"scanners": [box.to_dict()]}
    standards = AcceptanceStandards.model_validate(rd.acceptance_standards.load())
    values = {door: cloud_acceptance_values(stores, doc, standards, AcceptanceConfig(), {})
              for door, stores in doors.items()}
    assert values["run"] == values["dataset"] and values["run"][1] == []
    got = {v["parameter"]: v for v in values["run"][0]}
    assert set(got) == {"P_F", "P_S", "F"} and abs(got["P_S"]["value_mm"]) < 0.3
