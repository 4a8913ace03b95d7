"""report.html: atomic, self-contained, shows the run's numbers, degrades and escapes.

The run directory is built here: a real bundle adjustment of simulated thesis control
points (fringecal.calibration.synthetic + calibrate_run) gives the calibration files,
tables and histograms; the files of the other steps (manifest, summary, verification,
truth, acquisition and labelling tables) are written with plausible values.
"""

import json
import re
import shutil
from html.parser import HTMLParser

import numpy as np
import pandas as pd
import pytest
from typer.testing import CliRunner

from fringecal.calibration.run import calibrate_run
from fringecal.calibration.synthetic import dlt_start, simulate_control_points, thesis_truth, write_run_inputs
from fringecal.report import write_report
from fringecal.rundir import RunDir, package_versions, write_json_atomic
from fringecal.verification import evaluate_ballbar
from schemas import AcquiredPosesTable, AcquisitionTable, LabelOutcomesTable, write_table

POSE_COLUMNS = ["tx_mm", "ty_mm", "tz_mm", "omega_rad", "phi_rad", "kappa_rad"]
REFERENCE_MM = 1015.650
CAL_ERRORS_MM = [0.021, -0.034, 0.047, -0.012, 0.008, -0.041, 0.029, -0.003, 0.016]
TRUE_ERRORS_MM = [0.018, -0.029, 0.044, -0.010, 0.011, -0.037, 0.025, -0.006, 0.013]


def _ballbar(errors, mpe=0.1):
    names = [str(i + 1) for i in range(len(errors))]
    return evaluate_ballbar(REFERENCE_MM + np.array(errors), REFERENCE_MM, names, mpe, 2872.3, 0.0004, 2.0, 1.96)


