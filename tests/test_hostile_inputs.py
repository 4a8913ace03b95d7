"""The second bad-input battery (issue 31): a hostile but realistic user.

Every example of the issue, by class, as a case: the command, given the input, ends
with the documented status (2 for bad input), ONE line on stderr (``error: ...`` with
the file, folder, option or need), no traceback, and the folder it worked in --
the data set included -- listed exactly as before (names and sizes, hidden entries
too). A data set is a copy of the session's small simulated data set (frames
hard-linked, text files copied), damaged as the case says; ``fringecal run`` cases
stop before Prefect starts (its flow call is a trap). The cases that need a started
flow or a served deployment are in test_run_flow.py (a corrupt frame in the middle of
a stack, and the rerun) and test_serve.py (Ctrl-C, SIGTERM, the server gone).

Then: every command that writes stays in its output folder (path confinement), the
content digests found on read, the bounds refused in seconds, and the leftovers of a
killed ``fringecal simulate``.
"""

from __future__ import annotations

import errno
import json
import os
import shutil
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from fringecal.flows.cli import app
from fringecal.frames import POSE_COLUMNS
from fringecal.spheres.linking import LINK_COLUMNS

ROOT = Path(__file__).resolve().parents[1]
THESIS = ROOT / "configs" / "thesis"
ARTEFACT = THESIS / "artefact_cmm2.csv"
CENTRES = THESIS / "centres_scanner1_table6-3.csv"
SENSORS = THESIS / "sensors_refined_table6-8.csv"
BALLBAR_CENTRES = THESIS / "ballbar_verification_table6-9.csv"

runner = CliRunner()


# -- building inputs ------------------------------------------------------------------

def listing(root: Path) -> list[tuple[str, int]]:
    """Every entry under ``root`` (hidden ones too) with its size (-1 for folders)."""
    out = []
    for p in root.rglob("*"):
        try:
            size = p.lstat().st_size if not p.is_dir() or p.is_symlink() else -1
        except OSError:
            size = -2
        out.append((str(p.relative_to(root)), size))
    return sorted(out)


def write(d: Path, name: str, text: str | bytes) -> Path:
    p = d / name
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_bytes(text) if isinstance(text, bytes) else p.write_text(text)
    return p


def dataset(d: Path, small: Path) -> Path:
    """A copy of the small data set: frames hard-linked (never written through), text
    files and stores copied (the cases edit them)."""
    def copy(s, t):
        return os.link(s, t) if s.endswith(".png") else shutil.copy2(s, t)

    return Path(shutil.copytree(small, d / "ds", copy_function=copy))


def replace_lines(path: Path, edit: Callable[[list[str]], list[str]]) -> Path:
    path.write_text("\n".join(edit(path.read_text().splitlines())) + "\n")
    return path


def sensors_with_scanner(d: Path, name: str) -> Path:
    """The thesis's refined sensors with scanner1 renamed ``name``."""
    rows = SENSORS.read_text().splitlines()
    return write(d, "s.csv", "\n".join([rows[0]] + [r.replace(",scanner1,", f",{name},") for r in rows[1:]]) + "\n")


def calibration_json(d: Path, edit: Callable[[dict], None], covariance: bool = False) -> Path:
    """The thesis rig as a calibration.json (with a covariance when asked), edited."""
    from fringecal.calibration.file import rig_to_dict
    from fringecal.calibration.propagation import ParameterCovariances
    from fringecal.rig import load_rig

    rig = load_rig(SENSORS)
    n = 14 * len(rig.sensors)
    cov = ParameterCovariances(np.eye(n) * 1e-6, np.eye(n) * 1e-8, np.zeros(n), 0.0) if covariance else None
    doc = rig_to_dict(rig, covariances=cov)
    edit(doc)
    return write(d, "cal.json", json.dumps(doc))


def edited_run_calibration(d: Path) -> Path:
    """A run directory whose calibration.json (recorded by its bundle step) was edited
    afterwards: one digit, same size, its dates put back."""
    from fringecal.rig import load_rig
    from fringecal.rundir import RunDir
    from fringecal.steps.keys import digest_cache

    rd = RunDir(d / "run").create()
    rd.calibration.save(load_rig(SENSORS))
    rd.step_record("bundle", "").save({"step": "bundle", "item": "", "key": "k", "outputs": {
        rd.calibration.rel: digest_cache(rd).digest(rd.calibration.path)}})
    path, st = rd.calibration.path, rd.calibration.path.stat()
    path.write_text(path.read_text().replace("52.701", "52.702", 1))
    os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns))
    return rd.root


def _negative_variance(doc: dict) -> None:
    doc["covariance"]["adjustment"][8][8] = -1e-6  # C1's principal distance c


def _nan_parameter(doc: dict) -> None:
    doc["scanners"][1]["sensors"][0]["parameters"]["c"]["value"] = float("nan")


def rig_yaml(d: Path, sensors: Path) -> Path:
    """The thesis rig with another sensors table (every path absolute)."""
    rig = yaml.safe_load((THESIS / "rig.yaml").read_text())
    for k in ("sensors", "sensors_initial", "artefact", "rods", "artefact_poses", "ballbar", "materials"):
        rig[k] = str(THESIS / rig[k])
    rig["sensors"] = rig["sensors_initial"] = str(sensors)
    return write(d, "rig.yaml", yaml.safe_dump(rig))


