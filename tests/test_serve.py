"""`fringecal serve` on a real Prefect server: a local server started here (private
PREFECT_HOME, a free port, API authentication on), the run flow served with a short
interval on a tiny simulated rig, and a scheduled run seen to start and finish; the
refusals without a server, with an unreachable one and with wrong credentials. Every
process started here is stopped with its children (no orphans)."""

from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import httpx
import psutil
import pytest
from typer.testing import CliRunner

from fringecal.flows.cli import app

pytestmark = pytest.mark.slow  # whole runs: the fast tier (-m "not slow") leaves this module out

runner = CliRunner()
BIN = Path(sys.executable).parent
USER, PASSWORD = "fringecal", "test-password"
SERVER_START_S = 180
RUN_DEADLINE_S = 300


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _env(home: Path, **settings: str) -> dict:
    """The test session's environment without any Prefect API setting, a private home."""
    env = {k: v for k, v in os.environ.items() if not k.startswith(("PREFECT_API_", "PREFECT_PROFILE"))}
    env.update(PREFECT_HOME=str(home), PREFECT_PROFILES_PATH=str(home / "profiles.toml"),
               PREFECT_SERVER_ANALYTICS_ENABLED="false", **settings)
    return env


def _stop(proc: subprocess.Popen) -> None:
    """SIGTERM the process and every descendant, SIGKILL what is left after 20 s."""
    try:
        procs = [psutil.Process(proc.pid)]
        procs += procs[0].children(recursive=True)
    except psutil.NoSuchProcess:
        procs = []
    for p in procs:
        try:
            p.send_signal(signal.SIGTERM)
        except psutil.NoSuchProcess:
            pass
    _, alive = psutil.wait_procs(procs, timeout=20)
    for p in alive:
        try:
            p.kill()
        except psutil.NoSuchProcess:
            pass
    psutil.wait_procs(alive, timeout=10)
    proc.wait(timeout=10)
    left = [p.pid for p in procs if p.is_running() and p.status() != psutil.STATUS_ZOMBIE]
    assert not left, f"processes outlived the test: {left}"


def _tail(path: Path, n: int = 40) -> str:
    return "\n".join(path.read_text(errors="replace").splitlines()[-n:]) if path.exists() else ""


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    """A Prefect server on 127.0.0.1 with basic authentication, as docs/guide.md shows."""
    home = tmp_path_factory.mktemp("prefect-server")
    port = _free_port()
    url = f"http://127.0.0.1:{port}/api"
    log = home / "server.log"
    env = _env(home, PREFECT_SERVER_API_AUTH_STRING=f"{USER}:{PASSWORD}", PREFECT_UI_ENABLED="false")
    with open(log, "w") as out:
        proc = subprocess.Popen([str(BIN / "prefect"), "server", "start", "--host", "127.0.0.1", "--port", str(port)],
                                env=env, stdout=out, stderr=subprocess.STDOUT, start_new_session=True)
    try:
        deadline = time.monotonic() + SERVER_START_S
        while True:
            if proc.poll() is not None:
                pytest.fail(f"the Prefect server exited with status {proc.returncode}:\n{_tail(log)}")
            try:
                if httpx.get(f"{url}/health", timeout=2).status_code == 200:
                    break
            except httpx.HTTPError:
                pass
            if time.monotonic() > deadline:
                pytest.fail(f"the Prefect server did not answer within {SERVER_START_S} s:\n{_tail(log)}")
            time.sleep(1)
        yield url
    finally:
        _stop(proc)


def _client_env(home: Path, url: str, auth: str = f"{USER}:{PASSWORD}") -> dict:
    return _env(home, PREFECT_API_URL=url, PREFECT_API_AUTH_STRING=auth, PREFECT_LOGGING_LEVEL="INFO")


def _tiny_config(d: Path) -> Path:
    """The small thesis rig with one ball-bar position: the pipeline in about 12 s without
    Prefect (320 px is the smallest width at which every scanner still links)."""
    from fringecal.simulate.small_thesis import write_small_thesis_config

    d.mkdir(parents=True, exist_ok=True)
    return write_small_thesis_config(d, positions=(1,), name="tiny")


def test_serve_refuses_without_a_server(tmp_path, monkeypatch):
    monkeypatch.delenv("PREFECT_API_URL", raising=False)
    monkeypatch.setenv("PREFECT_PROFILES_PATH", str(tmp_path / "no-profiles.toml"))
    monkeypatch.chdir(tmp_path)  # no prefect.toml here
    res = runner.invoke(app, ["serve", "--out", str(tmp_path / "nightly")])
    assert res.exit_code == 2, res.output
    lines = res.output.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in res.output
    assert lines[0].startswith("error: fringecal serve needs a Prefect server, and none is configured")
    assert "prefect server start --host 127.0.0.1" in lines[0] and "PREFECT_API_URL=" in lines[0]
    assert sorted(tmp_path.iterdir()) == []


def test_serve_refuses_an_unreachable_server(small_config, tmp_path, monkeypatch):
    url = f"http://127.0.0.1:{_free_port()}/api"  # nobody listens there
    monkeypatch.setenv("PREFECT_API_URL", url)
    res = runner.invoke(app, ["serve", "--config", str(small_config), "--out", str(tmp_path / "nightly")])
    assert res.exit_code == 2, res.output
    lines = res.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"error: the Prefect server at {url} does not answer (")
    assert not (tmp_path / "nightly").exists()


