"""Recorded data sets: a good data set opens with the expected stacks in order, every
broken one stops with one message naming the offending folder or file, and no image
is read while validating."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import xarray as xr
import yaml

from fringecal.dataset import STORE_VARIABLES, DataSet, DataSetError, ProcessingOverrides, natural_key
from fringecal.fringe import importer
from fringecal.fringe.importer import FrameStackError, read_frames, write_frames
from fringecal.fringe.sequence import FringeSequence
from fringecal.schemas import TableError
from fringecal.store import COMPLETE_ATTR, StoreError, write_store

THESIS = Path(__file__).resolve().parents[1] / "configs" / "thesis"
SEQ = FringeSequence((8, 7, 6), 3, ("x", "y"))
SIZE = 16  # camera format of both scanners in the test's sensors_prior.csv
CONFIG = {
    "name": "cell-a",
    "reference_scanner": "scanner1",
    "description": "two thesis scanners, tiny images",
    "temperature_c": 20.5,
    "artefact_corrections": {"thermal": {"cte_per_c": 1.9e-6}, "sag": {"rods": "rods.csv"}},
    "processing": {"decode": {"min_modulation": 0.1}, "bundle": {"max_iterations": 30}},
}


# -- builders -----------------------------------------------------------------

def stack(folder: Path, h: int = SIZE, w: int = SIZE, seq: FringeSequence = SEQ) -> Path:
    """A PNG frame folder (values irrelevant: validation never reads them)."""
    if folder.exists():
        shutil.rmtree(folder)
    frames = np.full((seq.n_frames, h, w), 1000, np.uint16)
    return write_frames(folder, frames, seq, 12, fmt="png")


def store(path: Path, h: int = SIZE, w: int = SIZE, seq: FringeSequence = SEQ,
          variables=STORE_VARIABLES, attrs: dict | None = None) -> Path:
    """A decoded store with tau_x, tau_y (float32) and valid (bool) on ("v", "u")."""
    if path.exists():
        shutil.rmtree(path)
    data = {"tau_x": np.zeros((h, w), np.float32), "tau_y": np.ones((h, w), np.float32),
            "valid": np.ones((h, w), bool)}
    ds = xr.Dataset({v: (("v", "u"), data[v]) for v in variables},
                    attrs={"sequence": seq.to_dict()} if attrs is None else attrs)
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
    """The good data set: measurements 1, 2, 10 (10 has scanner2 as a store), ball-bar
    positions p1 (scanner1 binned 8x8, scanner2) and p2 (scanner2 store, binned), plus
    hidden and stray entries that must be ignored."""
    root.mkdir(parents=True)
    write_yaml(root / "dataset.yaml", CONFIG)
    shutil.copy(THESIS / "artefact_cmm2.csv", root / "artefact.csv")
    shutil.copy(THESIS / "rods.csv", root / "rods.csv")
    prior_table().to_csv(root / "sensors_prior.csv", index=False)
    poses = pd.read_csv(THESIS / "poses_scanner1_table6-1.csv", dtype=str).iloc[:3]
    poses.loc[2, "measurement"] = "10"
    poses.to_csv(root / "poses_planned.csv", index=False)
    m = root / "measurements"
    for name in ("1", "2", "10"):
        stack(m / name / "scanner1")
    for name in ("1", "2"):
        stack(m / name / "scanner2")
    store(m / "10" / "scanner2.zarr")
    (m / "notes.txt").write_text("stray file, ignored")
    (m / ".cache").mkdir()
    (m / "2" / "log.txt").write_text("stray file, ignored")
    (m / "2" / ".scanner9").mkdir()
    v = root / "verification"
    v.mkdir()
    shutil.copy(THESIS / "ballbar.csv", v / "ballbar.csv")
    stack(v / "p1" / "scanner1", 8, 8)
    stack(v / "p1" / "scanner2")
    store(v / "p2" / "scanner2.zarr", 8, 8)
    (v / "readme.md").write_text("stray file, ignored")
    return root


@pytest.fixture(scope="module")
def template(tmp_path_factory) -> Path:
    return build(tmp_path_factory.mktemp("template") / "ds")


@pytest.fixture
def root(template, tmp_path) -> Path:
    return Path(shutil.copytree(template, tmp_path / "ds"))


# -- the good data set ------------------------------------------------------------

def test_good_data_set_lists_stacks_in_natural_and_rig_order(root):
    ds = DataSet.open(root)
    assert ds.root == root and ds.scanners == ("scanner1", "scanner2")
    assert ds.measurement_names() == ["1", "2", "10"]
    assert [s.id for s in ds.measurements] == ["1-scanner1", "1-scanner2", "2-scanner1", "2-scanner2",
                                               "10-scanner1", "10-scanner2"]
    assert [s.format for s in ds.measurements] == ["frames"] * 5 + ["store"]
    assert ds.measurements[-1].path == root / "measurements" / "10" / "scanner2.zarr"
    assert ds.measurements[0].path == root / "measurements" / "1" / "scanner1"
    assert {(s.kind, s.width_px, s.height_px, s.sequence) for s in ds.measurements} == {("artefact", 16, 16, SEQ)}
    assert ds.position_names() == ["p1", "p2"]
    assert [(s.id, s.kind, s.format, s.width_px, s.height_px) for s in ds.verification] == [
        ("p1-scanner1", "ballbar", "frames", 8, 8), ("p1-scanner2", "ballbar", "frames", 16, 16),
        ("p2-scanner2", "ballbar", "store", 8, 8)]
    assert (ds.artefact, ds.rods, ds.sensors_prior, ds.poses_planned, ds.ballbar) == (
        root / "artefact.csv", root / "rods.csv", root / "sensors_prior.csv", root / "poses_planned.csv",
        root / "verification" / "ballbar.csv")


def test_config_is_parsed_with_corrections_and_overrides(root):
    cfg = DataSet.open(root).config
    assert (cfg.name, cfg.reference_scanner, cfg.temperature_c) == ("cell-a", "scanner1", 20.5)
    assert cfg.artefact_corrections.thermal.cte_per_c == 1.9e-6
    assert cfg.artefact_corrections.sag.rods == root / "rods.csv"  # relative to dataset.yaml
    assert cfg.processing.decode == {"min_modulation": 0.1} and cfg.processing.bundle == {"max_iterations": 30}
    assert cfg.processing.extraction is None


def test_certificate_identity_is_read_and_merged_into_the_run_config(root):
    """dataset.yaml's certificate block reaches the run configuration (the report's
    identity); a run configuration's own keys take precedence over it."""
    from fringecal.run.config import load_run_config

    identity = {"customer": "Acme Aero GmbH", "date": "2026-11-20", "scanners": {"scanner1": "FP-0042"},
                "artefact_certificate": {"number": "CMM-2026-117", "date": "2026-10-02"},
                "temperatures_c": {"air": 20.4}}
    write_yaml(root / "dataset.yaml", {**CONFIG, "certificate": identity})
    cert = DataSet.open(root).config.certificate
    assert cert.customer == "Acme Aero GmbH" and str(cert.date) == "2026-11-20"
    assert cert.artefact_certificate.number == "CMM-2026-117" and cert.scanners == {"scanner1": "FP-0042"}
    run = root.parent / "run.yaml"
    write_yaml(run, {"dataset": str(root), "certificate": {"customer": "Acme Aero, plant 2"}})
    merged = load_run_config(run).certificate
    assert merged.customer == "Acme Aero, plant 2" and merged.temperatures_c == {"air": 20.4}
    assert str(merged.artefact_certificate.date) == "2026-10-02"


