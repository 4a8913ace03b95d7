"""Named steps and their declared keys: a step sees only the settings it declares; a
changed input file (edited in place), setting or module reruns exactly the steps that
read it; a step's record is the one validity check. Runs the pipeline without Prefect
(`fringecal.steps.run_pipeline`) on the small data set made by `fringecal simulate`."""

import shutil
from pathlib import Path

import pandas as pd
import pytest

from fringecal import digests
from fringecal.digests import DigestCache, digest_path, module_files, source_digest
from fringecal.run.config import RunConfig, load_run_config
from fringecal.rundir import RunDir
from fringecal.steps import STEPS, current_record, get_step, pipeline, run_pipeline, run_step, step_key

pytestmark = pytest.mark.slow  # whole runs: the fast tier (-m "not slow") leaves this module out


def ran(records: dict) -> set[str]:
    """step:item of every instance that had to run."""
    return {f"{s}:{i}" if i else s for s, items in records.items() for i, r in items.items() if not r["reused"]}


def steps_that_ran(records: dict) -> set[str]:
    return {name.split(":")[0] for name in ran(records)}


@pytest.fixture(scope="module")
def data_run(small_dataset, small_dataset_run, tmp_path_factory):
    """A private copy of the small data set (the tests edit it), a private copy of the
    session's run of it (tests/conftest.py) and the step records of that run. The copied
    run is current for the copied data set: outside files count by content, not by where
    they lie (the first test's second run finds nothing to do; the last test moves the
    data set again). Its manifest, which step commands read their settings from, names
    the session's data set: the same files."""
    data = shutil.copytree(small_dataset[0], tmp_path_factory.mktemp("data") / "small")
    shared, first = small_dataset_run
    rd = RunDir(shutil.copytree(shared.root, tmp_path_factory.mktemp("run") / "run", symlinks=True))
    return data, rd, first


def test_every_step_ran_once_and_a_second_run_reuses_everything(data_run):
    data, rd, first = data_run
    cfg = load_run_config(dataset=data)
    assert list(first) == [s.name for s in pipeline(cfg)]
    # the calibration stacks first, then the positions' (which take their scanner's phase ripple)
    assert len(first["decode"]) == 8 and len(first["decode-positions"]) == 6 and len(first["spheres-first"]) == 8
    assert ran(first) == {f"{s}:{i}" if i else s for s, items in first.items() for i in items}
    again = run_pipeline(rd, cfg, workers=2)
    assert ran(again) == set()
    assert rd.verification.load()["calibrated"]["max_abs_error_mm"] < 0.2


def test_an_input_table_edited_in_place_reruns_the_steps_that_read_it(data_run):
    """rods.csv is read by the data set's ingest step, then (as the run's copy) by the
    second pass and the report. A rod length is not used for masking, so the second
    pass gives the same control points and nothing after it reruns."""
    data, rd, _ = data_run
    rods = data / "rods.csv"
    text = rods.read_text()
    try:
        rods.write_text(text.replace(text.splitlines()[1].split(",")[-1], "600.5", 1))
        records = run_pipeline(rd, load_run_config(dataset=data), workers=2)
        assert steps_that_ran(records) == {"ingest", "spheres-second", "report"}
        assert len([i for i, r in records["spheres-second"].items() if not r["reused"]]) == 8
    finally:
        rods.write_text(text)
    restored = run_pipeline(rd, load_run_config(dataset=data), workers=2)
    assert steps_that_ran(restored) == {"ingest", "spheres-second", "report"}


