"""Shared fixtures. Prefect state (database, results, cache keys) lives in a
temporary folder for the whole session, never in the user's ~/.prefect."""

from __future__ import annotations

import atexit
import os
import shutil
import tempfile
from pathlib import Path

if os.environ.get("PYTEST_XDIST_WORKER"):
    # one core per test worker: BLAS, OpenMP and numba threads of two workers on two cores
    # would oversubscribe them (and OpenBLAS's waiting threads spin), costing more than they give
    for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
        os.environ.setdefault(_var, "1")

_PREFECT_TMP = Path(tempfile.mkdtemp(prefix="fringecal-prefect-"))
# removed when this process ends: every test process made one (up to 17 MB) and left it,
# over a thousand in /tmp after two days of test runs
atexit.register(shutil.rmtree, _PREFECT_TMP, ignore_errors=True)
os.environ["PREFECT_HOME"] = str(_PREFECT_TMP / "home")
os.environ["PREFECT_LOCAL_STORAGE_PATH"] = str(_PREFECT_TMP / "storage")
os.environ["PREFECT_RESULTS_LOCAL_STORAGE_PATH"] = str(_PREFECT_TMP / "storage")
os.environ["PREFECT_SERVER_ANALYTICS_ENABLED"] = "false"
os.environ["PREFECT_LOGGING_LEVEL"] = "WARNING"
os.environ["PREFECT_LOGGING_EXTRA_LOGGERS"] = "fringecal"
os.environ["PREFECT_LOGGING_TO_API_WHEN_MISSING_FLOW"] = "ignore"  # steps run without a flow too
os.environ.setdefault("PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS", "120")
# commands the tests start as processes run this checkout's code too, not an installed copy
_CHECKOUT = str(Path(__file__).resolve().parents[1])
os.environ["PYTHONPATH"] = os.pathsep.join([_CHECKOUT, *filter(None, [os.environ.get("PYTHONPATH")])])

import numpy as np  # noqa: E402
import pytest  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
THESIS = ROOT / "configs" / "thesis"


def pytest_sessionstart(session):
    """In a fresh checkout, compile numba's kernels once, before the test workers start.

    Otherwise each xdist worker compiles every kernel it meets on its own (about 46 s of
    one core each: the renderer 24 s, the rest 22 s), twice the work on two cores; the
    run's own warm-up helpers (:mod:`fringecal.run.warmup`) compile them into the
    checkout's cache side by side (about 24 s), and every worker then loads them.

    That is a first run's warm-up on a cold cache, so it is checked here, while the
    renderer still compiles and before any test could compile a kernel into the same
    cache: the result goes to the workers in ``FRINGECAL_TEST_WARMUP_CHECK``
    (tests/test_kernel_warmup.py, which otherwise repeats it in a cache of its own)."""
    if os.environ.get("PYTEST_XDIST_WORKER") or not getattr(session.config.option, "numprocesses", None):
        return
    import json

    from fringecal import lifeline
    from fringecal.run import warmup

    helpers = warmup.start(renderer=True, others=True)
    for proc in sorted(helpers, key=lambda p: "renderer" in p.args):  # the renderer's helper last
        try:
            proc.wait(300)
            if "renderer" not in proc.args and proc.returncode is not None:
                from test_kernel_warmup import SESSION_CHECK, check

                result = check(dict(os.environ), Path(tempfile.mkdtemp(prefix="fringecal-warmup-")))
                if proc.returncode != 0:
                    result = {"step": "warm-up", "returncode": proc.returncode, "stderr": "(the session's warm-up)"}
                os.environ[SESSION_CHECK] = json.dumps(result)
        finally:
            lifeline.stop(proc)


def pytest_collection_modifyitems(config, items):
    """In a test worker: the modules with slow tests first, each module's tests together.

    The test command hands out whole modules (``--dist loadfile``, pyproject.toml), so a
    module's fixtures are made once (work stealing split modules and made, e.g.,
    test_run_flow's first run twice when the Dask test was stolen), and in this order
    (``--no-loadscope-reorder``): the long modules first, the last ones small, so
    that both workers end together."""
    if not os.environ.get("PYTEST_XDIST_WORKER"):
        return
    slow = {item.nodeid.split("::")[0] for item in items if item.get_closest_marker("slow")}
    order = {item: i for i, item in enumerate(items)}
    items.sort(key=lambda item: (item.nodeid.split("::")[0] not in slow, order[item]))


