"""Verdicts a script can trust: every command that verifies prints its result, then exits
with status 3 when the verification failed (FAIL, NOT ACCEPTED, drift beyond its
tolerance), 0 when it passed (or, for a run, nothing was verified), 2 on bad input; a
NaN never passes."""

from __future__ import annotations

import json

import pytest
from typer.testing import CliRunner

from fringecal.flows.cli import app
from fringecal.rundir import RunDir
from fringecal.verification.lengths import evaluate_ballbar

runner = CliRunner()
NAN = float("nan")


def test_nan_never_passes():
    assert evaluate_ballbar([1015.6, 1015.7], 1015.65, mpe_mm=0.2).passed
    for lengths, reference, mpe in (([1015.6, NAN], 1015.65, 0.2), ([1015.6, 1015.7], NAN, 0.2),
                                    ([1015.6, 1015.7], 1015.65, NAN), ([1015.6, NAN], 1015.65, None)):
        r = evaluate_ballbar(lengths, reference, mpe_mm=mpe)
        assert not r.passed and not r.to_dict()["pass"], (lengths, reference, mpe)
    from fringecal.acceptance.evaluate import verdict  # the ISO 14253-1 rule of the run and the acceptance test

    assert verdict(0.01, 0.02, 0.1) == "conformance"
    assert verdict(NAN, 0.02, 0.1) == verdict(0.01, NAN, 0.1) == verdict(0.01, 0.02, NAN) == "uncertainty zone"


@pytest.mark.parametrize("mpe, status, verdict", [("0.1", 3, "FAIL"), ("0.2", 0, "PASS")])
def test_verify_ballbar(thesis_dir, mpe, status, verdict):
    """Thesis table 6-9: max |error| 149 um, FAIL against 100 um, PASS against 200 um."""
    args = ["verify", "ballbar", "--centres", str(thesis_dir / "ballbar_verification_table6-9.csv"),
            "--reference-length-mm", "1015.650", "--mpe-mm", mpe]
    res = runner.invoke(app, args)
    assert res.exit_code == status, res.output
    out = res.stdout.strip().splitlines()
    assert out[-1] == verdict and any(line.startswith("mean length 1015.61") for line in out)  # printed first
    res = runner.invoke(app, [*args, "--json"])
    assert res.exit_code == status and json.loads(res.stdout)["pass"] is (status == 0)


def test_verify_ballbar_without_an_mpe_has_no_verdict(thesis_dir):
    res = runner.invoke(app, ["verify", "ballbar", "--centres", str(thesis_dir / "ballbar_verification_table6-9.csv"),
                              "--reference-length-mm", "1015.650"])
    assert res.exit_code == 0, res.output
    assert "PASS" not in res.stdout and "FAIL" not in res.stdout and " yes " not in res.stdout


def _verification(passed: bool) -> dict:
    """verification.json of three lengths, each with its budget's U: all three conform
    (|error| + U <= 100 um), or bb09 fails (150 um, U 30 um: non-conformance)."""
    errors = [0.04, -0.02, 0.03 if passed else 0.15]
    names = ["bb01", "bb04", "bb09"]
    lengths = [{"measurement": n, "error_mm": e, "U_mm": 0.03, "u_mm": 0.015, "covered": abs(e) <= 0.03,
                "iso14253": "conformance" if abs(e) + 0.03 <= 0.1 else "non-conformance"}
               for n, e in zip(names, errors)]
    return {"calibrated": {"reference_length_mm": 1015.65, "mean_length_mm": 1015.65 + sum(errors) / 3,
                           "max_abs_error_mm": max(map(abs, errors)), "volume_diagonal_mm": 2872.3,
                           "one_part_in": 2872.3 / max(map(abs, errors)), "mpe_mm": 0.1, "pass": passed,
                           "uncertainty": {"expanded_mm": 0.02, "coverage_factor": 1.96},
                           "positions": [{"measurement": n, "error_mm": e} for n, e in zip(names, errors)]},
            "uncertainty": {"coverage_factor": 2.0, "lengths": lengths, "not_covered": [], "budget": {},
                            "monte_carlo": None},
            "failures": []}


def _acceptance(accepted: bool) -> dict:
    verdict = "conformance" if accepted else "non-conformance"
    return {"coverage_factor": 2.0, "accepted": accepted, "within_mpe": accepted, "failures": [],
            "parameters": [{"name": "E", "scanner": "cell", "positions": 9, "measured_mm": 0.04 if accepted else 0.15,
                            "mpe_mm": 0.1, "U_mm": 0.05, "verdict": verdict, "worst_position": "bb09"}]}


def _summary(passed: bool) -> dict:
    """A run's summary as the flow returns it (what `fringecal run` prints and judges)."""
    from fringecal.acceptance.verdict import run_verdict
    from fringecal.run.summary import ballbar_summary

    ver = _verification(passed)
    return {"name": "small", "source": "simulated", "dataset": None, "simulation_profile": "ideal",
            "n_measurements": 8, "n_control_points": 3000, "rms_F_mm_before": 30.0, "rms_F_mm_after": 0.12,
            "rms_eps1_mm_after": 0.04, "rms_eps2_mm_after": 0.11, "one_part_in": 12000.0,
            "verification": ballbar_summary(ver), "verdict": run_verdict(ver, None),
            "truth": None, "bundle_seconds": 0.3, "total_seconds": 40.0, "compile_seconds": {},
            "tasks": {"ran": ["bundle"], "cached": []}}


