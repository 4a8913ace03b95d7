"""Interrupting ``fringecal run`` (issue 17, item 3).

SIGTERM while rendering and ``kill -9`` after the bundle adjustment (sphere extraction
was a third point until the test command needed the time), each followed by the same
command: no process of the command
outlives it (Prefect's temporary server, the kernel warm-up, the lifeline), the
interrupted writes' temporaries are gone after the next run, which says what it
reused, and the summary numbers are those of an uninterrupted run. SIGINT (a
terminal's Ctrl-C, sent to the whole process group; here while the ball-bar is
rendered, on a run whose progress lines go to a pipe and are checked too) and SIGTERM
end a run within seconds with one line and status 130 / 143.

The runs are subprocesses in sessions of their own, with a token in their
environment that every process they start inherits: a process still carrying it
after the command ended is an orphan.
"""

from __future__ import annotations

import json
import os
import re
import signal
import socket
import subprocess
import sys
import threading
import time
import uuid
from pathlib import Path

import pytest
from typer.testing import CliRunner

from fringecal import lifeline
from fringecal.flows import progress
from fringecal.flows.cli import app
from fringecal.run.resume import begin, finish, leftovers, remove_leftovers
from fringecal.rundir import RunDir

ROOT = Path(__file__).resolve().parents[1]
TAG = "FRINGECAL_INTERRUPT_TEST"
NUMBERS = ("n_measurements", "n_control_points", "rms_F_mm_before", "rms_F_mm_after", "rms_eps1_mm_after",
           "rms_eps2_mm_after", "one_part_in")
#: A signal ends the run within this many seconds (measured 0.3-0.5 s during rendering on 2 cores).
STOP_SECONDS = 6.0