def opencv_file(d: Path, key: str, value: str) -> Path:
    """scanner1 of the thesis rig as OpenCV writes it, with ``key: value``."""
    from fringecal.interop.opencv_storage import stereo_text
    from fringecal.rig import load_rig

    text, _, _ = stereo_text(load_rig(SENSORS).scanner("scanner1"))
    text = "\n".join(f"{key}: {value}" if ln.startswith(f"{key}:") else ln for ln in text.splitlines())
    return write(d, "scanner1.yml", text + "\n")


def tiny_stack(d: Path, damage: Callable[[np.ndarray], None] | None = None, bits: int = 16) -> Path:
    """A 12 x 20 px stack of 16-bit fringes (every frame at the same level), damaged."""
    from fringecal.fringe.importer import write_frames
    from fringecal.fringe.sequence import FringeSequence

    seq = FringeSequence((16, 15, 14, 12), 4)
    v, u = np.mgrid[0:12, 0:20]
    full = 2**bits - 1
    frames = np.stack([0.5 * full + 0.4 * full * np.cos(t * (u - 10) / 20 * 6 + 2 * np.pi * k / seq.n_steps)
                       for _, t, k in seq.frames()])
    frames = np.rint(frames).astype(np.uint16)
    if damage is not None:
        damage(frames)
    return write_frames(d / "stack", frames, seq, bits, fmt="png")


def _four_bits_short(frames: np.ndarray) -> None:
    frames[6] >>= 4  # x_015_02: one frame saved as 12-bit data in the 16-bit stack


def _double_trigger(frames: np.ndarray) -> None:
    frames[5] = frames[4]  # x_015_01 repeats x_015_00


def stack_folder(ds: Path, m: str = "5", scanner: str = "scanner1") -> Path:
    return ds / "measurements" / m / scanner


def decoded_in_place(ds: Path, m: str = "5", scanner: str = "scanner1") -> Path:
    """The stack of (m, scanner) replaced by its decoded store, as a data set may hold it."""
    from fringecal.fringe.measurement import decode_folder

    folder = stack_folder(ds, m, scanner)
    store = folder.with_name(f"{scanner}.zarr")
    decode_folder(folder, store)
    shutil.rmtree(folder)
    return store


