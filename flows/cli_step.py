"""``fringecal step NAME --run RUN_DIR`` and ``fringecal calibrate --run RUN_DIR``:
one pipeline step over an existing run directory, without Prefect.

The step is the same object the flow runs (:mod:`fringecal.steps`) and keeps the
same records, so a later ``fringecal run`` into the directory reuses what it wrote.
Settings come from ``--config`` (a run config; only the sections the step uses
matter), else from the run's ``manifest.json``, else the defaults.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Optional

import typer

from fringecal.flows.common import UserInputError, console, err_console, guarded

__all__ = ["step_command", "calibrate_command", "run_config_of"]


def run_config_of(run: Path, config: Optional[Path]):
    """The settings a step command uses (see the module notes)."""
    from fringecal.run.config import RunConfig, load_run_config
    from fringecal.rundir import RunDir

    if not run.is_dir():
        raise UserInputError(f"{run}: no such run directory")
    if config is not None:
        return load_run_config(config)
    rd = RunDir(run)
    if rd.manifest.exists():
        return RunConfig.model_validate(rd.read_manifest()["config"])
    return RunConfig()


def _run(name: str, run: Path, config: Optional[Path], force: bool) -> list[dict]:
    from fringecal.rundir import RunDir
    from fringecal.steps import get_step, run_step

    try:
        step = get_step(name)
    except KeyError as err:
        raise UserInputError(err.args[0]) from None
    cfg = run_config_of(run, config)
    rd = RunDir(run)
    return [run_step(step, rd, cfg, item, force=force) for item in step.items(rd, step.view(cfg))]


@guarded
def step_command(
    name: str = typer.Argument(..., help="The step (fringecal run's steps: ingest, decode, spheres-first, label, "
                                         "spheres-second, initialise, bundle, verify, evaluate, report, ...)."),
    run: Path = typer.Option(..., "--run", "-r", help="Run directory."),
    config: Optional[Path] = typer.Option(None, "--config", "-c", help="Run config YAML (default: the run's manifest)."),
    force: bool = typer.Option(False, "--force", help="Run even if the step's outputs are current."),
    as_json: bool = typer.Option(False, "--json", help="Print the step's records as JSON."),
):
    """Run one pipeline step over a run directory (every measurement of a per-measurement step).

    Exit status 0; 3 when the ball-bar (``verify``) or the acceptance test
    (``acceptance``) is NOT ACCEPTED under ISO 14253-1; 2 on bad input.
    """
    records = _run(name, run, config, force)
    if as_json:
        print(json.dumps(records, indent=2))
    else:
        ran = [r for r in records if not r["reused"]]
        console.print(f"{name}: {len(ran)} ran, {len(records) - len(ran)} current already "
                      f"({sum(r.get('seconds', 0.0) for r in ran):.1f} s)")
    _verdict(name, run)


def _verdict(name: str, run: Path) -> None:
    """``step verify`` and ``step acceptance`` exit with status 3 when their part of the
    run's verdict (:func:`fringecal.acceptance.verdict.run_verdict`: the ball-bar's
    lengths, or the acceptance test's parameters) is NOT ACCEPTED, as ``fringecal run``
    and ``fringecal verify acceptance`` do."""
    from fringecal.acceptance.verdict import run_verdict
    from fringecal.rundir import RunDir

    rd = RunDir(run)
    if name == "verify" and rd.verification.exists():
        verdict, what = run_verdict(rd.verification.load(), None), "ball-bar"
    elif name == "acceptance" and rd.acceptance.exists():
        verdict, what = run_verdict(None, rd.acceptance.load()), "acceptance test"
    else:
        return
    if verdict["accepted"] is False:
        err_console.print(f"[red]{what} {verdict['word']}[/]: {verdict['failing']} (exit status 3)",
                          highlight=False, soft_wrap=True)
        raise typer.Exit(3)


def calibrate_command(
    run: Path = typer.Option(..., "--run", "-r", help="Run directory (artefact.csv, tables/control_points.csv, "
                             "tables/poses_initial.csv, tables/sensors_initial.csv)."),
    config: Optional[Path] = typer.Option(None, "--config", "-c", help="Run config YAML whose bundle section to use "
                                          "(default: the run's manifest, else the defaults)."),
    force: bool = typer.Option(False, "--force", help="Adjust even if the outputs are current."),
    as_json: bool = typer.Option(False, "--json", help="Print the summary as JSON."),
):
    """Bundle adjustment: refine every sensor and artefact pose from the control points (the `bundle` step)."""
    from fringecal.calibration.bundle import StartValueError
    from fringecal.calibration.diagnostics import DegenerateCalibrationError
    from fringecal.calibration.dlt import DLTError
    from fringecal.config import ConfigError
    from fringecal.flows.common import fail
    from fringecal.rundir import RunDir

    try:
        record = _run("bundle", run, config, force)[0]
    except (DegenerateCalibrationError, StartValueError, DLTError, ConfigError) as err:
        fail(str(err))
    summary = RunDir(run).bundle_summary.load()
    if as_json:
        print(json.dumps({k: summary[k] for k in ("before", "after", "iterations", "converged", "diagnostics",
                                                  "one_part_in_1p96_sigma", "volume_diagonal_mm")}
                         | {"outputs": sorted(record["outputs"]), "reused": record["reused"]}, indent=2))
        return
    from rich.table import Table

    t = Table(title=f"bundle adjustment of {run} ({summary['iterations']} iterations, "
                    f"{'converged' if summary['converged'] else 'NOT converged'})")
    for c in ("", "F (mm)", "epsilon-1 (mm)", "epsilon-2 (mm)"):
        t.add_column(c, justify="right")
    for label in ("before", "after"):
        s = summary[label]
        t.add_row(label, f"{s['rms_f_mm']:.4f}", f"{s['rms_eps1_mm']:.4f}", f"{s['rms_eps2_mm']:.4f}")
    console.print(t)
    console.print(f"1.96 sigma epsilon-2: one part in {summary['one_part_in_1p96_sigma']:.0f} of the "
                  f"{summary['volume_diagonal_mm']:.0f} mm volume diagonal ({summary['volume_diagonal_source']})")
    for d in summary["diagnostics"]:
        err_console.print(f"[yellow]{d['kind']}[/]: {d['message']}", highlight=False)
    console.print(f"written: {', '.join(sorted(record['outputs']))}"
                  + (" (already current)" if record["reused"] else ""))