def _tagged(token: str) -> list[tuple[int, str]]:
    """(pid, command line) of every live process whose environment carries the token."""
    found = []
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            env = (d / "environ").read_bytes().split(b"\0")
            state = (d / "stat").read_bytes().rsplit(b")", 1)[1].split()[0]
            cmd = (d / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
        except OSError:
            continue
        if f"{TAG}={token}".encode() in env and state != b"Z":
            found.append((int(d.name), cmd))
    return found


def _no_orphans(token: str, timeout: float = 10.0) -> list:
    """Wait until no process carries the token; return those left after ``timeout``."""
    deadline = time.monotonic() + timeout
    while (left := _tagged(token)) and time.monotonic() < deadline:
        time.sleep(0.1)
    return left


class Run:
    """``fringecal run -c CONFIG --out OUT --json`` as a subprocess in its own session."""

    def __init__(self, config: Path, out: Path, logs: Path, json_out: bool = True):
        self.token = uuid.uuid4().hex
        self.out = out
        self.cmd = [sys.executable, "-m", "fringecal.flows.cli", "run", "-c", str(config), "--out", str(out)]
        self.cmd += ["--json"] if json_out else []
        self.logs = logs
        self.n = 0

    def start(self) -> subprocess.Popen:
        self.n += 1
        self.stdout = self.logs / f"{self.out.name}-{self.n}.out"
        self.stderr = self.logs / f"{self.out.name}-{self.n}.err"
        with open(self.stdout, "wb") as o, open(self.stderr, "wb") as e:
            self.proc = subprocess.Popen(self.cmd, cwd=ROOT, env={**os.environ, TAG: self.token}, stdout=o,
                                         stderr=e, stdin=subprocess.DEVNULL, start_new_session=True)
        return self.proc

    def wait_for(self, what: str, predicate, timeout: float = 240.0) -> None:
        deadline = time.monotonic() + timeout
        while not predicate():
            assert self.proc.poll() is None, f"the run ended before {what}: {self.errors()}"
            assert time.monotonic() < deadline, f"no {what} within {timeout} s"
            time.sleep(0.02)

    def finish(self, timeout: float = 300.0) -> dict:
        """The finished run's summary; the small rig's verdict is NOT ACCEPTED (exit status 3:
        its 320 px lengths' U cannot prove conformance, tests/test_run_flow.py)."""
        self.proc.wait(timeout)
        assert self.proc.returncode == 3, self.errors()
        return json.loads(self.stdout.read_text())

    def errors(self) -> str:
        return self.stderr.read_text(errors="replace")[-3000:]


def _stores(out: Path):
    return lambda: any(p.name.endswith(".zarr") and not p.name.startswith(".")
                       for p in (out / "measurements").glob("*.zarr"))


def _first_fits(out: Path):
    return lambda: any((out / "tables" / "fits_first").glob("*.csv"))


def _calibrated(out: Path):
    return lambda: (out / "calibration.json").exists()


@pytest.fixture(scope="module")
def reference(small_run):
    """The summary of one uninterrupted run of the small rig: the numbers every resumed
    run must give (the session's run, tests/conftest.py: its steps run without Prefect,
    which the flow calls as they are, tests/test_run_flow.py). Asked for only once the
    resumed run has finished: the test's commands run meanwhile, while another test
    worker may still be making the session's run (tests/test_run_flow.py starts from it)."""
    return small_run[1]


@pytest.mark.flow
@pytest.mark.slow
def test_sigterm_then_kill_9_then_the_same_command_resumes_to_the_same_numbers(request, small_config, tmp_path):
    """SIGTERM while rendering (one line, status 143, within seconds), kill -9 once the
    bundle adjustment has written its outputs (no orphans), then the same command
    resumes to the uninterrupted run's numbers. (SIGINT: the test below.)"""
    out = tmp_path / "killed"
    run = Run(small_config, out, tmp_path)
    for point, reached, sig in (("rendering", _stores(out), signal.SIGTERM),
                                ("the bundle adjustment's outputs", _calibrated(out), signal.SIGKILL)):
        run.start()
        run.wait_for(point, reached)
        alive = _tagged(run.token)
        assert any("uvicorn" in cmd for _, cmd in alive), alive  # Prefect's temporary server was running
        assert any("fringecal.lifeline" in cmd for _, cmd in alive), alive
        t0 = time.monotonic()
        os.kill(run.proc.pid, sig)
        run.proc.wait(60)
        if sig == signal.SIGKILL:
            assert run.proc.returncode == -signal.SIGKILL
        else:
            assert run.proc.returncode == 128 + sig, run.errors()
            assert time.monotonic() - t0 < STOP_SECONDS
            lines = [line for line in run.errors().splitlines() if line.strip() and not line[:2].isdigit()]
            assert len(lines) == 1 and lines[0].startswith("interrupted: "), lines
        left = _no_orphans(run.token)
        assert left == [], f"orphans after {sig.name} during {point}: {left}"
        assert RunDir(out).in_progress.exists()  # the next run knows this one was interrupted
    # what a kill in the middle of a write leaves (whether or not these kills hit one)
    (out / "measurements" / ".1-scanner1.zarr.tmp-0123456789ab").mkdir()
    (out / "measurements" / ".1-scanner1.zarr.tmp-0123456789ab" / "zarr.json").write_text("{}")
    (out / "tables" / ".poses.csv.0123456789ab.tmp").write_text("measurement,sc")
    run.start()
    summary = run.finish()
    reference = request.getfixturevalue("reference")
    for key in NUMBERS:
        assert summary[key] == reference[key], key
    assert summary["verification"]["max_abs_error_mm"] == reference["verification"]["max_abs_error_mm"]
    assert summary["verification"]["within_mpe"] == reference["verification"]["within_mpe"]
    assert summary["verdict"] == reference["verdict"]
    assert summary["truth"] == reference["truth"]
    assert leftovers(out) == [] and not RunDir(out).in_progress.exists()
    reused = summary["resumed"]["reused"]
    assert reused == len(summary["tasks"]["cached"]) > 0 and summary["tasks"]["ran"]
    assert f"resumed: {reused} step instances reused from the interrupted run" in run.errors()
    assert _no_orphans(run.token) == []


#: the progress line after which the Ctrl-C test interrupts the run: the ball-bar is rendered next
RENDERED = r"render measurements 8/8 done \(\d+ s\)"


@pytest.mark.flow
@pytest.mark.slow
def test_ctrl_c_stops_a_run_into_a_pipe_within_seconds_with_one_line(small_run, small_config, tmp_path):
    """Ctrl-C in a terminal (SIGINT to the whole process group) while the ball-bar is
    rendered: status 130 within seconds, one line, no orphans; the run knows it was
    interrupted. (SIGTERM: the test above.)

    The run directory is a copy of the session's run of the small rig (tests/conftest.py)
    without its ball-bar stores and their records: the command reuses the measurements'
    stores (the same keys; rendering them again here cost about 8 CPU-s) and renders the
    ball-bar, the state this test interrupts.

    Its output goes to a pipe, as in CI or under nohup, with PYTHONUNBUFFERED and
    FRINGECAL_PROGRESS unset: up to the interruption its lines are those
    tests/test_progress.py asks of a run into a pipe (checked here, on this run, which
    saves a command's start-up)."""
    import shutil

    from test_progress import assert_a_run_into_a_pipe_says_what_it_does

    out, token = shutil.copytree(small_run[0].root, tmp_path / "run", symlinks=True), uuid.uuid4().hex
    for store in [*(out / "measurements").glob("bb*.zarr"), *(out / "truth" / "measurements").glob("bb*.zarr"),
                  out / ".steps" / "simulate-ballbar"]:
        shutil.rmtree(store)
    env = {k: v for k, v in os.environ.items() if k not in (progress.ENV, "PYTHONUNBUFFERED")}
    cmd = [sys.executable, "-m", "fringecal.flows.cli", "run", "-c", str(small_config), "--out", str(out)]
    t0 = time.monotonic()
    with open(tmp_path / "stderr", "wb") as err:
        proc = subprocess.Popen(cmd, cwd=ROOT, env={**env, TAG: token}, stdout=subprocess.PIPE, stderr=err,
                                stdin=subprocess.DEVNULL, text=True, start_new_session=True)
    lines = []
    reader = threading.Thread(target=lambda: lines.extend((time.monotonic() - t0, ln) for ln in proc.stdout))
    reader.start()
    stderr = (tmp_path / "stderr").read_text
    deadline = time.monotonic() + 240
    while not any(re.search(RENDERED, ln) for _, ln in list(lines)):
        assert proc.poll() is None, f"the run ended before its stores were rendered: {stderr()[-3000:]}"
        assert time.monotonic() < deadline, "no stores rendered within 240 s"
        time.sleep(0.02)
    said = list(lines)
    t1 = time.monotonic()
    os.killpg(proc.pid, signal.SIGINT)  # Ctrl-C in a terminal: the whole foreground process group
    proc.wait(60)
    seconds = time.monotonic() - t1
    reader.join()
    assert proc.returncode == 128 + signal.SIGINT, stderr()
    assert seconds < STOP_SECONDS, seconds
    errors = [line for line in stderr().splitlines() if line.strip()]
    assert len(errors) == 1, errors
    assert errors[0].startswith("interrupted: ") and errors[0].endswith(
        f"finished and kept in {out}; rerun the same command to resume"), errors[0]
    assert "Traceback" not in "".join(ln for _, ln in lines)
    assert _no_orphans(token, timeout=5.0) == []
    assert RunDir(out).in_progress.exists()
    assert_a_run_into_a_pipe_says_what_it_does(said, RENDERED)


# -- the parts -------------------------------------------------------------------------------

PARENT = """
import subprocess, sys, time
from fringecal import lifeline
from fringecal.flows import progress
from fringecal.run import warmup as kernel_warmup
kernel_warmup.cache_is_cold = lambda: True
(warm,) = kernel_warmup.start()
child = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(600)"])
lifeline.adopt(child)
print(warm.pid, child.pid, flush=True)
time.sleep(600)
"""


def test_adopted_processes_end_when_their_parent_is_killed():
    """The kernel warm-up and any adopted child end within seconds of a ``kill -9``
    of the process that started them (the lifeline)."""
    parent = subprocess.Popen([sys.executable, "-c", PARENT], cwd=ROOT, stdout=subprocess.PIPE, text=True,
                              start_new_session=True)
    try:
        pids = [int(p) for p in parent.stdout.readline().split()]
        assert len(pids) == 2 and all(lifeline.process_start(p) for p in pids)
    finally:
        os.kill(parent.pid, signal.SIGKILL)
        parent.wait()
    deadline = time.monotonic() + 10
    while any(lifeline.process_start(p) for p in pids) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert [p for p in pids if lifeline.process_start(p)] == []


def test_the_lifeline_never_signals_a_recycled_pid():
    child = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(600)"])
    try:
        start = lifeline.process_start(child.pid)
        assert lifeline.kill_recorded({child.pid: start + "0"}, grace=0.2) == []  # another process's start
        time.sleep(0.2)
        assert child.poll() is None
        assert lifeline.kill_recorded({child.pid: start}, grace=2) == [child.pid]
        assert child.wait(5) == -signal.SIGTERM
    finally:
        child.kill()
        child.wait()


def test_leftovers_are_the_interrupted_writes_and_nothing_else(tmp_path):
    rd = RunDir(tmp_path / "run").create()
    keep = [rd.root / "tables" / "poses.csv", rd.root / ".steps" / "bundle" / "_.json",
            rd.root / "measurements" / "1-scanner1.zarr" / "zarr.json", rd.root / ".digests" / "index.json",
            rd.root / ".prefect" / "bundle-0123", rd.root / "report.html"]
    gone = [rd.root / "tables" / ".poses.csv.0123456789ab.tmp", rd.root / ".digests" / ".index.json.a1b2c3d4e5f6.tmp",
            rd.root / "measurements" / ".2-scanner1.zarr.tmp-0123456789ab" / "x" / "c" / "0",
            rd.root / "maps" / ".1-scanner1.zarr.old-abcdef012345" / "zarr.json"]
    for p in keep + gone:
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text("x")
    expected = sorted([gone[0], gone[1], gone[2].parents[2], gone[3].parent])
    assert leftovers(rd.root) == expected
    assert remove_leftovers(rd.root) == expected
    assert leftovers(rd.root) == [] and all(p.exists() for p in keep)


@pytest.mark.slow
def test_a_run_directory_another_run_writes_is_refused_before_any_work(small_config, tmp_path):
    """A record of a live process of this host: ``begin`` refuses, and so does the
    command (status 2, one line, nothing written, before Prefect starts); a record of
    a process that ended means the last run was interrupted."""
    rd = RunDir(tmp_path / "run").create()
    writer = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(600)"])
    try:
        rd.in_progress.save({"pid": writer.pid, "start": lifeline.process_start(writer.pid),
                             "host": socket.gethostname(), "started_utc": "2025-01-01T00:00:00+00:00",
                             "command": "fringecal run"})
        before = sorted(p.name for p in rd.root.iterdir())
        res = CliRunner().invoke(app, ["run", "-c", str(small_config), "--out", str(rd.root)])
        assert res.exit_code == 2, res.output
        first = res.stderr.strip().splitlines()[0]  # stdout: what the run checks and where it goes
        assert first.startswith(f"error: {rd.root}: another fringecal run is writing this run directory (pid "
                                f"{writer.pid}"), first
        assert "Traceback" not in res.output
        assert sorted(p.name for p in rd.root.iterdir()) == before
        with pytest.raises(ValueError, match="another fringecal run"):
            begin(rd, "fringecal run")
    finally:
        writer.kill()
        writer.wait()
    previous = begin(rd, "fringecal run")  # the writer is gone: it was interrupted
    assert previous["pid"] == writer.pid
    assert rd.in_progress.load()["pid"] == os.getpid()
    finish(rd)
    assert not rd.in_progress.exists() and begin(rd, "fringecal run") is None
