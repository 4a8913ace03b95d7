"""``fringecal run``, ``fringecal reproduce`` and ``fringecal serve``."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Optional

import typer

from fringecal.flows.common import (
    UserInputError,
    configured_prefect_api,
    console,
    err_console,
    fail,
    guarded,
    no_prefect_telemetry,
)
from fringecal.flows.progress import HELP as PROGRESS_HELP

__all__ = ["run_command", "reproduce_command", "REPRODUCE_CONTEXT", "serve_command", "validate_run_config", "make_task_runner",
           "reporter_for"]


def validate_run_config(config: Path | dict | None, overrides: dict | None = None, dataset: Path | None = None):
    """Load and check a run config and everything its data source names -- a simulated
    rig's files and hexapod reach, or a recorded data set's whole layout -- before
    any Prefect work."""
    from fringecal.config import ConfigError
    from fringecal.run.config import RunConfig, load_run_config

    if isinstance(config, dict):
        try:
            cfg = RunConfig.model_validate(config)
        except ValueError as err:
            raise ConfigError(f"run config: {err}") from None
    else:
        cfg = load_run_config(config, overrides, dataset)
    if cfg.source == "dataset":
        from fringecal.dataset import DataSet

        ds = DataSet.open(cfg.dataset)
        ds.check_frames()  # every frame's header, and one frame per orientation decoded
    else:
        check_simulation(cfg.simulate, cfg.acceptance.specification.depth_range_mm)
    return cfg


def check_simulation(sim, depth_range_mm=None) -> None:
    """A simulated rig's files, its acceptance positions inside the specified measuring
    volume (``depth_range_mm``), and every planned pose within the hexapod's reach."""
    from fringecal.simulate.source import load_simulated_rig

    sr = load_simulated_rig(sim, depth_range_mm)
    hx = sim.acquisition.hexapod
    if hx.enabled:
        from fringecal.hexapod import HexapodRig, load_hexapod_config
        from fringecal.hexapod.workspace import check_poses, describe_violations

        rig = HexapodRig.from_config(load_hexapod_config(hx.config))
        for pose, T in sr.planned.items():
            check = check_poses(rig.config, rig.platform_pose_for(T))
            if not check.ok:
                raise UserInputError(f"{sim.rig}: artefact pose {pose} is out of the hexapod's reach: "
                                     + "; ".join(describe_violations(rig.config, check)))


def make_task_runner(kind: str, max_workers: int, dask_address: str | None = None, dask_workers: int = 2):
    """Bounded threads, or a Dask cluster (a local one by default) through prefect-dask."""
    if kind == "threads":
        from prefect.task_runners import ThreadPoolTaskRunner

        return ThreadPoolTaskRunner(max_workers=max_workers)
    from prefect_dask import DaskTaskRunner

    if dask_address:
        return DaskTaskRunner(address=dask_address)
    return DaskTaskRunner(cluster_kwargs={"n_workers": dask_workers, "threads_per_worker": 1, "processes": True,
                                          "dashboard_address": None})


def _current(cfg, out: Path) -> dict | None:
    """The summary of ``out`` if every step of this config is current there (checked
    from the files' digests before Prefect starts, which costs seconds), else None."""
    from fringecal.run.summary import pipeline_status
    from fringecal.rundir import RunDir

    rd = RunDir(out)
    if not rd.summary.exists() or pipeline_status(rd, cfg) is not None:
        return None
    summary = rd.summary.load()
    n = len(summary["tasks"]["ran"]) + len(summary["tasks"]["cached"])
    err_console.print(f"{out} is up to date with this configuration (inputs, settings, code and every output "
                      "unchanged); --force reruns the flow from its cache")
    return {**summary, "tasks": {"ran": [], "cached": ["(all %d steps: outputs unchanged)" % n]}}


