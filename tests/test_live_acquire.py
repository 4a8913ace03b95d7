"""``fringecal acquire``: a live acquisition against the simulated control box served on a
pseudo-terminal (the driver opens a real tty path, as it would a USB serial adapter; the
box runs on the real clock) and a capture command that writes a small image stack
slowly, frame by frame. Full run, kill and resume, every fault, dry run."""

from __future__ import annotations

import itertools
import os
import select
import shlex
import shutil
import signal
import subprocess
import sys
import threading
import time
import tty
from collections import Counter
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml
from typer.testing import CliRunner

from fringecal.acquisition.live import TOLERANCE_MARGIN, reach_tolerance, stop_on_signals
from fringecal.acquisition.live_state import acquisition_lock
from fringecal.dataset import DataSet, DataSetError
from fringecal.flows.cli import app
from fringecal.frames import POSE_COLUMNS, Frame
from fringecal.fringe.importer import read_frames, write_frames
from fringecal.fringe.sequence import FringeSequence
from fringecal.hexapod import HexapodRig, load_hexapod_config
from fringecal.hexapod.kinematics import inverse_kinematics
from fringecal.hexapod.simulator import controller_for_url, get_controller
from fringecal.schemas import HexapodMovesTable, read_table

ROOT = Path(__file__).resolve().parents[1]
THESIS = ROOT / "configs" / "thesis"
SEQ = FringeSequence((8, 7), 3, ("x", "y"))  # 12 frames
W, H = 64, 48
SCANNERS = ("scanner1", "scanner2")
RIG = HexapodRig.from_config(load_hexapod_config())
runner = CliRunner()
_ids = itertools.count()

CAPTURE_SCRIPT = r'''
"""A scanner vendor's capture tool: copies a template stack into OUT slowly, frame by
frame, each frame file in two halves. Options key=value; a fault applies when its value
is "<measurement>:<scanner>"."""
import os, sys, time
template, out, measurement, scanner, log = sys.argv[1:6]
opts = dict(a.split("=", 1) for a in sys.argv[6:])
me = f"{measurement}:{scanner}"
with open(log, "a") as f:
    f.write(f"start {measurement} {scanner} {os.getpid()}\n")
delay = float(opts.get("slow_delay", "0.15") if opts.get("slow") == me else opts.get("delay", "0.01"))
if opts.get("fail") == me:
    print("vendor-scan 2.1: connecting to the camera", file=sys.stderr)
    print("[error] scanner offline: lamp error", file=sys.stderr)
    sys.exit(3)
names = sorted(n for n in os.listdir(template) if n.endswith(".png"))
if opts.get("skip") == me:
    names = names[:-1]
with open(os.path.join(template, "sequence.yaml"), "rb") as src, open(os.path.join(out, "sequence.yaml"), "wb") as dst:
    dst.write(src.read())
for i, name in enumerate(names):
    with open(os.path.join(template, name), "rb") as src:
        data = src.read()
    with open(os.path.join(out, name), "wb") as dst:
        dst.write(data[: len(data) // 2])
        dst.flush()
        time.sleep(delay)
        dst.write(data[len(data) // 2:])
    if opts.get("hang") == me and i == 2:
        time.sleep(3600)
    time.sleep(delay)
with open(os.path.join(out, "capture.txt"), "w") as f:
    f.write(str(os.getpid()))
with open(log, "a") as f:
    f.write(f"done {measurement} {scanner} {os.getpid()}\n")
'''


# -- the simulated box on a pseudo-terminal -------------------------------------------

