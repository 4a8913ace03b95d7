"""report.html: atomic, self-contained, shows the run's numbers, degrades and escapes.

The run directory is built here: a real bundle adjustment (the ``bundle`` step) of
simulated thesis control points (fringecal.simulate.control_points) gives the
calibration files, tables and histograms; the files of the other steps (manifest,
summary, verification, evaluation, acquisition, hexapod and labelling tables) are
written through their RunDir accessors with plausible values. Every file is reached
through RunDir: the tests spell no run-directory file name either.
"""

import json
import re
import shutil
import tomllib
from html.parser import HTMLParser
from importlib.resources import files
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import xarray as xr
from typer.testing import CliRunner

from fringecal.artefact import Artefact
from fringecal.report import NO_TRUTH, render_report, write_report
from fringecal.run.config import RunConfig
from fringecal.rundir import RunDir, package_versions
from fringecal.simulate.control_points import dlt_start, simulate_control_points, thesis_truth, write_run_inputs
from fringecal.steps import get_step, run_step
from fringecal.store import write_store
from fringecal.verification.lengths import evaluate_ballbar
from fringecal.verification.uncertainty import iso14253_verdict

POSE_COLUMNS = ["tx_mm", "ty_mm", "tz_mm", "omega_rad", "phi_rad", "kappa_rad"]
REFERENCE_MM = 1015.650
CAL_ERRORS_MM = [0.021, -0.034, 0.047, -0.012, 0.008, -0.041, 0.029, -0.003, 0.016]
TRUE_ERRORS_MM = [0.018, -0.029, 0.044, -0.010, 0.011, -0.037, 0.025, -0.006, 0.013]
POSITIONS = [f"bb{i + 1:02d}" for i in range(len(CAL_ERRORS_MM))]
SCANNERS = ("scanner1", "scanner2")
DIAGONAL_MM = 2872.3
LENGTH_U_MM = 0.050  # every length's U: |error| + U <= 100 um for CAL_ERRORS_MM (conformance)
CREATED = "2026-01-02T03:04:05Z"
COMMAND = "fringecal run --out runs/report-test"
SUMMARY_TIMINGS = {"simulate-render": 120.5, "spheres-first": 31.2, "bundle": 0.4, "verify": 25.0}
TIMINGS = {"simulate-render": 118.25, "spheres-first": 30.5, "bundle": 0.35, "verify": 24.0, "total": 175.0}
SECTIONS = [("rig", "Rig and artefact"), ("timing", "Timing"), ("results", "Calibration results"),
            ("scanners", "Scanners"), ("residuals", "Residuals"), ("crossval", "Cross-validation"),
            ("verification", "Verification (ball-bar)"), ("acceptance", "Acceptance test (VDI/VDE 2634 parts 2 and 3)"),
            ("truth", "Simulation truth"), ("provenance", "Provenance")]


def _ballbar(errors, mpe=0.1):
    return evaluate_ballbar(REFERENCE_MM + np.array(errors), REFERENCE_MM, POSITIONS[:len(errors)], mpe, DIAGONAL_MM,
                            0.0004, 2.0, 1.96)


def _budget(errors, U=LENGTH_U_MM, mpe=0.1) -> dict:
    """Each length's own U (the same for all) and its ISO 14253-1 verdict, as verification.json holds them."""
    lengths = [{"measurement": p, "error_mm": e, "u_mm": U / 2, "U_mm": U, "budget_mm": {}, "covered": abs(e) <= U,
                "iso14253": iso14253_verdict(e, U, mpe)} for p, e in zip(POSITIONS, errors)]
    return {"coverage_factor": 2.0, "lengths": lengths, "budget": {}, "monte_carlo": None,
            "not_covered": [e["measurement"] for e in lengths if not e["covered"]]}


def _config(**kw) -> dict:
    cfg = RunConfig(name="thesis", bundle={"start": "given", "volume_diagonal_mm": DIAGONAL_MM}, **kw)
    return cfg.model_dump(mode="json")


def _manifest(config: dict, source: str, inputs: dict) -> dict:
    return {"config": config, "config_digest": RunDir.config_digest(config), "source": source,
            "code_digest": "cd" * 32, "versions": package_versions(), "inputs": inputs}