def flip_a_byte(store: Path) -> Path:
    """One bit of one chunk of tau_x changed; size and modification time kept."""
    chunk = sorted((store / "tau_x").rglob("c/*/*"))[0]
    st = chunk.stat()
    data = bytearray(chunk.read_bytes())
    data[len(data) // 2] ^= 0x10
    chunk.write_bytes(bytes(data))
    os.utime(chunk, ns=(st.st_atime_ns, st.st_mtime_ns))
    return chunk


def duplicate_key(path: Path, key: str, value: str) -> Path:
    return replace_lines(path, lambda rows: rows + [f"{key}: {value}"])


def renamed_measurement(ds: Path, new: str) -> Path:
    (ds / "measurements" / "5").rename(ds / "measurements" / new)
    replace_lines(ds / "poses_planned.csv", lambda rows: [f"{new}," + r[2:] if r.startswith("5,") else r
                                                          for r in rows])
    return ds


def not_a_file(kind: str) -> Callable[[Path], Path]:
    def make(ds: Path) -> Path:
        frame = stack_folder(ds) / "x_016_03.png"
        frame.unlink()
        if kind == "fifo":
            os.mkfifo(frame)
        elif kind == "loop":
            os.symlink(frame.name, frame)
        else:
            os.symlink("/dev/null", frame)
        return frame
    return make


def alias_bomb(ds: Path) -> None:
    levels = ["a: &a [x, x, x, x, x, x, x, x, x, x]"] + [
        f"{b}: &{b} [" + ", ".join([f"*{a}"] * 10) + "]" for a, b in zip("abcdefgh", "bcdefghi")]
    text = (ds / "dataset.yaml").read_text()
    text = text.replace("processing:\n", "processing:\n  bundle:\n    bomb:\n" + "".join(f"      {ln}\n" for ln in levels))
    (ds / "dataset.yaml").write_text(text)


def many_spheres(d: Path, n: int = 1_000_000) -> Path:
    rows = [f"{i},{i * 0.1:.1f},0,0,50.8" for i in range(1, n + 1)]
    return write(d, "artefact.csv", "sphere_id,x_mm,y_mm,z_mm,diameter_mm\n" + "\n".join(rows) + "\n")


def many_rods(d: Path, n: int = 1_000_000) -> Path:
    rows = [f"r{i},1,2,1015.0" for i in range(n)]
    return write(d, "rods.csv", "rod_id,sphere_a,sphere_b,length_mm\n" + "\n".join(rows) + "\n")


# -- the cases ---------------------------------------------------------------------------

@dataclass(frozen=True)
class Case:
    id: str
    klass: int  # the class (1-7)
    args: Callable  # (work folder, small data set) -> command line
    message: str  # in the one line on stderr, after "error: "
    status: int = 2


def _run_ds(prepare: Callable[[Path], object]):
    """`fringecal run --dataset` on a damaged copy of the small data set."""
    def args(d: Path, small: Path):
        ds = dataset(d, small)
        prepare(ds)
        return ["run", "--dataset", ds, "--out", d / "run"]
    return args


CASES = [
    # 1. writes escape their folder
    Case("export-table-scanner-dotdot", 1, lambda d, s: ["export", "opencv", "--calibration",
                                                          sensors_with_scanner(d, "../../../../tmp/x"), "-o", d / "cv"],
         "s.csv: line 2, column 'scanner': value '../../../../tmp/x': a name must be one folder or file name: no '/'"),
    Case("export-table-scanner-absolute", 1, lambda d, s: ["export", "opencv", "--calibration",
                                                            sensors_with_scanner(d, "/tmp/x"), "-o", d / "cv"],
         "column 'scanner': value '/tmp/x': a name must be one folder or file name"),
    Case("export-calibration-json-scanner", 1, lambda d, s: [
        "export", "opencv", "--calibration",
        calibration_json(d, lambda doc: doc["scanners"][0].update(name="../../../../tmp/x")), "-o", d / "cv"],
         "cal.json: scanners[0] name '../../../../tmp/x': a name must be one folder or file name: no '/'"),
    Case("import-opencv-yaml-scanner", 1, lambda d, s: ["import", "opencv", "-s", opencv_file(d, "scanner", "/tmp/x"),
                                                         "-o", d / "prior.csv"],
         "scanner1.yml: scanner '/tmp/x': a name must be one folder or file name: no '/'"),
    Case("import-opencv-option-scanner", 1, lambda d, s: ["import", "opencv", "-s", opencv_file(d, "scanner", "s1"),
                                                           "--scanner", "..", "-o", d / "prior.csv"],
         "--scanner '..': '..' is not a name"),
    Case("simulate-config-scanner", 1, lambda d, s: [
        "simulate", "-o", d / "sim", "-c",
        write(d, "run.yaml", f"simulate:\n  rig: {rig_yaml(d, sensors_with_scanner(d, '../../../../tmp/x'))}\n")],
         "s.csv: line 2, column 'scanner': value '../../../../tmp/x'"),
    Case("run-poses-planned-measurement", 1, _run_ds(lambda ds: replace_lines(
        ds / "poses_planned.csv", lambda rows: [rows[0], "../../../../tmp/x" + rows[1][1:]] + rows[2:])),
         "poses_planned.csv: line 2, column 'measurement': value '../../../../tmp/x'"),
    # 2. silent corruption
    Case("run-store-flipped-byte", 2, _run_ds(lambda ds: flip_a_byte(decoded_in_place(ds))),
         "scanner1.zarr/tau_x/c/0/0: changed since the store was written"),
    Case("run-sequence-yaml-duplicate-key", 2, _run_ds(lambda ds: duplicate_key(
        stack_folder(ds, "9", "scanner2") / "sequence.yaml", "bit_depth", "16")),
         "9/scanner2/sequence.yaml: line 16: key 'bit_depth' is given twice (first on line 14)"),
    Case("run-dataset-yaml-second-reference", 2, _run_ds(lambda ds: duplicate_key(
        ds / "dataset.yaml", "reference_scanner", "scanner2")),
         "dataset.yaml: line 8: key 'reference_scanner' is given twice (first on line 2)"),
    Case("measure-negative-variance", 2, lambda d, s: [
        "measure", "--calibration", calibration_json(d, _negative_variance, covariance=True),
        "--stores", (d / "m").mkdir() or d / "m", "-o", d / "c.ply"],
         "cal.json: covariance 'adjustment': the variance of C1.c is -1e-06; a variance cannot be negative"),
    Case("measure-nan-parameter", 2, lambda d, s: [
        "measure", "--calibration", calibration_json(d, _nan_parameter), "--stores", (d / "m").mkdir() or d / "m",
        "-o", d / "c.ply"],
         "cal.json: scanner 'scanner2' sensor 'C2': parameter 'c' is nan; every parameter must be a finite number"),
    Case("export-run-calibration-edited", 2, lambda d, s: ["export", "opencv", "--run", edited_run_calibration(d),
                                                            "-o", d / "cv"],
         "run/calibration.json: changed since step bundle wrote it"),
    Case("decode-16-bit-frame-4-bits-short", 2, lambda d, s: ["decode", "-f", tiny_stack(d, _four_bits_short),
                                                              "-o", d / "m.zarr"],
         "stack/x_015_02.png: mean level"),
    Case("decode-double-trigger", 2, lambda d, s: ["decode", "-f", tiny_stack(d, _double_trigger), "-o", d / "m.zarr"],
         "stack/x_015_01.png: repeats the phase step before it"),
    # 3. failures that showed tracebacks (the started flow's are in test_run_flow.py)
    Case("run-measurement-name-250-characters", 3, _run_ds(lambda ds: renamed_measurement(ds, "m" * 250)),
         "folder name: 250 characters; a name has at most 100"),
    Case("run-header-only-sensors-prior", 3, _run_ds(lambda ds: replace_lines(ds / "sensors_prior.csv",
                                                                               lambda rows: rows[:1])),
         "sensors_prior.csv: no sensors (the table has a header and no rows)"),
    # 4. unbounded input
    Case("run-dataset-yaml-alias-bomb", 4, _run_ds(alias_bomb),
         "dataset.yaml: the document expands to more than 100,000 values through its aliases"),
    Case("run-artefact-a-million-spheres", 4, _run_ds(lambda ds: many_spheres(ds)),
         "artefact.csv: 1,000,000 rows; at most 200 can be used"),
    Case("run-a-million-rods", 4, _run_ds(lambda ds: many_rods(ds)),
         "rods.csv: 1,000,000 rows; at most 19,900 can be used"),
    # 5. the run directory and the data set
    Case("run-out-is-the-dataset", 5, lambda d, s: ["run", "--dataset", dataset(d, s), "--out", d / "ds"],
         "--out " + "{d}/ds: inside the data set"),
    Case("run-out-inside-the-dataset", 5, lambda d, s: ["run", "--dataset", dataset(d, s), "--out",
                                                         d / "ds" / "runs" / "a"], "/ds/runs/a: inside the data set"),
    Case("run-out-holds-the-dataset", 5, lambda d, s: ["run", "--dataset", dataset(d, s), "--out", d],
         ": holds the data set"),
    # 6. messages that mislead
    Case("semicolon-decimal-comma-csv", 6, lambda d, s: [
        "pose", "-a", write(d, "a.csv", ARTEFACT.read_text().replace(",", ";").replace(".", ",")),
        "--centres", CENTRES, "-o", d / "p.csv"],
         "a.csv: line 1: the columns are separated by semicolons, not commas"),
    Case("sensor-table-width-320.5", 6, lambda d, s: [
        "export", "opencv", "--calibration", write(d, "s.csv", SENSORS.read_text().replace(",2048,2048,", ",320.5,2048,",
                                                                                            1)), "-o", d / "cv"],
         "s.csv: line 2, column 'width_px': value '320.5' is not an integer"),
    Case("sequence-yaml-width-320.5", 6, _run_ds(lambda ds: replace_lines(
        stack_folder(ds) / "sequence.yaml", lambda rows: [r if not r.startswith("width_px") else "width_px: 320.5"
                                                          for r in rows])),
         "5/scanner1/sequence.yaml: width_px: Input should be a valid integer, got a number with a fractional part"),
    Case("frame-is-a-symlink-loop", 6, _run_ds(not_a_file("loop")), "x_016_03.png: a symbolic link loop, not a frame"),
    Case("frame-is-a-fifo", 6, _run_ds(not_a_file("fifo")), "x_016_03.png: a FIFO (named pipe), not a frame file"),
    Case("frame-is-a-device", 6, _run_ds(not_a_file("device")), "x_016_03.png: a character device, not a frame"),
    Case("dataset-yaml-bad-processing", 6, _run_ds(lambda ds: replace_lines(
        ds / "dataset.yaml", lambda rows: rows + ["  bundle:", "    gamma1: -1"])),
         "dataset.yaml: invalid configuration: processing.bundle.gamma1"),
    Case("reference-length-in-metres", 6, lambda d, s: ["verify", "ballbar", "--centres", BALLBAR_CENTRES,
                                                         "-L", "1.01565", "--mpe-mm", "0.1"],
         "--reference-length-mm 1.01565: the measured lengths average 1015.61 mm, 1000 times the reference: "
         "given in metres? (1015.65 mm)"),
]


@pytest.fixture
def trapped(monkeypatch):
    """`fringecal run` may validate but not start Prefect (its flow call is a trap)."""
    def trap(*args, **kwargs):
        raise AssertionError("the command went on to run the flow")

    monkeypatch.setattr("fringecal.flows.cli_run._execute", trap)


def one_line(res, status: int, message: str) -> str:
    """The one line on stderr: ``error: ...`` holding ``message``, exit ``status``, no traceback."""
    assert res.exit_code == status, res.output
    assert res.exception is None or isinstance(res.exception, SystemExit), repr(res.exception)
    assert "Traceback" not in res.output
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: "), res.stderr
    assert message in lines[0], lines[0]
    return lines[0]


@pytest.mark.parametrize("case", CASES, ids=[f"{c.klass}-{c.id}" for c in CASES])
def test_hostile_input_stops_with_one_line_and_changes_nothing(case, small_dataset, trapped, tmp_path, monkeypatch):
    work = tmp_path / "work"
    work.mkdir()
    monkeypatch.chdir(work)
    args = [str(a) for a in case.args(work, small_dataset[0])]
    before = listing(work)
    t0 = time.perf_counter()
    res = runner.invoke(app, args)
    seconds = time.perf_counter() - t0
    one_line(res, case.status, case.message.replace("{d}", str(work)))
    assert listing(work) == before
    assert seconds < 15, f"refused after {seconds:.1f} s"  # class 4: within seconds, not minutes


# -- 3. a second run, a full disk, a scanner that never sees three spheres --------------

def test_a_second_run_into_a_busy_run_directory_is_refused_at_once(small_config, tmp_path, monkeypatch):
    """Another process holds the run directory's lock (as a run does from before Prefect
    starts): status 2 (documented), one line, nothing written (issue 31: exit 1 and a
    traceback when the first run had not yet recorded itself)."""
    import fcntl

    from fringecal.rundir import RunDir

    def trap(*args, **kwargs):
        raise AssertionError("the command went on to start Prefect")

    monkeypatch.setattr("fringecal.flows.cli_run.make_task_runner", trap)
    monkeypatch.setattr("fringecal.run.warmup.start", lambda *needed: [])
    rd = RunDir(tmp_path / "run").create()
    fd = os.open(rd.lock.path, os.O_RDWR | os.O_CREAT)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)  # another open file description: another run, to flock
        before = listing(tmp_path)
        res = runner.invoke(app, ["run", "-c", str(small_config), "--out", str(rd.root)])
        one_line(res, 2, f"{rd.root}: another fringecal run is writing this run directory")
        assert listing(tmp_path) == before
    finally:
        os.close(fd)