def _quiet_prefect(verbose: bool) -> None:
    """Progress bars instead of Prefect's log lines; the temporary server's own
    shutdown chatter (events still in flight when the process ends) is not news; no
    telemetry notice."""
    no_prefect_telemetry()
    os.environ.setdefault("PREFECT_LOGGING_EXTRA_LOGGERS", "fringecal")
    os.environ.setdefault("PREFECT_LOGGING_TO_API_WHEN_MISSING_FLOW", "ignore")
    if not verbose:
        os.environ.setdefault("PREFECT_LOGGING_LEVEL", "WARNING")
        os.environ.setdefault("PREFECT_SERVER_LOGGING_LEVEL", "CRITICAL")


def _left_out(names) -> str:
    """`` (left out: 12)`` for the measurements the adjustment left out; empty without."""
    return f" (left out: {', '.join(names)})" if names else ""


def _print_summary(summary: dict, run_dir: Path) -> None:
    from rich.table import Table

    t = Table(title=f"fringecal run -> {run_dir}", show_header=False)
    t.add_column("", style="bold")
    t.add_column("", justify="right")
    v, tr = summary.get("verification"), summary.get("truth")
    source = summary.get("dataset") or "simulated rig"
    if summary.get("simulation_profile"):
        source += f", {summary['simulation_profile']} profile"
    if summary.get("black_boxes_only"):  # no sensor model: no F, eps1, eps2
        rows = [("source", str(source)),
                ("measurements / sphere centres", f"{summary['n_measurements']} / {summary['n_control_points']:,}"),
                ("black boxes only: RMS of the centres", f"{1000 * summary['rms_centre_mm']:.1f} um")]
    else:
        rows = [
            ("source", str(source)),
            ("measurements / control points", f"{summary['n_measurements']} / {summary['n_control_points']:,}"
             + _left_out(summary.get("measurements_left_out"))),
            ("RMS F before -> after", f"{summary['rms_F_mm_before']:.3f} mm -> {1000 * summary['rms_F_mm_after']:.1f} um"),
            ("RMS eps1 / eps2 after", f"{1000 * summary['rms_eps1_mm_after']:.1f} / {1000 * summary['rms_eps2_mm_after']:.1f} um"),
            ("one part in (1.96 sigma eps2)", f"{summary['one_part_in']:,.0f}"),
        ]
    sm = summary.get("sensor_model")
    if sm:
        how = "held-out data" if sm["chosen_by"].startswith("cross") else sm["chosen_by"].split(" (")[0]
        how = "no residual pattern" if how == "residual pattern" else how
        rows.append(("sensor model (chosen by)", f"{sm['model']} ({how})"))
        if sm.get("residual_pattern_z") is not None:
            flag = ("[red]lens model too simple[/]" if sm["residual_pattern_z"] > sm["residual_pattern_threshold"]
                    else "no pattern")
            rows.append(("  residual pattern Z (threshold)",
                         f"{sm['residual_pattern_z']:.1f} ({sm['residual_pattern_threshold']:g}): {flag}"))
        if sm.get("prism_verdict") == "undecided" and sm.get("prism_wald_p") is None:
            why = ": too few measurements" if "too few" in (sm.get("prism_message") or "") else " (fringecal.log)"
            rows.append(("  thin-prism terms", f"[yellow]not tested{why}[/]"))
        elif sm.get("prism_wald_p") is not None:
            flag = ("[red]present, not modelled[/]" if sm["lens_model_too_simple"] and sm["prism_present"]
                    else "present, modelled" if sm["prism_present"]
                    else "[yellow]not decided: too few measurements[/]" if sm["prism_verdict"] == "undecided"
                    else "none")
            kappa = "" if sm["prism_wald_kappa"] is None else f", kappa {sm['prism_wald_kappa']:.2g}"
            rows.append(("  thin-prism terms: Wald p (threshold)",
                         f"{sm['prism_wald_p']:.2g} ({sm['prism_wald_alpha']:g}{kappa}): {flag}"))
    dec = summary.get("decoding")
    if dec:
        fits = sum(d["phase_ripple"]["fits"] for d in dec)
        fixed = [c for d in dec for c in d["phase_ripple"]["corrected"]]
        zs = [d["phase_ripple"]["largest_z"] for d in dec if d["phase_ripple"]["largest_z"] is not None]
        if fixed:
            worst = max(d["phase_ripple"]["largest_corrected_rms_rad"] or 0.0 for d in dec)
            rows.append(("phase ripple (decoder)", f"[yellow]corrected in {len(fixed)} of {fits}[/] "
                                                   f"(largest {1000 * worst:.1f} mrad RMS)"))
        elif fits:
            rows.append(("phase ripple (decoder)", f"none in {fits} fits (largest Z {max(zs):.1f})"))
    if v:
        rows.append((f"ball-bar max |error| (MPE {1000 * v['mpe_mm']:.0f} um)",
                     f"{1000 * v['max_abs_error_mm']:.1f} um = 1/{v['one_part_in']:,.0f} of "
                     f"{v['volume_diagonal_mm']:.0f} mm"))
        measured = [e for e in v.get("lengths") or [] if e.get("U_mm") is not None]
        if measured:
            worst = max(measured, key=lambda e: abs(e["error_mm"]))
            rows.append((f"  its U (k = {v['length_coverage_factor']:g}), ISO 14253-1",
                         f"{1000 * worst['U_mm']:.1f} um, {worst['iso14253']}"))
        if v.get("not_covered"):
            rows.append(("  [red]not covered by the budget[/]", ", ".join(v["not_covered"])))
        outside = {p: f for p, f in (v.get("outside_observed_region") or {}).items() if f > 0}
        if outside:
            rows.append(("  outside the observed region",
                         f"{len(outside)} of {v['n_lengths']} positions, up to {100 * max(outside.values()):.0f} %"))
        if v.get("monte_carlo_disagreements"):
            rows.append(("  [yellow]Monte Carlo disagrees (JCGM 101)[/]",
                         f"{len(v['monte_carlo_disagreements'])} of {len(measured)} lengths, below"))
    rows.append(verdict_row(summary.get("verdict")))
    if tr:
        if tr.get("rms_eps1_mm_true_params") is not None:
            rows += [("truth: eps1 / eps2 floor", f"{1000 * tr['rms_eps1_mm_true_params']:.1f} / "
                                                  f"{1000 * tr['rms_eps2_mm_true_params']:.1f} um")]
        if tr.get("verification_max_abs_error_true_params_mm") is not None:
            rows.append(("truth: ball-bar max |error|",
                         f"{1000 * tr['verification_max_abs_error_true_params_mm']:.1f} um"))
        rows.append(("truth: max position / angle error", f"{tr['max_position_error_mm']:.3f} mm / "
                                                          f"{1e3 * tr['max_angle_error_rad']:.3f} mrad"))
    rows += [("bundle adjustment / total", f"{summary['bundle_seconds']:.2f} s / {summary['total_seconds']:.0f} s")]
    compiled = sum((summary.get("compile_seconds") or {}).values()) + summary.get("kernel_wait_seconds", 0.0)
    if compiled:
        rows.append(("  of which compiling kernels", f"{compiled:.0f} s (first run on this machine only)"))
    rows.append(("tasks run / from cache", f"{len(summary['tasks']['ran'])} / {len(summary['tasks']['cached'])}"))
    for k, val in rows:
        t.add_row(k, val)
    console.print(t)
    for line in (v or {}).get("monte_carlo_disagreements") or []:
        console.print(f"[yellow]Monte Carlo does not confirm the linear length uncertainty[/] at {line}",
                      soft_wrap=True)
    console.print(f"report: {run_dir / 'report.html'}")