def pytest_xdist_make_scheduler(config, log):
    """Under ``--dist loadfile``: the test modules that use the Prefect test server
    (``prefect_harness``) go to one worker as if they were one module, so that one
    server serves them all (starting one, with its database, costs about 7 s of CPU,
    and it keeps polling while the session lasts) instead of one in each worker."""
    if config.getvalue("dist") != "loadfile":
        return None
    from xdist.scheduler import LoadFileScheduling

    here = Path(__file__).parent
    flows = {f"{here.name}/{p.name}" for p in here.glob("test_*.py") if "prefect_harness" in p.read_text()}

    class OnePrefectServer(LoadFileScheduling):
        def _split_scope(self, nodeid: str) -> str:
            module = nodeid.split("::", 1)[0]
            return "prefect_harness" if module in flows else module

    return OnePrefectServer(config, log)


@pytest.fixture(scope="session")
def thesis_dir() -> Path:
    return THESIS


@pytest.fixture(scope="session")
def pose1(thesis_dir):
    """T_world_artefact of the thesis's first pose (table 6-1, scanner 1)."""
    import pandas as pd

    from fringecal.frames import Frame

    row = pd.read_csv(thesis_dir / "poses_scanner1_table6-1.csv").iloc[0]
    return Frame.from_params(row[["tx_mm", "ty_mm", "tz_mm", "omega_rad", "phi_rad", "kappa_rad"]].to_numpy(float))


@pytest.fixture(scope="session")
def thesis_rig():
    from fringecal.rig import load_rig

    return load_rig(THESIS / "sensors_refined_table6-8.csv")


@pytest.fixture(scope="session")
def thesis_artefact():
    from fringecal.artefact import load_artefact

    return load_artefact(THESIS / "artefact_cmm2.csv")


#: node ids of this process's tests that ask for ``prefect_harness`` and have not run yet
_HARNESS_USERS: set[str] = set()
#: the open harness (an ExitStack), None before it starts and once it is stopped
_HARNESS: dict = {"stack": None}


def pytest_collection_finish(session):
    _HARNESS_USERS.update(item.nodeid for item in session.items if "prefect_harness" in item.fixturenames)


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_teardown(item, nextitem):
    """The Prefect test server stops after the last test that asks for it, not at the
    session's end: idle, it keeps polling its database (about 40 CPU-s over a session
    whose flow tests ended at 40 % of it). Its tests all run in one worker (one scope,
    ``pytest_xdist_make_scheduler``), so that worker sees the last of them; a worker that
    collected some it does not run keeps the server to the end, as before."""
    yield
    _HARNESS_USERS.discard(item.nodeid)
    if not _HARNESS_USERS and _HARNESS["stack"] is not None:
        _HARNESS["stack"].close()
        _HARNESS["stack"] = None


@pytest.fixture(scope="session")
def prefect_harness():
    """One temporary Prefect server for the flow tests of the session (stopped after the
    last of them, ``pytest_runtest_teardown``)."""
    from contextlib import ExitStack

    from prefect.testing.utilities import prefect_test_harness

    with ExitStack() as stack:
        stack.enter_context(prefect_test_harness(server_startup_timeout=120))
        _HARNESS["stack"] = stack
        yield
        _HARNESS["stack"] = None


@pytest.fixture
def rng():
    return np.random.default_rng(12345)


def write_small_config(d: Path) -> Path:
    """A small simulated thesis rig: four of the twelve poses (four stand-offs), three
    ball-bar positions, 320 px cameras and a short fringe sequence -- the whole pipeline
    in well under a minute (:func:`fringecal.simulate.small_thesis.write_small_thesis_config`)."""
    from fringecal.simulate.small_thesis import write_small_thesis_config

    return write_small_thesis_config(d)


@pytest.fixture(scope="session")
def small_config(tmp_path_factory) -> Path:
    return write_small_config(tmp_path_factory.mktemp("config"))