def _enospc(path):
    def fail(*args, **kwargs):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))
    return fail


# ENOSPC under decode, measure and run: one line with the path, the free space and roughly
# what the command needs; status 2; nothing half-written (issue 31: exit 1 and up to 921 lines)

def test_a_full_disk_under_decode(small_dataset, tmp_path, monkeypatch):
    work = tmp_path / "work"
    work.mkdir()
    monkeypatch.setattr("xarray.Dataset.to_zarr", _enospc(work / "m.zarr"))
    before = listing(tmp_path)
    res = runner.invoke(app, ["decode", "-f", str(stack_folder(small_dataset[0])), "-o", str(work / "m.zarr")])
    line = one_line(res, 2, f"{work / 'm.zarr'}: no space left on the device (")
    assert "decoding 1 stack(s) needs roughly 2.46 MB in" in line  # 320 x 320 px x 6 maps x 4 bytes
    assert listing(tmp_path) == before


def test_a_full_disk_under_measure(small_dataset, tmp_path, monkeypatch):
    from fringecal.calibration.file import write_calibration_json
    from fringecal.fringe.measurement import decode_folder
    from fringecal.rig import load_rig

    work = tmp_path / "work"
    (work / "5").mkdir(parents=True)
    decode_folder(stack_folder(small_dataset[0]), work / "5" / "scanner1.zarr")
    cal = write_calibration_json(load_rig(small_dataset[0] / "sensors_prior.csv"), work / "cal.json")
    monkeypatch.setattr("fringecal.measure.run.write_cloud", _enospc(work / "c.ply"))
    before = listing(tmp_path)
    res = runner.invoke(app, ["measure", "--calibration", str(cal), "--stores", str(work / "5"), "-o",
                              str(work / "c.ply"), "--no-uncertainty"])
    line = one_line(res, 2, f"{work / 'c.ply'}: no space left on the device (")
    assert "the point cloud needs roughly 4.1 MB" in line  # 102,400 pixels x 40 bytes
    assert listing(tmp_path) == before