def verdict_row(verdict: dict | None) -> tuple[str, str]:
    """The table's one verdict line: ACCEPTED, NOT ACCEPTED with the failing components
    in brief (per test and parameter: failing / judged), or NOT VERIFIED."""
    if not verdict or verdict.get("accepted") is None:
        return ("verdict", "[yellow]NOT VERIFIED[/] (no ball-bar and no acceptance measurements)")
    label = "verdict (ISO 14253-1)"
    if verdict["accepted"]:
        return (label, f"[green]{verdict['word']}[/]")
    return (label, f"[red]{verdict['word']}[/]: {verdict['failing']}")


def _kernels_needed(cfg, until: Optional[str]) -> tuple[bool, bool]:
    """(renderer, the others): which compiled kernels a run of ``cfg`` up to ``until``
    uses, so that a first run warms up only those (``fringecal.run.warmup``). The source's
    first steps (preparing the rig, moving the hexapod, reading a data set) need none."""
    from fringecal.steps import pipeline

    names = [s.name for s in pipeline(cfg)]
    reached = names if until is None or until not in names else names[:names.index(until) + 1]
    return "simulate-render" in reached, bool(set(reached) - {"simulate-prepare", "simulate-hexapod", "ingest"})


def _execute(cfg, run_dir: Path, runner: Optional[str], dask_address: Optional[str], workers: Optional[int],
             verbose: bool, command: str, reporter, until: Optional[str] = None, fresh_digests: bool = False) -> dict:
    """Run the flow into ``run_dir``. Ctrl-C or SIGTERM ends the command within seconds
    with one line (:mod:`fringecal.flows.interrupt`); no helper process outlives it
    (:mod:`fringecal.lifeline`); a rerun resumes and says what it reused. The run
    directory is claimed (:func:`fringecal.run.resume.claim`) before Prefect starts, so a
    second command into it is refused at once; Prefect's log lines go to the run's log
    file (:mod:`fringecal.flows.prefect_logs`), and a failure ends with one line
    (:func:`fringecal.flows.common.guarded`). ``fresh_digests`` (``--force``) forgets the
    run's digest cache: every file is hashed again."""
    import shutil

    from fringecal import lifeline
    from fringecal.flows import prefect_logs
    from fringecal.flows.common import log_failures_to, needs_space
    from fringecal.run import resume
    from fringecal.run import warmup as kernel_warmup
    from fringecal.rundir import RunDir

    rd = RunDir(run_dir)
    if (owner := resume.busy(rd)) is not None:
        raise UserInputError(resume.describe_busy(rd, owner))
    resume.claim(rd)
    if fresh_digests:
        shutil.rmtree(rd.digest_cache_dir, ignore_errors=True)
    needs_space(run_dir, lambda: run_size_estimate(cfg), "the run")
    log_failures_to(rd.log.path)
    from fringecal.flows.interrupt import armed

    warmup, server = [], None
    try:
        with armed(run_dir):
            # first run on this machine: the kernels compile in helpers while Prefect starts
            warmup = kernel_warmup.start(*_kernels_needed(cfg, until))
            _quiet_prefect(verbose)
            api = configured_prefect_api()
            reporter.say(f"starting Prefect: the flow reports to {api}" if api else
                         "starting Prefect and its temporary server for this command (a first run on a machine "
                         "also sets up its database)")
            with reporter.running():  # from here a line at least every 30 s, also while the server starts
                # the server's process starts up while this one imports the flow's modules
                starting = _launch_temporary_server()
                from fringecal.flows.run_flow import NotAccepted, run_flow

                if not verbose:
                    prefect_logs.to_file(rd.log.path)

                kind = runner or cfg.runner.kind
                # one thread policy: the worker pool, numba's and BLAS's threads from runner.cores
                policy = cfg.thread_policy(workers or (cfg.runner.dask_workers if kind == "dask" else None))
                task_runner = make_task_runner(kind, policy.workers, dask_address or cfg.runner.dask_address,
                                               policy.workers)
                flow = run_flow.with_options(task_runner=task_runner)
                server = starting.wait()
                if server is not None:  # local Dask workers report to it instead of each starting
                    os.environ["PREFECT_API_URL"] = server.api_url  # a temporary server of their own
                reporter.say(f"running the flow into {run_dir} ({kind})")
                try:
                    summary = flow(cfg, str(run_dir), None, command, until, policy.workers)
                except NotAccepted as verdict:  # the flow run ended Failed; its outputs are written
                    summary = verdict.summary
    finally:
        if server is not None:
            os.environ.pop("PREFECT_API_URL", None)
        for proc in warmup:
            lifeline.stop(proc)
        prefect_logs.restore()
        resume.release(rd)
    if summary.get("resumed"):
        n = summary["resumed"]["reused"]
        reporter.say(f"resumed: {n} step instance{'' if n == 1 else 's'} reused from the interrupted run")
    return summary


