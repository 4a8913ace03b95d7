"""The bad-input battery (issue 17): every command given wrong input stops with ONE
clear line (``error: ...``), exit status 2, no traceback, and writes nothing.

Each case builds its inputs in a fresh folder (the working directory too, so that
default output paths land there), lists every entry of it (hidden ones included),
runs the command in-process and checks: the status, the first line of stderr (it
starts with ``error:`` and holds a distinctive part of the message: the file and
line and column, or the option), no traceback, and the same listing afterwards.

The cases are those the issue found handled badly (crashes, wrong answers with
status 0, late refusals, silent surprises) and a representative set of the ones
it found handled well (unknown config keys, a scanner without a projector,
duplicate ids, Excel's BOM and CRLF, truss mechanisms, hexapod limits, missing
files...), so that both stay so. Image stacks are tested in test_bad_frames.py.
A few cases also run as a subprocess: ``fringecal run`` must refuse in seconds,
before Prefect starts.
"""

from __future__ import annotations

import itertools
import os
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import pytest
from typer.testing import CliRunner

from fringecal.flows.cli import app

ROOT = Path(__file__).resolve().parents[1]
THESIS = ROOT / "configs" / "thesis"
ARTEFACT = THESIS / "artefact_cmm2.csv"
CENTRES = THESIS / "centres_scanner1_table6-3.csv"
BALLBAR_CENTRES = THESIS / "ballbar_verification_table6-9.csv"
SENSORS = THESIS / "sensors_refined_table6-8.csv"
_hexsim = itertools.count()


# -- building inputs ------------------------------------------------------------------

def lines_of(path: Path) -> list[str]:
    return path.read_text().splitlines()


def write(d: Path, name: str, text: str | bytes) -> Path:
    p = d / name
    if isinstance(text, bytes):
        p.write_bytes(text)
    else:
        p.write_text(text)
    return p


def edited(d: Path, source: Path, name: str, line: int, column: str, value: str) -> Path:
    """``source`` with the cell (CSV ``line``, header = 1; ``column``) set to ``value``."""
    rows = lines_of(source)
    header = rows[0].split(",")
    cells = rows[line - 1].split(",")
    cells[header.index(column)] = value
    rows[line - 1] = ",".join(cells)
    return write(d, name, "\n".join(rows) + "\n")


def artefact(d: Path, line: int = 3, column: str = "x_mm", value: str = "inf") -> Path:
    return edited(d, ARTEFACT, "artefact.csv", line, column, value)


def centres(d: Path, line: int = 2, column: str = "y_mm", value: str = "-inf") -> Path:
    return edited(d, CENTRES, "centres.csv", line, column, value)


def rig(d: Path, artefact_path: Path) -> Path:
    """The thesis rig with another artefact table."""
    text = (THESIS / "rig.yaml").read_text()
    for key in ("sensors", "sensors_initial", "rods", "artefact_poses", "ballbar", "materials"):
        value = next(ln.split(":", 1)[1].strip() for ln in text.splitlines() if ln.startswith(f"{key}:"))
        text = text.replace(f"{key}: {value}", f"{key}: {THESIS / value}")
    text = text.replace("artefact: artefact_cmm2.csv", f"artefact: {artefact_path}")
    if "rods" in text and artefact_path != ARTEFACT:
        text = "\n".join(ln for ln in text.splitlines() if not ln.startswith("rods:")) + "\n"
    return write(d, "rig.yaml", text)


def run_config(d: Path, text: str, name: str = "run.yaml") -> Path:
    return write(d, name, text)


def unwritable(d: Path) -> Path:
    """A folder nothing can be created in, even by root (``/proc``); skip if none."""
    candidates = [Path("/proc")]
    if os.geteuid() != 0:
        locked = d / "locked"
        locked.mkdir()
        locked.chmod(0o555)
        candidates.insert(0, locked)
    for c in candidates:
        try:
            fd, probe = tempfile.mkstemp(dir=c)
        except OSError:
            return c
        os.close(fd)
        os.unlink(probe)
    pytest.skip("no unwritable folder on this machine")