def test_planned_poses_edited_or_deleted_rerun_ingest_and_labelling_only(data_run):
    """A plan 1 mm off singles out the same labels: ingest and the labelling rerun, nothing
    else. The plan deleted (issue 28): every view of the small thesis rig whose spheres
    decide it is labelled from the scanners' views alone -- the link both scanners' possible
    labellings agree on in every measurement, then each measurement by both views together
    (in measurement 12 scanner1's ambiguous triangle by scanner2's two spheres) -- exactly
    as with the plan; scanner2's two spheres of measurement 12 stay unlabelled, as with the
    plan. Only the report reruns besides, and the calibration is the same file, to the
    last byte (tolerance zero)."""
    data, rd, _ = data_run
    poses = data / "poses_planned.csv"
    original = poses.read_bytes()
    planned_labels, planned_out = rd.sphere_fits_labelled.load(), rd.label_outcomes.load()
    calibration = (rd.root / "calibration.json").read_bytes()
    try:
        df = pd.read_csv(poses)
        df.loc[0, "tx_mm"] += 1.0
        df.to_csv(poses, index=False)
        assert steps_that_ran(run_pipeline(rd, load_run_config(dataset=data))) == {"ingest", "label"}
        poses.unlink()
        records = run_pipeline(rd, load_run_config(dataset=data))
        assert not rd.poses_planned.exists()
        out = rd.label_outcomes.load()
        labelled = out["status"] == "labelled"
        assert labelled.sum() == 7 and set(out.loc[labelled, "method"]) == {"linked pose"}
        assert list(out["status"]) == list(planned_out["status"])
        assert list(out.loc[~labelled, "reason"]) == ["too_few_candidates"]
        assert "scanner1, scanner2 together" in out.loc[(out["measurement"] == "12") & labelled, "message"].iloc[0]
        assert rd.sphere_fits_labelled.load()["sphere_id"].equals(planned_labels["sphere_id"])
        assert steps_that_ran(records) == {"ingest", "label", "report"}
        assert (rd.root / "calibration.json").read_bytes() == calibration
    finally:
        poses.write_bytes(original)
    run_pipeline(rd, load_run_config(dataset=data))


def test_one_setting_reruns_the_steps_that_declare_it(data_run, tmp_path):
    data, rd, _ = data_run
    own = tmp_path / "run.yaml"
    own.write_text("bundle:\n  gamma2: 0.5\n")
    records = run_pipeline(rd, load_run_config(own, dataset=data))
    assert steps_that_ran(records) == {"bundle", "cross-validate", "verify", "acceptance", "report"}
    back = run_pipeline(rd, load_run_config(dataset=data))
    assert steps_that_ran(back) == {"bundle", "cross-validate", "verify", "acceptance", "report"}


@pytest.mark.parametrize("module, expected", [
    ("fringecal.report", {"report"}),
    ("fringecal.verification.lengths", {"verify", "acceptance"}),  # same numbers, so the report stays current
])
def test_a_changed_module_reruns_only_the_steps_that_run_it(data_run, tmp_path, monkeypatch, module, expected):
    data, rd, _ = data_run
    original = digests._module_file(module)
    edited = tmp_path / original.name
    edited.write_text(original.read_text() + "\n# an edit\n")
    real = digests._module_file
    monkeypatch.setattr(digests, "_module_file", lambda name: edited if name == module else real(name))
    assert steps_that_ran(run_pipeline(rd, load_run_config(dataset=data))) == expected
    monkeypatch.undo()
    assert steps_that_ran(run_pipeline(rd, load_run_config(dataset=data))) == expected


def test_a_changed_output_is_recomputed_and_the_record_is_the_one_check(data_run):
    data, rd, _ = data_run
    cfg = load_run_config(dataset=data)
    step = get_step("label")
    view = step.view(cfg)
    key = step_key(step, rd, view, "")
    assert current_record(step, rd, view, "", key)["key"] == key
    good = rd.scanner_links.path.read_text()
    rd.scanner_links.path.write_text(good.replace("scanner2", "scanner2 "))
    assert current_record(step, rd, view, "", key) is None
    rec = run_step(step, rd, cfg)
    assert not rec["reused"] and rd.scanner_links.path.read_text() == good
    assert current_record(step, rd, view, "", key) is not None


def test_a_step_sees_only_what_it_declares():
    cfg = RunConfig()
    view = STEPS["bundle"].view(cfg)
    assert view.bundle.gamma1 == 1.0 and "bundle" in view.keyed()
    with pytest.raises(AttributeError, match="'extraction' was not declared"):
        view.extraction
    first = STEPS["spheres-first"].view(cfg)
    assert set(first.keyed()) == {"extraction.candidates", "extraction.rejection"}
    with pytest.raises(AttributeError, match="extraction.labelling"):
        first.extraction.labelling
    # a location (where a data set is) is readable but not keyed
    assert "dataset" not in STEPS["decode"].view(RunConfig(dataset=Path("."))).keyed()