@pytest.fixture(scope="module")
def base_run(tmp_path_factory):
    rd = RunDir(tmp_path_factory.mktemp("report-run")).create()
    rig, art, poses = thesis_truth()
    sim = simulate_control_points(rig, art, poses, spacing_px=40, rng=31)
    start_rig, start_poses = dlt_start(sim, rng=31)
    write_run_inputs(rd, sim, start_rig, start_poses)
    run_step(get_step("bundle"), rd, RunConfig(bundle={"start": "given", "volume_diagonal_mm": DIAGONAL_MM}))
    bs = rd.bundle_summary.load()
    rd.rods.save(pd.DataFrame({"rod_id": ["r1", "r2", "r3"], "sphere_a": list(art.ids[:3]),
                               "sphere_b": list(art.ids[1:4]),
                               "length_mm": np.linalg.norm(art.centres[1:4] - art.centres[:3], axis=1)}))
    rd.ballbar.save(Artefact(("A", "B"), [[0.0, 0.0, 0.0], [REFERENCE_MM, 0.0, 0.0]], [30.002, 29.998],
                             name="ballbar"))

    config = _config(simulate={"acquisition": {"camera_width_px": 512}, "verification": {"scheme": "thesis9"}})
    rd.manifest.save(_manifest(config, "simulated", {"configs/thesis/artefact_cmm2.csv": "ab" * 32}))
    cal, true = _ballbar(CAL_ERRORS_MM), _ballbar(TRUE_ERRORS_MM)
    rd.verification.save({"calibrated": cal.to_dict(), "uncertainty": _budget(CAL_ERRORS_MM), "failures": [],
                          "recorded_by": {p: list(SCANNERS) for p in POSITIONS}})
    rd.evaluation.save({
        "max_position_error_mm": 0.61, "max_angle_error_rad": 2.1e-4, "rms_f_mm_true_params": 0.168,
        "rms_eps1_mm_true_params": 0.0449, "rms_eps2_mm_true_params": 0.1608,
        "sensors": [{"sensor": s.name, "position_error_mm": 0.1 * (i + 1), "angle_error_rad": 5e-5 * (i + 1),
                     "c_error_mm": 0.003 * (i - 1), "max_sigma_ratio_position_angles_c": 1.1 + 0.2 * i}
                    for i, s in enumerate(rig.sensors)],
        "verification_true_params": {**true.to_dict(), "failures": []}})
    # what an earlier execution recorded; the report takes only when/how/how long from it
    rd.summary.save({
        "name": "thesis", "source": "simulated", "n_measurements": bs["n_measurements"],
        "verification": {"pass": True}, "created_utc": CREATED, "command": COMMAND,
        "timings": SUMMARY_TIMINGS, "total_seconds": 181.0})
    planned = poses[POSE_COLUMNS].to_numpy() + np.array([0.004, -0.003, 0.002, 1e-5, -2e-5, 1e-5])
    moves = poses[["measurement", *POSE_COLUMNS]].copy()
    for j, c in enumerate(POSE_COLUMNS):
        moves[f"planned_{c}"] = planned[:, j]
    moves["translation_error_mm"] = np.linalg.norm(planned[:, :3] - poses[POSE_COLUMNS[:3]].to_numpy(), axis=1)
    moves["rotation_error_rad"] = 2.4e-5
    moves["hexapod"] = True
    rd.hexapod_moves.save(moves)
    rows = [{"measurement": f"{m}-{s}", "kind": "artefact", "pose": m, "scanner": s} for m in poses.measurement
            for s in SCANNERS]
    rows += [{"measurement": f"{p}-{s}", "kind": "ballbar", "pose": p, "scanner": s} for p in POSITIONS
             for s in SCANNERS]
    acq = pd.DataFrame(rows)
    acq["store"] = [rd.store(m).rel for m in acq.measurement]
    acq["source"] = "simulated"
    rd.acquisition.save(acq)
    labels = acq[acq.kind == "artefact"][["measurement", "scanner"]].assign(
        status="labelled", reason="", method="planned", n_candidates=4, n_labelled=4, rms_mm=0.05, message="")
    labels.loc[3, ["status", "reason", "n_labelled", "message"]] = ["refused", "too_few_spheres", 0,
                                                                    "two candidates only"]
    rd.label_outcomes.save(labels.reset_index(drop=True))
    return rd


@pytest.fixture
def rd(base_run, tmp_path):
    dest = tmp_path / "run"
    shutil.copytree(base_run.root, dest)
    return RunDir(dest)


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


def _well_formed(page: str) -> None:
    nesting = _Nesting()
    nesting.feed(page)
    assert nesting.errors == [] and nesting.stack == []


def _verification_rows(page: str) -> dict[str, list[str]]:
    """Position -> the text of its cells in the verification table (the first; the lengths' budget follows)."""
    table = _section(page, "verification")
    rows = re.findall(r"<tr>(<td.*?)</tr>", table, re.S)
    out = {}
    for r in rows:
        cells = [re.sub(r"<[^>]+>", "", c) for c in re.findall(r"<td[^>]*>(.*?)</td>", r, re.S)]
        if cells and cells[0] in POSITIONS and cells[0] not in out:
            out[cells[0]] = cells
    return out


def test_report_is_written_atomically_and_self_contained(rd):
    path = write_report(rd, TIMINGS)
    assert path == rd.report.path
    assert [p.name for p in rd.root.iterdir() if p.name.startswith(f".{rd.report.path.name}")] == []
    page = rd.report.load()
    assert page.startswith("<!DOCTYPE html>") and page.rstrip().endswith("</html>")
    links = re.findall(r'\b(?:src|href)\s*=\s*["\']?([^"\'\s>]*)', page, re.I)
    assert len(links) >= 5  # the navigation and the images at least
    assert all(v.startswith("data:image/png;base64,") or v.startswith("#") for v in links), links
    for anchor in {v[1:] for v in links if v.startswith("#")}:
        assert f'id="{anchor}"' in page
    assert not re.search(r"<script|<link|<iframe|@import|url\(", page, re.I)
    # two histograms, the ball-bar plot and per scanner its residual maps, observed regions and uncertainty maps
    assert page.count("data:image/png;base64,") == 3 + 3 * len(SCANNERS)
    _well_formed(page)


def test_a_path_and_a_rundir_give_the_same_page(rd):
    a = render_report(rd, TIMINGS, generated="2026-05-06 07:08:09")
    b = render_report(str(rd.root), TIMINGS, generated="2026-05-06 07:08:09")
    assert a == b and "2026-05-06 07:08:09" in a


def test_a_failed_render_leaves_the_previous_report(rd, monkeypatch):
    from fringecal.report import figures

    write_report(rd, TIMINGS)
    before = rd.report.path.read_bytes()

    def broken(*args):
        raise RuntimeError("plotting failed")

    monkeypatch.setattr(figures, "ballbar_png", broken)
    with pytest.raises(RuntimeError):
        write_report(rd, TIMINGS)
    assert rd.report.path.read_bytes() == before
    assert not any(p.name.endswith(".tmp") for p in rd.root.iterdir())