def dataset_without_yaml(d: Path) -> Path:
    (d / "ds").mkdir()
    write(d / "ds", "artefact.csv", ARTEFACT.read_text())
    return d / "ds"


def sensors_without_projector(d: Path) -> Path:
    rows = lines_of(SENSORS)
    return write(d, "sensors.csv", "\n".join(rows[:2] + rows[3:]) + "\n")


# -- the cases ----------------------------------------------------------------------------

@dataclass(frozen=True)
class Case:
    id: str
    args: Callable[[Path], list]
    message: str  # in the first line of stderr, after "error: "
    status: int = 2


def _ballbar(d, *options):
    return ["verify", "ballbar", "--centres", BALLBAR_CENTRES, "-L", "1015.65", *options]


CASES = [
    # crashes with tracebacks (issue 17)
    Case("pose-artefact-inf", lambda d: ["pose", "-a", artefact(d), "--centres", CENTRES, "-o", d / "p.csv"],
         "artefact.csv: line 3, column 'x_mm': value 'inf' is not a finite number"),
    Case("pose-centres-minus-inf", lambda d: ["pose", "-a", ARTEFACT, "--centres", centres(d), "-o", d / "p.csv"],
         "centres.csv: line 2, column 'y_mm': value '-inf' is not a finite number"),
    Case("pose-centres-overflow", lambda d: ["pose", "-a", ARTEFACT, "--centres", centres(d, 4, "z_mm", "1e999"),
                                             "-o", d / "p.csv"],
         "centres.csv: line 4, column 'z_mm': value '1e999' is not a finite number"),
    Case("ballbar-centres-inf", lambda d: ["verify", "ballbar", "--centres",
                                           edited(d, BALLBAR_CENTRES, "bb.csv", 3, "x_mm", "Infinity"),
                                           "-L", "1015.65"],
         "bb.csv: line 3, column 'x_mm': value 'Infinity' is not a finite number"),
    Case("run-rig-artefact-inf", lambda d: ["run", "-c", run_config(d, f"simulate:\n  rig: {rig(d, artefact(d))}\n"),
                                            "-o", d / "run"],
         "artefact.csv: line 3, column 'x_mm': value 'inf' is not a finite number"),
    Case("run-config-is-a-folder", lambda d: ["run", "-c", d, "-o", d / "run"], "--config"),
    Case("pose-artefact-is-a-folder", lambda d: ["pose", "-a", d, "--centres", CENTRES, "-o", d / "p.csv"],
         "is a folder; expected a CSV file"),
    Case("run-out-is-a-file", lambda d: ["run", "-o", write(d, "run", "x")], "is a file; expected a folder"),
    Case("run-out-inside-a-file", lambda d: ["run", "-o", write(d, "f", "x") / "run"], "is a file, not a folder"),
    Case("pose-out-is-a-folder", lambda d: ["pose", "-a", ARTEFACT, "--centres", CENTRES, "-o", d],
         "is a folder; expected the name of a file to write"),
    # wrong answers with status 0 (issue 17)
    Case("ballbar-negative-reference", lambda d: ["verify", "ballbar", "--centres", BALLBAR_CENTRES, "-L", "-1015.65"],
         "--reference-length-mm: must be greater than 0 mm, got -1015.65"),
    Case("ballbar-nan-reference", lambda d: ["verify", "ballbar", "--centres", BALLBAR_CENTRES, "-L", "nan"],
         "--reference-length-mm: must be a finite number"),
    Case("ballbar-inf-reference", lambda d: ["verify", "ballbar", "--centres", BALLBAR_CENTRES, "-L", "inf"],
         "--reference-length-mm: must be a finite number"),
    Case("ballbar-zero-diagonal", lambda d: _ballbar(d, "--volume-diagonal-mm", "0"),
         "--volume-diagonal-mm: must be greater than 0"),
    Case("ballbar-negative-mpe", lambda d: _ballbar(d, "--mpe-mm", "-1"), "--mpe-mm: must be greater than 0"),
    Case("ballbar-nan-mpe", lambda d: _ballbar(d, "--mpe-mm", "nan"), "--mpe-mm: must be a finite number"),
    Case("ballbar-negative-certificate-u", lambda d: _ballbar(d, "--certificate-u-mm", "-0.001"),
         "--certificate-u-mm: must be at least 0"),
    Case("ballbar-zero-certificate-k", lambda d: _ballbar(d, "--certificate-k", "0"),
         "--certificate-k: must be greater than 0"),
    Case("ballbar-nan-k", lambda d: _ballbar(d, "--k", "nan"), "--k: must be a finite number"),
    Case("fit-sphere-negative-noise", lambda d: ["fit", "sphere", "-p", write(d, "p.csv", "x_mm,y_mm,z_mm\n1,2,3\n"),
                                                 "--robust", "--noise-mm", "-1"],
         "--noise-mm: must be greater than 0 mm, got -1"),
    Case("fit-plane-nan-noise", lambda d: ["fit", "plane", "-p", write(d, "p.csv", "x_mm,y_mm,z_mm\n1,2,3\n"),
                                           "--noise-mm", "nan"], "--noise-mm: must be a finite number"),
    Case("fit-sphere-inf-radius", lambda d: ["fit", "sphere", "-p", write(d, "p.csv", "x_mm,y_mm,z_mm\n1,2,3\n"),
                                             "--radius-mm", "inf"], "--radius-mm: must be a finite number"),
    # found late (issue 17): an unwritable --out, a Latin-1 byte
    Case("run-out-unwritable", lambda d: ["run", "-o", unwritable(d) / "fringecal-bad-inputs" / "run"],
         "cannot write in"),
    Case("pose-out-unwritable", lambda d: ["pose", "-a", ARTEFACT, "--centres", CENTRES, "-o", unwritable(d) / "p.csv"],
         "cannot write in"),
    Case("artefact-latin1-byte", lambda d: ["pose", "-a", write(d, "artefact.csv", ARTEFACT.read_bytes().replace(
        b"\n3,", b"\n3\xe9,", 1)), "--centres", CENTRES, "-o", d / "p.csv"],
         "artefact.csv: line 4, column 'sphere_id': byte 0xe9 (character 2 of the line) is not UTF-8"),
    Case("centres-latin1-bytes", lambda d: ["verify", "ballbar", "--centres", write(
        d, "bb.csv", BALLBAR_CENTRES.read_bytes().replace(b",A,", b",\xb5A,", 2)), "-L", "1015.65"],
         "bb.csv: 2 problem(s), the first on line 2, column 'sphere_id': byte 0xb5"),
    Case("utf16-table", lambda d: ["pose", "-a", write(d, "a.csv", ARTEFACT.read_text().encode("utf-16")),
                                   "--centres", CENTRES, "-o", d / "p.csv"], "a.csv: line 1: the file is UTF-16 text"),
    Case("config-latin1-byte", lambda d: ["run", "-c", write(d, "run.yaml", b"name: caf\xe9\n"), "-o", d / "run"],
         "run.yaml: line 1: byte 0xe9 is not UTF-8 text"),
    # silently surprising (issue 17)
    Case("empty-config", lambda d: ["run", "-c", write(d, "run.yaml", ""), "-o", d / "run"],
         "run.yaml: the file is empty; omit --config to run the default configuration"),
    Case("comments-only-config", lambda d: ["run", "-c", write(d, "run.yaml", "# nothing yet\n"), "-o", d / "run"],
         "run.yaml: the file is empty"),
    Case("workers-zero", lambda d: ["run", "--workers", "0", "-o", d / "run"], "--workers: must be at least 1, got 0"),
    Case("pose-two-sphere-artefact", lambda d: ["pose", "-a", write(d, "a.csv", "\n".join(lines_of(ARTEFACT)[:3]) + "\n"),
                                                "--centres", CENTRES, "-o", d / "p.csv"],
         "a.csv: 2 sphere(s); a pose needs at least 3 spheres"),
    Case("run-two-sphere-artefact", lambda d: ["run", "-c", run_config(d, "simulate:\n  rig: " + str(rig(d, write(
        d, "a.csv", "\n".join(lines_of(ARTEFACT)[:3]) + "\n"))) + "\n"), "-o", d / "run"],
         "a.csv: an artefact needs at least three spheres"),
    Case("config-nan", lambda d: ["run", "-c", run_config(d, "verification:\n  mpe_mm: .nan\n"), "-o", d / "run"],
         "run.yaml: invalid configuration: verification.mpe_mm: Input should be a finite number"),
    Case("config-negative-noise", lambda d: ["run", "-c", run_config(d, "extraction:\n  rejection:\n    noise_mm: -1\n"),
                                             "-o", d / "run"], "rejection.noise_mm: must be a finite length > 0"),
    Case("config-inf-workers", lambda d: ["run", "-c", run_config(d, "runner:\n  max_workers: .inf\n"),
                                          "-o", d / "run"], "runner.max_workers"),
    # handled well before issue 17: stay so
    Case("config-unknown-key", lambda d: ["run", "-c", run_config(d, "bundel:\n  gamma1: 2\n"), "-o", d / "run"],
         "run.yaml: invalid configuration: bundel: unknown key"),
    Case("config-not-a-mapping", lambda d: ["run", "-c", run_config(d, "- 1\n- 2\n"), "-o", d / "run"],
         "expected a mapping at the top level"),
    Case("config-bad-yaml", lambda d: ["run", "-c", run_config(d, "bundle: [1, 2\n"), "-o", d / "run"],
         "run.yaml: not valid YAML"),
    Case("config-missing", lambda d: ["run", "-c", d / "nope.yaml", "-o", d / "run"], "nope.yaml: file not found"),
    Case("config-simulate-and-dataset", lambda d: ["run", "-c", run_config(d, f"simulate: {{}}\ndataset: {d}\n"),
                                                   "-o", d / "run"], "give either simulate"),
    Case("dataset-missing", lambda d: ["run", "--dataset", d / "nowhere", "-o", d / "run"],
         "--dataset", ),
    Case("dataset-without-yaml", lambda d: ["run", "--dataset", dataset_without_yaml(d), "-o", d / "run"],
         "dataset.yaml: file not found"),
    Case("run-unknown-runner", lambda d: ["run", "--runner", "mpi", "-o", d / "run"],
         "--runner must be threads or dask"),
    Case("run-unknown-until", lambda d: ["run", "--until", "nosuchstep", "-o", d / "run"],
         "--until nosuchstep: not a step of this run"),
    Case("scanner-without-projector", lambda d: ["export", "opencv", "--calibration", sensors_without_projector(d),
                                                 "-o", d / "cv"], "needs one camera and one projector"),
    Case("sensor-unknown-role", lambda d: ["export", "opencv", "--calibration", edited(d, SENSORS, "s.csv", 3, "role", "lidar"),
                                           "-o", d / "cv"], "line 3, column 'role'"),
    Case("artefact-duplicate-id", lambda d: ["pose", "-a", artefact(d, 3, "sphere_id", "1"), "--centres", CENTRES,
                                             "-o", d / "p.csv"],
         "artefact.csv: line 3, column 'sphere_id': value '1' is a duplicate (first on line 2)"),
    Case("artefact-nan-cell", lambda d: ["pose", "-a", artefact(d, 5, "z_mm", "NaN"), "--centres", CENTRES,
                                         "-o", d / "p.csv"],
         "artefact.csv: line 5, column 'z_mm': value is missing"),
    Case("artefact-bom-crlf", lambda d: ["pose", "-a", write(d, "artefact.csv", b"\xef\xbb\xbf" + artefact(
        d, 4, "diameter_mm", "-50").read_bytes().replace(b"\n", b"\r\n")), "--centres", CENTRES, "-o", d / "p.csv"],
         "artefact.csv: line 4, column 'diameter_mm': value -50.0 must be > 0"),
    Case("centres-duplicate-row", lambda d: ["pose", "-a", ARTEFACT, "--centres", write(
        d, "c.csv", "\n".join(lines_of(CENTRES) + lines_of(CENTRES)[1:2]) + "\n"), "-o", d / "p.csv"],
         "duplicate"),
    Case("pose-artefact-missing", lambda d: ["pose", "-a", d / "nope.csv", "--centres", CENTRES, "-o", d / "p.csv"],
         "nope.csv: file not found"),
    Case("fit-not-a-number", lambda d: ["fit", "sphere", "-p", write(d, "p.csv", "x_mm,y_mm,z_mm\n1,2,3\n4,five,6\n")],
         "p.csv: line 3, column 'y_mm': value 'five' is not a number"),
    Case("fit-missing-column", lambda d: ["fit", "plane", "-p", write(d, "p.csv", "x,y,z\n1,2,3\n")],
         "missing required column(s)"),
    Case("truss-mechanism", lambda d: ["artefact", "truss", "--supports", "5:xyz,1:xyz", "-o", d / "f.csv"],
         "is a mechanism"),
    Case("truss-unknown-sphere-in-rods", lambda d: ["artefact", "truss", "--rods", edited(
        d, THESIS / "rods.csv", "rods.csv", 2, "sphere_b", "16"), "-o", d / "f.csv"],
         "line 2, column 'sphere_b': sphere '16' is not in artefact"),
    Case("truss-out-is-a-folder", lambda d: ["artefact", "truss", "-o", d], "--out"),
    Case("thermal-nan-temperature", lambda d: ["artefact", "thermal", "-t", "nan", "-o", d / "a.csv"],
         "--temperature-c: must be a finite number"),
    Case("thermal-negative-u-cte", lambda d: ["artefact", "thermal", "-t", "21", "--u-cte", "-1e-7", "-o", d / "a.csv"],
         "--u-cte: must be at least 0"),
    Case("cme-zero-mass-change", lambda d: ["artefact", "cme", "--mass-change-pct", "0"],
         "--mass-change-pct: must not be 0"),
    Case("moisture-negative-thickness", lambda d: ["artefact", "moisture", "--series", write(
        d, "m.csv", "time_s,mass_g\n0,10\n60,10.1\n"), "--thickness-mm", "-2"], "--thickness-mm: must be greater than 0"),
    Case("hexapod-move-outside-stroke", lambda d: ["hexapod", "move", "--port", f"hexsim://bad{next(_hexsim)}",
                                                   "--counts", "5000,5000,5000,5000,5000,10500"],
         "outside the stroke"),
    Case("hexapod-bad-pose", lambda d: ["hexapod", "ik", "--pose", "1,2,3"], "expected 6 comma-separated"),
    Case("hexapod-nan-limit", lambda d: ["hexapod", "workspace", "--limit-mm", "nan"],
         "--limit-mm: must be a finite number"),
    Case("hexapod-zero-scan", lambda d: ["hexapod", "drift", "--centres", THESIS / "drift_table4-1.csv",
                                         "--scan-s", "0"], "--scan-s: must be greater than 0"),
    Case("hexapod-plan-out-is-a-folder", lambda d: ["hexapod", "plan", "-o", d], "--out"),
    Case("report-no-run", lambda d: ["report", "--run", d / "nope"], "no such run directory"),
    Case("step-unknown", lambda d: ["step", "nosuchstep", "--run", d], "no step 'nosuchstep'"),
    Case("acceptance-no-run", lambda d: ["verify", "acceptance", "--run", d / "nope"], "--run"),
    Case("plan-no-run", lambda d: ["verify", "plan", "--run", d / "nope"], "--run"),
    Case("reproduce-no-run", lambda d: ["reproduce", "--run", d / "nope"], "no such run directory"),
    Case("reproduce-old-spelling-no-run", lambda d: ["reproduce", d / "nope"], "--run"),  # RUN_DIR as before
    Case("reproduce-two-runs", lambda d: ["reproduce", "--run", d, d / "other"], "one run directory, as --run"),
    Case("measure-no-calibration-in-run", lambda d: ["measure", "--run", d, "-s", d, "-o", d / "c.ply"],
         "a folder without calibration.json"),
    Case("export-no-calibration-in-run", lambda d: ["export", "opencv", "--calibration", d, "-o", d / "cv"],
         "--calibration"),
    Case("ballbar-run-without-ballbar", lambda d: ["verify", "ballbar", "-r", d], "the run measured no ball-bar"),
    Case("decode-no-frames", lambda d: ["decode", "-f", d / "nope", "-o", d / "m.zarr"], "--frames"),
    Case("decode-out-is-a-file", lambda d: ["decode", "-f", d, "-o", write(d, "m.zarr", "x")],
         "--out"),
    Case("decode-nan-modulation", lambda d: ["decode", "-f", d, "-o", d / "m.zarr", "--min-modulation", "nan"],
         "--min-modulation"),
    Case("simulate-out-exists", lambda d: ["simulate", "-o", d], "already exists"),
    Case("measure-frames-and-stores", lambda d: ["measure", "--calibration", d / "cal.json", "-f", d, "-s", d, "-o", d / "c.ply"],
         "not both, not none"),
    Case("import-opencv-inf-width", lambda d: ["import", "opencv", "-s", d / "s.yml", "-o", d / "p.csv",
                                               "--camera-width-mm", "inf"], "--camera-width-mm: must be a finite"),
    Case("acquire-inf-timeout", lambda d: ["acquire", "-d", d, "--hexapod", "hexsim://x", "--timeout", "inf"],
         "--timeout: must be a finite number"),
]