def test_a_full_disk_under_run(small_config, tmp_path, monkeypatch):
    work = tmp_path / "work"
    work.mkdir()
    monkeypatch.setattr("fringecal.flows.cli_run.make_task_runner", _enospc(work / "run" / "manifest.json"))
    monkeypatch.setattr("fringecal.run.warmup.start", lambda *needed: [])
    res = runner.invoke(app, ["run", "-c", str(small_config), "--out", str(work / "run")])
    line = one_line(res, 2, f"{work / 'run' / 'manifest.json'}: no space left on the device (")
    assert "the run needs roughly 91.8 MB in" in line  # 14 stores of 320 x 320 px x 64 bytes
    assert not (work / "run" / "manifest.json").exists()


def _unlinked_run(tmp_path, centres, poses, outcomes=None):
    """A run directory holding what the initialise step reads: the thesis's two scanners,
    labelled centres, their poses, scanner1 linked to itself only, and optionally the
    label outcomes."""
    import pandas as pd

    from fringecal.artefact import load_artefact
    from fringecal.rig import load_rig
    from fringecal.rundir import RunDir

    rd = RunDir(tmp_path / "run").create()
    rd.sensors_prior.save(load_rig(SENSORS))
    rd.artefact.save(load_artefact(ARTEFACT))
    rd.sphere_centres.save(centres)
    rd.poses.save(poses)
    links = [{"scanner": "scanner1", "reference": "scanner1", "tx_mm": 0.0, "ty_mm": 0.0, "tz_mm": 0.0,
              "omega_rad": 0.0, "phi_rad": 0.0, "kappa_rad": 0.0, "n_measurements": len(poses), "n_rejected": 0,
              "translation_spread_mm": 0.0, "rotation_spread_rad": 0.0, "u_translation_mm": 0.0,
              "u_rotation_rad": 0.0, "via": "scanner1"}] if len(poses) else []
    rd.scanner_links.save(pd.DataFrame(links, columns=list(LINK_COLUMNS)))
    ms = sorted(set(centres["measurement"]) | set(outcomes["measurement"] if outcomes is not None else []), key=int)
    rd.acquisition.save(pd.DataFrame([{"measurement": f"{m}-{s}", "kind": "artefact", "pose": m, "scanner": s,
                                       "store": f"measurements/{m}-{s}.zarr", "source": "simulated"}
                                      for m in ms for s in ("scanner1", "scanner2")]))
    if outcomes is not None:
        rd.label_outcomes.save(outcomes)
    return rd


def test_a_scanner_that_never_sees_three_spheres_is_named(small_config, tmp_path):
    """Scanner2 sees two spheres of each pose: its link to the reference scanner cannot
    exist; the step says so once, with the spheres it saw, and what would link it (issue
    31: a ValueError; issue 28: the reference listed as unlinked to itself)."""
    import pandas as pd

    from fringecal.spheres.pose import estimate_poses_file

    centres = pd.read_csv(CENTRES, dtype={"measurement": str, "sphere_id": str})
    two = centres.groupby("measurement").head(2).assign(scanner="scanner2")
    estimate_poses_file(ARTEFACT, CENTRES, tmp_path / "poses.csv")
    poses = pd.read_csv(tmp_path / "poses.csv", dtype={"measurement": str})
    rd = _unlinked_run(tmp_path, pd.concat([centres, two], ignore_index=True), poses)
    before = listing(tmp_path)
    res = runner.invoke(app, ["step", "initialise", "--run", str(rd.root), "-c", str(small_config)])
    line = one_line(res, 2, f"{rd.root}: 1 scanner(s) cannot be placed in the frame of the reference scanner "
                            "(scanner1): scanner scanner2: labelled spheres per measurement, most first: ")
    assert "A view needs three or more of the artefact's spheres" in line and "label_outcomes.csv" in line
    assert line.count("scanner2") == 1 and "scanner scanner1:" not in line
    assert listing(tmp_path) == before