def test_report_shows_the_numbers_of_the_run(rd):
    execution = {"created_utc": "2026-03-04T05:06:07+00:00", "command": "fringecal run --out runs/now"}
    page = write_report(rd, TIMINGS, execution).read_text(encoding="utf-8")
    bs = rd.bundle_summary.load()
    results = _section(page, "results")
    for key in ("rms_f_mm", "rms_eps1_mm", "rms_eps2_mm"):
        assert f"{bs['after'][key] * 1000:.1f} µm" in results
        assert f"{bs['before'][key]:.3f} mm" in results
    assert f"1 part in {bs['one_part_in_1p96_sigma']:,.0f}" in results
    assert "2872.3 mm volume diagonal" in results
    assert "168.0 µm" in results and "44.9 µm" in results and "160.8 µm" in results  # floor of evaluation.json
    assert "true parameters (simulation)" in results and NO_TRUTH not in page
    assert f"{bs['bundle_seconds']:.2f} s" in results  # the adjustment's own wall time

    params = _section(page, "scanners")
    assert params.count("(fixed)") == 6  # the reference camera's external parameters
    assert params.count("±") == 4 * 14 - 6
    assert len(re.findall(r"<tr><td", params.split("Strongest correlations")[0])) == 2 * 14
    c2 = bs["parameters"][[p["name"] for p in bs["parameters"]].index("C2.c")]
    assert f"{c2['value']:.2f}" in params

    ver = _section(page, "verification")
    assert "47.0 µm" in ver  # max |error| of CAL_ERRORS_MM
    assert "44.0 µm" in ver  # ... and with the true parameters (evaluation.json)
    assert f"calibrated / true = {0.047 / 0.044:.2f}" in ver
    assert ver.count('class="pass">PASS') == 18 and "FAIL" not in ver
    assert "k = 1.96" in ver and "1015.6500 mm" in ver
    assert "(9 positions, placed as in thesis section 6.9.3)" in ver and "9 recorded, 9 length(s) measured" in ver
    rows = _verification_rows(page)
    assert list(rows) == POSITIONS
    for p, cal, true in zip(POSITIONS, CAL_ERRORS_MM, TRUE_ERRORS_MM):
        assert rows[p][1] == "scanner1, scanner2"
        assert rows[p][2] == f"{REFERENCE_MM + cal:.4f} mm"
        assert rows[p][3] == f"{cal * 1000:.1f} µm" and rows[p][5] == f"{true * 1000:.1f} µm"
    head = page.split("<nav>")[0]
    assert '<span class="badge pass">ACCEPTED</span>' in head
    assert execution["created_utc"] in head and CREATED not in page  # the execution passed in, not the summary's

    timing = _section(page, "timing")
    assert "simulate-render" in timing and "118.2 s (1 min 58 s)" in timing and "30.5 s" in timing
    assert "0.35 s" in timing and "175.0 s (2 min 55 s)" in timing and "Timings from this run" in timing
    assert f"{100 * 118.25 / 175.0:.0f} %" in timing

    rig = _section(page, "rig")
    assert "scanner1 (reference)" in rig and "1400 × 1050 px" in rig
    assert "15 (diameters" in rig and "used to move the artefact" in rig and "512 px wide" in rig
    assert "<td>3</td>" in rig.split("Rods")[1][:30]  # rods.csv
    assert "spheres A, B, diameters 30.002, 29.998 mm, centre distance 1015.6500 mm" in rig
    assert "24 from 12 artefact poses and 2 scanner(s)" in rig and "18 from 9 positions" in rig
    assert "Rendered by the simulator" in rig and "simulated rig" in rig
    assert "23 of 24 measurements labelled" in rig and "too_few_spheres" in rig
    moves = rd.hexapod_moves.load()
    assert f"translation error max {moves.translation_error_mm.max() * 1000:.1f} µm" in rig

    sphere_rows = re.findall(r"<tr><td class=\"l\">([^<]*)</td><td class=\"l\">([^<]*)</td><td class=\"l\">([^<]*)"
                             r"</td><td>\d+</td><td>[^<]*</td><td>([\d.]+) µm", _section(page, "residuals"))
    shown = [float(r[3]) for r in sphere_rows[:10]]
    per_sphere = rd.residuals_per_sphere.load()
    assert shown == sorted(shown, reverse=True)
    assert shown[0] == pytest.approx(per_sphere["rms_eps2_mm"].max() * 1000, abs=0.06)

    truth = _section(page, "truth")
    assert "610.0 µm" in truth and "210.0 µrad" in truth and "44.0 µm" in truth  # evaluation.json
    assert truth.count("<tr><td") == 4  # one row per sensor

    prov = _section(page, "provenance")
    man = rd.manifest.load()
    assert man["config_digest"] in prov and "cd" * 32 in prov and "numpy" in prov
    assert "ab" * 32 in prov and "configs/thesis/artefact_cmm2.csv" in prov and "camera_width_px: 512" in prov
    assert execution["command"] in prov and execution["created_utc"] in prov
    assert str(rd.root) not in page  # no absolute path of the machine that wrote it


def test_sections_in_order_after_the_certificate(rd):
    page = render_report(rd, TIMINGS, generated="2026-05-06 07:08:09")
    assert re.findall(r'<section id="([^"]+)">\s*<h2>([^<]*)</h2>', page) == SECTIONS
    nav = re.search(r"<nav>(.*?)</nav>", page, re.S).group(1)
    assert re.findall(r'<a href="#([^"]+)">([^<]*)</a>', nav) == SECTIONS
    assert page.index('<header id="certificate"') < page.index("<nav>")
    assert "<title>Calibration report: thesis</title>" in page
    assert page.rstrip().endswith("on 2026-05-06 07:08:09 UTC from the files of the run directory run.</p></footer>\n"
                                  "</body>\n</html>")


def _certificate(page: str) -> str:
    m = re.search(r'<header id="certificate" class="certificate">(.*?)</header>', page, re.S)
    assert m
    return m.group(1)


def _cells(html_: str) -> list[list[str]]:
    return [[re.sub(r"<[^>]+>", "", c.replace("<br>", " ")).strip() for c in re.findall(r"<t[dh][^>]*>(.*?)</t[dh]>", r, re.S)]
            for r in re.findall(r"<tr>(.*?)</tr>", html_, re.S)]


IDENTITY = {"customer": "Acme Aero GmbH", "cell": "hall 3, wing jig", "place": "Bremen", "date": "2026-11-20",
            "operator": "R. Tarvaz", "scanners": {"scanner1": "FP-0042"},
            "artefact_certificate": {"number": "CMM-2026-117", "date": "2026-10-02", "issuer": "PTB"},
            "ballbar_certificate": {"number": "BB-88"}, "temperatures_c": {"air": 20.4, "artefact": 20.1},
            "approved_by": "Q. Manager"}