def test_optional_parts_may_be_absent(root):
    for name in ("rods.csv", "poses_planned.csv"):
        (root / name).unlink()
    shutil.rmtree(root / "verification")
    write_yaml(root / "dataset.yaml", {"name": "minimal", "reference_scanner": "scanner2"})
    ds = DataSet.open(root)
    assert (ds.rods, ds.poses_planned, ds.ballbar, ds.verification) == (None, None, None, ())
    assert ds.position_names() == [] and len(ds.measurements) == 6
    assert ds.config.processing == ProcessingOverrides() and ds.config.description is None


def test_validation_reads_headers_but_decodes_no_image(root, monkeypatch):
    """Every frame's header is read (a file that is not a PNG is refused) but no pixel is
    decoded: a PNG with damaged image data passes, and any decoding fails the test."""
    bad = root / "measurements" / "2" / "scanner1" / "y_006_02.png"
    data = bad.read_bytes()
    at = data.index(b"IDAT")
    i = at + 4 + int.from_bytes(data[at - 4:at], "big") // 2  # the middle of the image data
    bad.write_bytes(data[:i] + bytes([data[i] ^ 0xFF]) + data[i + 1:])

    def forbidden(*args, **kwargs):
        raise AssertionError("an image was decoded during validation")

    for reader in ("read_png", "read_bmp", "read_tif"):
        monkeypatch.setattr(importer, reader, forbidden)
    assert len(DataSet.open(root).measurements) == 6
    monkeypatch.undo()
    with pytest.raises(FrameStackError, match=r"y_006_02\.png: corrupt or unreadable PNG \(image data"):
        read_frames(bad.parent)
    bad.write_bytes(b"not a png")
    with pytest.raises(FrameStackError, match=r"y_006_02\.png: corrupt or unreadable PNG \(no PNG signature\)"):
        DataSet.open(root)