class PtyBox:
    """The simulated control box behind a pseudo-terminal: a thread relays each line the
    driver writes to the slave to the box and writes the box's reply back. ``hook(line,
    box)`` sees each line first (to inject a fault at a given command)."""

    def __init__(self, hook=None):
        self.box = controller_for_url(f"hexsim://pty{next(_ids)}?clock=real&speed_mm_s=2000")
        self.hook = hook
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)
        self.path = os.ttyname(self.slave)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._relay, daemon=True)
        self._thread.start()

    def _relay(self):
        buf = bytearray()
        while not self._stop.is_set():
            if not select.select([self.master], [], [], 0.05)[0]:
                continue
            buf += os.read(self.master, 4096)
            while b"\n" in buf:
                i = buf.index(b"\n") + 1
                line, buf = bytes(buf[:i]), buf[i:]
                if self.hook is not None:
                    self.hook(line, self.box)
                reply = self.box.handle(line)
                if reply:
                    os.write(self.master, reply)

    def commands(self) -> list[str]:
        """Every line received, checksum removed."""
        return [text.rpartition("*")[0] if "*" in text else text for _, text in self.box.log]

    def close(self):
        self._stop.set()
        self._thread.join()
        os.close(self.master)
        os.close(self.slave)


@pytest.fixture
def pty_box():
    boxes = []

    def make(hook=None):
        boxes.append(PtyBox(hook))
        return boxes[-1]

    yield make
    for b in boxes:
        b.close()


# -- the data set and the capture tool --------------------------------------------------

def build_dataset(root: Path, n_poses: int = 3) -> Path:
    """dataset.yaml, artefact.csv, sensors_prior.csv (two thesis scanners, 64x48 px cameras),
    poses_planned.csv (the first poses of table 6-1)."""
    root.mkdir(parents=True)
    (root / "dataset.yaml").write_text(yaml.safe_dump({"name": "live", "reference_scanner": "scanner1"}))
    shutil.copy(THESIS / "artefact_cmm2.csv", root / "artefact.csv")
    prior = pd.read_csv(THESIS / "sensors_refined_table6-8.csv", dtype=str)
    cams = prior["role"] == "camera"
    prior.loc[cams, "width_px"], prior.loc[cams, "height_px"] = str(W), str(H)
    prior.to_csv(root / "sensors_prior.csv", index=False)
    poses = pd.read_csv(THESIS / "poses_scanner1_table6-1.csv", dtype={"measurement": str}).iloc[:n_poses]
    poses[["measurement", *POSE_COLUMNS]].to_csv(root / "poses_planned.csv", index=False)
    return root


class Tool:
    """The capture tool: its template stack, its log, and the --capture template."""

    def __init__(self, d: Path, width: int = W, height: int = H):
        d.mkdir(parents=True, exist_ok=True)
        self.script = d / "vendor_scan.py"
        self.script.write_text(CAPTURE_SCRIPT)
        self.template = d / f"template_{width}x{height}"
        rng = np.random.default_rng(7)
        write_frames(self.template, rng.integers(500, 3500, (SEQ.n_frames, height, width)).astype(np.uint16),
                     SEQ, 12, fmt="png")
        self.log = d / "capture.log"
        self.log.touch()

    def command(self, **opts) -> str:
        args = [sys.executable, str(self.script), str(self.template), "{out}", "{measurement}", "{scanner}",
                str(self.log), *(f"{k}={v}" for k, v in opts.items())]
        return " ".join(shlex.quote(a) if "{" not in a else a for a in args)

    def events(self, kind: str = "start") -> list[tuple[str, str, int]]:
        out = []
        for line in self.log.read_text().splitlines():
            k, m, s, pid = line.split()
            if k == kind:
                out.append((m, s, int(pid)))
        return out

    def running(self, pid: int) -> bool:
        """Whether ``pid`` is still this tool's capture (a live process running the script)."""
        try:
            cmdline = Path(f"/proc/{pid}/cmdline").read_bytes()
            state = Path(f"/proc/{pid}/stat").read_text().rpartition(")")[2].split()[0]
        except OSError:
            return False
        return str(self.script).encode() in cmdline and state != "Z"

    def starts(self) -> Counter:
        return Counter((m, s) for m, s, _ in self.events("start"))