def test_views_no_scanner_can_decide_without_a_plan_are_named_with_what_would(small_config, tmp_path):
    """Every view ambiguous and no plan (issue 28): one line naming the scanner that cannot
    be linked once (never the reference as unlinked), its measurements, and what would
    decide them -- the planned poses or more spheres per view; nothing written."""
    import pandas as pd

    ms = [str(m) for m in range(1, 13)]
    outcomes = pd.DataFrame([{"measurement": m, "scanner": s, "status": "refused", "reason": "ambiguous",
                              "method": "distances", "n_candidates": 4, "n_labelled": 0, "rms_mm": float("nan"),
                              "message": f"ambiguous: measurement {m}, scanner {s}, 4 candidate(s): ..."}
                             for m in ms for s in ("scanner1", "scanner2")])
    centres = pd.DataFrame(columns=["measurement", "scanner", "sphere_id", "x_mm", "y_mm", "z_mm"])
    poses = pd.DataFrame(columns=["measurement", "scanner", *POSE_COLUMNS, "rms_mm", "n_spheres"])
    rd = _unlinked_run(tmp_path, centres, poses, outcomes)
    before = listing(tmp_path)
    res = runner.invoke(app, ["step", "initialise", "--run", str(rd.root), "-c", str(small_config)])
    line = one_line(res, 2, f"{rd.root}: 1 scanner(s) cannot be placed in the frame of the reference scanner "
                            "(scanner1): the reference scanner scanner1 itself has no labelled view (ambiguous")
    assert "scanner scanner2: ambiguous" in line and line.count("scanner2") == 1
    assert "in measurement(s) 1, 2, 3, 4, 5, 6, ... (12 in all)" in line
    assert "The planned poses (poses_planned.csv in the data set) or views with more spheres" in line
    assert listing(tmp_path) == before


# -- every command that writes stays in its folder ----------------------------------------

#: every command, and how its writes stay in its output: ``contained``: run on valid
#: input, every new file lies inside its output (test_a_writing_command_writes_only_inside
#: _its_output); ``names``: it builds paths from names, each checked where it enters and
#: joined by ``confined`` (CASES of class 1, test_names_that_lead_out_are_refused_by_every
#: _writer); ``run directory``: every path through RunDir, which refuses one out of it
#: (test_run_directory_paths_stay_inside); ``its --out only``: it writes the one path the
#: user named, atomically; ``no file``: it writes nothing
WRITERS = {
    "pose": "contained", "fit sphere": "no file", "fit plane": "no file", "artefact truss": "contained",
    "artefact sag": "contained", "artefact thermal": "contained", "artefact rigidity": "no file",
    "artefact cte": "no file", "artefact moisture": "no file", "artefact cme": "no file",
    "artefact consistency": "contained", "hexapod plan": "contained", "hexapod ik": "no file",
    "hexapod fk": "no file", "hexapod workspace": "no file", "hexapod drift": "no file", "hexapod move": "no file",
    "hexapod run-file": "no file", "export opencv": "names", "import opencv": "names", "simulate": "names",
    "decode": "names", "measure": "its --out only", "verify ballbar": "no file", "verify plan": "run directory",
    "verify acceptance": "run directory", "run": "run directory", "reproduce": "run directory",
    "serve": "run directory", "step": "run directory", "calibrate": "run directory", "report": "run directory",
    "acquire": "names",
}


def _commands(group=None, prefix=""):
    import typer.main

    cmd = typer.main.get_command(app) if group is None else group
    for name, sub in getattr(cmd, "commands", {}).items():
        if getattr(sub, "commands", None):
            yield from _commands(sub, f"{prefix}{name} ")
        else:
            yield f"{prefix}{name}", sub


def test_every_command_is_listed_with_its_confinement():
    """A new command must say how its writes stay inside its output folder; one that
    writes nothing has no option naming an output."""
    commands = dict(_commands())
    assert sorted(commands) == sorted(WRITERS)
    assert sorted(c for c, how in WRITERS.items() if how == "contained") == sorted(set(CONTAINED) & set(WRITERS)
                                                                                  - {"export opencv"})
    for name, how in WRITERS.items():
        outputs = {o for p in commands[name].params for o in getattr(p, "opts", [])} & {"--out", "-o", "--commands"}
        assert (how == "no file") == (not outputs and name not in ("calibrate", "report", "step", "acquire",
                                                                      "verify acceptance")), name


CONTAINED = {
    "pose": lambda o: ["pose", "-a", ARTEFACT, "--centres", CENTRES, "-o", o / "p.csv"],
    "artefact truss": lambda o: ["artefact", "truss", "-o", o / "f.csv"],
    "artefact sag": lambda o: ["artefact", "sag", "--use-gravity", "0,-1,0", "-o", o / "s.csv"],
    "artefact thermal": lambda o: ["artefact", "thermal", "-t", "23.4", "-o", o / "a.csv"],
    "artefact consistency": lambda o: ["artefact", "consistency", "-o", o / "c.csv"],
    "hexapod plan": lambda o: ["hexapod", "plan", "-o", o / "plan.csv", "--commands", o / "moves.txt"],
    "export opencv": lambda o: ["export", "opencv", "--calibration", SENSORS, "-o", o / "cv"],
}


@pytest.mark.parametrize("command", sorted(CONTAINED))
def test_a_writing_command_writes_only_inside_its_output(command, tmp_path, monkeypatch):
    work, out = tmp_path / "work", tmp_path / "work" / "out"
    out.mkdir(parents=True)
    monkeypatch.chdir(work)
    before = listing(tmp_path)
    res = runner.invoke(app, [str(a) for a in CONTAINED[command](out)])
    assert res.exit_code == 0, res.output
    new = sorted(set(listing(tmp_path)) - set(before))
    assert new and all(p.startswith("work/out/") for p, _ in new), new