@pytest.mark.parametrize("w, h, ok", [(9, 8, True), (8, 9, True), (16, 15, True), (10, 8, False),
                                      (8, 6, False), (32, 32, True)])
def test_verification_binning_keeps_the_aspect_ratio_within_one_pixel(root, w, h, ok):
    """Camera 16x16: a verification stack may have any pixel count within one pixel of square."""
    stack(root / "verification" / "p1" / "scanner1", h, w)
    if ok:
        src = DataSet.open(root).verification[0]
        assert (src.id, src.width_px, src.height_px) == ("p1-scanner1", w, h)
    else:
        with pytest.raises(DataSetError, match=f"{w}x{h} px, not the aspect ratio"):
            DataSet.open(root)


def test_natural_key_orders_digit_runs_by_value():
    names = ["pos10", "10", "2", "pos2", "1b", "1a", "a"]
    assert sorted(names, key=natural_key) == ["1a", "1b", "2", "10", "a", "pos2", "pos10"]


# -- broken data sets -----------------------------------------------------------------
# Each case breaks the good data set and returns (path the message starts with, fragments).

def _csv_edit(path: Path, edit) -> None:
    df = pd.read_csv(path, dtype=str, keep_default_na=False)
    edit(df).to_csv(path, index=False)


def no_root(r):
    shutil.rmtree(r)
    return r, ("no such data set folder",)


def root_is_file(r):
    shutil.rmtree(r)
    r.write_text("x")
    return r, ("not a folder",)


def no_yaml(r):
    (r / "dataset.yaml").unlink()
    return r / "dataset.yaml", ("missing", "reference_scanner")


def yaml_not_yaml(r):
    (r / "dataset.yaml").write_text("name: [unclosed\n")
    return r / "dataset.yaml", ("not valid YAML",)


def yaml_unknown_key(r):
    write_yaml(r / "dataset.yaml", {**CONFIG, "processing": {"decod": {"x": 1}}})
    return r / "dataset.yaml", ("processing.decod: unknown key",)


def yaml_unknown_nested_key(r):
    write_yaml(r / "dataset.yaml", {**CONFIG, "artefact_corrections": {"thermal": {"cte": 1e-6}}})
    return r / "dataset.yaml", ("artefact_corrections.thermal.cte: unknown key",)


def yaml_unknown_certificate_key(r):
    write_yaml(r / "dataset.yaml", {**CONFIG, "certificate": {"customer": "A", "serial": "B"}})
    return r / "dataset.yaml", ("certificate.serial: unknown key",)