def test_steps_keys_include_their_own_code_only():
    report = module_files(["fringecal.steps.report"])
    assert "fringecal.report" in report and "fringecal.calibration.bundle" not in report
    assert "fringecal.rundir" not in report  # infrastructure: where files go, not what is computed
    bundle = module_files(["fringecal.steps.bundle"])
    assert "fringecal.calibration.kernels" in bundle and "fringecal.report" not in bundle
    assert source_digest(["fringecal.steps.report"]) != source_digest(["fringecal.steps.bundle"])


def test_a_report_template_is_part_of_the_report_steps_code(tmp_path, monkeypatch):
    """Editing only a template or the style sheet must rewrite the report on the next run."""
    import fringecal.report as report

    copy = tmp_path / "report"
    shutil.copytree(Path(report.__file__).parent, copy, ignore=shutil.ignore_patterns("__pycache__"))
    real = digests._module_file

    def in_copy(name):
        path = real(name)
        if path is not None and name.startswith("fringecal.report"):
            return copy / path.relative_to(Path(report.__file__).parent)
        return path

    monkeypatch.setattr(digests, "_module_file", in_copy)
    before = source_digest(["fringecal.steps.report"])
    css = copy / "templates" / "report.css"
    css.write_text(css.read_text() + "\n/* edited */\n")
    assert source_digest(["fringecal.steps.report"]) != before


def test_digest_cache_rehashes_only_changed_files(tmp_path, monkeypatch):
    folder = tmp_path / "store"
    folder.mkdir()
    (folder / "a").write_bytes(b"1" * 1000)
    (folder / "b").write_bytes(b"2" * 1000)
    old = 1_000_000_000_000_000_000  # files last modified long ago
    for p in folder.iterdir():
        import os

        os.utime(p, ns=(old, old))
    # their change time (ctime, part of the signature since issue 31) is now: no racy window here
    monkeypatch.setattr(digests, "_RACY_NS", -10**18)
    cache = DigestCache(tmp_path / ".digests")
    first = cache.digest(folder)
    assert first == digest_path(folder)
    calls = []
    monkeypatch.setattr(digests, "digest_path", lambda p: calls.append(p) or digest_path(p))
    assert DigestCache(tmp_path / ".digests").digest(folder) == first and calls == []  # from disk, no hashing
    (folder / "b").write_bytes(b"3" * 1000)  # edited in place: new mtime
    assert cache.digest(folder) != first and len(calls) == 1


def test_step_command_shares_the_records_of_the_pipeline(data_run, tmp_path):
    """`fringecal step NAME --run RUN_DIR`: the same step objects and records, no Prefect."""
    import json

    from typer.testing import CliRunner

    from fringecal.flows.cli import app

    data, rd, _ = data_run
    runner = CliRunner()
    res = runner.invoke(app, ["step", "spheres-first", "--run", str(rd.root), "--json"])
    assert res.exit_code == 0, res.output
    records = json.loads(res.stdout)
    assert len(records) == 8 and all(r["reused"] for r in records)
    res = runner.invoke(app, ["step", "label", "--run", str(rd.root), "--force"])
    assert res.exit_code == 0 and "label: 1 ran, 0 current already" in res.output
    assert steps_that_ran(run_pipeline(rd, load_run_config(dataset=data))) == set()  # same content, same keys
    res = runner.invoke(app, ["step", "nosuch", "--run", str(rd.root)])
    assert res.exit_code == 2 and "no step 'nosuch'" in res.output


def test_a_data_set_moved_elsewhere_keeps_every_key(data_run, tmp_path):
    """Outside files count by content, not by where they lie: a copy of the data set in
    another folder is the same input, so nothing reruns."""
    import os

    data, rd, _ = data_run
    moved = shutil.copytree(data, tmp_path / "elsewhere" / "cell",
                            copy_function=lambda s, d: os.link(s, d) if s.endswith(".png") else shutil.copy2(s, d))
    assert ran(run_pipeline(rd, load_run_config(dataset=moved))) == set()