def test_certificate_page_states_identity_verdict_components_chain_and_approval(rd):
    config = _config(simulate={"acquisition": {"camera_width_px": 512}}, certificate=IDENTITY)
    rd.manifest.save(_manifest(config, "simulated", {"configs/thesis/artefact_cmm2.csv": "ab" * 32}))
    cert = _certificate(render_report(rd, TIMINGS, generated="2026-05-06 07:08:09"))
    assert re.search(r'<h1>Calibration certificate <span class="badge pass">ACCEPTED</span></h1>', cert)
    number = re.search(r"Certificate No\. <b>(FC-[0-9A-F]{4}-[0-9A-F]{4}-[0-9A-F]{4})</b>", cert).group(1)
    rows = {r[0]: r[1] for r in _cells(cert.split('<table class="kv identity">')[1].split("</table>")[0])}
    assert rows["Customer"] == "Acme Aero GmbH" and rows["Cell"] == "hall 3, wing jig" and rows["Place"] == "Bremen"
    assert rows["Date of calibration"] == "2026-11-20" and rows["Operator"] == "R. Tarvaz"
    assert rows["Scanners"] == "scanner1: serial FP-0042; scanner2: serial ______"  # a serial not stated: a blank
    assert rows["Artefact (CMM) certificate"] == "CMM-2026-117 (2026-10-02, PTB)"
    assert rows["Ball-bar certificate"] == "BB-88" and rows["Acceptance objects certificate"] == ""
    assert rows["Temperatures"] == "air 20.4 °C, artefact 20.1 °C"
    assert "A simulated run (simulation profile ideal): this certificate certifies no physical cell." in cert
    # the verdict with its rule, and the ball-bar's component: the largest |error| of CAL_ERRORS_MM with its U
    assert "<b>Verdict: ACCEPTED</b>" in cert and "ISO 14253-1 per component" in cert
    table = _cells(cert.split('<table class="verdicts">')[1].split("</table>")[0])
    assert table[0] == ["Quality parameter", "scanner1", "scanner2", "MPE"]
    assert table[1] == ["ball-bar lengths of the ball-bar verification (9 positions)",
                        "47.0 µm (U 50.0 µm) conformance, 9 pos.", "100.0 µm"]
    chain = re.findall(r"<li><b>([^<]*)</b><br>([^<]*)</li>", cert)
    assert [c[0] for c in chain] == ["CMM certificate", "Artefact", "Calibration", "Lengths"]
    assert chain[0][1] == "CMM-2026-117 (2026-10-02, PTB)" and chain[1][1].startswith("15 spheres, artefact.csv")
    bs = rd.bundle_summary.load()
    assert f"{bs['n_control_points']:,} control points in {bs['n_measurements']} measurements" in chain[2][1]
    assert chain[3][1] == "ball-bar 1015.6500 mm (certificate BB-88), 9 lengths measured, largest |error| 47.0 µm"
    assert "Name: R. Tarvaz" in cert and "Name: Q. Manager" in cert and cert.count("Signature:") == 2
    # the number follows the results: the same files give the same number, another verification another
    again = _certificate(render_report(rd, TIMINGS, generated="2027-01-01 00:00:00"))
    assert number in again
    ver = rd.verification.load()
    ver["calibrated"]["positions"][0]["error_mm"] = 0.022
    rd.verification.save(ver)
    assert number not in _certificate(render_report(rd, TIMINGS))


def test_certificate_without_identity_leaves_fields_to_fill_in(rd):
    cert = _certificate(render_report(rd, TIMINGS))
    rows = _cells(cert.split('<table class="kv identity">')[1].split("</table>")[0])
    blank = [r[0] for r in rows if r[1] == ""]
    assert blank == ["Customer", "Cell", "Place", "Operator", "Artefact (CMM) certificate", "Ball-bar certificate",
                     "Acceptance objects certificate", "Temperatures"]
    assert cert.count('<td class="blank">') == len(blank)
    assert "Date of calibration</th><td>2026-01-02 (run started)" in cert  # the summary's execution


def test_scanner_sections_show_maps_from_the_binned_residuals(rd):
    """The bundle step's binned table holds every control point once per sensor, with the
    residuals' RMS per cell; the report draws each scanner's maps from it."""
    bins = rd.residuals_binned.load()
    per_sphere = rd.residuals_per_sphere.load()
    for scanner in SCANNERS:
        mine = bins[bins.scanner == scanner]
        n = int(per_sphere[per_sphere.scanner == scanner]["n_points"].sum())
        for role in ("camera", "projector"):
            part = mine[mine.role == role]
            assert part["n_points"].sum() == n  # every point once over each sensor's image
            # the RMS over all cells equals the RMS over the points (per-sphere table, same points)
            rms = np.sqrt((part["n_points"] * part["rms_eps2_mm"] ** 2).sum() / n)
            expected = np.sqrt((per_sphere[per_sphere.scanner == scanner].eval("n_points * rms_eps2_mm ** 2")).sum() / n)
            assert rms == pytest.approx(expected, rel=1e-9)
        cam = mine[mine.role == "camera"]
        width = rd.calibration.load().scanner(scanner).camera.format.width_px
        assert (cam.nx == 16).all() and cam.u_px.between(0, width).all()
    cells = bins.drop_duplicates("sensor").eval("nx * ny").sum()
    assert not bins.duplicated(["sensor", "ix", "iy"]).any() and len(bins) <= cells  # one row per cell, not per point
    section = _section(render_report(rd, TIMINGS), "scanners")
    for scanner in SCANNERS:
        assert f"<h3>Scanner {scanner}</h3>" in section
        assert f'alt="residuals and control points over the images of {scanner}"' in section
        assert f'alt="uncertainty of a measured point over the camera image of {scanner}"' in section
    assert "the depths of the artefact spheres that gave control points" in section  # no specification
    assert "Not available: acceptance.json is not in the run directory." in section