@pytest.fixture(scope="module")
def base_run(tmp_path_factory):
    run = tmp_path_factory.mktemp("report-run")
    rig, art, poses = thesis_truth()
    sim = simulate_control_points(rig, art, poses, spacing_px=40, rng=31)
    start_rig, start_poses = dlt_start(sim, rng=31)
    write_run_inputs(run, sim, start_rig, start_poses, {"start": "given", "volume_diagonal_mm": 2872.3})
    calibrate_run(run)
    bs = json.loads((run / "bundle_summary.json").read_text())

    config = {"name": "thesis", "acquisition": {"camera_width_px": 512, "hexapod": {"enabled": True}},
              "verification": {"scheme": "thesis9", "mpe_mm": 0.1}}
    write_json_atomic(run / "manifest.json", {
        "config": config, "config_digest": RunDir.config_digest(config), "versions": package_versions(),
        "inputs": {"artefact": {"path": "configs/thesis/artefact_cmm2.csv", "sha256": "ab" * 32}},
        "created_utc": "2026-01-02T03:04:05Z", "command": "fringecal run --out runs/report-test"})
    cal, true = _ballbar(CAL_ERRORS_MM), _ballbar(TRUE_ERRORS_MM)
    write_json_atomic(run / "verification.json", {"calibrated": cal.to_dict(), "true": true.to_dict(),
                                                  "failures": [], "scheme": "thesis9"})
    write_json_atomic(run / "truth.json", {
        "max_position_error_mm": 0.61, "max_angle_error_rad": 2.1e-4, "rms_f_mm_true_params": 0.168,
        "rms_eps1_mm_true_params": 0.0449, "rms_eps2_mm_true_params": 0.1608,
        "sensors": [{"sensor": s.name, "position_error_mm": 0.1 * (i + 1), "angle_error_rad": 5e-5 * (i + 1),
                     "c_error_mm": 0.003 * (i - 1), "max_sigma_ratio_position_angles_c": 1.1 + 0.2 * i}
                    for i, s in enumerate(rig.sensors)]})
    write_json_atomic(run / "summary.json", {
        "n_measurements": bs["n_measurements"], "n_control_points": bs["n_control_points"],
        "rms_F_mm_before": bs["before"]["rms_f_mm"], "rms_F_mm_after": bs["after"]["rms_f_mm"],
        "rms_eps1_mm_after": bs["after"]["rms_eps1_mm"], "rms_eps2_mm_after": bs["after"]["rms_eps2_mm"],
        "one_part_in": bs["one_part_in_1p96_sigma"], "bundle_seconds": 0.4, "total_seconds": 181.0,
        "verification": {"reference_length_mm": REFERENCE_MM, "mean_length_mm": cal.mean_length_mm,
                         "max_abs_error_mm": cal.max_abs_error_mm, "volume_diagonal_mm": 2872.3,
                         "pass": cal.passed},
        "truth": {"max_position_error_mm": 0.61, "max_angle_error_rad": 2.1e-4, "rms_eps1_mm_true_params": 0.0449,
                  "rms_eps2_mm_true_params": 0.1608,
                  "verification_max_abs_error_true_params_mm": true.max_abs_error_mm}})
    reached = poses.rename(columns=lambda c: c).copy()
    planned = reached[POSE_COLUMNS].to_numpy() + np.array([0.004, -0.003, 0.002, 1e-5, -2e-5, 1e-5])
    acq_poses = reached[["measurement", *POSE_COLUMNS]].copy()
    for j, c in enumerate(POSE_COLUMNS):
        acq_poses[f"planned_{c}"] = planned[:, j]
    acq_poses["translation_error_mm"] = np.linalg.norm(planned[:, :3] - reached[POSE_COLUMNS[:3]].to_numpy(), axis=1)
    acq_poses["rotation_error_rad"] = 2.4e-5
    acq_poses["hexapod"] = True
    write_table(acq_poses, run / "tables/acquisition_poses.csv", AcquiredPosesTable)
    acq = pd.DataFrame([{"measurement": f"{m}-{s}", "pose": m, "scanner": s, "store": f"measurements/{m}-{s}.zarr",
                         "valid_fraction": 0.3, "sphere_pixels": 20000}
                        for m in poses.measurement for s in ("scanner1", "scanner2")])
    write_table(acq, run / "tables/acquisition.csv", AcquisitionTable)
    labels = acq[["measurement", "scanner"]].assign(status="labelled", reason="", method="planned", n_candidates=4,
                                                     n_labelled=4, rms_mm=0.05, message="")
    labels.loc[3, ["status", "reason", "n_labelled", "message"]] = ["refused", "too_few_spheres", 0,
                                                                    "two candidates only"]
    write_table(labels, run / "tables/label_outcomes.csv", LabelOutcomesTable)
    return run


@pytest.fixture
def run(base_run, tmp_path):
    dest = tmp_path / "run"
    shutil.copytree(base_run, dest)
    return dest


class _Nesting(HTMLParser):
    """Checks that every element is closed in order (void elements excepted)."""

    VOID = {"meta", "img", "br", "hr", "link", "input", "wbr"}

    def __init__(self):
        super().__init__()
        self.stack, self.errors = [], []

    def handle_starttag(self, tag, attrs):
        if tag not in self.VOID:
            self.stack.append(tag)

    def handle_endtag(self, tag):
        if not self.stack or self.stack[-1] != tag:
            self.errors.append((tag, list(self.stack[-3:]), self.getpos()))
        else:
            self.stack.pop()


def _section(page: str, anchor: str) -> str:
    m = re.search(rf'<section id="{anchor}">(.*?)</section>', page, re.S)
    assert m, anchor
    return m.group(1)


TIMINGS = {"acquire": 120.5, "extract": 31.2, "bundle-adjustment": 0.4, "verification": 25.0, "total": 181.0}


def test_report_is_written_atomically_and_self_contained(run):
    path = write_report(run, TIMINGS)
    assert path == run / "report.html"
    assert [p.name for p in run.iterdir() if p.name.startswith(".report")] == []
    page = path.read_text(encoding="utf-8")
    assert page.startswith("<!DOCTYPE html>") and page.rstrip().endswith("</html>")
    links = re.findall(r'\b(?:src|href)\s*=\s*["\']?([^"\'\s>]*)', page, re.I)
    assert len(links) >= 5  # the navigation and the three images at least
    assert all(v.startswith("data:image/png;base64,") or v.startswith("#") for v in links), links
    for anchor in {v[1:] for v in links if v.startswith("#")}:
        assert f'id="{anchor}"' in page
    assert not re.search(r"<script|<link|<iframe|@import|url\(", page, re.I)
    assert page.count("data:image/png;base64,") == 3  # two histograms and the ball-bar plot
    nesting = _Nesting()
    nesting.feed(page)
    assert nesting.errors == [] and nesting.stack == []


