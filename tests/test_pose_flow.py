"""The pose flow and `fringecal pose` under a temporary Prefect server."""

import json

import pandas as pd
import pytest
from typer.testing import CliRunner

from fringecal.flows.cli import app
from fringecal.tasks.refs import Ref, digest_path, ref_for

runner = CliRunner()


@pytest.mark.flow
def test_pose_flow_writes_table_and_caches(prefect_harness, thesis_dir, tmp_path):
    from fringecal.flows.pose_flow import pose_flow

    out = tmp_path / "poses.csv"
    first = pose_flow(str(thesis_dir / "artefact_cmm2.csv"), str(thesis_dir / "centres_scanner2_table6-6.csv"), str(out))
    assert isinstance(first["poses"], Ref) and first["poses"].exists_unchanged()
    poses = pd.read_csv(out)
    assert len(poses) == 12 and poses.loc[0, "tx_mm"] == pytest.approx(1675.549, abs=0.002)
    second = pose_flow(str(thesis_dir / "artefact_cmm2.csv"), str(thesis_dir / "centres_scanner2_table6-6.csv"), str(out))
    assert second["poses"] == first["poses"]


def test_cli_pose_json_and_skipped_groups(thesis_dir, tmp_path):
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




def test_cli_pose_nothing_written_when_no_group_gives_a_pose(thesis_dir, tmp_path):
    centres = pd.read_csv(thesis_dir / "centres_scanner1_table6-3.csv")
    cpath = tmp_path / "centres.csv"
    centres[centres.sphere_id.isin([5, 6])].to_csv(cpath, index=False)  # two spheres per group
    out = tmp_path / "poses.csv"
    res = runner.invoke(app, ["pose", "--artefact", str(thesis_dir / "artefact_cmm2.csv"),
                              "--centres", str(cpath), "--out", str(out)])
    assert res.exit_code == 2
    assert "no group gives a pose" in res.output and "nothing written" in res.output
    assert list(tmp_path.iterdir()) == [cpath]


def test_pose_command_runs_without_prefect(thesis_dir, tmp_path):
    """No Prefect server configured: the command never imports Prefect (no temporary server)."""
    import os
    import subprocess
    import sys

    out = tmp_path / "poses.csv"
    code = ("import sys; from fringecal.flows.cli import main; sys.argv = ['fringecal', 'pose', '-a', sys.argv[1], '--centres', "
            "sys.argv[2], '-o', sys.argv[3], '--json']\n"
            "try:\n    main()\nexcept SystemExit as e:\n    assert not e.code, e.code\n"
            "assert 'prefect' not in sys.modules, 'prefect imported'")
    env = {k: v for k, v in os.environ.items() if not k.startswith("PREFECT_")}
    env["PREFECT_HOME"] = str(tmp_path / "prefect-home")  # no profile with an API URL
    proc = subprocess.run([sys.executable, "-c", code, str(thesis_dir / "artefact_cmm2.csv"),
                           str(thesis_dir / "centres_scanner2_table6-6.csv"), str(out)],
                          capture_output=True, text=True, env=env, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-2000:]
    poses = pd.read_csv(out)
    assert len(poses) == 12 and poses.loc[0, "tx_mm"] == pytest.approx(1675.549, abs=0.002)


@pytest.mark.flow
def test_cli_pose_runs_as_a_flow_on_a_configured_server(prefect_harness, thesis_dir, tmp_path, monkeypatch):
    from prefect.client.orchestration import get_client
    from prefect.settings import PREFECT_API_URL

    monkeypatch.setenv("PREFECT_API_URL", PREFECT_API_URL.value())
    out = tmp_path / "poses.csv"
    res = runner.invoke(app, ["pose", "--artefact", str(thesis_dir / "artefact_cmm2.csv"),
                              "--centres", str(thesis_dir / "centres_scanner2_table6-6.csv"), "--out", str(out)])
    assert res.exit_code == 0, res.output
    assert len(pd.read_csv(out)) == 12
    with get_client(sync_client=True) as client:
        runs = client.read_flow_runs()
    assert any(r.name and r.parameters.get("out") == str(out) for r in runs)


@pytest.mark.parametrize("where", ["env", "profile", "prefect.toml", "none"])
def test_configured_prefect_api_is_found_where_prefect_looks(where, tmp_path, monkeypatch):
    from fringecal.flows.common import configured_prefect_api

    for k in ("PREFECT_API_URL", "PREFECT_PROFILE", "PREFECT_PROFILES_PATH"):
        monkeypatch.delenv(k, raising=False)
    monkeypatch.setenv("PREFECT_HOME", str(tmp_path))
    monkeypatch.chdir(tmp_path)
    url = "http://127.0.0.1:4200/api"
    if where == "env":
        monkeypatch.setenv("PREFECT_API_URL", url)
    elif where == "profile":
        (tmp_path / "profiles.toml").write_text(
            f'active = "lab"\n[profiles.lab]\nPREFECT_API_URL = "{url}"\n[profiles.other]\n')
    elif where == "prefect.toml":
        (tmp_path / "prefect.toml").write_text(f'[api]\nurl = "{url}"\n')
    else:
        (tmp_path / "profiles.toml").write_text('active = "ephemeral"\n[profiles.ephemeral]\n')
    assert configured_prefect_api() == (None if where == "none" else url)
