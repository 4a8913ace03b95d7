"""fringecal installs as one package that runs from any folder.

``pip install .`` (not editable) into a fresh virtual environment outside the checkout;
the environment takes the test environment's dependencies through a ``.pth`` line, so
the test builds and installs fringecal itself but downloads nothing else. Then, from an
empty folder: ``fringecal --version``, a short run (the bundled default configuration,
until its first step) and ``pip show -f`` listing one top-level package.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import sysconfig
import tomllib
from pathlib import Path

import pytest

import fringecal

ROOT = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.slow


def _run(args, cwd, env=None, timeout=600):
    return subprocess.run([str(a) for a in args], cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)


@pytest.fixture(scope="module")
def installed(tmp_path_factory) -> tuple[Path, dict, Path]:
    """The fresh environment, the environment variables to run it with, an empty folder."""
    base = tmp_path_factory.mktemp("installed")
    source = base / "source"  # a copy: building in the checkout would leave build/ behind
    shutil.copytree(ROOT, source, ignore=shutil.ignore_patterns(".git", ".venv", "build", "*.egg-info", "site",
                                                                  "__pycache__", "runs", ".pytest_cache"))
    venv = base / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True)
    purelib = Path(_run([venv / "bin" / "python", "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                        base).stdout.strip())
    (purelib / "test-environment-dependencies.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}  # nothing of the checkout on the path
    res = _run([venv / "bin" / "python", "-m", "pip", "install", "-q", "--no-deps", source], base, env)
    assert res.returncode == 0, res.stderr[-3000:]
    work = base / "elsewhere"
    work.mkdir()
    return venv, env | {"PATH": f"{venv / 'bin'}{os.pathsep}{env['PATH']}"}, work


def test_version_from_anywhere(installed):
    venv, env, work = installed
    res = _run([venv / "bin" / "fringecal", "--version"], work, env)
    assert res.returncode == 0, res.stderr
    assert res.stdout.strip() == f"fringecal {fringecal.__version__}" != "fringecal 0.0.0+checkout"
    where = _run([venv / "bin" / "python", "-c", "import fringecal.flows.cli, fringecal.schemas, fringecal.config as c; "
                  "print(fringecal.flows.cli.__file__); print(c.configs_dir())"], work, env).stdout.split()
    assert all(str(venv) in w for w in where), where


def test_a_short_run_from_another_folder(installed):
    venv, env, work = installed
    res = _run([venv / "bin" / "fringecal", "run", "--out", "demo", "--until", "simulate-prepare"], work, env)
    assert res.returncode == 0, (res.stdout + res.stderr)[-3000:]
    manifest = (work / "demo" / "manifest.json").read_text()
    assert '"name": "thesis' in manifest and (work / "demo" / "artefact.csv").is_file()
    assert (work / "demo" / "tables" / "acquisition.csv").read_text().count("\n") > 24


def test_one_top_level_package(installed):
    venv, env, work = installed
    res = _run([venv / "bin" / "python", "-m", "pip", "show", "-f", "fringecal"], work, env)
    assert res.returncode == 0, res.stderr
    files = [line.strip() for line in res.stdout.split("Files:", 1)[1].splitlines() if line.strip()]
    tops = {f.split("/")[0] for f in files if not f.startswith("..")}
    assert {t for t in tops if not t.endswith(".dist-info")} == {"fringecal"}
    for name in ("fringecal/flows/cli.py", "fringecal/schemas/tables.py", "fringecal/configs/run_thesis.yaml",
                 "fringecal/configs/thesis/artefact_cmm2.csv", "fringecal/py.typed",
                 "fringecal/report/templates/base.html.j2"):
        assert name in files, name
    assert any(f.endswith("licenses/LICENSE") for f in files)


def test_the_package_list_names_every_package_folder():
    setuptools = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    mapped = {name: ROOT / folder for name, folder in setuptools["package-dir"].items()}
    found = {"fringecal." + ".".join(p.parent.relative_to(ROOT / "fringecal").parts) if p.parent != ROOT / "fringecal"
             else "fringecal" for p in (ROOT / "fringecal").rglob("__init__.py")}
    for name, folder in mapped.items():
        found |= {name + "".join("." + part for part in p.parent.relative_to(folder).parts)
                  for p in folder.rglob("__init__.py")}
    assert set(setuptools["packages"]) == found
