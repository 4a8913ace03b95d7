"""``fringecal hexapod`` commands (typer CliRunner; move/run-file against hexsim://)."""

from __future__ import annotations

import itertools
import json

import numpy as np
import pytest
from typer.testing import CliRunner

from fringecal.flows.cli import app
from fringecal.hexapod import load_hexapod_config
from fringecal.hexapod.kinematics import forward_kinematics, inverse_kinematics
from fringecal.hexapod.simulator import get_controller
from fringecal.schemas import HexapodPlanTable, read_table

runner = CliRunner()
CFG = load_hexapod_config()
_ids = itertools.count()


def run(*args):
    return runner.invoke(app, ["hexapod", *args])


def flat(res) -> str:
    """Output with rich's line wrapping undone."""
    return " ".join(res.output.split())


def test_ik_json_gives_the_leg_lengths():
    res = run("ik", "--pose", "100,-50,800,2,-1,5", "--json")
    assert res.exit_code == 0, res.output
    out = json.loads(res.output)
    pose = np.array([100, -50, 800, *np.radians([2, -1, 5])])
    lengths = inverse_kinematics(CFG.platform, pose)
    assert [leg["length_mm"] for leg in out["legs"]] == pytest.approx(lengths, abs=1e-9)
    assert [leg["stroke_mm"] for leg in out["legs"]] == pytest.approx(lengths - 750.0, abs=1e-9)
    assert [leg["counts"] for leg in out["legs"]] == np.rint((lengths - 750.0) * 20).astype(int).tolist()
    assert out["in_workspace"] is True


def test_ik_table_and_bad_pose():
    res = run("ik", "--pose", "0,0,833.167,0,0,0")
    assert res.exit_code == 0 and "1000.0003" in res.output and "inside the workspace" in res.output
    res = run("ik", "--pose", "0,0,833")
    assert res.exit_code == 2 and "expected 6 comma-separated" in flat(res)
    res = run("ik", "--pose", "0,0,1400,0,0,0")
    assert res.exit_code == 0 and "outside the workspace" in flat(res) and "stroke" in flat(res)


def test_fk_from_counts():
    res = run("fk", "--counts", "5000,5000,5000,5000,5000,5000", "--json")
    out = json.loads(res.output)
    assert out["pose"]["pz_mm"] == pytest.approx(np.sqrt(1000**2 - 553.02200077**2), abs=1e-6)
    assert out["residual_mm"] < 1e-9
    res = run("fk", "--lengths", "100,3000,100,3000,100,3000")
    assert res.exit_code == 2 and "did not converge" in flat(res)


def test_workspace_report():
    out = json.loads(run("workspace", "--json").output)
    assert all(a["reaches_limit"] for a in out["axes"])
    out = json.loads(run("workspace", "--limit-mm", "600", "--json").output)
    px = out["axes"][0]
    assert px["axis"] == "px" and not px["reaches_limit"] and "base joint" in px["upper_limited_by"]


def test_plan_writes_table_and_command_file(tmp_path):
    res = run("plan", "--out", str(tmp_path / "plan.csv"), "--commands", str(tmp_path / "moves.txt"))
    assert res.exit_code == 0, res.output
    assert "12 of 12 poses reachable" in flat(res)
    plan = read_table(tmp_path / "plan.csv", HexapodPlanTable)
    lines = [ln for ln in (tmp_path / "moves.txt").read_text().splitlines() if ln.startswith("MOVEALL")]
    assert len(lines) == 12
    assert lines[0] == "MOVEALL " + " ".join(str(plan.loc[0, f"counts_{i}"]) for i in range(1, 7))
    res = run("plan", "--grid", "--json")
    assert json.loads(res.output)["n_reachable"] == 5
    res = run("plan", "--grid", "--station-per-standoff", "--json")
    assert json.loads(res.output)["n_reachable"] == 12


def test_drift_command(thesis_dir):
    res = run("drift", "--centres", str(thesis_dir / "drift_table4-1.csv"), "--json")
    out = json.loads(res.output)
    assert out["mean_displacement_um"] == pytest.approx(96.55, abs=0.01)
    assert out["expected_scan_drift_um"] == pytest.approx(12.07, abs=0.01) and out["ok"] is False
    res = run("drift", "--centres", str(thesis_dir / "nope.csv"))
    assert res.exit_code == 2 and "file not found" in flat(res)


def test_move_against_the_simulator():
    name = f"cli{next(_ids)}"
    res = run("move", "--port", f"hexsim://{name}", "--pose", "150,-100,900,1,0,-2", "--json")
    assert res.exit_code == 0, res.output
    out = json.loads(res.output)
    assert out["counts_read"] == out["counts_target"]
    assert get_controller(name).motion_log() == ["MOVEALL " + " ".join(map(str, out["counts_target"]))]
    reached = [out["pose_reached"][k] for k in ("px_mm", "py_mm", "pz_mm")]
    assert reached == pytest.approx([150, -100, 900], abs=0.1)
    # the box keeps its state between invocations: FK of its encoders is the reached pose
    lengths = 750.0 + np.array(get_controller(name).encoder_counts()) / 20.0
    assert forward_kinematics(CFG.platform, lengths, CFG.home_pose.vector).poses[:3] == pytest.approx(reached)


def test_move_refusals_and_faults_exit_cleanly():
    name = f"cli{next(_ids)}"
    res = run("move", "--port", f"hexsim://{name}", "--counts", "5000,5000,5000,5000,5000,10500")
    assert res.exit_code == 2 and "outside the stroke" in flat(res)
    assert get_controller(name).motion_log() == []
    name = f"cli{next(_ids)}"
    res = run("move", "--port", f"hexsim://{name}?fault=timeout&after=3", "--pose", "100,0,833,0,0,0")
    assert res.exit_code == 1 and "hexapod fault (timeout)" in flat(res)
    box = get_controller(name)
    assert len(box.motion_log()) == 1 and box.log[-1][1].startswith("STOP")
    res = run("move", "--port", "hexsim://?fault=unplugged", "--pose", "0,0,833,0,0,0")
    assert res.exit_code == 1 and "cannot open the hexapod controller" in flat(res)


def test_run_file(tmp_path):
    path = tmp_path / "moves.txt"
    path.write_text("HOME\nMOVEALL 5000 5000 5000 5000 5000 5000\nPOS?\n")
    name = f"cli{next(_ids)}"
    res = run("run-file", str(path), "--port", f"hexsim://{name}")
    assert res.exit_code == 0, res.output
    assert get_controller(name).motion_log() == ["HOME", "MOVEALL 5000 5000 5000 5000 5000 5000"]