@pytest.fixture
def tool(tmp_path) -> Tool:
    return Tool(tmp_path / "vendor")


def acquire(ds: Path, url: str, capture: str, *more: str):
    res = runner.invoke(app, ["acquire", "--dataset", str(ds), "--hexapod", url, "--capture", capture,
                              "--settle", "0", *more])
    return res, " ".join(res.output.split())


def listing(root: Path) -> list[str]:
    return sorted(str(p.relative_to(root)) for p in root.rglob("*"))


def moves_table(ds: Path) -> pd.DataFrame:
    return read_table(ds / "hexapod_moves.csv", HexapodMovesTable).set_index("measurement")


def only_queries_after_one_move(box: PtyBox) -> bool:
    """The box received one MOVEALL, and nothing but POS? after it."""
    commands = box.commands()
    moves = [i for i, c in enumerate(commands) if c.startswith(("MOVE", "HOME", "STOP"))]
    return len(moves) == 1 and commands[moves[0]].startswith("MOVEALL") and \
        set(commands[moves[0] + 1:]) == {"POS?"}


def staging(ds: Path) -> list[Path]:
    return [p for p in (ds / "measurements").glob("*/.*") if p.is_dir()]


# -- the full acquisition -----------------------------------------------------------------

@pytest.mark.slow
def test_full_acquisition_gives_a_data_set_and_the_reached_poses(tmp_path, tool, pty_box):
    ds = build_dataset(tmp_path / "ds")
    box = pty_box()
    res, out = acquire(ds, box.path, tool.command(), "--settle", "0.1")
    assert res.exit_code == 0, out
    opened = DataSet.open(ds)
    assert opened.measurement_names() == ["1", "2", "3"] and opened.scanners == SCANNERS
    assert opened.hexapod_moves == ds / "hexapod_moves.csv"
    assert tool.starts() == {(m, s): 1 for m in "123" for s in SCANNERS}
    assert not staging(ds)
    # every stack is the vendor's, frame for frame
    want = read_frames(tool.template).frames
    for src in opened.measurements:
        np.testing.assert_array_equal(read_frames(src.path).frames, want)
    # the hexapod log: planned as in poses_planned.csv, reached from the counts the box ended at
    moves = moves_table(ds)
    planned = pd.read_csv(ds / "poses_planned.csv", dtype={"measurement": str}).set_index("measurement")
    commands = box.commands()
    targets = [c for c in commands if c.startswith("MOVEALL")]
    assert len(targets) == 3
    for m, target in zip("123", targets):
        row = moves.loc[m]
        T_planned = Frame.from_params(planned.loc[m, list(POSE_COLUMNS)].to_numpy(float))
        np.testing.assert_allclose([row[f"planned_{c}"] for c in POSE_COLUMNS], T_planned.params, atol=1e-9)
        counts = np.array([row[f"counts_{i}"] for i in range(1, 7)])
        want_counts, pose = RIG.counts_for(T_planned)
        assert target.split()[1:] == [str(c) for c in want_counts]
        assert np.abs(counts - want_counts).max() <= RIG.config.actuator.position_tolerance_counts
        T_reached, _ = RIG.artefact_pose_from_counts(counts, near=pose)
        np.testing.assert_allclose([row[c] for c in POSE_COLUMNS], T_reached.params, atol=1e-6)
        dt, dr = T_reached.difference(T_planned)
        assert row.translation_error_mm == pytest.approx(dt, abs=1e-6)
        assert dt <= row.tolerance_mm and dr <= row.tolerance_rad
        assert (row.tolerance_mm, row.tolerance_rad) == pytest.approx(reach_tolerance(RIG, pose), rel=1e-8)
        assert row.moves == 1 and row.hexapod
    np.testing.assert_array_equal(counts, box.box.encoder_counts())  # the last row is where the box stands
    # a rerun has nothing to do: nothing moved, nothing captured
    before = len(commands)
    res, out = acquire(ds, box.path, tool.command())
    assert res.exit_code == 0, out
    assert "measurement 3: complete, skipped" in out
    assert tool.starts() == {(m, s): 1 for m in "123" for s in SCANNERS}
    assert all(not c.startswith(("MOVE", "HOME")) for c in box.commands()[before:])