def test_a_failed_render_leaves_the_previous_report(run, monkeypatch):
    import fringecal.report as report

    write_report(run, TIMINGS)
    before = (run / "report.html").read_bytes()

    def broken(*args):
        raise RuntimeError("plotting failed")

    monkeypatch.setattr(report, "_ballbar_png", broken)
    with pytest.raises(RuntimeError):
        write_report(run, TIMINGS)
    assert (run / "report.html").read_bytes() == before
    assert not any(p.name.endswith(".tmp") for p in run.iterdir())


def test_report_shows_the_numbers_of_the_run(run):
    page = write_report(run, TIMINGS).read_text(encoding="utf-8")
    bs = json.loads((run / "bundle_summary.json").read_text())
    results = _section(page, "results")
    for key in ("rms_f_mm", "rms_eps1_mm", "rms_eps2_mm"):
        assert f"{bs['after'][key] * 1000:.1f} µm" in results
        assert f"{bs['before'][key]:.3f} mm" in results
    assert f"1 part in {bs['one_part_in_1p96_sigma']:,.0f}" in results
    assert "2872.3 mm volume diagonal" in results
    assert "44.9 µm" in results and "160.8 µm" in results  # residual floor of truth.json

    params = _section(page, "parameters")
    assert params.count("(fixed)") == 6  # the reference camera's external parameters
    assert params.count("±") == 4 * 14 - 6
    assert len(re.findall(r"<tr><td", params.split("Strongest correlations")[0])) == 2 * 14
    c2 = bs["parameters"][[p["name"] for p in bs["parameters"]].index("C2.c")]
    assert f"{c2['value']:.2f}" in params

    ver = _section(page, "verification")
    assert "47.0 µm" in ver  # max |error| of CAL_ERRORS_MM
    assert "44.0 µm" in ver  # ... and with the true parameters
    assert f"calibrated / true = {0.047 / 0.044:.2f}" in ver
    assert ver.count('class="pass">PASS') == 18 and "FAIL" not in ver
    assert "k = 1.96" in ver and "1015.6500 mm" in ver
    assert '<span class="badge pass">PASS</span>' in page.split("<nav>")[0]

    timing = _section(page, "timing")
    assert "acquire" in timing and "120.5 s (2 min 0 s)" in timing and "31.2 s" in timing and "0.40 s" in timing
    assert "181.0 s (3 min 1 s)" in timing and "Timings from this run" in timing

    rig = _section(page, "rig")
    assert "scanner1 (reference)" in rig and "1400 × 1050 px" in rig
    assert "15 (diameters" in rig and "used to move the artefact" in rig and "512 px wide" in rig
    assert "24 from 12 artefact poses" in rig and "11 of 12 measurements labelled" not in rig
    assert "23 of 24 measurements labelled" in rig and "too_few_spheres" in rig

    sphere_rows = re.findall(r"<tr><td class=\"l\">([^<]*)</td><td class=\"l\">([^<]*)</td><td class=\"l\">([^<]*)"
                             r"</td><td>\d+</td><td>[^<]*</td><td>([\d.]+) µm", _section(page, "residuals"))
    shown = [float(r[3]) for r in sphere_rows[:10]]
    per_sphere = pd.read_csv(run / "tables/residuals_per_sphere.csv")
    assert shown == sorted(shown, reverse=True)
    assert shown[0] == pytest.approx(per_sphere["rms_eps2_mm"].max() * 1000, abs=0.06)

    prov = _section(page, "provenance")
    digest = json.loads((run / "manifest.json").read_text())["config_digest"]
    assert digest in prov and "numpy" in prov and "ab" * 32 in prov and "camera_width_px: 512" in prov