@pytest.mark.parametrize("passed, status", [(True, 0), (False, 3)])
def test_run_exits_3_after_the_summary_when_the_run_is_not_accepted(small_config, tmp_path, monkeypatch, passed,
                                                                   status):
    monkeypatch.setattr("fringecal.flows.cli_run._execute", lambda *args, **kwargs: _summary(passed))
    args = ["run", "--config", str(small_config), "--out", str(tmp_path / "run")]
    res = runner.invoke(app, args)
    assert res.exit_code == status, res.output
    out = " ".join(res.stdout.split())
    assert "tasks run / from cache" in out  # the summary first
    assert ("verdict (ISO 14253-1) │ ACCEPTED │" if passed else
            "verdict (ISO 14253-1) │ NOT ACCEPTED: ball-bar: E 1/3 │") in out
    assert "PASS" not in out and "FAIL" not in out
    if not passed:
        assert res.stderr.strip() == "NOT ACCEPTED: ball-bar: E 1/3 (exit status 3)"
    res = runner.invoke(app, [*args, "--json"])
    assert res.exit_code == status and json.loads(res.stdout)["verdict"]["accepted"] is passed


def test_a_run_that_is_not_verified_exits_0_and_says_so(small_config, tmp_path, monkeypatch):
    """No ball-bar and no acceptance measurements: nothing was judged (status 0, NOT VERIFIED)."""
    from fringecal.acceptance.verdict import run_verdict

    summary = {**_summary(True), "verification": None, "verdict": run_verdict(None, None)}
    monkeypatch.setattr("fringecal.flows.cli_run._execute", lambda *args, **kwargs: summary)
    res = runner.invoke(app, ["run", "--config", str(small_config), "--out", str(tmp_path / "run")])
    assert res.exit_code == 0, res.output
    out = " ".join(res.stdout.split())
    assert "│ verdict │ NOT VERIFIED (no ball-bar and no" in out and "ACCEPTED" not in out


def test_reproduce_exits_3_when_the_numbers_agree_but_the_run_is_not_accepted(small_config, tmp_path, monkeypatch):
    from fringecal.run.config import load_run_config

    rd = RunDir(tmp_path / "run").create()
    rd.manifest.save({"config": load_run_config(small_config).model_dump(mode="json")})
    rd.summary.save(_summary(False))
    monkeypatch.setattr("fringecal.flows.cli_run._execute", lambda *args, **kwargs: _summary(False))
    res = runner.invoke(app, ["reproduce", str(rd.root)])
    assert res.exit_code == 3, res.output
    assert "reproduced: the summary numbers are identical" in res.stdout
    assert res.stderr.strip() == "NOT ACCEPTED: ball-bar: E 1/3 (exit status 3)"
    rd.summary.save(_summary(True))  # the same numbers, another verdict: not reproduced
    res = runner.invoke(app, ["reproduce", str(rd.root)])
    assert res.exit_code == 1 and "verdict: 'ACCEPTED' -> 'NOT ACCEPTED'" in " ".join(res.output.split())


@pytest.mark.parametrize("ok, status", [(True, 0), (False, 3)])
def test_step_verify_and_step_acceptance(tmp_path, monkeypatch, ok, status):
    """The steps' own results decide (the steps themselves are replaced: they need a
    calibrated run, which tests/test_run_flow.py makes)."""
    rd = RunDir(tmp_path / "run").create()
    rd.verification.save(_verification(ok))
    rd.acceptance.save(_acceptance(ok))
    monkeypatch.setattr("fringecal.flows.cli_step._run", lambda *args, **kwargs: [])
    for step, line in (("verify", "ball-bar NOT ACCEPTED: ball-bar: E 1/3 (exit status 3)"),
                       ("acceptance", "acceptance test NOT ACCEPTED: acceptance: E 1/1 (exit status 3)")):
        res = runner.invoke(app, ["step", step, "--run", str(rd.root)])
        assert res.exit_code == status, res.output
        assert res.stdout.startswith(f"{step}: 0 ran") and res.stderr.strip() == ("" if ok else line)


@pytest.mark.parametrize("ok, status", [(True, 0), (False, 3)])
def test_verify_acceptance(tmp_path, monkeypatch, ok, status):
    rd = RunDir(tmp_path / "run").create()
    rd.calibration.path.write_text("<calibration/>")  # the command only checks that the run is calibrated
    rd.acceptance.save(_acceptance(ok))
    monkeypatch.setattr("fringecal.steps.run_step", lambda *args, **kwargs: None)
    res = runner.invoke(app, ["verify", "acceptance", "--run", str(rd.root)])
    assert res.exit_code == status, res.output
    assert res.stdout.strip().splitlines()[-1].startswith("ACCEPTED" if ok else "NOT ACCEPTED")


@pytest.mark.parametrize("tolerance, status", [("50", 0), ("5", 3)])
def test_hexapod_drift(thesis_dir, tolerance, status):
    """Thesis table 4-1: 12.07 um expected in a 15 s scan."""
    args = ["hexapod", "drift", "--centres", str(thesis_dir / "drift_table4-1.csv"), "--tolerance-um", tolerance]
    res = runner.invoke(app, args)
    assert res.exit_code == status, res.output
    text = " ".join(res.stdout.split())
    assert ("EXCEEDS the 5 um tolerance" if status else "within the 50 um tolerance") in text
    res = runner.invoke(app, [*args, "--json"])
    assert res.exit_code == status and json.loads(res.stdout)["ok"] is (status == 0)