def test_reach_tolerance_bounds_every_count_error_the_driver_accepts():
    """Truth: forward kinematics at every corner of the accepted count-error box (tolerance
    + 0.5 counts of rounding per leg) lands within the bound; the worst corner is the bound
    without its margin (the linearisation is exact to 0.1 %)."""
    planned = pd.read_csv(THESIS / "poses_scanner1_table6-1.csv")
    cpm, tol = RIG.config.actuator.counts_per_mm, RIG.config.actuator.position_tolerance_counts
    corners = np.array(list(itertools.product([-1.0, 1.0], repeat=6))) * (tol + 0.5)
    for params in planned[list(POSE_COLUMNS)].to_numpy(float)[[0, 5, 11]]:
        pose = RIG.platform_pose_for(Frame.from_params(params))
        T = RIG.artefact_pose_for(pose)
        exact = (inverse_kinematics(RIG.config.platform, pose) - RIG.config.actuator.retracted_length_mm) * cpm
        errors = np.array([T.difference(RIG.artefact_pose_from_counts(exact + c, near=pose)[0]) for c in corners])
        bound = np.array(reach_tolerance(RIG, pose))
        assert np.all(errors.max(axis=0) <= bound)
        np.testing.assert_allclose(errors.max(axis=0), bound / TOLERANCE_MARGIN, rtol=1e-3)  # the worst corner


# -- interrupting and resuming ------------------------------------------------------------

def test_sigint_and_sigterm_only_request_a_stop():
    before = signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)
    for sig in (signal.SIGTERM, signal.SIGINT):
        with stop_on_signals() as stop:
            assert not stop.wait(0.01)
            os.kill(os.getpid(), sig)
            assert stop.wait(5.0) and stop.reason == sig.name
    assert (signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)) == before