def shared_folder(tmp_path_factory, name: str, make) -> Path:
    """A folder made once per test session for every test worker: ``make(folder)`` fills
    it in the first worker that asks (the others wait for it, under a file lock) unless a
    worker already did. Without xdist the folder is this session's. Readers must not
    change it: another worker may be reading it."""
    import fcntl
    import shutil

    root = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        root = root.parent  # the session's folder, above the workers' own
    folder, done = root / f"shared-{name}", root / f"shared-{name}.done"
    with open(root / f"shared-{name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not done.exists():
            shutil.rmtree(folder, ignore_errors=True)  # a worker that failed while making it
            folder.mkdir()
            make(folder)
            done.touch()
    return folder


@pytest.fixture(scope="session")
def small_run(small_config, tmp_path_factory):
    """One uninterrupted run of the small rig (in this process, without Prefect: the
    flow calls the same steps, tests/test_run_flow.py; every step but the report, from
    which no figure of the summary comes), made once per session for all workers: its
    run directory (read only) and its summary as ``fringecal run --json`` prints it
    (tests/test_interrupt.py's reference, the calibration of tests/test_measure.py)."""
    import json

    from fringecal.run.config import load_run_config
    from fringecal.run.summary import manifest, run_summary
    from fringecal.rundir import RunDir
    from fringecal.steps import run_pipeline

    def make(folder: Path) -> None:
        cfg = load_run_config(small_config)
        rd = RunDir(folder / "run").create()
        rd.manifest.save(manifest(cfg))
        run_pipeline(rd, cfg, workers=2, until="evaluate")
        (folder / "summary.json").write_text(json.dumps(run_summary(rd, cfg)))

    folder = shared_folder(tmp_path_factory, "small-run", make)
    return RunDir(folder / "run"), json.loads((folder / "summary.json").read_text())


@pytest.fixture(scope="session")
def small_dataset(small_config, tmp_path_factory) -> tuple[Path, Path]:
    """The small rig written as a recorded data set by ``fringecal simulate`` (PNG frames),
    and its truth folder; made once per session for all workers (tests copy it to edit it)."""
    from fringecal.run.config import load_run_config
    from fringecal.simulate.export import write_dataset

    def make(d: Path) -> None:
        write_dataset(load_run_config(small_config), d / "small", d / "small-truth", "png")

    d = shared_folder(tmp_path_factory, "small-dataset", make)
    return d / "small", d / "small-truth"


def write_dataset_reusing(cfg, out: Path, truth_out: Path, base: Path, check: tuple[str, ...]) -> Path:
    """``write_dataset(cfg, out, truth_out, "png")`` for a data set that shares image
    stacks with the data set ``base`` (the session's small data set): the same rig,
    seeds and settings give the same frames, so each stack ``base`` holds under the
    same measurement id (``measurements/<m>/<scanner>``, ``verification/<position>/<scanner>``)
    is hard-linked from there instead of rendered and PNG-encoded again. Everything
    else -- the tables, the truth, the stacks ``base`` lacks (acceptance objects,
    objects to measure) -- is written as ``write_dataset`` writes it.

    The stacks named in ``check`` (measurement ids) are rendered anyway and must equal
    ``base``'s byte for byte: the premise that both data sets are written alike is
    tested, not assumed. Readers must not change the linked frames (``base`` is shared)."""
    import filecmp

    import fringecal.simulate.export as export

    stacks = {f"{m.name}-{s.name}": s for kind in ("measurements", "verification") if (base / kind).is_dir()
              for m in (base / kind).iterdir() if m.is_dir() and m.name != "acceptance"
              for s in m.iterdir() if s.is_dir()}
    linked = type("Linked", (), {})
    render, write = export.render_frames, export.write_frames
    written: dict[str, Path] = {}

    def render_or_link(measurement, *args, **kwargs):
        if measurement in stacks and measurement not in check:
            return type("Measurement", (), {"frames": (linked, stacks[measurement]), "sequence": None})()
        return render(measurement, *args, **kwargs)

    def write_or_link(folder, frames, *args, **kwargs):
        if isinstance(frames, tuple) and frames[0] is linked:
            shutil.copytree(frames[1], folder, copy_function=os.link)
            return Path(folder)
        written[Path(folder).parts[-2] + "-" + Path(folder).name] = Path(folder).relative_to(
            next(p for p in Path(folder).parents if p.name.endswith(".tmp")))
        return write(folder, frames, *args, **kwargs)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(export, "render_frames", render_or_link)
        mp.setattr(export, "write_frames", write_or_link)
        data = export.write_dataset(cfg, out, truth_out, "png")
    for measurement in check:
        ours, theirs = data / written[measurement], stacks[measurement]
        names = sorted(p.name for p in theirs.iterdir())
        assert sorted(p.name for p in ours.iterdir()) == names, measurement
        match, mismatch, errors = filecmp.cmpfiles(ours, theirs, names, shallow=False)
        assert not mismatch and not errors, (measurement, mismatch, errors)
    return data


@pytest.fixture(scope="session")
def small_dataset_run(small_dataset, tmp_path_factory):
    """The small data set run through every step (in this process, without Prefect),
    made once per session for all workers: its run directory (read only) and the step
    records of that first run (tests/test_steps.py copies both, tests/test_opencv_interop.py
    reads its calibration)."""
    import json

    from fringecal.run.config import load_run_config
    from fringecal.run.summary import manifest
    from fringecal.rundir import RunDir
    from fringecal.steps import run_pipeline

    def make(folder: Path) -> None:
        cfg = load_run_config(dataset=small_dataset[0])
        rd = RunDir(folder / "run").create()
        rd.manifest.save(manifest(cfg))
        (folder / "records.json").write_text(json.dumps(run_pipeline(rd, cfg, workers=2)))

    folder = shared_folder(tmp_path_factory, "small-dataset-run", make)
    return RunDir(folder / "run"), json.loads((folder / "records.json").read_text())