def test_names_that_lead_out_are_refused_by_every_writer(tmp_path):
    """The writers that build paths from names refuse one that leads out, before writing:
    OpenCV export (a rig whose name escaped every check), the data set export's folders,
    and a symbolic link inside the output folder that leads out of it."""
    from fringecal.interop.opencv_storage import write_rig
    from fringecal.names import OutsideFolderError, UnsafeNameError, confined
    from fringecal.rig import load_rig
    from fringecal.simulate.export import _folder

    rig = load_rig(SENSORS)
    object.__setattr__(rig.scanners[0], "name", "../x")  # as if a name had escaped every check
    with pytest.raises(UnsafeNameError, match=r"scanner '\.\./x': a name must be one folder or file name"):
        write_rig(rig, tmp_path / "cv")
    with pytest.raises(UnsafeNameError, match=r"folder name '/tmp/x'"):
        _folder(tmp_path, "measurements", "/tmp/x", "scanner1")
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "link").symlink_to(tmp_path.parent)
    with pytest.raises(OutsideFolderError, match=r"would be written outside"):
        confined(tmp_path / "out", "link", "scanner1.yml")
    assert sorted(p.name for p in tmp_path.rglob("*")) == ["link", "out"]  # nothing was written


def test_run_directory_paths_stay_inside(tmp_path):
    from fringecal.names import OutsideFolderError
    from fringecal.rundir import RunDir

    rd = RunDir(tmp_path / "run")
    for bad in ("../../x", "/tmp/x", "a/../../x"):
        with pytest.raises(OutsideFolderError, match="outside the run directory"):
            rd.store(bad)
        with pytest.raises(OutsideFolderError):
            rd.truth.object(bad)
    assert rd.store("1-scanner1").path == tmp_path / "run" / "measurements" / "1-scanner1.zarr"


# -- content digests found on read ------------------------------------------------------

def test_a_changed_run_file_is_found_and_named(tmp_path):
    """A table a step wrote, changed afterwards (same size, its dates put back): the next
    step that reads it refuses it, naming the file and the step that wrote it; the flow
    recomputes it (current_record), saying so."""
    from fringecal.rundir import RunDir
    from fringecal.steps.keys import RunFileChanged, check_unchanged, digest_cache

    rd = RunDir(tmp_path / "run").create()
    rd.poses.save(_poses_table())
    rd.step_record("label", "").save({"step": "label", "item": "", "key": "k",
                                      "outputs": {rd.poses.rel: digest_cache(rd).digest(rd.poses.path)}})
    check_unchanged(rd, [rd.poses])
    text = rd.poses.path.read_text()
    st = rd.poses.path.stat()
    rd.poses.path.write_text(text.replace("0.5", "0.6", 1))
    os.utime(rd.poses.path, ns=(st.st_atime_ns, st.st_mtime_ns))
    with pytest.raises(RunFileChanged, match=r"tables/poses\.csv: changed since step label wrote it"):
        check_unchanged(rd, [rd.poses])


def _poses_table():
    import pandas as pd

    return pd.DataFrame([{"measurement": "1", "scanner": "scanner1", "tx_mm": 0.5, "ty_mm": 1.0, "tz_mm": 2.0,
                          "omega_rad": 0.1, "phi_rad": 0.2, "kappa_rad": 0.3, "rms_mm": 0.01, "n_spheres": 4}])


def test_the_digest_cache_sees_a_same_size_rewrite_with_its_mtime_put_back(tmp_path, monkeypatch):
    """The cache keyed on size, mtime and inode kept a rewritten file's old digest (stale
    results "up to date", --force no help); the change time, which no program can set
    back, is in the key now."""
    from fringecal import digests
    from fringecal.digests import DigestCache, digest_path

    monkeypatch.setattr(digests, "_RACY_NS", -10**18)  # every entry kept: only the signature decides
    f = tmp_path / "t.csv"
    f.write_text("a,b\n1,2\n")
    cache = DigestCache(tmp_path / ".digests")
    old = cache.digest(f)
    st = f.stat()
    time.sleep(0.01)
    f.write_text("a,b\n1,3\n")
    os.utime(f, ns=(st.st_atime_ns, st.st_mtime_ns))
    assert f.stat().st_size == st.st_size and f.stat().st_mtime_ns == st.st_mtime_ns
    assert cache.digest(f) == digest_path(f) != old
    assert DigestCache(tmp_path / ".digests").digest(f) == digest_path(f)  # the persisted entry too


# -- 4. bounds ------------------------------------------------------------------------------

def test_a_points_table_beyond_its_bound_is_refused_before_parsing(tmp_path, monkeypatch):
    """2**24 points (a 4096 x 4096 camera) is the bound; shown with a small one."""
    from fringecal.schemas import MAX_POINTS, PointsTable

    assert MAX_POINTS == 4096 * 4096
    monkeypatch.setattr(PointsTable, "_max_rows", 10)
    points = write(tmp_path, "p.csv", "x_mm,y_mm,z_mm\n" + "1,2,3\n" * 11)
    res = runner.invoke(app, ["fit", "sphere", "-p", str(points)])
    one_line(res, 2, "p.csv: 11 rows; at most 10 can be used (every pixel of a 4096 x 4096 camera")