def listing(d: Path) -> list[str]:
    return sorted(str(p.relative_to(d)) for p in d.rglob("*"))


@pytest.mark.parametrize("case", CASES, ids=[c.id for c in CASES])
def test_bad_input_stops_with_one_line_and_writes_nothing(case, tmp_path, monkeypatch):
    work = tmp_path / "work"
    work.mkdir()
    monkeypatch.chdir(work)
    args = [str(a) for a in case.args(work)]
    before = listing(work)
    res = CliRunner().invoke(app, args)
    assert res.exit_code == case.status, res.output
    assert res.exception is None or isinstance(res.exception, SystemExit), res.exception
    assert "Traceback" not in res.output
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert lines and lines[0].startswith("error: "), res.output
    assert case.message in lines[0], lines[0]
    assert listing(work) == before


# -- end to end: `fringecal run` refuses in seconds, before Prefect starts ----------------

@pytest.mark.parametrize("make, message", [
    # one process is enough to time the refusal; the same refusals in-process are CASES
    # run-config-is-a-folder and run-out-is-a-file
    (lambda d: ["-c", str(run_config(d, f"simulate:\n  rig: {rig(d, artefact(d))}\n"))],
     "line 3, column 'x_mm': value 'inf' is not a finite number"),
], ids=["artefact-inf"])
def test_run_refuses_before_prefect_starts(make, message, tmp_path):
    args = make(tmp_path)
    if "-o" not in args:
        args += ["-o", str(tmp_path / "run")]
    before = listing(tmp_path)
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "fringecal.flows.cli", "run", *args], cwd=tmp_path, capture_output=True,
                          text=True, timeout=120)
    seconds = time.perf_counter() - t0
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.startswith("error: ") and len(proc.stderr.strip().splitlines()) == 1, proc.stderr
    assert message in proc.stderr and "Traceback" not in proc.stderr + proc.stdout
    assert seconds < 30, f"{seconds:.1f} s: refused too late"
    assert listing(tmp_path) == before


# -- what still works -------------------------------------------------------------------

def test_excel_bom_and_crlf_exports_read_like_plain_csv(tmp_path):
    from fringecal.artefact import load_artefact

    excel = write(tmp_path, "excel.csv", b"\xef\xbb\xbf" + ARTEFACT.read_bytes().replace(b"\n", b"\r\n"))
    a, b = load_artefact(ARTEFACT), load_artefact(excel)
    assert a.ids == b.ids and (a.centres == b.centres).all() and (a.diameters == b.diameters).all()
    res = CliRunner().invoke(app, ["pose", "-a", str(excel), "--centres", str(CENTRES), "-o", str(tmp_path / "p.csv")])
    assert res.exit_code == 0, res.output
    assert len(lines_of(tmp_path / "p.csv")) > 1