def run_size_estimate(cfg) -> float:
    """Roughly the bytes a run writes: per image stack (measurement, position) a store of
    its decoded maps and the maps and labels derived from it, some 16 float32 values per
    camera pixel before compression (an upper bound: the stores are compressed)."""
    if cfg.source == "dataset":
        from fringecal.dataset import DataSet

        stacks = DataSet.open(cfg.dataset).stacks()
        pixels = sum(s.width_px * s.height_px for s in stacks)
    else:
        from fringecal.simulate.source import acquisition_table, load_simulated_rig

        sr = load_simulated_rig(cfg.simulate)
        width = cfg.simulate.acquisition.camera_width_px
        pixels = len(acquisition_table(sr)) * width * width
    return 16 * 4 * pixels


def reporter_for(mode: Optional[str], out) -> object:
    """The progress reporter of ``--progress`` (:func:`fringecal.flows.progress.choose`)."""
    from fringecal.flows.progress import ENV, choose

    try:
        return choose(mode, out)
    except ValueError as err:
        raise UserInputError(f"{'--progress' if mode else ENV}: {err}") from None


def _what(config: Optional[Path], dataset: Optional[Path]) -> str:
    if dataset is not None:
        return f"the data set {dataset}" + (f" with the settings of {config}" if config else "")
    return str(config) if config else "configs/run_thesis.yaml (the default: the simulated thesis rig)"