def test_uncertainty_map_is_the_propagated_covariance_at_each_depth(rd):
    """The map's value at a cell is the point's u from the covariance through the
    triangulation (a point straight ahead, checked against an independent Jacobian)."""
    from fringecal.calibration.file import read_calibration
    from fringecal.calibration.propagation import (
        frame_free_covariance,
        scanner_block,
        triangulate_mm,
        uncertainty_at_depth,
    )

    cal = read_calibration(rd.calibration.path)
    rig = cal.rig
    cov = scanner_block(frame_free_covariance(rig, cal.covariances.total), rig, "scanner2")
    sc = rig.scanner("scanner2")
    m = uncertainty_at_depth(sc, cov, 2600.0, nx=4)
    assert m.u_mm.shape == (4, 4)  # a square camera: 4 x 4 cells
    cam_mm = sc.camera.format.pixel_to_mm(np.array([[m.u_px[1], m.v_px[1]]]))
    origin, d = sc.camera.rays(cam_mm)
    X = origin + d * 2600.0 / (d @ sc.camera.R[2])
    assert sc.camera.to_sensor(X)[0, 2] == pytest.approx(2600.0)
    prj = sc.projector.project(X)
    p0 = np.concatenate([sc.camera.params, sc.projector.params])
    J = np.zeros((3, 28))
    for j in range(28):
        h = 1e-7 * max(1.0, abs(p0[j]))
        plus, minus = p0.copy(), p0.copy()
        plus[j] += h
        minus[j] -= h
        J[:, j] = (triangulate_mm(type(sc)(sc.name, sc.camera.with_params(plus[:14]),
                                            sc.projector.with_params(plus[14:])), cam_mm, prj)[0]
                   - triangulate_mm(type(sc)(sc.name, sc.camera.with_params(minus[:14]),
                                             sc.projector.with_params(minus[14:])), cam_mm, prj)[0]) / (2 * h)
    assert m.u_mm[1, 1] == pytest.approx(np.sqrt(np.trace(J @ cov @ J.T)), rel=1e-3)


def test_print_style_sheet_repeats_headers_and_hides_the_navigation(rd):
    page = render_report(rd, TIMINGS)
    css = re.search(r"<style>(.*?)</style>", page, re.S).group(1)
    assert re.search(r"@page\s*{[^}]*size:\s*A4", css) and 'counter(page) " of " counter(pages)' in css
    printed = css[css.index("@media print"):]
    assert re.search(r"\bnav\s*{\s*display:\s*none", printed)
    assert re.search(r"\bthead\s*{\s*display:\s*table-header-group", printed)
    assert re.search(r"\btr\b[^{]*{\s*break-inside:\s*avoid", printed)
    # every table but the label/value ones has its header row in <thead>, repeated on each printed page
    tables = re.findall(r"<table([^>]*)>\s*(<\w+)", page)
    assert len(tables) > 20
    assert {(attrs, first) for attrs, first in tables} <= {("", "<thead"), (' class="long"', "<thead"),
                                                           (' class="kv"', "<tr"), (' class="kv identity"', "<tr"),
                                                           (' class="verdicts"', "<thead"),
                                                           (' class="approval"', "<thead")}
    # a table of more than 25 rows may break across pages, a shorter one is kept whole
    residuals = _section(page, "residuals")
    assert residuals.count('<table class="long">') == 1 and "All " in residuals


def test_templates_are_package_data():
    names = {p.name for p in (files("fringecal.report") / "templates").iterdir()}
    assert {"base.html.j2", "macros.html.j2", "certificate.html.j2", "report.css"} <= names
    assert {f"{anchor}.html.j2" for anchor, _ in SECTIONS} <= names
    pyproject = tomllib.loads((Path(__file__).parents[1] / "pyproject.toml").read_text())
    assert "report/templates/*" in pyproject["tool"]["setuptools"]["package-data"]["fringecal"]
    assert any(d.replace(" ", "").startswith("jinja2>=3.1") for d in pyproject["project"]["dependencies"])


def test_true_column_is_matched_by_position_name(rd):
    ev = rd.evaluation.load()
    true = ev["verification_true_params"]
    true["positions"] = [dict(p, error_mm=0.001 * (i + 1)) for i, p in enumerate(true["positions"])][::-1]
    true["positions"] = [p for p in true["positions"] if p["measurement"] != "bb05"]  # not measured
    rd.evaluation.save(ev)
    rows = _verification_rows(write_report(rd, TIMINGS).read_text(encoding="utf-8"))
    for i, p in enumerate(POSITIONS):
        expected = "not measured" if p == "bb05" else f"{i + 1:.1f} µm"
        assert rows[p][5] == expected, p


def test_a_length_outside_its_mpe_makes_the_run_not_accepted(rd):
    errors = CAL_ERRORS_MM[:8] + [0.130]
    ver = rd.verification.load()
    ver["calibrated"] = _ballbar(errors).to_dict()
    ver["uncertainty"] = _budget(errors, U=0.020)
    ver["failures"] = [{"position": "bb09", "scanner": "scanner2", "sphere_id": "B", "reason": "too few points"}]
    rd.verification.save(ver)
    page = write_report(rd, TIMINGS).read_text(encoding="utf-8")
    head = page.split("<nav>")[0]
    assert '<span class="badge fail">NOT ACCEPTED</span></h1>' in head and "PASS" not in head
    # 130 um - U 20 um > 100 um: non-conformance proven; the others conform (47 + 20 um <= 100 um)
    assert ("not accepted (ball-bar: E 1/9): ball-bar E bb09: non-conformance (value 130.0 µm, U 20.0 µm, "
            "limit 100.0 µm).") in head
    section = _section(page, "verification")
    assert section.count('class="fail">FAIL') == 1 and "130.0 µm" in section
    assert '<span class="badge fail">NOT ACCEPTED</span> (conformance not proven: ball-bar: E 1/9)' in section
    assert "too few points" in section and "1 problem(s)" in section


def test_the_badge_is_pass_only_when_every_length_conformance_is_proven(rd):
    """Every length within its MPE, but one with a U too large to prove it (45 + 60 um > 100 um):
    the run is not accepted, and the page says which length and why."""
    ver = rd.verification.load()
    ver["uncertainty"] = _budget(CAL_ERRORS_MM, U=0.060)
    rd.verification.save(ver)
    head = write_report(rd, TIMINGS).read_text(encoding="utf-8").split("<nav>")[0]
    assert '<span class="badge fail">NOT ACCEPTED</span>' in head and "PASS" not in head
    assert "ball-bar E bb03: uncertainty zone (value 47.0 µm, U 60.0 µm, limit 100.0 µm)" in head
    assert "bb02" not in head  # 34 + 60 um <= 100 um: conformance
    ver["uncertainty"] = None  # no budget: no length's U is known, none is proven
    rd.verification.save(ver)
    head = write_report(rd, TIMINGS).read_text(encoding="utf-8").split("<nav>")[0]
    assert "not accepted (ball-bar: E 9/9)" in head and "U n/a" in head