def yaml_no_name(r):
    write_yaml(r / "dataset.yaml", {"reference_scanner": "scanner1"})
    return r / "dataset.yaml", ("name: Field required",)


def yaml_no_reference(r):
    write_yaml(r / "dataset.yaml", {"name": "x"})
    return r / "dataset.yaml", ("reference_scanner: Field required",)


def no_artefact(r):
    (r / "artefact.csv").unlink()
    return r / "artefact.csv", ("missing",)


def bad_artefact(r):
    def edit(df):
        df.loc[1, "diameter_mm"] = ""
        return df
    _csv_edit(r / "artefact.csv", edit)
    return r / "artefact.csv", ("line 3", "diameter_mm")


def two_spheres(r):
    _csv_edit(r / "artefact.csv", lambda df: df.iloc[:2])
    return r / "artefact.csv", ("2 sphere(s)", "at least 3")


def rod_unknown_sphere(r):
    _csv_edit(r / "rods.csv", lambda df: pd.concat([df, pd.DataFrame(
        [{"rod_id": "99", "sphere_a": "1", "sphere_b": "42", "length_mm": "500"}])], ignore_index=True))
    return r / "rods.csv", ("line 41", "sphere '42'")


def no_prior(r):
    (r / "sensors_prior.csv").unlink()
    return r / "sensors_prior.csv", ("missing",)


def bad_prior(r):
    def edit(df):
        df.loc[2, "c_mm"] = "-52.6"
        return df
    _csv_edit(r / "sensors_prior.csv", edit)
    return r / "sensors_prior.csv", ("line 4", "c_mm")


def unknown_reference(r):
    write_yaml(r / "dataset.yaml", {**CONFIG, "reference_scanner": "scanner9"})
    return r / "dataset.yaml", ("'scanner9'", str(r / "sensors_prior.csv"), "scanner1, scanner2")


def no_measurements(r):
    shutil.rmtree(r / "measurements")
    return r / "measurements", ("missing",)


def empty_measurements(r):
    shutil.rmtree(r / "measurements")
    (r / "measurements" / ".hidden").mkdir(parents=True)
    (r / "measurements" / "notes.txt").write_text("")
    return r / "measurements", ("no measurement folder",)


def scanner_missing(r):
    shutil.rmtree(r / "measurements" / "2" / "scanner2")
    return r / "measurements" / "2", ("scanner 'scanner2'", "every measurement needs every scanner")


def empty_measurement(r):
    shutil.rmtree(r / "measurements" / "2")
    (r / "measurements" / "2").mkdir()
    return r / "measurements" / "2", ("without scanner stacks",)


def unknown_scanner(r):
    shutil.copytree(r / "measurements" / "1" / "scanner1", r / "measurements" / "1" / "scanner3")
    return r / "measurements" / "1" / "scanner3", ("frames but no prior calibration", "'scanner3'")


def unknown_scanner_store(r):
    store(r / "measurements" / "10" / "scanner5.zarr")
    return r / "measurements" / "10" / "scanner5.zarr", ("no prior calibration", "'scanner5'")


def prior_without_frames(r):
    df = prior_table()
    extra = df[df["scanner"] == "scanner2"].assign(scanner="scanner3", sensor=["C3", "P3"])
    pd.concat([df, extra]).to_csv(r / "sensors_prior.csv", index=False)
    return r / "sensors_prior.csv", ("scanner 'scanner3' has no frames",)


def ambiguous(r):
    stack(r / "measurements" / "10" / "scanner2")
    return r / "measurements" / "10", ("ambiguous", "frame folder scanner2/", "store scanner2.zarr")


def sequence_steps_differ(r):
    stack(r / "measurements" / "2" / "scanner2", seq=FringeSequence((8, 7, 6), 4))
    return (r / "measurements" / "2" / "scanner2" / "sequence.yaml",
            (str(r / "measurements" / "1" / "scanner1" / "sequence.yaml"), "steps 3 vs 4"))