def test_serve_refuses_wrong_credentials(server, tmp_path):
    config = _tiny_config(tmp_path / "config")
    res = subprocess.run([str(BIN / "fringecal"), "serve", "--config", str(config), "--out", str(tmp_path / "nightly")],
                         env=_client_env(tmp_path / "home", server, auth=f"{USER}:wrong"), capture_output=True,
                         text=True, timeout=120)
    assert res.returncode == 2, res.stdout + res.stderr
    assert res.stderr.strip() == (f"error: the Prefect server at {server} refuses fringecal's credentials (HTTP 401): "
                                  "set PREFECT_API_AUTH_STRING to its PREFECT_SERVER_API_AUTH_STRING (user:password)")
    assert not (tmp_path / "nightly").exists()


def test_a_scheduled_run_starts_and_finishes(server, small_run, tmp_path):
    """The served run goes into a copy of the session's run of the small rig
    (tests/conftest.py), as a nightly run goes into last night's run directory: the
    tiny rig is that rig with one ball-bar position, so its stores and its adjustment
    are current there and the scheduled run renders nothing and adjusts nothing again
    (about 12 CPU-s less); it verifies, judges and reports, and finishes as before."""
    # nobody without the password reads or triggers runs; the health probe answers anyone
    assert httpx.post(f"{server}/flow_runs/filter", json={}, timeout=10).status_code == 401
    assert httpx.get(f"{server}/health", timeout=10).status_code == 200
    config = _tiny_config(tmp_path / "config")
    out = shutil.copytree(small_run[0].root, tmp_path / "nightly", symlinks=True)
    log = tmp_path / "serve.log"
    # a 2 s interval and the runner asking for due runs every second (Prefect's default: 10 s):
    # the first scheduled run starts about 3 s after serving starts instead of 10-20 s
    env = {**_client_env(tmp_path / "home", server), "PREFECT_RUNNER_POLL_FREQUENCY": "1"}
    with open(log, "w") as f:
        proc = subprocess.Popen([str(BIN / "fringecal"), "serve", "--config", str(config), "--out", str(out),
                                 "--interval", "2", "--name", "test-serve"],
                                env=env, stdout=f, stderr=subprocess.STDOUT, start_new_session=True)
    try:
        run = _wait_for_a_finished_scheduled_run(server, proc, log)
        _ctrl_c_stops_serving_within_seconds(proc, log, out)
    finally:
        _stop(proc)
    auth = (USER, PASSWORD)
    deployment = httpx.get(f"{server}/deployments/{run['deployment_id']}", auth=auth, timeout=10).json()
    assert deployment["name"] == "test-serve" and run["auto_scheduled"]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["command"] == "scheduled test-serve" and summary["name"] == "tiny"
    assert summary["verification"]["n_lengths"] >= 1 and summary["n_measurements"] == 8
    # the tiny rig's length cannot prove conformance (its U is larger than the MPE): the run
    # wrote everything, and its state says NOT ACCEPTED, as summary.json does
    assert summary["verdict"]["accepted"] is False and (out / "report.html").exists()
    assert run["state_type"] == "FAILED"
    assert run["state"]["message"].startswith(f"NOT ACCEPTED: {summary['verdict']['failing']} (")


def _ctrl_c_stops_serving_within_seconds(proc: subprocess.Popen, log: Path, out: Path) -> None:
    """Ctrl-C (SIGINT): serving ends within 5 s (it hung 60 s before issue 31), status 130,
    and the terminal shows the serving line and one line saying it stopped -- Prefect's
    output is in OUT/fringecal.log -- with every process serve started gone."""
    kids = psutil.Process(proc.pid).children(recursive=True)
    t0 = time.monotonic()
    proc.send_signal(signal.SIGINT)
    status = proc.wait(timeout=30)
    seconds = time.monotonic() - t0
    assert status == 130 and seconds < 5, (status, seconds, _tail(log))
    lines = [ln for ln in log.read_text().splitlines() if ln.strip()]
    assert len(lines) == 2 and lines[0].startswith("serving deployment 'test-serve'"), lines
    assert lines[1] == (f"stopped serving (SIGINT); a run in progress was stopped, its finished steps are kept in "
                        f"{out} for the next run")
    assert (out / "fringecal.log").stat().st_size > 0
    _, alive = psutil.wait_procs(kids, timeout=5)
    assert not [p for p in alive if p.status() != psutil.STATUS_ZOMBIE], alive


def _wait_for_a_finished_scheduled_run(url: str, proc: subprocess.Popen, log: Path) -> dict:
    """Poll the server until a run of a deployment created by its scheduler ends:
    Completed, or Failed with the run's verdict (NOT ACCEPTED) as its message; a run
    that crashed or failed with an error fails the test."""
    deadline = time.monotonic() + RUN_DEADLINE_S
    seen = {}
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            pytest.fail(f"fringecal serve exited with status {proc.returncode}:\n{_tail(log)}")
        ended = {"flow_runs": {"state": {"type": {"any_": ["COMPLETED", "FAILED", "CRASHED"]}}}}
        res = httpx.post(f"{url}/flow_runs/filter", json=ended, auth=(USER, PASSWORD), timeout=10)
        res.raise_for_status()
        for run in res.json():
            seen[run["id"]] = run["state_type"]
            verdict = run["state_type"] == "FAILED" and (run.get("state") or {}).get("message", "").startswith(
                "NOT ACCEPTED")
            if run["deployment_id"] and (run["state_type"] == "COMPLETED" or verdict):
                return run
            if run["state_type"] in ("FAILED", "CRASHED"):
                message = (run.get("state") or {}).get("message", "")
                pytest.fail(f"scheduled run {run['name']} {run['state_type']} ({message}):\n{_tail(log, 80)}")
        time.sleep(0.5)
    pytest.fail(f"no scheduled run finished within {RUN_DEADLINE_S} s (runs: {seen}):\n{_tail(log, 80)}")
