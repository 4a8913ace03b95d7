"""``fringecal run``, ``fringecal reproduce`` and ``fringecal serve``."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Optional

import typer

from .common import UserInputError, console, err_console, fail, guarded

__all__ = ["run_command", "reproduce_command", "serve_command", "validate_run_config", "make_task_runner"]


def validate_run_config(config: Path | dict | None, overrides: dict | None = None):
    """Load and check a run config and every file it names, before any Prefect work."""
    from fringecal.acquisition import AcquisitionInputs
    from fringecal.config import ConfigError
    from fringecal.runconfig import RunConfig, load_run_config

    if isinstance(config, dict):
        try:
            cfg = RunConfig.model_validate(config)
        except ValueError as err:
            raise ConfigError(f"run config: {err}") from None
        cfg.rig_config()
    else:
        cfg = load_run_config(config, overrides)
    # sensors (one camera and one projector per scanner), artefact, rods, materials and poses
    inputs = AcquisitionInputs.from_run_config(cfg)
    if len(inputs.artefact) < 3:
        raise ConfigError(f"{cfg.rig_config().artefact}: an artefact needs at least three spheres for a pose")
    return cfg


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
    """The summary of an up-to-date run of this config in ``out`` (checked by content
    digests before Prefect starts, which costs seconds), or None."""
    from fringecal.rundir import up_to_date

    summary = up_to_date(out, cfg.model_dump(mode="json"))
    if summary is not None:
        n = len(summary["tasks"]["ran"]) + len(summary["tasks"]["cached"])
        summary = {**summary, "tasks": {"ran": [], "cached": ["(all %d steps: outputs unchanged)" % n]}}
        err_console.print(f"{out} is up to date with this configuration (every output unchanged); --force reruns "
                          "the flow from its cache")
    return summary


def _quiet_prefect(verbose: bool) -> None:
    """Progress bars instead of Prefect's log lines; the temporary server's own
    shutdown chatter (events still in flight when the process ends) is not news."""
    if not verbose:
        os.environ.setdefault("PREFECT_LOGGING_LEVEL", "WARNING")
        os.environ.setdefault("PREFECT_SERVER_LOGGING_LEVEL", "CRITICAL")


def _print_summary(summary: dict, run_dir: Path) -> None:
    from rich.table import Table

    t = Table(title=f"fringecal run -> {run_dir}", show_header=False)
    t.add_column("", style="bold")
    t.add_column("", justify="right")
    v, tr = summary["verification"], summary.get("truth") or {}
    rows = [
        ("measurements / control points", f"{summary['n_measurements']} / {summary['n_control_points']:,}"),
        ("RMS F before -> after", f"{summary['rms_F_mm_before']:.3f} mm -> {1000 * summary['rms_F_mm_after']:.1f} um"),
        ("RMS eps1 / eps2 after", f"{1000 * summary['rms_eps1_mm_after']:.1f} / {1000 * summary['rms_eps2_mm_after']:.1f} um"),
        ("one part in (1.96 sigma eps2)", f"{summary['one_part_in']:,.0f}"),
        ("ball-bar max |error|", f"{1000 * v['max_abs_error_mm']:.1f} um = 1/{v['one_part_in']:,.0f} of "
                                 f"{v['volume_diagonal_mm']:.0f} mm"),
        ("verification (MPE %.0f um)" % (1000 * v["mpe_mm"]), "[green]PASS[/]" if v["pass"] else "[red]FAIL[/]"),
    ]
    if tr:
        rows += [("truth: eps1 / eps2 floor", f"{1000 * tr['rms_eps1_mm_true_params']:.1f} / "
                                              f"{1000 * tr['rms_eps2_mm_true_params']:.1f} um"),
                 ("truth: ball-bar max |error|", f"{1000 * tr['verification_max_abs_error_true_params_mm']:.1f} um"),
                 ("truth: max position / angle error", f"{tr['max_position_error_mm']:.3f} mm / "
                                                       f"{1e3 * tr['max_angle_error_rad']:.3f} mrad")]
    rows += [("bundle adjustment / total", f"{summary['bundle_seconds']:.2f} s / {summary['total_seconds']:.0f} s"),
             ("tasks run / from cache", f"{len(summary['tasks']['ran'])} / {len(summary['tasks']['cached'])}")]
    for k, val in rows:
        t.add_row(k, val)
    console.print(t)
    console.print(f"report: {run_dir / 'report.html'}")


def _execute(cfg, run_dir: Path, runner: Optional[str], dask_address: Optional[str], workers: Optional[int],
             verbose: bool, command: str, progress_console=None) -> dict:
    _quiet_prefect(verbose)
    from flows.progress import RichProgress
    from flows.run_flow import run_flow

    kind = runner or cfg.runner.kind
    task_runner = make_task_runner(kind, workers or cfg.runner.max_workers, dask_address or cfg.runner.dask_address,
                                   workers or cfg.runner.dask_workers)
    flow = run_flow.with_options(task_runner=task_runner)
    with RichProgress(progress_console or console).running():
        return flow(cfg.model_dump(mode="json"), str(run_dir), None, command)


@guarded
def run_command(
    config: Optional[Path] = typer.Option(None, "--config", "-c", help="Run config YAML (default: configs/run_thesis.yaml, the simulated thesis rig)."),
    out: Path = typer.Option(Path("runs/thesis"), "--out", "-o", help="Run directory."),
    runner: Optional[str] = typer.Option(None, "--runner", help="threads (default) or dask."),
    dask_address: Optional[str] = typer.Option(None, "--dask-address", help="Scheduler of an existing Dask cluster."),
    workers: Optional[int] = typer.Option(None, "--workers", help="Threads, or local Dask workers."),
    as_json: bool = typer.Option(False, "--json", help="Print summary.json."),
    verbose: bool = typer.Option(False, "--verbose", "-v", help="Show Prefect's logs."),
    force: bool = typer.Option(False, "--force", help="Run the flow even if the run directory is up to date."),
):
    """Acquire, decode, extract and label spheres, calibrate, verify and report: the thesis experiment."""
    if runner not in (None, "threads", "dask"):
        raise UserInputError(f"--runner must be threads or dask, not {runner!r}")
    cfg = validate_run_config(config)
    summary = None if force else _current(cfg, out)
    if summary is None:
        summary = _execute(cfg, out, runner, dask_address, workers, verbose, "fringecal run",
                           err_console if as_json else console)
    if as_json:
        print(json.dumps(summary, indent=2))
    else:
        _print_summary(summary, out)


@guarded
def reproduce_command(
    run_dir: Path = typer.Argument(..., help="A run directory with manifest.json."),
    out: Optional[Path] = typer.Option(None, "--out", "-o", help="Recompute into a new directory (default: in place, from the cache)."),
    verbose: bool = typer.Option(False, "--verbose", "-v"),
):
    """Rerun a run from its manifest and compare the summary numbers."""
    from fringecal.rundir import RunDir

    rd = RunDir(run_dir)
    manifest = rd.read_manifest()
    old = json.loads(rd.summary.read_text()) if rd.summary.exists() else None
    cfg = validate_run_config(manifest["config"])
    target = out or run_dir
    summary = _execute(cfg, target, None, None, None, verbose, f"fringecal reproduce {run_dir}")
    _print_summary(summary, target)
    if old is None:
        return
    keys = ["n_measurements", "n_control_points", "rms_F_mm_after", "rms_eps1_mm_after", "rms_eps2_mm_after",
            "one_part_in"]
    diffs = [(k, old[k], summary[k]) for k in keys if abs(float(old[k]) - float(summary[k])) > 1e-9 * max(1.0, abs(float(old[k])))]
    dv = abs(old["verification"]["max_abs_error_mm"] - summary["verification"]["max_abs_error_mm"])
    if dv > 1e-9:
        diffs.append(("verification.max_abs_error_mm", old["verification"]["max_abs_error_mm"],
                      summary["verification"]["max_abs_error_mm"]))
    if diffs:
        fail("reproduction differs: " + "; ".join(f"{k}: {a!r} -> {b!r}" for k, a, b in diffs), code=1)
    console.print("[green]reproduced:[/] the summary numbers are identical")


@guarded
def serve_command(
    config: Optional[Path] = typer.Option(None, "--config", "-c", help="Run config YAML."),
    out: Path = typer.Option(Path("runs/nightly"), "--out", "-o", help="Run directory of the scheduled runs."),
    cron: str = typer.Option("0 2 * * *", "--cron", help="Schedule (cron, local time)."),
    name: str = typer.Option("nightly-reverification", "--name", help="Deployment name."),
):
    """Serve the run flow as a scheduled deployment (e.g. a nightly re-verification)."""
    cfg = validate_run_config(config)
    from flows.run_flow import run_flow

    console.print(f"serving deployment {name!r} on schedule {cron!r}; runs write to {out} (Ctrl-C stops)")
    run_flow.serve(name=name, cron=cron, parameters={"config": cfg.model_dump(mode="json"), "run_dir": str(out),
                                                      "command": f"scheduled {name}"})
