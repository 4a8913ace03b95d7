"""The run's summary (summary.json and the console table) names the measurements the
adjustment left out, so that a user who missed the warning still sees them."""

import json

from flows.cli_run import _print_summary
from fringecal.run.config import load_run_config
from fringecal.run.summary import run_summary
from fringecal.rundir import RunDir


def test_left_out_measurements_are_in_the_summary_and_its_table(small_run, small_config, tmp_path, capsys):
    rd = RunDir(tmp_path / "run")
    rd.root.mkdir()
    for entry in small_run[0].root.iterdir():  # the session's small run, read through links
        if entry.name != rd.bundle_summary.path.name:
            (rd.root / entry.name).symlink_to(entry, entry.is_dir())
    bs = json.loads(small_run[0].bundle_summary.path.read_text())
    cfg = load_run_config(small_config)
    rd.bundle_summary.save(bs)
    assert run_summary(rd, cfg)["measurements_left_out"] == []
    reason = "control points on 2 sphere(s) only (4, 5): its rotation about the line through the two sphere centres"
    rd.bundle_summary.save({**bs, "dropped_measurements": [{"measurement": "12", "reason": reason}]})
    summary = run_summary(rd, cfg)
    assert summary["measurements_left_out"] == ["12"]
    # what the flow adds to the summary before it prints it (flows/run_flow.py)
    _print_summary({**summary, "total_seconds": 1.0, "compile_seconds": 0.0, "tasks": {"ran": [], "cached": []}},
                   rd.root)
    row = next(line for line in capsys.readouterr().out.splitlines() if "measurements / control points" in line)
    assert f"{summary['n_measurements']} / {summary['n_control_points']:,} (left out: 12)" in row
