"""Progress of a run: rich bars on a terminal, timestamped lines otherwise, a compile line
that ticks while numba compiles, and a first line before anything heavy loads (a whole
run into a pipe: :func:`assert_a_run_into_a_pipe_says_what_it_does`, on the run that
tests/test_interrupt.py stops with Ctrl-C)."""

from __future__ import annotations

import io
import os
import re
import subprocess
import sys
import time

import pytest
from rich.console import Console
from typer.testing import CliRunner

from fringecal import compile_clock
from fringecal.flows import progress
from fringecal.flows.cli import app

STAMP = re.compile(r"^\d\d:\d\d:\d\d ")


def _plain(**settings) -> tuple[progress.PlainProgress, io.StringIO]:
    out = io.StringIO()
    reporter = progress.PlainProgress(Console(file=out))
    for k, v in settings.items():
        setattr(reporter, k, v)
    return reporter, out


def test_the_reporter_follows_the_terminal_unless_forced(monkeypatch):
    monkeypatch.delenv(progress.ENV, raising=False)
    pipe, terminal = Console(file=io.StringIO()), Console(file=io.StringIO(), force_terminal=True)
    assert isinstance(progress.choose(None, pipe), progress.PlainProgress)
    assert isinstance(progress.choose(None, terminal), progress.RichProgress)
    assert isinstance(progress.choose("plain", terminal), progress.PlainProgress)
    monkeypatch.setenv(progress.ENV, "none")
    assert isinstance(progress.choose(None, terminal), progress.Silent)
    assert isinstance(progress.choose("rich", pipe), progress.RichProgress)  # the option wins
    with pytest.raises(ValueError, match="one of auto, rich, plain, none, not 'bars'"):
        progress.choose("bars", pipe)


def test_bad_progress_modes_are_input_errors(monkeypatch, tmp_path):
    res = CliRunner().invoke(app, ["run", "--progress", "bars", "--out", str(tmp_path / "run")])
    assert res.exit_code == 2 and "--progress: progress mode must be one of" in res.stderr
    monkeypatch.setenv(progress.ENV, "loud")
    res = CliRunner().invoke(app, ["run", "--out", str(tmp_path / "run")])
    assert res.exit_code == 2 and "FRINGECAL_PROGRESS: progress mode must be one of" in res.stderr
    assert not (tmp_path / "run").exists()


def test_plain_lines_say_each_step_start_and_end_and_count_at_a_modest_rate():
    reporter, out = _plain(every=3600.0)
    reporter.step("render measurements", 3)
    reporter.advance("render measurements")
    reporter.advance("render measurements")  # within `every`: no line
    reporter.advance("render measurements")
    reporter.step("bundle adjustment", 1)
    lines = out.getvalue().splitlines()
    assert all(STAMP.match(line) for line in lines), lines
    assert [line[9:] for line in lines] == ["render measurements 0/3", "render measurements 3/3 done (0 s)",
                                            "bundle adjustment 0/1"]
    reporter.every = 0.0
    reporter.step("decode stacks", 2)
    reporter.advance("decode stacks")
    assert out.getvalue().splitlines()[-1][9:] == "decode stacks 1/2"


def test_plain_lines_never_leave_a_silent_wait():
    reporter, out = _plain(quiet=0.0)
    reporter.step("bundle adjustment", 1)
    reporter.tick()  # the timer's call, here with nothing said for `quiet` seconds
    assert re.fullmatch(r"bundle adjustment 0/1 \(\d+ s\)", out.getvalue().splitlines()[-1][9:])


def test_plain_compile_line_ticks_before_the_kernel_is_compiled():
    reporter, out = _plain(every=0.5)
    reporter.clock = clock = compile_clock.CompileClock()
    clock.observer = reporter.compiling
    clock.start("fringecal.simulate.render.render_kernel")
    time.sleep(1.1)
    reporter.tick()
    clock.end("fringecal.simulate.render.render_kernel")
    time.sleep(0.6)
    reporter.tick()
    said = [line[9:] for line in out.getvalue().splitlines()]
    assert said == [f"{progress.COMPILING}: render_kernel ...", f"{progress.COMPILING}: 1 s, 0 kernels compiled",
                    f"{progress.COMPILING}: 1 s, 1 kernel compiled"]