def test_missing_optional_files_give_notes(rd):
    for f in (rd.evaluation, rd.verification, rd.hexapod_moves, rd.histogram("eps2")):
        f.remove()
    page = write_report(rd).read_text(encoding="utf-8")
    assert (f"Not available: {rd.evaluation.rel} is not in the run directory: this simulated run has not been "
            f"evaluated") in _section(page, "truth")
    assert f"Not available: {rd.verification.rel} is not in the run directory" in _section(page, "verification")
    assert f"{rd.histogram('eps2').rel} is not in the run directory" in _section(page, "residuals")
    assert f"{rd.hexapod_moves.rel} is not in the run directory" in _section(page, "rig")
    # only verification.json decides, not what an earlier execution put in the summary
    assert '<span class="badge none">NOT VERIFIED</span>' in page
    timing = _section(page, "timing")  # no timings passed in: the summary's
    assert f"Timings from {rd.summary.rel}" in timing and "120.5 s (2 min 0 s)" in timing
    assert "181.0 s (3 min 1 s)" in timing
    assert CREATED in page.split("<nav>")[0] and COMMAND in _section(page, "provenance")
    assert page.count("data:image/png;base64,") == 1 + 3 * len(SCANNERS)  # eps1's histogram and the maps
    assert "Could not be shown" not in page
    _well_formed(page)


def test_crossval_section_states_the_jackknife_and_the_model_error_it_gave(rd):
    """The bundle step's jackknife (its replicas and noise-only worlds, from the summary)
    and the model-error term it gave each length (the verification's): RMS and largest,
    also when the halves could not be calibrated."""
    bs = rd.bundle_summary.load()
    assert bs["jackknife"]["replicas"] == 12 and bs["jackknife"]["noise_draws"] == 4
    ver = rd.verification.load()
    terms = [0.012, 0.030, 0.021, 0.008, 0.017, 0.026, 0.011, 0.019, 0.005]
    for e, t in zip(ver["uncertainty"]["lengths"], terms):
        e["jackknife"] = {"spread_mm": 0.04, "noise_spread_mm": 0.01, "u_calibration_mm": 0.01, "model_error_mm": t,
                          "replicas": 12, "noise_draws": 4}
    rd.verification.save(ver)
    rd.crossval.save({"verdict": "not possible", "reason": "too few measurements in each half"})
    text = re.sub(r"\s+", " ", re.sub(r"<[^>]+>", " ", _section(write_report(rd).read_text(encoding="utf-8"),
                                                                    "crossval")))
    assert "Not possible: too few measurements in each half" in text
    assert "12 replicas, each without one measurement, in the data and in 4 worlds of noise alone" in text
    rms = 1000 * float(np.sqrt(np.mean(np.square(terms))))
    assert f"{rms:.1f} µm RMS, largest 30.0 µm at bb02" in text


def test_residuals_section_states_the_decoding_and_the_phase_ripple_corrected(rd):
    """Per scanner, what the decoder wrote into each store's summary
    (fringecal.fringe.measurement.decoding_summary), read from the stores' metadata."""
    page = _section(write_report(rd).read_text(encoding="utf-8"), "residuals")
    assert "the run has no decoded image stack" in re.sub(r"\s+", " ", page)
    stacks = {"1-scanner1": (0.41, 0.040, 0.046, {"x": (1234.5, True, 0.1587), "y": (900.0, True, 0.15)}),
              "2-scanner1": (0.43, 0.043, 0.045, {"x": (3.2, False, 0.001)}),
              "1-scanner2": (0.40, 0.041, 0.044, {})}
    for name, (valid, ex, ey, ripple) in stacks.items():
        summary = {"valid_fraction": valid, "median_phase_error_x_rad": ex, "median_phase_error_y_rad": ey}
        if ripple:
            summary["phase_ripple"] = {o: {"z": z, "applied": a, "excess_rms_rad": r} for o, (z, a, r) in ripple.items()}
        write_store(rd.store(name).path, xr.Dataset(attrs={"summary": summary}))
    text = re.sub(r"\s+", " ", re.sub(r"<[^>]+>", " ", _section(write_report(rd).read_text(encoding="utf-8"),
                                                                    "residuals")))
    assert "Corrected: 1-scanner1 x, 1-scanner1 y." in text
    assert "scanner1 2 42.0 % 41.5 / 45.5 3 1234.5 2: largest 158.7 mrad RMS" in text
    assert "scanner2 1 40.0 % 41.0 / 44.0 0 - none" in text


def test_timing_shows_kernel_compilation_apart(rd):
    """A first run's compilation is shown per step and in total; a warm run has no column."""
    page = render_report(rd, TIMINGS, generated="2026-05-06 07:08:09",
                         compile_seconds={"simulate-render": 21.25, "bundle": 0.0, "spheres-first": 3.5})
    timing = _section(page, "timing")
    assert "<th>of which compiling kernels</th>" in timing
    assert "21.2 s" in timing and "3.50 s" in timing and "24.8 s" in timing  # per step, then the total
    assert timing.count("<td></td>") >= 2  # the bundle (0 s) and verify steps compiled nothing
    warm = _section(render_report(rd, TIMINGS, generated="2026-05-06 07:08:09"), "timing")
    assert "compiling" not in warm


def test_a_run_without_ballbar_recordings_is_not_verified(rd):
    acq = rd.acquisition.load()
    rd.acquisition.save(acq[acq.kind == "artefact"])
    rd.verification.remove()
    page = write_report(rd, TIMINGS).read_text(encoding="utf-8")
    assert '<span class="badge none">NOT VERIFIED</span>' in page.split("<nav>")[0]
    assert "the run has no ball-bar recordings" in _section(page, "verification")
    assert "none (the calibration is not verified)" in _section(page, "rig")


