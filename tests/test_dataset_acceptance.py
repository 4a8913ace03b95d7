"""Recorded data sets with the acceptance test (VDI/VDE 2634 parts 2 and 3) in
``verification/acceptance/``: the stacks of the sphere, dumbbell and flat open with
their kinds, ingest copies their certificates and lists them in the acquisition table,
decode turns them into stores like any other stack (tau against the phases the frames
were written with), and every broken acceptance folder stops with one message naming
the offending file or folder."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import xarray as xr
import yaml

from fringecal.acceptance.standards import AcceptanceStandards, load_standards
from fringecal.config import ConfigError
from fringecal.dataset import ACCEPTANCE_TESTS, DataSet, DataSetError
from fringecal.fringe.importer import write_frames
from fringecal.fringe.sequence import FringeSequence
from fringecal.run.config import load_run_config
from fringecal.rundir import RunDir
from fringecal.steps import get_step, run_step
from fringecal.store import write_store

THESIS = Path(__file__).resolve().parents[1] / "configs" / "thesis"
SEQ = FringeSequence((8, 7, 6), 3, ("x", "y"))
SIZE = 16  # camera format of both scanners in the test's sensors_prior.csv
STANDARDS = yaml.safe_load((THESIS / "acceptance.yaml").read_text())


# -- builders -----------------------------------------------------------------

def true_tau(h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
    """The projector phases (rad) the frames of :func:`stack` encode: ramps across the image."""
    v, u = np.mgrid[0:h, 0:w]
    return -2.5 + 5.0 * u / max(w - 1, 1) + 0.1 * v / h, 2.0 - 4.0 * v / max(h - 1, 1)


def stack(folder: Path, h: int = SIZE, w: int = SIZE, seq: FringeSequence = SEQ) -> Path:
    """A 16-bit PNG frame folder of I = 2000 + 1500 cos(t tau + 2 pi k / N)."""
    if folder.exists():
        shutil.rmtree(folder)
    tau = dict(zip("xy", true_tau(h, w)))
    frames = np.stack([np.rint(2000 + 1500 * np.cos(t * tau[o] + 2 * np.pi * k / seq.n_steps))
                       for o, t, k in seq.frames()]).astype(np.uint16)
    return write_frames(folder, frames, seq, 12, fmt="png")


def store(path: Path, h: int = SIZE, w: int = SIZE, seq: FringeSequence = SEQ) -> Path:
    """A decoded store: tau_x, tau_y of :func:`true_tau`, every pixel valid."""
    if path.exists():
        shutil.rmtree(path)
    tau_x, tau_y = true_tau(h, w)
    ds = xr.Dataset({"tau_x": (("v", "u"), tau_x.astype(np.float32)),
                     "tau_y": (("v", "u"), tau_y.astype(np.float32)),
                     "valid": (("v", "u"), np.ones((h, w), bool))}, attrs={"sequence": seq.to_dict()})
    return write_store(path, ds)


def write_yaml(path: Path, data) -> None:
    path.write_text(yaml.safe_dump(data, sort_keys=False))


def prior_table() -> pd.DataFrame:
    df = pd.read_csv(THESIS / "sensors_refined_table6-8.csv", dtype=str)
    cams = df["role"] == "camera"
    df.loc[cams, "width_px"] = str(SIZE)
    df.loc[cams, "height_px"] = str(SIZE)
    return df


def build(root: Path) -> Path:
    """Measurements 1, 2 (both scanners); ball-bar position p1 (scanner1); acceptance:
    sphere s1 (scanner1), s2 (scanner2, a binned 8x8 store), dumbbell d1 (both
    scanners), flat f1 (scanner2, binned 8x8 frames); stray and hidden entries."""
    root.mkdir(parents=True)
    write_yaml(root / "dataset.yaml", {"name": "cell-b", "reference_scanner": "scanner1"})
    shutil.copy(THESIS / "artefact_cmm2.csv", root / "artefact.csv")
    prior_table().to_csv(root / "sensors_prior.csv", index=False)
    for m in ("1", "2"):
        for s in ("scanner1", "scanner2"):
            stack(root / "measurements" / m / s)
    v = root / "verification"
    v.mkdir()
    shutil.copy(THESIS / "ballbar.csv", v / "ballbar.csv")
    stack(v / "p1" / "scanner1")
    a = v / "acceptance"
    a.mkdir()
    write_yaml(a / "standards.yaml", STANDARDS)
    stack(a / "sphere" / "s1" / "scanner1")
    store(a / "sphere" / "s2" / "scanner2.zarr", 8, 8)
    stack(a / "dumbbell" / "d1" / "scanner1")
    stack(a / "dumbbell" / "d1" / "scanner2")
    stack(a / "flat" / "f1" / "scanner2", 8, 8)
    (a / "certificates.pdf").write_text("stray file, ignored")
    (a / ".staging").mkdir()
    (a / "sphere" / ".s9").mkdir()
    return root


@pytest.fixture(scope="module")
def template(tmp_path_factory) -> Path:
    return build(tmp_path_factory.mktemp("template") / "ds")


@pytest.fixture
def root(template, tmp_path) -> Path:
    return Path(shutil.copytree(template, tmp_path / "ds"))


# -- the good data set ------------------------------------------------------------

def test_acceptance_stacks_are_listed_with_their_kinds_in_test_position_scanner_order(root):
    ds = DataSet.open(root)
    a = root / "verification" / "acceptance"
    assert ds.acceptance_standards == a / "standards.yaml"
    assert [(s.id, s.kind, s.group, s.scanner, s.format, s.width_px, s.height_px) for s in ds.acceptance] == [
        ("s1-scanner1", "sphere", "s1", "scanner1", "frames", 16, 16),
        ("s2-scanner2", "sphere", "s2", "scanner2", "store", 8, 8),
        ("d1-scanner1", "dumbbell", "d1", "scanner1", "frames", 16, 16),
        ("d1-scanner2", "dumbbell", "d1", "scanner2", "frames", 16, 16),
        ("f1-scanner2", "flat", "f1", "scanner2", "frames", 8, 8)]
    assert ds.acceptance[1].path == a / "sphere" / "s2" / "scanner2.zarr"
    assert {s.sequence for s in ds.acceptance} == {SEQ}
    assert [ds.acceptance_position_names(t) for t in ACCEPTANCE_TESTS] == [["s1", "s2"], ["d1"], ["f1"]]
    # the ball-bar is untouched: "acceptance" is not one of its positions
    assert ds.position_names() == ["p1"] and ds.ballbar == root / "verification" / "ballbar.csv"
    assert [s.id for s in ds.stacks()] == ["1-scanner1", "1-scanner2", "2-scanner1", "2-scanner2",
                                           "p1-scanner1"] + [s.id for s in ds.acceptance]
    with pytest.raises(ValueError, match="no acceptance test 'plane'"):
        ds.acceptance_position_names("plane")


def test_positions_sort_naturally_within_a_test(root):
    for name in ("s10", "s9"):
        stack(root / "verification" / "acceptance" / "sphere" / name / "scanner1")
    assert DataSet.open(root).acceptance_position_names("sphere") == ["s1", "s2", "s9", "s10"]


def test_a_verification_folder_with_only_the_acceptance_test_opens_without_a_ballbar(root):
    (root / "verification" / "ballbar.csv").unlink()
    shutil.rmtree(root / "verification" / "p1")
    ds = DataSet.open(root)
    assert (ds.ballbar, ds.verification, ds.position_names()) == (None, (), [])
    assert len(ds.acceptance) == 5


def test_without_the_acceptance_folder_nothing_changes(root):
    shutil.rmtree(root / "verification" / "acceptance")
    ds = DataSet.open(root)
    assert (ds.acceptance_standards, ds.acceptance) == (None, ())
    assert [s.id for s in ds.verification] == ["p1-scanner1"]


def test_a_certificate_without_measurements_is_allowed_and_that_object_is_not_tested(root):
    shutil.rmtree(root / "verification" / "acceptance" / "dumbbell")
    ds = DataSet.open(root)
    assert [s.kind for s in ds.acceptance] == ["sphere", "sphere", "flat"]
    assert load_standards(ds.acceptance_standards).dumbbell.length_mm == 500.0


@pytest.mark.parametrize("w, h, ok", [(8, 8, True), (9, 8, True), (32, 32, True), (10, 8, False)])
def test_acceptance_stacks_may_be_binned_but_keep_the_aspect_ratio(root, w, h, ok):
    folder = root / "verification" / "acceptance" / "dumbbell" / "d1" / "scanner2"
    stack(folder, h, w)
    if ok:
        src = DataSet.open(root).acceptance[3]
        assert (src.id, src.width_px, src.height_px) == ("d1-scanner2", w, h)
    else:
        with pytest.raises(DataSetError) as err:
            DataSet.open(root)
        assert str(err.value).startswith(f"{folder / 'sequence.yaml'}: image is 10x8 px, not the aspect ratio")


# -- processing settings of dataset.yaml -------------------------------------------

def test_processing_acceptance_section_is_merged_into_the_run_config(root, tmp_path):
    config = yaml.safe_load((root / "dataset.yaml").read_text())
    config["processing"] = {"acceptance": {"exclude_fraction": 0.01, "limits": {"P_F": 0.3, "E": None}}}
    write_yaml(root / "dataset.yaml", config)
    assert DataSet.open(root).config.processing.acceptance == config["processing"]["acceptance"]
    acc = load_run_config(dataset=root).acceptance
    assert (acc.exclude_fraction, acc.limits.P_F, acc.limits.E) == (0.01, 0.3, None)
    assert (acc.limits.P_S, acc.coverage_factor) == (0.1, 2.0)  # defaults where the data set is silent
    own = tmp_path / "run.yaml"
    own.write_text("acceptance:\n  limits:\n    P_F: 0.25\n")  # the run config wins key by key
    acc = load_run_config(own, dataset=root).acceptance
    assert (acc.limits.P_F, acc.limits.E, acc.exclude_fraction) == (0.25, None, 0.01)
    config["processing"]["acceptance"]["exclude_fractoin"] = 0.02
    write_yaml(root / "dataset.yaml", config)
    with pytest.raises(ConfigError, match="acceptance.exclude_fractoin: unknown key"):
        load_run_config(dataset=root)


# -- ingest and decode ---------------------------------------------------------------

def test_ingest_writes_the_acceptance_rows_and_standards_and_decode_decodes_them(root, tmp_path):
    rd = RunDir(tmp_path / "run").create()
    cfg = load_run_config(dataset=root)
    ingest = get_step("ingest")
    standards = root / "verification" / "acceptance" / "standards.yaml"
    assert standards in ingest.reads(rd, ingest.view(cfg), "")
    run_step(ingest, rd, cfg)

    table = rd.acquisition.load()
    rows = table[table["kind"].isin(ACCEPTANCE_TESTS)]
    assert [tuple(r) for r in rows[["measurement", "kind", "pose", "scanner", "source"]].itertuples(index=False)] == [
        ("s1-scanner1", "sphere", "s1", "scanner1", "verification/acceptance/sphere/s1/scanner1"),
        ("s2-scanner2", "sphere", "s2", "scanner2", "verification/acceptance/sphere/s2/scanner2.zarr"),
        ("d1-scanner1", "dumbbell", "d1", "scanner1", "verification/acceptance/dumbbell/d1/scanner1"),
        ("d1-scanner2", "dumbbell", "d1", "scanner2", "verification/acceptance/dumbbell/d1/scanner2"),
        ("f1-scanner2", "flat", "f1", "scanner2", "verification/acceptance/flat/f1/scanner2")]
    assert list(rows["store"]) == [rd.store(m).rel for m in rows["measurement"]]
    assert list(table["kind"]).count("artefact") == 4 and list(table["kind"]).count("ballbar") == 1
    doc = rd.acceptance_standards.load()
    assert doc == AcceptanceStandards.model_validate(STANDARDS).model_dump(mode="json")
    assert (doc["sphere"]["diameter_mm"], doc["dumbbell"]["length_mm"], doc["flat"]["flatness_mm"]) == (
        127.0, 500.0, 0.003)

    decode, positions = get_step("decode"), get_step("decode-positions")
    # every stack, the calibration stacks first, then the positions' (acceptance ones included)
    items = decode.items(rd, decode.view(cfg)) + positions.items(rd, positions.view(cfg))
    assert sorted(items) == sorted(table["measurement"])
    assert set(decode.items(rd, decode.view(cfg))) == set(table.loc[table["kind"] == "artefact", "measurement"])
    for item, kind, pose, size in (("d1-scanner1", "dumbbell", "d1", 16), ("f1-scanner2", "flat", "f1", 8),
                                   ("s2-scanner2", None, None, 8)):
        run_step(positions, rd, cfg, item)
        maps = rd.store(item).open()
        tau_x, tau_y = true_tau(size, size)
        # frames rounded to integers with B = 1500: the decoded phase is within 1e-3 rad
        # of the truth (a decoded store is copied in: its float32 values)
        assert maps["valid"].values.all()
        np.testing.assert_allclose(maps["tau_x"].values, tau_x, atol=1e-3)
        np.testing.assert_allclose(maps["tau_y"].values, tau_y, atol=1e-3)
        if kind is not None:  # decoded here: the store says what it is
            assert (maps.attrs["kind"], maps.attrs["pose"], maps.attrs["scanner"]) == (kind, pose, item[3:])


def test_ingest_removes_the_standards_of_an_earlier_run_when_the_acceptance_folder_goes(root, tmp_path):
    rd = RunDir(tmp_path / "run").create()
    run_step(get_step("ingest"), rd, load_run_config(dataset=root))
    assert rd.acceptance_standards.exists()
    shutil.rmtree(root / "verification" / "acceptance")
    run_step(get_step("ingest"), rd, load_run_config(dataset=root))
    assert not rd.acceptance_standards.exists()
    assert set(rd.acquisition.load()["kind"]) == {"artefact", "ballbar"}


# -- broken acceptance folders ----------------------------------------------------------
# Each case breaks the good data set and returns (path the message starts with, fragments).

def A(r: Path) -> Path:
    return r / "verification" / "acceptance"


def no_standards(r):
    (A(r) / "standards.yaml").unlink()
    return A(r) / "standards.yaml", ("missing", "sphere, dumbbell, flat")


def standards_is_a_folder(r):
    (A(r) / "standards.yaml").unlink()
    (A(r) / "standards.yaml").mkdir()
    return A(r) / "standards.yaml", ("not a file",)


def object_not_in_standards(r):
    write_yaml(A(r) / "standards.yaml", {k: v for k, v in STANDARDS.items() if k != "flat"})
    return A(r) / "standards.yaml", ("no certificate 'flat'", str(A(r) / "flat"), "length_mm, width_mm")


def standards_unknown_key(r):
    write_yaml(A(r) / "standards.yaml", {**STANDARDS, "sphere": {"diametre_mm": 127.0}})
    return A(r) / "standards.yaml", ("sphere.diametre_mm: unknown key", "sphere.diameter_mm: Field required")


def standards_bad_value(r):
    write_yaml(A(r) / "standards.yaml", {**STANDARDS, "dumbbell": {**STANDARDS["dumbbell"], "length_mm": -500}})
    return A(r) / "standards.yaml", ("dumbbell.length_mm", "greater than 0")


def standards_unknown_object(r):
    write_yaml(A(r) / "standards.yaml", {**STANDARDS, "ballbar": {"length_mm": 800}})
    return A(r) / "standards.yaml", ("ballbar: unknown key",)


def unknown_test_folder(r):
    shutil.copytree(A(r) / "flat", A(r) / "plane")
    return A(r) / "plane", ("unknown acceptance test folder", "sphere/, dumbbell/, flat/")


def empty_test_folder(r):
    shutil.rmtree(A(r) / "flat" / "f1")
    return A(r) / "flat", ("no position folder", "acceptance/flat/<position>/<scanner>/")


def empty_position_folder(r):
    (A(r) / "sphere" / "s3").mkdir()
    return A(r) / "sphere" / "s3", ("position folder without scanner stacks",)


def stack_directly_in_test_folder(r):
    shutil.rmtree(A(r) / "flat" / "f1")
    stack(A(r) / "flat" / "scanner2")
    return A(r) / "flat" / "scanner2", ("a stack directly in the test folder", "acceptance/flat/<position>/<scanner>/")


def store_directly_in_test_folder(r):
    store(A(r) / "sphere" / "scanner1.zarr")
    return A(r) / "sphere" / "scanner1.zarr", ("a stack directly in the test folder",)


def unknown_scanner(r):
    stack(A(r) / "sphere" / "s1" / "scanner7")
    return A(r) / "sphere" / "s1" / "scanner7", ("no prior calibration", "'scanner7'")


def wrong_image_size(r):
    stack(A(r) / "flat" / "f1" / "scanner2", 6, 8)
    return A(r) / "flat" / "f1" / "scanner2" / "sequence.yaml", ("8x6 px", "aspect ratio", "16x16 px")


def wrong_sequence(r):
    stack(A(r) / "sphere" / "s1" / "scanner1", seq=FringeSequence((8, 7, 6), 4))
    return A(r) / "sphere" / "s1" / "scanner1" / "sequence.yaml", ("measurements/1/scanner1", "steps 3 vs 4")


def empty_acceptance_folder(r):
    shutil.rmtree(A(r))
    (A(r) / ".hidden").mkdir(parents=True)
    return A(r), ("empty acceptance folder", "standards.yaml")


def no_test_folder(r):
    for t in ACCEPTANCE_TESTS:
        shutil.rmtree(A(r) / t)
    return A(r), ("no test folder", "sphere/, dumbbell/, flat/")


def acceptance_is_a_file(r):
    shutil.rmtree(A(r))
    A(r).write_text("x")
    return A(r), ("not a folder", "reserved")


def position_named_like_acceptance(r):
    shutil.copytree(r / "verification" / "p1", r / "verification" / "Acceptance")
    return r / "verification" / "Acceptance", ("reserved acceptance folder",)


def ballbar_without_positions(r):
    shutil.rmtree(r / "verification" / "p1")
    return r / "verification", ("no position folder",)


def positions_without_ballbar(r):
    (r / "verification" / "ballbar.csv").unlink()
    return r / "verification" / "ballbar.csv", ("missing",)


def position_collides_with_ballbar_position(r):
    shutil.move(str(A(r) / "sphere" / "s1"), str(A(r) / "sphere" / "p1"))
    return A(r) / "sphere" / "p1" / "scanner1", ("'p1-scanner1'", str(r / "verification" / "p1" / "scanner1"))


def position_collides_with_measurement(r):
    shutil.move(str(A(r) / "dumbbell" / "d1"), str(A(r) / "dumbbell" / "2"))
    return A(r) / "dumbbell" / "2" / "scanner1", ("'2-scanner1'", str(r / "measurements" / "2" / "scanner1"))


def position_collides_across_tests(r):
    shutil.move(str(A(r) / "flat" / "f1"), str(A(r) / "flat" / "d1"))
    return A(r) / "flat" / "d1" / "scanner2", ("'d1-scanner2'", str(A(r) / "dumbbell" / "d1" / "scanner2"))


def position_name_reused_by_another_scanner(r):
    """No store ids collide (s1 is scanner1's, the flat's s1 scanner2's), but one name
    would stand for two placements of two objects."""
    shutil.move(str(A(r) / "flat" / "f1"), str(A(r) / "flat" / "s1"))
    return A(r) / "flat" / "s1", ("position name 's1'", str(A(r) / "sphere" / "s1"))


CASES = [no_standards, standards_is_a_folder, object_not_in_standards, standards_unknown_key, standards_bad_value,
         standards_unknown_object, unknown_test_folder, empty_test_folder, empty_position_folder,
         stack_directly_in_test_folder, store_directly_in_test_folder, unknown_scanner, wrong_image_size,
         wrong_sequence, empty_acceptance_folder, no_test_folder, acceptance_is_a_file,
         position_named_like_acceptance, ballbar_without_positions, positions_without_ballbar,
         position_collides_with_ballbar_position, position_collides_with_measurement,
         position_collides_across_tests, position_name_reused_by_another_scanner]


@pytest.mark.parametrize("breaker", CASES, ids=[c.__name__ for c in CASES])
def test_broken_acceptance_folder_names_the_offending_path(root, breaker):
    where, fragments = breaker(root)
    with pytest.raises(DataSetError) as info:
        DataSet.open(root)
    message = str(info.value)
    assert type(info.value) is DataSetError
    assert message.startswith(f"{where}:"), message
    for fragment in fragments:
        assert fragment in message, (fragment, message)