def test_failing_verification_is_reported_as_fail(run):
    ver = json.loads((run / "verification.json").read_text())
    ver["calibrated"] = _ballbar(CAL_ERRORS_MM[:8] + [0.130]).to_dict()
    write_json_atomic(run / "verification.json", ver)
    page = write_report(run, TIMINGS).read_text(encoding="utf-8")
    assert '<span class="badge fail">FAIL</span>' in page.split("<nav>")[0]
    section = _section(page, "verification")
    assert section.count('class="fail">FAIL') == 1 and "130.0 µm" in section


def test_missing_optional_files_give_notes(run):
    for name in ("truth.json", "verification.json", "tables/acquisition_poses.csv", "figures/eps2_hist.png"):
        (run / name).unlink()
    summary = json.loads((run / "summary.json").read_text())
    del summary["verification"], summary["truth"]
    write_json_atomic(run / "summary.json", summary)
    page = write_report(run).read_text(encoding="utf-8")
    assert "Not available: truth.json is absent" in _section(page, "truth")
    assert "Not available: verification.json is not in the run directory" in _section(page, "verification")
    assert "figures/eps2_hist.png is not in the run directory" in _section(page, "residuals")
    assert "tables/acquisition_poses.csv is not in the run directory" in _section(page, "rig")
    assert '<span class="badge none">NOT VERIFIED</span>' in page
    assert "Timings from summary.json" in _section(page, "timing")  # no timings passed in
    assert page.count("data:image/png;base64,") == 1


def test_malformed_file_is_named_and_the_rest_is_shown(run):
    (run / "bundle_summary.json").write_text('{"before": ')
    page = write_report(run, TIMINGS).read_text(encoding="utf-8")
    assert "Could not be shown" in _section(page, "results") and "bundle_summary.json" in _section(page, "results")
    assert _section(page, "parameters").count("(fixed)") == 6


def test_hostile_strings_are_escaped(run):
    cal = json.loads((run / "calibration.json").read_text())
    cal["scanners"][1]["sensors"][0]["name"] = '<script>alert("x")</script>'
    (run / "calibration.json").write_text(json.dumps(cal))
    man = json.loads((run / "manifest.json").read_text())
    man["config"]["name"] = "<img src=x onerror=alert(1)>"
    man["command"] = "fringecal run --out '</code><b>'"
    write_json_atomic(run / "manifest.json", man)
    bs = json.loads((run / "bundle_summary.json").read_text())
    bs["diagnostics"] = [{"kind": "single_pose", "severity": "warning", "subject": "s", "parameters": [],
                          "message": "scanner <b>scanner2</b> & friends"}]
    write_json_atomic(run / "bundle_summary.json", bs)
    page = write_report(run, TIMINGS).read_text(encoding="utf-8")
    assert "<script" not in page and "<img src=x" not in page and "<b>scanner2" not in page
    assert "&lt;script&gt;alert(&quot;x&quot;)&lt;/script&gt;" in page
    assert "&lt;img src=x onerror=alert(1)&gt;" in page
    assert "scanner &lt;b&gt;scanner2&lt;/b&gt; &amp; friends" in page
    assert "&lt;/code&gt;&lt;b&gt;" in page


def test_not_a_run_directory(tmp_path):
    with pytest.raises(FileNotFoundError, match="not a run directory"):
        write_report(tmp_path)
    assert not (tmp_path / "report.html").exists()


def test_cli_rewrites_the_report(run, tmp_path):
    from flows.cli import app

    runner = CliRunner()
    res = runner.invoke(app, ["report", "--run", str(run)])
    assert res.exit_code == 0, res.output
    page = (run / "report.html").read_text(encoding="utf-8")
    assert "Timings from summary.json" in page and "181.0 s" in page
    res = runner.invoke(app, ["report", "--run", str(tmp_path / "nowhere")])
    assert res.exit_code == 2 and "no such run directory" in res.output
    empty = tmp_path / "empty"
    empty.mkdir()
    res = runner.invoke(app, ["report", "--run", str(empty)])
    assert res.exit_code == 2 and "not a run directory" in res.output.replace("\n", "")