def test_yaml_keeps_merges_and_refuses_recursion(tmp_path):
    from fringecal.config import ConfigError, read_yaml_mapping

    ok = write(tmp_path, "ok.yaml", "base: &b {a: 1, b: 2}\nuse:\n  <<: *b\n  b: 3\n")
    assert read_yaml_mapping(ok)["use"] == {"a": 1, "b": 3}
    with pytest.raises(ConfigError, match=r"loop\.yaml: line 1: an alias refers to the value that holds it"):
        read_yaml_mapping(write(tmp_path, "loop.yaml", "a: &x [1, *x]\n"))


# -- 5. a killed `fringecal simulate` ----------------------------------------------------

def test_the_next_simulate_removes_what_a_killed_one_left(tmp_path, monkeypatch):
    """Hidden temporaries of an export whose process is gone are removed (with a line
    saying so); those of a running export, and unmarked folders, are kept."""
    import subprocess
    import sys

    from fringecal.simulate.export import OWNER_FILE

    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    pid = int(dead.stdout)
    from fringecal.lifeline import process_start

    gone = tmp_path / ".old.0123456789ab.tmp"
    write(gone, "measurements/1/scanner1/x.png", b"\0" * 1000)
    write(gone, OWNER_FILE, json.dumps({"pid": pid, "start": "1", "host": os.uname().nodename}))
    alive = tmp_path / ".busy.0123456789ac.tmp"
    write(alive, OWNER_FILE, json.dumps({"pid": os.getpid(), "start": process_start(os.getpid()),
                                         "host": os.uname().nodename}))
    other = tmp_path / ".mine.0123456789ad.tmp"
    other.mkdir()
    calls = []
    monkeypatch.setattr("fringecal.simulate.export.write_dataset", lambda *a, **k: calls.append(a))
    res = runner.invoke(app, ["simulate", "-o", str(tmp_path / "new")])
    assert res.exit_code == 0, res.output
    assert f"removed {gone} (0 MB), left by an interrupted fringecal simulate" in res.stdout
    assert not gone.exists() and alive.exists() and other.exists() and len(calls) == 1


# -- 7. serving ----------------------------------------------------------------------------
# (Ctrl-C on a real `fringecal serve` with a real Prefect server: test_serve.py)

@pytest.fixture
def ending(monkeypatch):
    """serving._end records its line and status instead of ending the process."""
    import threading

    from fringecal.flows import serving

    ended = []
    done = threading.Event()

    def end(line, code):
        ended.append((line, code))
        done.set()

    monkeypatch.setattr(serving, "_end", end)
    return ended, done


def test_serve_says_once_that_the_server_is_gone(ending, tmp_path):
    """The watchdog's third unanswered health check in a row ends serving with one line
    (issue 31: 800 lines of warnings in three minutes, and never that the server was gone)."""
    import httpx

    from fringecal.flows import serving

    ended, done = ending
    answers = iter([200, 200, "down", 200, "down", "down", "down"])

    def get(url, timeout):
        assert url == "http://127.0.0.1:4200/api/health"
        a = next(answers, "down")
        if a == "down":
            raise httpx.ConnectError("connection refused")
        return httpx.Response(a)

    serving.watch_server("http://127.0.0.1:4200/api", tmp_path / "nightly", tmp_path / "nightly" / "fringecal.log",
                         poll_seconds=0.01, misses=3, get=get)
    assert done.wait(5)
    (line, code), = ended
    assert code == serving.EXIT_SERVER_GONE == 1
    assert line.startswith("error: the Prefect server at http://127.0.0.1:4200/api stopped answering (since ")
    assert f"its finished steps are kept in {tmp_path / 'nightly'} for the next run" in line


def test_sigterm_ends_serving_with_one_line_even_through_prefects_runner(ending, tmp_path):
    """SIGTERM reaches serve's handler even after Prefect's runner put its own in place
    (its graceful shutdown waited for the runs and ended with a traceback)."""
    import signal

    from prefect.runner.runner import Runner

    from fringecal.flows import serving

    ended, done = ending
    previous = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    handle = Runner.handle_sigterm
    try:
        serving.arm_signals(tmp_path / "nightly")
        signal.signal(signal.SIGTERM, Runner().handle_sigterm)  # what Runner.start does
        os.kill(os.getpid(), signal.SIGTERM)
        assert done.wait(5)
    finally:
        Runner.handle_sigterm = handle
        for s, h in previous.items():
            signal.signal(s, h)
    assert ended == [(f"stopped serving (SIGTERM); a run in progress was stopped, its finished steps are kept in "
                      f"{tmp_path / 'nightly'} for the next run", 143)]


def test_ending_serve_stops_every_process_it_started(tmp_path):
    """In a process of its own (here it would stop this test worker's helpers): a child
    and a grandchild that ignore nothing are gone within GRACE_SECONDS."""
    import subprocess
    import sys

    script = ("import subprocess, sys, time\n"
              "from fringecal.flows import serving\n"
              "child = subprocess.Popen([sys.executable, '-c', 'import subprocess, sys, time; "
              "subprocess.Popen([sys.executable, \\'-c\\', \\'import time; time.sleep(60)\\']); time.sleep(60)'])\n"
              "time.sleep(0.5)\n"
              "kids = serving._descendants(child.pid) + [child.pid]\n"
              "t0 = time.monotonic(); serving._stop_children()\n"
              "print(len(kids), all(not serving._alive(p) for p in kids), round(time.monotonic() - t0, 1))\n")
    res = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=30)
    n, gone, seconds = res.stdout.split()
    assert n == "2" and gone == "True" and float(seconds) < 3, res.stdout + res.stderr
