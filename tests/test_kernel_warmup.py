"""The first-run warm-up compiles the later kernels with the signatures the pipeline uses.

In a fresh checkout the test session's own start is such a first run: the controller
runs the warm-up on the cold cache before any test worker starts, and checks it at once
(tests/conftest.py, :func:`warm_up_and_check`), before any test could compile a kernel
into the same cache. The test reads that check. When the session started warm, the
test repeats the whole sequence in a cache folder of its own (about 27 s of one core)."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow  # whole runs: the fast tier (-m "not slow") leaves this module out

CHECK = str(Path(__file__).with_name("warmup_check.py"))
#: where the session's start records its check (tests/conftest.py)
SESSION_CHECK = "FRINGECAL_TEST_WARMUP_CHECK"


def warm_up_and_check(env: dict, folder: Path) -> dict:
    """Run the warm-up as a first run does, then the check: its exit status, the compile
    seconds it printed and the end of its error output."""
    warm = subprocess.run([sys.executable, "-m", "fringecal.run.warmup"], env=env, capture_output=True, text=True)
    if warm.returncode != 0:
        return {"step": "warm-up", "returncode": warm.returncode, "stderr": warm.stderr[-2000:]}
    return check(env, folder)


def check(env: dict, folder: Path) -> dict:
    res = subprocess.run([sys.executable, CHECK, str(folder)], env=env, capture_output=True, text=True)
    lines = res.stdout.strip().splitlines()
    return {"step": "check", "returncode": res.returncode, "stderr": res.stderr[-3000:],
            "compile_seconds": float(lines[-1]) if res.returncode == 0 and lines else None}


def test_warm_up_leaves_nothing_for_the_bundle_to_compile(tmp_path):
    recorded = os.environ.get(SESSION_CHECK)
    if recorded:
        result = json.loads(recorded)
    else:
        env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "numba")}
        cold = subprocess.run([sys.executable, "-c", "from fringecal.run import warmup as k; print(k.cache_is_cold())"],
                              env=env, capture_output=True, text=True)
        assert cold.stdout.strip() == "True", cold.stderr[-2000:]
        result = warm_up_and_check(env, tmp_path)
    assert result["returncode"] == 0, (result["step"], result["stderr"])
    assert result["compile_seconds"] == 0.0  # every kernel came from the cache