def test_a_dataset_run_says_there_is_no_truth(rd):
    config = _config(dataset="/data/cell-a")
    rd.manifest.save(_manifest(config, "dataset", {"/data/cell-a/artefact.csv": "ef" * 32}))
    rd.evaluation.remove()
    rd.hexapod_moves.remove()
    acq = rd.acquisition.load()
    acq["source"] = [f"measurements/{p}/{s}" for p, s in zip(acq.pose, acq.scanner)]
    rd.acquisition.save(acq)
    page = write_report(rd, TIMINGS).read_text(encoding="utf-8")
    assert "Traceback" not in page and "Could not be shown" not in page
    assert f"Not available: {rd.evaluation.rel} is {NO_TRUTH}." in _section(page, "truth")
    results = _section(page, "results")
    assert results.count(NO_TRUTH) == 1 and 'rowspan="3"' in results
    ver = _section(page, "verification")
    assert ver.count(NO_TRUTH) == 2 and f'rowspan="{len(POSITIONS)}"' in ver  # the note row and the column
    assert ver.count('class="pass">PASS') == len(POSITIONS) and "calibrated / true" not in ver
    assert "(9 positions)" in ver  # no simulation scheme
    rows = _verification_rows(page)
    assert [rows[p][3] for p in POSITIONS] == [f"{e * 1000:.1f} µm" for e in CAL_ERRORS_MM]
    rig = _section(page, "rig")
    assert "not moved by a hexapod here" in rig and "recorded data set /data/cell-a" in rig
    assert "Read from the data set" in rig and "42 image stacks or stores" in rig and "px wide" not in rig
    assert "recorded data set /data/cell-a" in page.split("<nav>")[0]
    assert '<span class="badge pass">ACCEPTED</span>' in page.split("<nav>")[0]
    assert "simulated run" not in page.split("<nav>")[0]
    assert "ef" * 32 in _section(page, "provenance")
    _well_formed(page)


def test_malformed_file_is_named_and_the_rest_is_shown(rd):
    rd.bundle_summary.path.write_text('{"before": ')
    moves = rd.hexapod_moves.path
    moves.write_text(moves.read_text().replace("translation_error_mm", "translation_err", 1))
    page = write_report(rd, TIMINGS).read_text(encoding="utf-8")
    results = _section(page, "results")
    assert "Could not be shown" in results and rd.bundle_summary.rel in results
    rig = _section(page, "rig")
    assert "Could not be shown" in rig and rd.hexapod_moves.rel in rig and "translation_error_mm" in rig
    assert "24 from 12 artefact poses" in rig  # the acquisition table is still shown
    assert _section(page, "scanners").count("(fixed)") == 6
    assert str(rd.root) not in page
    _well_formed(page)


def test_hostile_strings_are_escaped(rd):
    cal = json.loads(rd.calibration.path.read_text())
    cal["scanners"][1]["sensors"][0]["name"] = '<script>alert("x")</script>'
    rd.calibration.path.write_text(json.dumps(cal))
    man = rd.manifest.load()
    man["config"]["name"] = "<img src=x onerror=alert(1)>"
    rd.manifest.save(man)
    summary = rd.summary.load()
    summary["command"] = "fringecal run --out '</code><b>'"
    rd.summary.save(summary)
    bs = rd.bundle_summary.load()
    bs["diagnostics"] = [{"kind": "single_pose", "severity": "warning", "subject": "s", "parameters": [],
                          "message": "scanner <b>scanner2</b> & friends"}]
    rd.bundle_summary.save(bs)
    ver = rd.verification.load()
    ver["failures"] = [{"position": "<i>bb01</i>", "scanner": "s", "sphere_id": "A", "reason": "<u>x</u>"}]
    rd.verification.save(ver)
    page = write_report(rd, TIMINGS).read_text(encoding="utf-8")
    assert "<script" not in page and "<img src=x" not in page and "<b>scanner2" not in page
    assert "<i>bb01" not in page and "<u>x" not in page
    assert "&lt;script&gt;alert(&#34;x&#34;)&lt;/script&gt;" in page  # markupsafe: &#34; for "
    assert "&lt;img src=x onerror=alert(1)&gt;" in page
    assert "scanner &lt;b&gt;scanner2&lt;/b&gt; &amp; friends" in page
    assert "&lt;/code&gt;&lt;b&gt;" in page
    _well_formed(page)


def test_not_a_run_directory(tmp_path):
    with pytest.raises(FileNotFoundError, match="not a run directory"):
        write_report(tmp_path)
    assert not RunDir(tmp_path).report.exists()


def test_cli_rewrites_the_report(rd, tmp_path):
    from fringecal.flows.cli import app

    runner = CliRunner()
    res = runner.invoke(app, ["report", "--run", str(rd.root)])
    assert res.exit_code == 0, res.output
    page = rd.report.load()
    timing = _section(page, "timing")
    assert f"Timings from {rd.summary.rel}" in timing and "181.0 s" in timing and "120.5 s" in timing
    assert CREATED in page.split("<nav>")[0] and COMMAND in _section(page, "provenance")
    res = runner.invoke(app, ["report", "--run", str(rd.root), "--pdf", str(tmp_path / "r.pdf")],
                        env={"FRINGECAL_CHROMIUM": str(tmp_path / "no-chromium")})
    assert res.exit_code == 2 and "cannot write a PDF without headless Chromium" in res.output.replace("\n", "")
    assert "apt-get install chromium" in res.output.replace("\n", "") and not (tmp_path / "r.pdf").exists()
    res = runner.invoke(app, ["report", "--run", str(tmp_path / "nowhere")])
    assert res.exit_code == 2 and "no such run directory" in res.output
    empty = tmp_path / "empty"
    empty.mkdir()
    res = runner.invoke(app, ["report", "--run", str(empty)])
    assert res.exit_code == 2 and "not a run directory" in res.output.replace("\n", "")