def sequence_counts_differ(r):
    stack(r / "verification" / "p1" / "scanner2", seq=FringeSequence((16, 15, 14, 12), 3))
    return (r / "verification" / "p1" / "scanner2" / "sequence.yaml",
            ("measurements/1/scanner1/sequence.yaml", "fringe counts (8, 7, 6) vs (16, 15, 14, 12)"))


def store_orientation_differs(r):
    store(r / "measurements" / "10" / "scanner2.zarr", seq=FringeSequence((8, 7, 6), 3, ("x",)))
    return r / "measurements" / "10" / "scanner2.zarr", ("orientations ('x', 'y') vs ('x',)",)


def frames_wrong_size(r):
    stack(r / "measurements" / "2" / "scanner1", h=12)
    return (r / "measurements" / "2" / "scanner1" / "sequence.yaml",
            ("16x12 px", "camera 'C1'", "16x16 px", "sensors_prior.csv"))


def store_wrong_size(r):
    store(r / "measurements" / "10" / "scanner2.zarr", w=20)
    return r / "measurements" / "10" / "scanner2.zarr", ("20x16 px", "camera 'C2'", "16x16 px")


def verification_wrong_aspect(r):
    stack(r / "verification" / "p1" / "scanner1", 6, 8)
    return r / "verification" / "p1" / "scanner1" / "sequence.yaml", ("8x6 px", "aspect ratio", "16x16 px")


def planned_without_folder(r):
    shutil.rmtree(r / "measurements" / "10")
    return r / "poses_planned.csv", ("'10'", str(r / "measurements" / "10"))


def folder_without_plan(r):
    shutil.copytree(r / "measurements" / "2", r / "measurements" / "11")
    return r / "measurements" / "11", ("no planned pose", str(r / "poses_planned.csv"))


def verification_empty(r):
    shutil.rmtree(r / "verification")
    (r / "verification").mkdir()
    return r / "verification", ("empty verification folder",)


def no_ballbar(r):
    (r / "verification" / "ballbar.csv").unlink()
    return r / "verification" / "ballbar.csv", ("missing",)


def ballbar_three_spheres(r):
    shutil.copy(r / "artefact.csv", r / "verification" / "ballbar.csv")
    _csv_edit(r / "verification" / "ballbar.csv", lambda df: df.iloc[:3])
    return r / "verification" / "ballbar.csv", ("exactly two spheres", "['1', '2', '3']")


def ballbar_wrong_ids(r):
    _csv_edit(r / "verification" / "ballbar.csv", lambda df: df.assign(sphere_id=["A", "C"]))
    return r / "verification" / "ballbar.csv", ("A and B", "['A', 'C']")


def ballbar_bad_table(r):
    _csv_edit(r / "verification" / "ballbar.csv", lambda df: df.drop(columns="z_mm"))
    return r / "verification" / "ballbar.csv", ("z_mm",)


def no_position(r):
    for p in ("p1", "p2"):
        shutil.rmtree(r / "verification" / p)
    return r / "verification", ("no position folder",)


def empty_position(r):
    (r / "verification" / "3").mkdir()
    return r / "verification" / "3", ("without scanner stacks",)


def position_unknown_scanner(r):
    shutil.copytree(r / "verification" / "p1" / "scanner2", r / "verification" / "p2" / "scanner7")
    return r / "verification" / "p2" / "scanner7", ("no prior calibration", "'scanner7'")


def store_incomplete(r):
    meta = r / "measurements" / "10" / "scanner2.zarr" / "zarr.json"
    doc = json.loads(meta.read_text())
    doc["attributes"][COMPLETE_ATTR] = False
    meta.write_text(json.dumps(doc))
    return r / "measurements" / "10" / "scanner2.zarr", ("incomplete store",)


def store_corrupt(r):
    chunks = r / "measurements" / "10" / "scanner2.zarr" / "tau_y" / "c"
    shutil.rmtree(chunks)
    return r / "measurements" / "10" / "scanner2.zarr", ("corrupt store", "'tau_y'")