class _ServerStart:
    """Prefect's temporary server starting in a helper thread (its process boots on
    another core while the command imports the flow); :meth:`wait` returns it once it
    answers, or raises what its start raised."""

    def __init__(self, server):
        import threading

        self.server, self.error = server, None
        self.thread = None
        if server is not None and not server.running:
            self.thread = threading.Thread(target=self._start, name="prefect-server-start", daemon=True)
            self.thread.start()

    def _start(self) -> None:
        try:
            self.server.start()
        except Exception as err:  # handed to the main thread by wait()
            self.error = err

    def wait(self):
        if self.thread is not None:
            self.thread.join()
            self.thread = None
        if self.error is not None:
            raise self.error
        return self.server


def _launch_temporary_server() -> _ServerStart:
    """Start Prefect's temporary server, adopted by the lifeline
    (:mod:`fringecal.lifeline`: it never outlives the command, even one killed with
    ``kill -9``): a helper thread launches its process and waits for it to answer, while
    the command goes on (:meth:`_ServerStart.wait`: 3-4 s of the server's start under the
    flow's imports). It is the instance Prefect's clients use when no API is configured,
    so they find it running. No server (``wait()`` returns None) when a Prefect server
    is configured."""
    from prefect.settings import PREFECT_API_URL

    if PREFECT_API_URL.value():
        return _ServerStart(None)
    from prefect.server.api.server import SubprocessASGIServer

    from fringecal import lifeline

    server = SubprocessASGIServer()
    if server.running:
        return _ServerStart(server)
    launch = getattr(server, "_run_uvicorn_command", None)  # Prefect's one spawn of the server process
    if launch is not None:
        def adopted():
            proc = launch()
            lifeline.adopt(proc)
            return proc

        server._run_uvicorn_command = adopted
    starting = _ServerStart(server)
    if launch is None:
        starting.wait()
        if server.server_process is not None:
            lifeline.adopt(server.server_process)
    return starting


def _apart(cfg, out: Path) -> None:
    """A run directory outside the data set it calibrates (and not around it)."""
    if cfg.source == "dataset":
        from fringecal.flows.validate import apart

        apart(out, "--out", cfg.dataset)


def _check_inputs(config: Optional[Path], dataset: Optional[Path], out: Path, workers: Optional[int] = None) -> None:
    """The options' paths and numbers, before the config is read (flows/validate.py)."""
    from fringecal.flows.validate import input_file, input_folder, output_folder, whole

    input_file(config, "--config", "run config YAML file")
    input_folder(dataset, "--dataset", "data set folder")
    output_folder(out, "--out")
    whole(workers, "--workers")