def test_scanner_section_shows_each_correction_field_with_its_rms_and_u(rd):
    """A calibration whose C1 has a correction field (coefficients a_j = 0.4 um * (-1)^j,
    u_j = 0.1 um) and P1 a zero one: the parameter table of scanner1 gains two rows, the
    field's RMS over the format with its first-order u (RMS = sqrt(sum a^2) = 1.744 um,
    u = sqrt(sum (a_j u_j)^2) / RMS = 0.1 um, noise alone sqrt(sum u^2) = 0.44 um) and its
    largest displacement; a sensor without a field says none; one line explains. A
    14-parameter rig's section has neither (test_report_shows_the_numbers_of_the_run
    counts its rows)."""
    from fringecal.lens.field import FORMAT_GRID_POINTS as FIELD_GRID
    from fringecal.lens.field import CorrectionField, field_names, field_terms
    from fringecal.report.sections.scanners import field_displacement

    base = _section(write_report(rd, TIMINGS).read_text(encoding="utf-8"), "scanners")
    assert "correction field" not in base.lower()
    K = field_terms()
    a = 4e-4 * (-1.0) ** np.arange(K)
    u = np.full(K, 1e-4)
    cal = json.loads(rd.calibration.path.read_text())
    for sensor, coefs in zip(cal["scanners"][0]["sensors"], (a, np.zeros(K))):
        sensor["correction_field"] = {"degree": 4, "coefficients": {
            n: {"value": float(v), "unit": "mm", "free": True, "u": float(w)} for n, v, w in zip(field_names(), coefs, u)}}
    rd.calibration.path.write_text(json.dumps(cal))
    rig = rd.calibration.load()
    c1 = field_displacement(rig, 0)
    rms = float(np.sqrt(np.sum(a ** 2)))  # the basis is orthonormal over the format
    assert c1["rms_mm"] == pytest.approx(rms, rel=1e-9) and rms * 1e3 == pytest.approx(1.7436, abs=1e-4)
    assert c1["u_rms_mm"] == pytest.approx(np.sqrt(np.sum((a * u) ** 2)) / rms, rel=1e-12) == pytest.approx(1e-4)
    assert c1["noise_mm"] == pytest.approx(np.sqrt(K) * 1e-4)
    fmt = rig.sensors[0].format  # the largest on a finer grid: the 41 x 41 one misses little of it
    g = np.linspace(-0.5, 0.5, 4 * FIELD_GRID - 3)
    m = np.stack(np.meshgrid(g * fmt.width_mm, g * fmt.height_mm), axis=-1).reshape(-1, 2)
    fine = np.linalg.norm(CorrectionField.zero(fmt.width_mm, fmt.height_mm).with_coefficients(a).value(m), axis=-1)
    assert 0.97 * fine.max() <= c1["largest_mm"] <= fine.max()
    assert field_displacement(rig, 1) == {"rms_mm": 0.0, "largest_mm": 0.0, "u_rms_mm": pytest.approx(1e-4),
                                          "noise_mm": pytest.approx(np.sqrt(K) * 1e-4)}
    assert field_displacement(rig, 2) is None  # scanner2: no field
    page = write_report(rd, TIMINGS).read_text(encoding="utf-8")
    scanners = _section(page, "scanners")
    part1, part2 = scanners.split("Scanner scanner2")
    rows = {re.sub(r"<[^>]+>", "", r.split("</td>")[0]): [re.sub(r"<[^>]+>", "", c)
                                                           for c in re.findall(r"<td[^>]*>(.*?)</td>", r, re.S)]
            for r in re.findall(r"<tr>(<td.*?)</tr>", part1, re.S)}
    assert rows["correction field, RMS over the format"][2] == "1.74 ± 0.10 (noise alone 0.44)"
    assert rows["correction field, largest over the format"][2] == f"{c1['largest_mm'] * 1e3:.3g}"
    assert rows["correction field, RMS over the format"][1] == "µm"
    assert "correction field, RMS over the format" in part2 and part2.count(">none<") == 4  # C2, P2
    assert scanners.count("Correction field: the smooth displacement f") == 2
    _well_formed(page)


def test_scanner_section_shows_the_observed_region_of_each_sensor(rd):
    """The bundle step's observed regions, recounted from the control points it read
    (tables/control_points.csv): the page states each sensor's covered fraction of its
    format (rounded to 1 %) beside a figure of the grid per scanner; a calibration.json
    without regions (written before them) gives a note and the rest of the section."""
    from fringecal.calibration.file import read_calibration
    from fringecal.lens.observed_region import ObservedRegion

    cal = read_calibration(rd.calibration.path)
    cp = rd.control_points.load()
    section = _section(render_report(rd, TIMINGS), "scanners")
    for sc in cal.rig.scanners:
        mine = cp[cp.scanner == sc.name]
        for sensor, columns in ((sc.camera, ["u_px", "v_px"]), (sc.projector, ["tau_x_rad", "tau_y_rad"])):
            fmt = sensor.format
            truth = ObservedRegion.from_observations(sensor.image_mm(mine[columns].to_numpy(float)), fmt.width_mm,
                                                     fmt.height_mm)
            assert cal.observed_regions[sensor.name] == truth and 0 < truth.fraction <= 1
            assert f"{sensor.name} ({sensor.role}) {100 * truth.fraction:.0f} %" in section
        assert f'alt="regions of the image planes of {sc.name} the calibration observed"' in section
    doc = json.loads(rd.calibration.path.read_text())
    for sc in doc["scanners"]:
        for se in sc["sensors"]:
            del se["observed_region"]
    rd.calibration.path.write_text(json.dumps(doc))
    page = write_report(rd, TIMINGS).read_text(encoding="utf-8")
    section = _section(page, "scanners")
    assert section.count("records no observed region of") == 2 and "the calibration observed\"" not in section
    assert 'alt="residuals and control points over the images of scanner1"' in section
    _well_formed(page)


def test_a_left_out_measurement_is_listed_once_with_its_reason(rd):
    """A measurement the adjustment left out is one of its diagnoses (the kind says why);
    ``dropped_measurements`` repeats it, so only a summary without that diagnosis gets a
    row of its own."""
    bs = rd.bundle_summary.load()
    reason = "control points on 2 sphere(s) only (4, 5): its rotation about the line through the two sphere centres"
    diagnosis = {"kind": "pose_unobservable", "severity": "warning", "subject": "13",
                 "message": f"measurement 13 has {reason}: its pose cannot be adjusted and it is left out",
                 "parameters": []}
    rd.bundle_summary.save({**bs, "diagnostics": [*bs.get("diagnostics", []), diagnosis],
                            "dropped_measurements": [{"measurement": "13", "reason": reason},
                                                     {"measurement": "14", "reason": "no control points"}]})
    results = _section(write_report(rd).read_text(encoding="utf-8"), "results")
    assert results.count("control points on 2 sphere(s) only (4, 5)") == 1 and "pose_unobservable" in results
    assert results.count("14: no control points") == 1