def store_without_valid(r):
    store(r / "measurements" / "10" / "scanner2.zarr", variables=("tau_x", "tau_y"))
    return r / "measurements" / "10" / "scanner2.zarr", ("['valid']",)


def store_without_sequence(r):
    store(r / "verification" / "p2" / "scanner2.zarr", 8, 8, attrs={"scanner": "scanner2"})
    return r / "verification" / "p2" / "scanner2.zarr", ("no 'sequence' attribute",)


def frame_missing(r):
    (r / "measurements" / "2" / "scanner1" / "x_007_01.png").unlink()
    return r / "measurements" / "2" / "scanner1" / "x_007_01.png", ("missing frame",)


def sequence_yaml_bad(r):
    spec = r / "measurements" / "1" / "scanner2" / "sequence.yaml"
    write_yaml(spec, {**yaml.safe_load(spec.read_text()), "gain": 2})
    return spec, ("gain: unknown key",)


CASES = [
    # 1: root and dataset.yaml
    (no_root, DataSetError), (root_is_file, DataSetError), (no_yaml, DataSetError),
    (yaml_not_yaml, DataSetError), (yaml_unknown_key, DataSetError), (yaml_unknown_nested_key, DataSetError),
    (yaml_unknown_certificate_key, DataSetError), (yaml_no_name, DataSetError), (yaml_no_reference, DataSetError),
    # 2: tables
    (no_artefact, DataSetError), (bad_artefact, TableError), (two_spheres, DataSetError),
    (rod_unknown_sphere, TableError), (no_prior, DataSetError), (bad_prior, TableError),
    (unknown_reference, DataSetError),
    # 3, 4, 5, 6: measurement folders and scanners
    (no_measurements, DataSetError), (empty_measurements, DataSetError), (scanner_missing, DataSetError),
    (empty_measurement, DataSetError), (unknown_scanner, DataSetError), (unknown_scanner_store, DataSetError),
    (prior_without_frames, DataSetError), (ambiguous, DataSetError),
    # 7, 8: sequences and image sizes
    (sequence_steps_differ, DataSetError), (sequence_counts_differ, DataSetError),
    (store_orientation_differs, DataSetError), (frames_wrong_size, DataSetError),
    (store_wrong_size, DataSetError), (verification_wrong_aspect, DataSetError),
    # 9: planned poses
    (planned_without_folder, DataSetError), (folder_without_plan, DataSetError),
    # 10: verification
    (verification_empty, DataSetError), (no_ballbar, DataSetError), (ballbar_three_spheres, DataSetError),
    (ballbar_wrong_ids, DataSetError), (ballbar_bad_table, TableError), (no_position, DataSetError),
    (empty_position, DataSetError), (position_unknown_scanner, DataSetError),
    # 11: stores; frame folders (importer errors propagate)
    (store_incomplete, StoreError), (store_corrupt, StoreError), (store_without_valid, DataSetError),
    (store_without_sequence, DataSetError), (frame_missing, FrameStackError), (sequence_yaml_bad, FrameStackError),
]


@pytest.mark.parametrize("breaker, error", CASES, ids=[c[0].__name__ for c in CASES])
def test_broken_data_set_names_the_offending_path(root, breaker, error):
    where, fragments = breaker(root)
    with pytest.raises(error) as info:
        DataSet.open(root)
    message = str(info.value)
    assert type(info.value) is error
    assert message.startswith(f"{where}:"), message
    for fragment in fragments:
        assert fragment in message, (fragment, message)


def test_stacks_whose_store_ids_collide_are_refused(root):
    """Position "1" next to measurement "1": both would become the store 1-scanner1."""
    shutil.move(str(root / "verification" / "p1"), str(root / "verification" / "1"))
    with pytest.raises(DataSetError) as err:
        DataSet.open(root)
    message = str(err.value)
    assert message.startswith(str(root / "verification" / "1" / "scanner1")) and "'1-scanner1'" in message
    assert str(root / "measurements" / "1" / "scanner1") in str(err.value)