@guarded
def run_command(
    config: Optional[Path] = typer.Option(None, "--config", "-c", help="Run config YAML (default: configs/run_thesis.yaml, the simulated thesis rig)."),
    dataset: Optional[Path] = typer.Option(None, "--dataset", "-d", help="A recorded data set folder to calibrate (replaces the config's source)."),
    out: Path = typer.Option(Path("runs/thesis"), "--out", "-o", "--run", "-r",
                             help="Run directory to write, or to resume and bring up to date."),
    until: Optional[str] = typer.Option(None, "--until", help="Stop after this step (e.g. simulate-render, decode, bundle)."),
    runner: Optional[str] = typer.Option(None, "--runner", help="threads (default) or dask."),
    dask_address: Optional[str] = typer.Option(None, "--dask-address", help="Scheduler of an existing Dask cluster."),
    workers: Optional[int] = typer.Option(None, "--workers", help="Threads, or local Dask workers."),
    as_json: bool = typer.Option(False, "--json", help="Print summary.json."),
    verbose: bool = typer.Option(False, "--verbose", "-v", help="Show Prefect's logs."),
    force: bool = typer.Option(False, "--force", help="Run the flow even if the run directory is up to date."),
    progress: Optional[str] = typer.Option(None, "--progress", help=PROGRESS_HELP),
):
    """Calibrate: decode or simulate the measurements, extract and label spheres, adjust, verify and report.

    Exit status 0 (ACCEPTED, or NOT VERIFIED: no ball-bar and no acceptance
    measurements), 3 when the run's verdict is NOT ACCEPTED (the summary is printed
    first), 2 on bad input, 1 on a hexapod fault.
    """
    reporter = reporter_for(progress, err_console if as_json else console)
    reporter.say(f"fringecal run: checking {_what(config, dataset)}; the run goes to {out}")
    from fringecal.steps import pipeline

    if runner not in (None, "threads", "dask"):
        raise UserInputError(f"--runner must be threads or dask, not {runner!r}")
    if config is not None:  # a bundled configuration by name (-c run_thesis_realistic), as README says
        from fringecal.config import bundled_config

        config = bundled_config(config)
    _check_inputs(config, dataset, out, workers)
    cfg = validate_run_config(config, dataset=dataset)
    _apart(cfg, out)
    if until is not None and until not in (names := [s.name for s in pipeline(cfg)]):
        raise UserInputError(f"--until {until}: not a step of this run; the steps are {', '.join(names)}")
    summary = None if force or until else _current(cfg, out)
    if summary is None:
        from fringecal.hexapod import HexapodFault

        try:
            summary = _execute(cfg, out, runner, dask_address, workers, verbose, "fringecal run", reporter, until,
                               fresh_digests=force)
        except HexapodFault as err:  # the controller, not the input: its own status
            fail(f"hexapod: {err}", code=1)
    if as_json:
        print(json.dumps(summary, indent=2))
    elif until is None:
        _print_summary(summary, out)
    else:
        console.print(f"stopped after {until}: {len(summary['tasks']['ran'])} step instances ran, "
                      f"{len(summary['tasks']['cached'])} from the cache -> {out}")
    not_accepted(summary)


def not_accepted(summary: dict) -> None:
    """Exit with status 3 when the run's verdict is NOT ACCEPTED (after the summary is
    printed), so that a script can tell it from an accepted or unverified run (0) and
    from bad input (2). A summary without a verdict (``--until``) judges nothing."""
    verdict = summary.get("verdict") or {}
    if verdict.get("accepted") is False:
        err_console.print(f"[red]{verdict['word']}[/]: {verdict['failing']} (exit status 3)", highlight=False,
                          soft_wrap=True)
        raise typer.Exit(3)


