"""The pose flow and `fringecal pose` under a temporary Prefect server."""

import json

import pandas as pd
import pytest
from typer.testing import CliRunner

from flows.cli import app
from tasks.refs import Ref, digest_path, ref_for

runner = CliRunner()


@pytest.mark.flow
def test_pose_flow_writes_table_and_caches(prefect_harness, thesis_dir, tmp_path):
    from flows.pose_flow import pose_flow

    out = tmp_path / "poses.csv"
    first = pose_flow(str(thesis_dir / "artefact_cmm2.csv"), str(thesis_dir / "centres_scanner2_table6-6.csv"), str(out))
    assert isinstance(first["poses"], Ref) and first["poses"].exists_unchanged()
    poses = pd.read_csv(out)
    assert len(poses) == 12 and poses.loc[0, "tx_mm"] == pytest.approx(1675.549, abs=0.002)
    second = pose_flow(str(thesis_dir / "artefact_cmm2.csv"), str(thesis_dir / "centres_scanner2_table6-6.csv"), str(out))
    assert second["poses"] == first["poses"]


@pytest.mark.flow
def test_cli_pose_json_and_skipped_groups(prefect_harness, thesis_dir, tmp_path):
    centres = pd.read_csv(thesis_dir / "centres_scanner1_table6-3.csv")
    centres = centres[~((centres.measurement == 3) & (centres.sphere_id.isin([8, 9])))]
    cpath = tmp_path / "centres.csv"
    centres.to_csv(cpath, index=False)
    out = tmp_path / "poses.csv"
    res = runner.invoke(app, ["pose", "--artefact", str(thesis_dir / "artefact_cmm2.csv"),
                              "--centres", str(cpath), "--out", str(out), "--json"])
    assert res.exit_code == 0, res.output
    doc = json.loads(res.stdout[res.stdout.index("{"):])
    assert len(doc["poses"]) == 11
    assert doc["skipped"] == [{"measurement": "3", "scanner": "scanner1", "reason": "2 points; at least 3 are needed for a pose (spheres 5, 6)"}]


def test_cli_pose_bad_input_fails_before_any_work(thesis_dir, tmp_path):
    bad = tmp_path / "centres.csv"
    bad.write_text("measurement,scanner,sphere_id,x_mm,y_mm\n1,s1,5,0,0\n")
    out = tmp_path / "poses.csv"
    res = runner.invoke(app, ["pose", "--artefact", str(thesis_dir / "artefact_cmm2.csv"),
                              "--centres", str(bad), "--out", str(out)])
    assert res.exit_code == 2
    assert "centres.csv" in res.output and "missing required column(s) ['z_mm']" in res.output
    assert not out.exists()


def test_refs_digest_files_and_directories(tmp_path):
    (tmp_path / "store").mkdir()
    (tmp_path / "store" / "a").write_text("1")
    (tmp_path / "store" / ".lock").write_text("ignored")
    r = ref_for(tmp_path / "store", "store")
    (tmp_path / "store" / ".lock").write_text("changed")
    assert r.exists_unchanged()
    (tmp_path / "store" / "a").write_text("2")
    assert not r.exists_unchanged() and digest_path(tmp_path / "store") != r.digest