def test_rich_compile_line_is_updated_by_a_timer_while_numba_compiles():
    """Inside ``running()`` the compile clock is numba's; a compilation that has not
    ended yet shows its seconds growing (the timer's tick, not the compilation's end).
    The clock counts the whole process, so the seconds are read against its count before."""
    reporter = progress.RichProgress(Console(file=io.StringIO(), force_terminal=True))
    with reporter.running():
        clock = compile_clock.install()
        before = clock.busy_seconds()
        clock.start("fringecal.kernels.slow")  # numba's start event, in this thread
        try:
            time.sleep(2.3)
            description = reporter.progress.tasks[reporter.tasks[progress.COMPILING]].description
        finally:
            clock.end("fringecal.kernels.slow")
    shown = re.fullmatch(rf"{re.escape(progress.COMPILING)}: (\d+) s, \d+ kernels? compiled", description)
    assert shown and before + 1.4 <= int(shown.group(1)) <= before + 3.5, (before, description)
    assert clock.observer is None and progress._reporter is None


TELEMETRY = """
import sys
if sys.argv[1] == "ours":
    from fringecal.flows.common import no_prefect_telemetry
    no_prefect_telemetry()
from prefect.analytics import is_telemetry_enabled
from prefect.settings import PREFECT_SERVER_ANALYTICS_ENABLED
print(is_telemetry_enabled(), PREFECT_SERVER_ANALYTICS_ENABLED.value())
"""


def test_runs_we_start_send_no_telemetry_and_so_show_no_notice(tmp_path):
    """Prefect prints its telemetry notice on a terminal when its client telemetry is on;
    what fringecal sets before it imports Prefect turns client and server telemetry off."""
    ci = {"CI", "GITHUB_ACTIONS", "GITLAB_CI", "JENKINS_URL", "TRAVIS", "CIRCLECI", "BUILDKITE", "TF_BUILD",
          "CODEBUILD_BUILD_ID", "BITBUCKET_COMMIT", "TEAMCITY_VERSION", "DRONE", "SEMAPHORE", "APPVEYOR", "BUDDY",
          "CI_NAME", "DO_NOT_TRACK", "PREFECT_SERVER_ANALYTICS_ENABLED"}
    env = {k: v for k, v in os.environ.items() if k not in ci} | {"PREFECT_HOME": str(tmp_path)}
    said = {who: subprocess.run([sys.executable, "-c", TELEMETRY, who], env=env, capture_output=True, text=True,
                                timeout=120).stdout.split() for who in ("prefect", "ours")}
    assert said == {"prefect": ["True", "True"], "ours": ["False", "False"]}


def assert_a_run_into_a_pipe_says_what_it_does(lines: list[tuple[float, str]], until: str) -> None:
    """``fringecal run`` with its output in a file or pipe (CI, nohup): a first line at
    once, then timestamped lines as the steps start and end, never 40 s of silence.

    ``lines``: (seconds since the command started, line) as read from its standard
    output, PYTHONUNBUFFERED and FRINGECAL_PROGRESS unset, the small rig's run read up to
    ``until`` (the line it waited for). The run is tests/test_interrupt.py's Ctrl-C run:
    one command start for both tests."""
    first_at, first = lines[0]
    assert first_at < 5.0 and STAMP.match(first) and "fringecal run: checking" in first, lines[:3]
    said = [ln[9:].strip() for _, ln in lines if STAMP.match(ln)]
    assert any(s.startswith("starting Prefect") for s in said) and "simulated rig 0/1" in said, said
    assert any(re.fullmatch(until, s) for s in said), said
    gaps = [b[0] - a[0] for a, b in zip(lines, lines[1:])]
    assert max(gaps) < progress.PlainProgress.quiet + 5, list(zip(gaps, said))