@guarded
def reproduce_command(
    ctx: typer.Context,
    run: Optional[Path] = typer.Option(None, "--run", "-r", help="A run directory with manifest.json."),
    out: Optional[Path] = typer.Option(None, "--out", "-o", help="Recompute into a new directory (default: in place, from the cache)."),
    verbose: bool = typer.Option(False, "--verbose", "-v", help="Show Prefect's logs."),
    progress: Optional[str] = typer.Option(None, "--progress", help=PROGRESS_HELP),
):
    """Rerun a run from its manifest and compare the summary numbers.

    Exit status 0, 1 when the numbers (or the verdict) differ, 3 when they agree but
    the run's verdict is NOT ACCEPTED, 2 on bad input.
    """
    reporter = reporter_for(progress, console)
    run = _one_run(run, ctx.args)
    if run is None:
        raise UserInputError("give the run directory to reproduce: --run RUN_DIR")
    from fringecal.flows.validate import input_folder, output_folder

    input_folder(run, "--run", "run directory")
    output_folder(out, "--out")
    reporter.say(f"fringecal reproduce: reading {run}; the run goes to {out or run}")
    from fringecal.rundir import RunDir

    rd = RunDir(run)
    manifest = rd.read_manifest()
    old = rd.summary.load() if rd.summary.exists() else None
    cfg = validate_run_config(manifest["config"])
    target = out or run
    _apart(cfg, target)
    summary = _execute(cfg, target, None, None, None, verbose, f"fringecal reproduce --run {run}", reporter)
    _print_summary(summary, target)
    if old is not None:
        diffs = _differences(old, summary)
        if diffs:
            fail("reproduction differs: " + "; ".join(f"{k}: {a!r} -> {b!r}" for k, a, b in diffs), code=1)
        console.print("[green]reproduced:[/] the summary numbers are identical")
    not_accepted(summary)


#: ``reproduce`` also takes the run directory as its one argument (its older spelling,
#: ``fringecal reproduce RUN_DIR``), kept out of the help
REPRODUCE_CONTEXT = {"allow_extra_args": True}


def _one_run(run: Optional[Path], args: list[str]) -> Optional[Path]:
    """--run, or the older positional RUN_DIR (one, and not a second one)."""
    paths = ([run] if run is not None else []) + [Path(a) for a in args]
    if len(paths) > 1:
        raise UserInputError(f"one run directory, as --run RUN_DIR; got {', '.join(map(str, paths))}")
    return paths[0] if paths else None


def _differences(old: dict, new: dict) -> list[tuple]:
    keys = ["n_measurements", "n_control_points", "rms_F_mm_after", "rms_eps1_mm_after", "rms_eps2_mm_after",
            "one_part_in"]
    diffs = [(k, old[k], new[k]) for k in keys
             if abs(float(old[k]) - float(new[k])) > 1e-9 * max(1.0, abs(float(old[k])))]
    a, b = (old.get("verification") or {}).get("max_abs_error_mm"), (new.get("verification") or {}).get("max_abs_error_mm")
    if (a is None) != (b is None) or (a is not None and abs(a - b) > 1e-9):
        diffs.append(("verification.max_abs_error_mm", a, b))
    a, b = (old.get("verdict") or {}).get("word"), (new.get("verdict") or {}).get("word")
    if a is not None and b is not None and a != b:  # a summary from before the verdict existed has none
        diffs.append(("verdict", a, b))
    return diffs


SERVER_HELP = ("start one with `prefect server start --host 127.0.0.1` and point fringecal at it with "
               "PREFECT_API_URL=http://127.0.0.1:4200/api (docs/guide.md, \"Scheduled runs\")")


def _schedule(cron: Optional[str], interval: Optional[float], timezone: str):
    """The deployment's schedule: ``--cron`` (default nightly at 02:00) or ``--interval``."""
    import math
    from zoneinfo import ZoneInfo, ZoneInfoNotFoundError

    from prefect.schedules import Cron, Interval

    if cron is not None and interval is not None:
        raise UserInputError("give --cron or --interval, not both")
    try:
        ZoneInfo(timezone)
    except (ZoneInfoNotFoundError, ValueError):
        raise UserInputError(f"--timezone {timezone!r}: not an IANA time zone (e.g. UTC, Europe/Berlin)") from None
    if interval is not None:
        if not (math.isfinite(interval) and interval >= 1):
            raise UserInputError(f"--interval {interval}: expected a number of seconds >= 1")
        return Interval(interval, timezone=timezone), f"every {interval:g} s"
    cron = "0 2 * * *" if cron is None else cron
    try:
        return Cron(cron, timezone=timezone), f"cron {cron!r} ({timezone})"
    except ValueError as err:
        raise UserInputError(f"--cron {cron!r}: not a cron schedule ({err}); e.g. \"0 2 * * *\" for 02:00 "
                             "every night") from None


