"""One verdict per run (issue 27): summary.json's ``verdict``, the verdict line of
``fringecal run``, the report's badge, the exit status and the flow run's Prefect state
all say what ``acceptance.json`` and the ball-bar's ISO 14253-1 verdicts say.

One small simulated cell (320 px, four poses, three ball-bar positions, one sphere,
dumbbell and flat position per scanner) is run twice into one run directory: with
generous limits (every parameter's and every length's conformance proven: ACCEPTED)
and with the demo's limits (NOT ACCEPTED); the second run reruns only the steps that
read the limits.
"""

from __future__ import annotations

import json
import re
import shutil

import pytest
import yaml
from typer.testing import CliRunner

from fringecal.flows.cli import app
from fringecal.rundir import RunDir
from fringecal.simulate.small_thesis import write_small_thesis_config

pytestmark = pytest.mark.slow  # whole runs: the fast tier (-m "not slow") leaves this module out

runner = CliRunner()

#: Limits no value of the small cell comes near (mm): every conformance is proven.
GENEROUS = {"verification": {"mpe_mm": 2.0},
            "acceptance": {"limits": {"P_F": 20.0, "P_S": 2.0, "SD": 2.0, "E": 2.0, "F": 20.0}}}


def _iso14253(value: float, U: float | None, limit: float) -> str:
    """ISO 14253-1, written out again: a U that is not known proves nothing."""
    if U is None:
        return "uncertainty zone"
    if abs(value) + U <= limit:
        return "conformance"
    return "non-conformance" if abs(value) - U > limit else "uncertainty zone"


@pytest.fixture(scope="module")
def runs(prefect_harness, small_run, tmp_path_factory):
    """label -> what `fringecal run` printed, its exit status and the run's files, for
    the generous limits ("accepted") and then the demo's ("not accepted").

    The run directory starts as a copy of the session's run of the small rig
    (tests/conftest.py): this cell is that rig with acceptance objects, so its
    calibration stores, spheres and bundle adjustment have the same keys and are reused
    (the same files a run from nothing would write; a copied run stays current,
    tests/test_steps.py); the first `fringecal run` renders the acceptance objects and
    runs every step from the verification on, which is all the verdict reads
    (about 13 CPU-s less than rendering and adjusting the rig again)."""
    d = tmp_path_factory.mktemp("verdict")
    base = yaml.safe_load(write_small_thesis_config(d, acceptance={"sphere": 1, "dumbbell": 1, "flat": 1})
                          .read_text())
    out = shutil.copytree(small_run[0].root, d / "run", symlinks=True)
    results = {}
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("COLUMNS", "160")
        for label, extra in (("accepted", GENEROUS), ("not accepted", {})):
            path = d / f"{label.replace(' ', '-')}.yaml"
            path.write_text(yaml.safe_dump({**base, **extra}))
            res = runner.invoke(app, ["run", "--config", str(path), "--out", str(out)])
            rd = RunDir(out)
            results[label] = {"config": path, "status": res.exit_code, "stdout": res.stdout, "stderr": res.stderr,
                              "output": res.output, "summary": rd.summary.load(), "acceptance": rd.acceptance.load(),
                              "verification": rd.verification.load(), "report": rd.report.load()}
    results["run_dir"] = out
    results["not accepted"]["copy"] = shutil.copytree(out, d / "not-accepted", symlinks=True)
    return results


@pytest.fixture(params=["accepted", "not accepted"])
def run(request, runs):
    return request.param, runs[request.param]


@pytest.mark.flow
def test_summary_verdict_is_acceptance_json_and_the_ballbar_rule(run):
    label, r = run
    verdict, acc, ver = r["summary"]["verdict"], r["acceptance"], r["verification"]
    assert acc["accepted"] is (label == "accepted") and verdict["accepted"] is acc["accepted"]
    assert verdict["word"] == label.upper() and verdict["ran"] == ["ball-bar", "acceptance"]
    assert r["summary"]["acceptance"]["accepted"] is acc["accepted"]
    ballbar = [c for c in verdict["components"] if c["test"] == "ball-bar"]
    accepted = [c for c in verdict["components"] if c["test"] == "acceptance"]
    # every acceptance parameter, as acceptance.json judges it
    assert [(c["name"], c["scanner"], c["value_mm"], c["U_mm"], c["limit_mm"], c["verdict"]) for c in accepted] == [
        (p["name"], p["scanner"], p["measured_mm"], p["U_mm"], p["mpe_mm"], p["verdict"]) for p in acc["parameters"]]
    assert {p["name"] for p in acc["parameters"]} == {"P_F", "P_S", "SD", "E", "F"}
    # every ball-bar length with its own budget's U, judged by ISO 14253-1 against the MPE
    mpe = ver["calibrated"]["mpe_mm"]
    assert mpe == (2.0 if label == "accepted" else 0.1)
    lengths = ver["uncertainty"]["lengths"]
    assert [(c["position"], c["value_mm"], c["U_mm"], c["limit_mm"]) for c in ballbar] == [
        (e["measurement"], e["error_mm"], e["U_mm"], mpe) for e in lengths]
    assert [c["verdict"] for c in ballbar] == [_iso14253(e["error_mm"], e["U_mm"], mpe) for e in lengths]
    assert [c["verdict"] for c in ballbar] == [e["iso14253"] for e in lengths]
    # one U per length in the summary: the budget's; the GUM U belongs to the mean length
    summary_lengths = r["summary"]["verification"]["lengths"]
    assert [e["U_mm"] for e in summary_lengths] == [e["U_mm"] for e in lengths]
    assert r["summary"]["verification"]["mean_length"]["U_mm"] == ver["calibrated"]["uncertainty"]["expanded_mm"]
    assert "expanded_uncertainty_mm" not in r["summary"]["verification"]
    assert verdict["accepted"] is all(c["verdict"] == "conformance" for c in verdict["components"]
                                      if c["limit_mm"] is not None)
    if label == "not accepted":  # the demo's limits: the scanners' form (P_F, F) fails 0.5 mm outright
        failing = {(c["name"], c["scanner"]) for c in accepted if c["verdict"] == "non-conformance"}
        assert {("P_F", "scanner1"), ("P_F", "scanner2"), ("F", "scanner1"), ("F", "scanner2")} <= failing


