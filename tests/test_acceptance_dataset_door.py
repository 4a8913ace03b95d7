"""The acceptance test of a recorded data set from its ``verification/`` folder alone:
a small simulated rig written as a data set (``fringecal simulate``: the acceptance
objects' stacks in ``verification/acceptance/``), then processed by ``run --dataset``
up to the acceptance step, which finds every object and gives every parameter."""

import shutil

import pytest

from fringecal.run.config import load_run_config
from fringecal.run.summary import manifest
from fringecal.rundir import RunDir
from fringecal.simulate.small_thesis import write_small_thesis_config
from fringecal.steps import run_pipeline

pytestmark = pytest.mark.slow  # whole runs: the fast tier (-m "not slow") leaves this module out


def test_acceptance_of_a_data_set_from_its_verification_folder(small_dataset, small_dataset_run, tmp_path):
    """The run directory starts as a copy of the session's run of the small data set
    (tests/conftest.py): this data set is that rig with acceptance objects and two of
    its three ball-bar positions, written alike, so its stacks decode to the same
    stores and its spheres and adjustment have the same keys there and are reused (the
    same files a run from nothing writes; a copied run stays current,
    tests/test_steps.py); what this test is about, the acceptance objects' stacks and
    the acceptance step, runs.

    For the same reason the data set is written with those stacks linked from the
    session's data set instead of rendered again (conftest.write_dataset_reusing: one
    calibration stack and one ball-bar stack are rendered anyway and must be the same
    bytes); the acceptance objects' stacks are rendered."""
    from conftest import write_dataset_reusing

    config = write_small_thesis_config(tmp_path, width=320, poses=(1, 5, 9, 12), positions=(1, 9),
                                       acceptance={"sphere": 1, "dumbbell": 1, "flat": 1})
    sim = load_run_config(config)
    data = write_dataset_reusing(sim, tmp_path / "data", tmp_path / "data-truth", small_dataset[0],
                                 check=("12-scanner2", "bb09-scanner1"))
    assert sorted(p.name for p in (data / "verification" / "acceptance").iterdir()) == \
        ["dumbbell", "flat", "sphere", "standards.yaml"]
    cfg = load_run_config(config, dataset=data)
    rd = RunDir(shutil.copytree(small_dataset_run[0].root, tmp_path / "run", symlinks=True))
    rd.manifest.save(manifest(cfg))
    run_pipeline(rd, cfg, workers=2, until="acceptance")
    assert not rd.truth.acceptance_positions.exists()       # nothing but the data set
    doc = rd.acceptance.load()
    got = {(p["name"], p["scanner"]): p for p in doc["parameters"]}
    for name in ("P_F", "P_S", "SD", "F"):
        for scanner in ("scanner1", "scanner2"):
            assert got[(name, scanner)]["positions"] == 1
    assert got[("E", "cell")]["positions"] == 2
    assert doc["failures"] == []
    # at 320 px with the short sequence the values are noise-sized but the sizes are right:
    # diameter within 1 mm of 127 mm, dumbbell within 1 mm of 500 mm
    for scanner in ("scanner1", "scanner2"):
        assert abs(got[("P_S", scanner)]["measured_mm"]) < 1.0
        assert abs(got[("SD", scanner)]["measured_mm"]) < 1.0
        assert 0 < got[("F", scanner)]["measured_mm"] < 5.0