def _check_prefect_server(api: str) -> None:
    """The configured Prefect server answers and accepts fringecal's credentials."""
    import httpx
    from prefect.client.orchestration import get_client

    try:
        httpx.get(api.rstrip("/") + "/health", timeout=10).raise_for_status()
    except httpx.HTTPError as err:
        raise UserInputError(f"the Prefect server at {api} does not answer ({type(err).__name__}: {err}); "
                             + SERVER_HELP) from None
    try:
        with get_client(sync_client=True) as client:
            client.hello()
    except httpx.HTTPStatusError as err:
        if err.response.status_code != 401:
            raise UserInputError(f"the Prefect server at {api}: {err}") from None
        raise UserInputError(f"the Prefect server at {api} refuses fringecal's credentials (HTTP 401): set "
                             "PREFECT_API_AUTH_STRING to its PREFECT_SERVER_API_AUTH_STRING (user:password)") from None


@guarded
def serve_command(
    config: Optional[Path] = typer.Option(None, "--config", "-c", help="Run config YAML."),
    dataset: Optional[Path] = typer.Option(None, "--dataset", "-d", help="A recorded data set folder."),
    out: Path = typer.Option(Path("runs/nightly"), "--out", "-o", "--run", "-r",
                             help="Run directory of the scheduled runs."),
    cron: Optional[str] = typer.Option(None, "--cron", help="Schedule (cron; default \"0 2 * * *\", 02:00 every night)."),
    interval: Optional[float] = typer.Option(None, "--interval", help="Run every SECONDS instead of on a cron schedule."),
    timezone: str = typer.Option("UTC", "--timezone", help="IANA time zone of the schedule (e.g. Europe/Berlin)."),
    name: str = typer.Option("nightly-reverification", "--name", help="Deployment name."),
):
    """Serve the run flow as a scheduled deployment (e.g. a nightly re-verification) on a
    Prefect server: PREFECT_API_URL (or the active profile) must name one, started with
    `prefect server start --host 127.0.0.1` (Prefect's temporary server cannot schedule).
    One run at a time; each run's verdict is in OUT/summary.json, and a run that is NOT
    ACCEPTED ends in Prefect's Failed state with the verdict as its message. Once
    serving, the terminal shows one line for what ends it, the details go to
    OUT/fringecal.log. Ctrl-C or SIGTERM stops serving within seconds (status 130 or
    143), as does a Prefect server that stops answering (one line, status 1); a run in
    progress is then stopped, and the next run resumes its finished steps.
    """
    no_prefect_telemetry()
    api = configured_prefect_api()
    if api is None:
        raise UserInputError("fringecal serve needs a Prefect server, and none is configured (Prefect's temporary "
                             "server cannot schedule runs): " + SERVER_HELP)
    schedule, when = _schedule(cron, interval, timezone)
    _check_inputs(config, dataset, out)
    cfg = validate_run_config(config, dataset=dataset)
    _apart(cfg, out)
    _check_prefect_server(api)
    from prefect.types.entrypoint import EntrypointType

    from fringecal.flows import serving
    from fringecal.flows.run_flow import run_flow
    from fringecal.rundir import RunDir

    run_dir = out.expanduser().absolute()  # the runs start in their own processes and folders
    log = RunDir(run_dir).log.path
    console.print(f"serving deployment {name!r} ({when}) on {api}; runs write to {run_dir}, the details to {log} "
                  "(Ctrl-C stops)", soft_wrap=True, highlight=False)
    serving.detach(log)
    serving.arm_signals(run_dir)
    serving.watch_server(api, run_dir, log)
    run_flow.serve(name=name, schedule=schedule, limit=1, entrypoint_type=EntrypointType.MODULE_PATH,
                   print_starting_message=False,
                   parameters={"config": cfg.model_dump(mode="json"), "run_dir": str(run_dir),
                               "command": f"scheduled {name}"})