@pytest.mark.flow
def test_cli_line_and_exit_status_follow_the_verdict(run):
    label, r = run
    verdict = r["summary"]["verdict"]
    table = re.sub(r"[\s│]+", " ", r["stdout"])
    assert "PASS" not in r["output"] and "FAIL" not in r["output"]
    if label == "accepted":
        assert r["status"] == 0, r["output"]
        assert " verdict (ISO 14253-1) ACCEPTED " in table and "exit status 3" not in r["stderr"]
    else:
        assert r["status"] == 3, r["output"]
        assert verdict["failing"].startswith("ball-bar: E 3/3; acceptance: ") and "P_F 2/2" in verdict["failing"]
        assert f" verdict (ISO 14253-1) NOT ACCEPTED: {verdict['failing']} " in table
        assert r["stderr"].strip().splitlines()[-1] == f"NOT ACCEPTED: {verdict['failing']} (exit status 3)"


@pytest.mark.flow
def test_report_badge_follows_the_verdict(run):
    label, r = run
    head = r["report"].split("<nav>")[0]
    limited = [c for c in r["summary"]["verdict"]["components"] if c["limit_mm"] is not None]
    if label == "accepted":
        assert '<span class="badge pass">ACCEPTED</span></h1>' in head and "NOT ACCEPTED" not in head
        assert f"conformance proven under ISO 14253-1 for all {len(limited)} limited components" in head
    else:
        from fringecal.report.sections.certificate import NAMED

        assert '<span class="badge fail">NOT ACCEPTED</span></h1>' in head and "badge pass" not in head
        failing = [c for c in limited if c["verdict"] != "conformance"]
        if len(failing) > NAMED:  # counted in the sentence; the verdict table on page one shows each
            assert f"conformance not proven for {len(failing)} of {len(limited)} limited components" in head
        for c in limited if len(failing) <= NAMED else []:
            where = f"ball-bar E {c['position']}" if c["test"] == "ball-bar" else f"{c['name']} ({c['scanner']})"
            assert (f"{where}: {c['verdict']} (" in head) is (c["verdict"] != "conformance"), where
    # the acceptance section says what acceptance.json says
    badge = "ACCEPTED" if r["acceptance"]["accepted"] else "NOT ACCEPTED"
    assert f'<span class="badge {"pass" if badge == "ACCEPTED" else "fail"}">{badge}</span> under ISO 14253-1' in \
        r["report"]


@pytest.mark.flow
def test_verify_acceptance_and_report_rewrite_agree(runs):
    """The commands that judge the run directory again say the same as the run did."""
    rd = RunDir(runs["not accepted"]["copy"])
    res = runner.invoke(app, ["verify", "acceptance", "--run", str(rd.root)])
    assert res.exit_code == 3 and res.stdout.strip().splitlines()[-1].startswith("NOT ACCEPTED")
    res = runner.invoke(app, ["verify", "acceptance", "--run", str(rd.root), "--config",
                              str(runs["accepted"]["config"]), "--json"])
    assert res.exit_code == 0 and json.loads(res.stdout)["accepted"] is True
    # acceptance.json now accepts, while verification.json still holds the demo's MPE: the
    # rewritten page's badge says NOT ACCEPTED for the ball-bar's lengths alone
    assert runner.invoke(app, ["report", "--run", str(rd.root)]).exit_code == 0
    head = rd.report.load().split("<nav>")[0]
    assert "NOT ACCEPTED</span></h1>" in head and "(ball-bar: E 3/3)" in head and "acceptance:" not in head


@pytest.mark.flow
def test_flow_run_state_follows_the_verdict(runs):
    """A served or scheduled run: Failed with the verdict when not accepted, after
    writing every output; Completed when accepted."""
    from fringecal.flows.run_flow import NotAccepted, run_flow

    out = runs["run_dir"]
    rd = RunDir(out)
    state = run_flow(str(runs["not accepted"]["config"]), str(out), return_state=True)
    failing = runs["not accepted"]["summary"]["verdict"]["failing"]
    assert state.is_failed() and state.message.startswith(f"NOT ACCEPTED: {failing} (outputs and summary.json")
    data = state.result(raise_on_failure=False)
    assert isinstance(data, NotAccepted) and data.summary["verdict"] == rd.summary.load()["verdict"]
    assert data.summary["tasks"]["ran"] == []  # the same run: every step from the cache
    state = run_flow(str(runs["accepted"]["config"]), str(out), return_state=True)
    assert state.is_completed() and state.result()["verdict"]["word"] == "ACCEPTED"
    assert rd.summary.load()["verdict"]["accepted"] is True