def _cli(ds, url, capture):
    return subprocess.Popen([sys.executable, "-m", "fringecal.flows.cli", "acquire", "--dataset", str(ds), "--hexapod", url,
                             "--capture", capture, "--settle", "0"], cwd=ROOT, start_new_session=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _wait_for(condition, what: str, timeout: float = 40.0):
    end = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < end, f"timed out waiting for {what}"
        time.sleep(0.02)


def _frames_in_staging(ds: Path, m: str, s: str) -> int:
    """Frame files in the staging folder of (m, s) (0 when there is none)."""
    return max((len(list(p.glob("*.png"))) for p in staging(ds) if p.parent.name == m
                and p.name.startswith(f".{s}.")), default=0)


@pytest.mark.slow
def test_sigint_stops_cleanly_and_sigkill_loses_nothing_complete(tmp_path, tool, pty_box):
    ds = build_dataset(tmp_path / "ds")
    box = pty_box()
    # SIGINT (Ctrl-C) while scanner2 of measurement 1 is capturing: a clean, resumable stop
    def interrupt():
        _wait_for(lambda: _frames_in_staging(ds, "1", "scanner2") >= 2, "capture 1/scanner2")
        os.kill(os.getpid(), signal.SIGINT)

    threading.Thread(target=interrupt, daemon=True).start()
    res, out = acquire(ds, box.path, tool.command(slow="1:scanner2"))
    assert res.exit_code == 130, out
    assert "interrupted by SIGINT: 0 of 3 measurements complete, nothing half-written" in out
    assert (ds / "measurements/1/scanner1/sequence.yaml").is_file()
    assert not (ds / "measurements/1/scanner2").exists() and not staging(ds)
    # SIGKILL of the command while scanner2 of measurement 2 is writing its frames
    proc = _cli(ds, box.path, tool.command(slow="2:scanner2"))
    _wait_for(lambda: _frames_in_staging(ds, "2", "scanner2") >= 2, "capture 2/scanner2")
    proc.kill()
    proc.communicate(timeout=30)
    half = [p for p in staging(ds) if p.parent.name == "2"]
    assert len(half) == 1 and not (ds / "measurements/2/scanner2").exists()
    assert list(moves_table(ds).index) == ["1"]
    # resume: measurement 1 is skipped, 2 is moved to again and captures scanner2 only
    res, out = acquire(ds, box.path, tool.command())
    assert res.exit_code == 0, out
    assert not half[0].exists() and not staging(ds)
    assert tool.starts() == {("1", "scanner1"): 1, ("1", "scanner2"): 2, ("2", "scanner1"): 1,
                             ("2", "scanner2"): 2, ("3", "scanner1"): 1, ("3", "scanner2"): 1}
    last = [pid for m, s, pid in tool.events() if (m, s) == ("2", "scanner2")][-1]
    assert (ds / "measurements/2/scanner2/capture.txt").read_text() == str(last)  # not the half-written one
    opened = DataSet.open(ds)
    assert [s.id for s in opened.measurements] == [f"{m}-{s}" for m in "123" for s in SCANNERS]
    for src in opened.measurements:
        assert read_frames(src.path).frames.shape == (SEQ.n_frames, H, W)
    moves = moves_table(ds)
    assert list(moves.index) == ["1", "2", "3"] and list(moves.moves) == [2, 2, 1]
    targets = [c for c in box.commands() if c.startswith("MOVEALL")]
    assert len(targets) == 5 and targets[0] == targets[1] and targets[2] == targets[3]
    orphan = [pid for m, s, pid in tool.events() if (m, s) == ("2", "scanner2")][0]
    _wait_for(lambda: not tool.running(orphan), "the orphaned capture to fail", timeout=10)  # its folder is gone


# -- faults ----------------------------------------------------------------------------

def test_failing_capture_stops_with_its_stderr(tmp_path, tool, pty_box):
    ds = build_dataset(tmp_path / "ds")
    box = pty_box()
    res, out = acquire(ds, box.path, tool.command(fail="1:scanner2"))
    assert res.exit_code == 4, out
    assert out.count("error:") == 1
    assert "measurement 1, scanner scanner2: the capture command exited with status 3" in out
    assert "[error] scanner offline: lamp error" in out
    assert (ds / "measurements/1/scanner1").is_dir() and not (ds / "measurements/1/scanner2").exists()
    assert not (ds / "hexapod_moves.csv").exists()
    assert tool.starts() == {("1", "scanner1"): 1, ("1", "scanner2"): 1}
    assert only_queries_after_one_move(box)


def test_retries_repeat_a_failed_capture_at_the_same_pose(tmp_path, tool, pty_box):
    ds = build_dataset(tmp_path / "ds", n_poses=1)
    box = pty_box()
    res, out = acquire(ds, box.path, tool.command(fail="1:scanner1"), "--retries", "1")
    assert res.exit_code == 4 and "(attempt 2 of 2)" in out and "retrying (1 of 1)" in out
    assert tool.starts() == {("1", "scanner1"): 2} and only_queries_after_one_move(box)


def test_capture_timeout_stops_the_command(tmp_path, tool, pty_box):
    ds = build_dataset(tmp_path / "ds")
    box = pty_box()
    res, out = acquire(ds, box.path, tool.command(hang="1:scanner1"), "--timeout", "1.5")
    assert res.exit_code == 4, out
    assert "measurement 1, scanner scanner1: the capture command was still running 1.5 s after it started" in out
    (pid,) = [p for _, _, p in tool.events()]
    assert not tool.running(pid)  # stopped and reaped
    assert not (ds / "measurements/1/scanner1").exists()
    assert only_queries_after_one_move(box)


def test_incomplete_stack_is_not_taken(tmp_path, tool, pty_box):
    ds = build_dataset(tmp_path / "ds")
    box = pty_box()
    res, out = acquire(ds, box.path, tool.command(skip="1:scanner2"), "--timeout", "1.5")
    assert res.exit_code == 4, out
    assert "measurement 1, scanner scanner2: incomplete image stack 1.5 s after the capture started" in out
    assert "y_008_02.png: missing frame (1 of 12 frames missing" in out
    assert (ds / "measurements/1/scanner1").is_dir() and not (ds / "measurements/1/scanner2").exists()
    with pytest.raises(DataSetError, match="scanner 'scanner2' has no frames in any measurement folder"):
        DataSet.open(ds)  # the kept staging folder is hidden: never used
    assert only_queries_after_one_move(box)


def test_wrong_stack_size_is_refused(tmp_path, pty_box):
    ds = build_dataset(tmp_path / "ds", n_poses=1)
    small = Tool(tmp_path / "vendor", 32, 24)
    box = pty_box()
    res, out = acquire(ds, box.path, small.command())
    assert res.exit_code == 4, out
    assert "images are 32x24 px, but the camera of scanner 'scanner1' in sensors_prior.csv is 64x48 px" in out
    assert small.starts() == {("1", "scanner1"): 1} and only_queries_after_one_move(box)


def test_hexapod_fault_on_the_pty_stops_everything(tmp_path, tool, pty_box):
    """The second move ends 40 counts off on leg 3: the driver stops the box, and nothing
    is sent after its STOP."""
    moves = itertools.count(1)

    def fault_on_second_move(line, box):
        if line.startswith(b"MOVEALL") and next(moves) == 2:
            box.fault, box.fault_after, box.fault_leg = "mismatch", box.n_received, 3

    ds = build_dataset(tmp_path / "ds")
    box = pty_box(fault_on_second_move)
    res, out = acquire(ds, box.path, tool.command())
    assert res.exit_code == 1, out
    assert "measurement 2: hexapod stopped: encoders disagree with the target beyond 2 counts (leg 3 +40)" in out
    commands = box.commands()
    second = [i for i, c in enumerate(commands) if c.startswith("MOVEALL")][1]
    assert set(commands[second + 1:-1]) == {"POS?"} and commands[-1] == "STOP"
    assert tool.starts() == {("1", "scanner1"): 1, ("1", "scanner2"): 1}
    assert list(moves_table(ds).index) == ["1"]
    assert not (ds / "measurements/2").exists()


def test_hexapod_stall_on_hexsim(tmp_path, tool):
    ds = build_dataset(tmp_path / "ds")
    name = f"live{next(_ids)}"
    res, out = acquire(ds, f"hexsim://{name}?fault=stall&leg=2", tool.command())
    assert res.exit_code == 1, out
    assert "measurement 1: hexapod stopped: no encoder progress for 25 polls" in out
    log = [t.rpartition("*")[0] for _, t in get_controller(name).log]
    assert sum(t.startswith("MOVEALL") for t in log) == 1 and log[-1] == "STOP"
    assert tool.starts() == {} and not (ds / "measurements").exists()


def test_pose_outside_the_workspace_is_refused_before_anything_moves(tmp_path, tool, pty_box):
    ds = build_dataset(tmp_path / "ds")
    poses = pd.read_csv(ds / "poses_planned.csv", dtype={"measurement": str})
    poses.loc[1, "tx_mm"] += 400.0
    poses.to_csv(ds / "poses_planned.csv", index=False)
    before = listing(ds)
    box = pty_box()
    res, out = acquire(ds, box.path, tool.command())
    assert res.exit_code == 2, out
    assert "1 planned pose(s) outside the hexapod's workspace; nothing was moved: measurement 2:" in out
    assert "stroke" in out or "joint" in out
    assert box.commands() == [] and tool.starts() == {} and listing(ds) == before


@pytest.mark.parametrize("template, message", [
    ("{python} {script} --scanner {scanner}", "no {out} placeholder"),
    ("{python} {script} {out} {scanners}", "unknown placeholder {scanners}"),
    ("no-such-vendor-scan {out}", "program 'no-such-vendor-scan' not found"),
    ("{python} 'unbalanced {out}", "cannot split it like a shell line"),
])
def test_bad_capture_template_is_refused_before_anything_moves(tmp_path, tool, pty_box, template, message):
    ds = build_dataset(tmp_path / "ds")
    box = pty_box()
    template = template.replace("{python}", sys.executable).replace("{script}", str(tool.script))
    res, out = acquire(ds, box.path, template)
    assert res.exit_code == 2 and message in out, out
    assert box.commands() == []


def test_bad_data_set_and_second_acquirer_are_refused(tmp_path, tool, pty_box):
    ds = build_dataset(tmp_path / "ds")
    box = pty_box()
    (ds / "measurements" / "7" / "scanner1").mkdir(parents=True)
    res, out = acquire(ds, box.path, tool.command())
    assert res.exit_code == 2 and f"{ds / 'measurements' / '7'}: measurement folder has no planned pose" in out
    shutil.rmtree(ds / "measurements" / "7")
    (ds / "measurements" / "2").mkdir()
    (ds / "measurements" / "2" / "scanner2").write_text("notes")
    res, out = acquire(ds, box.path, tool.command())
    assert res.exit_code == 2 and "a file where the stack of scanner 'scanner2' belongs" in out
    shutil.rmtree(ds / "measurements")
    with acquisition_lock(ds):
        res, out = acquire(ds, box.path, tool.command())
    assert res.exit_code == 2 and "another `fringecal acquire` is running on this data set" in out
    assert box.commands() == []


def test_moves_table_must_name_measurement_folders(tmp_path, tool, pty_box):
    ds = build_dataset(tmp_path / "ds", n_poses=1)
    res, out = acquire(ds, pty_box().path, tool.command())
    assert res.exit_code == 0, out
    moves = pd.read_csv(ds / "hexapod_moves.csv", dtype=str)
    moves.loc[0, "measurement"] = "9"
    moves.to_csv(ds / "hexapod_moves.csv", index=False)
    with pytest.raises(DataSetError, match="hexapod move of measurement '9', which has no measurement folder"):
        DataSet.open(ds)


# -- dry run ------------------------------------------------------------------------------

def test_dry_run_only_queries(tmp_path, tool, pty_box):
    ds = build_dataset(tmp_path / "ds")
    poses = pd.read_csv(ds / "poses_planned.csv", dtype={"measurement": str})
    box = pty_box()
    before = listing(ds)
    res = runner.invoke(app, ["acquire", "--dataset", str(ds), "--hexapod", box.path, "--dry-run",
                              "--capture", tool.command()])
    out = " ".join(res.output.split())
    assert res.exit_code == 0, out
    assert f"{box.box.name} 1.0 10000; encoders [5000, 5000, 5000, 5000, 5000, 5000] IDLE" in out
    assert "dry run ok: nothing moved, nothing captured; 3 measurement(s) to acquire" in out
    assert set(box.commands()) == {"ID?", "POS?"}
    # an unreachable pose: reported with the others, still only queries
    poses.loc[2, "tz_mm"] -= 800.0
    poses.to_csv(ds / "poses_planned.csv", index=False)
    before = listing(ds)
    res = runner.invoke(app, ["acquire", "--dataset", str(ds), "--hexapod", box.path, "--dry-run"])
    out = " ".join(res.output.split())
    assert res.exit_code == 2 and "dry run: 1 problem(s) would stop the acquisition: measurement 3: outside" in out
    assert set(box.commands()) == {"ID?", "POS?"} and listing(ds) == before
    assert tool.starts() == {}
