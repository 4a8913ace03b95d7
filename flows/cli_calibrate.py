"""``fringecal calibrate --run RUN_DIR``: the bundle adjustment of a run directory."""

from __future__ import annotations

import json
from pathlib import Path

import typer
from rich.console import Console

console = Console()
err_console = Console(stderr=True)


def _fail(message: str):
    err_console.print(f"[bold red]error:[/] {message}", highlight=False)
    raise typer.Exit(2)


def calibrate(
    run: Path = typer.Option(..., "--run", "-r", help="Run directory (artefact.csv, tables/control_points.csv, "
                             "tables/poses_initial.csv, tables/sensors_initial.csv[, calibrate.yaml])."),
    as_json: bool = typer.Option(False, "--json", help="Print the summary as JSON."),
):
    """Bundle adjustment: refine every sensor and artefact pose from the control points.

    Registered in flows/cli.py wrapped in ``guarded`` (bad tables exit with status 2);
    configuration and degenerate-geometry errors are reported here the same way.
    """
    from fringecal.calibration.bundle import StartValueError
    from fringecal.calibration.diagnostics import DegenerateCalibrationError
    from fringecal.calibration.dlt import DLTError
    from fringecal.calibration.run import load_config, load_problem
    from fringecal.config import ConfigError

    try:
        load_problem(run, load_config(run))  # every input checked before Prefect starts
    except ConfigError as err:
        _fail(str(err))
    from flows.calibrate_flow import calibrate_flow

    try:
        out = calibrate_flow(str(run))
    except (DegenerateCalibrationError, StartValueError, DLTError, ConfigError) as err:
        _fail(str(err))
    if as_json:
        doc = {k: v for k, v in out.items() if k != "outputs"}
        doc["outputs"] = {k: r.path for k, r in out["outputs"].items()}
        print(json.dumps(doc, indent=2))
        return
    from rich.table import Table

    t = Table(title=f"bundle adjustment of {run} ({out['iterations']} iterations, "
                    f"{'converged' if out['converged'] else 'NOT converged'})")
    for c in ("", "F (mm)", "epsilon-1 (mm)", "epsilon-2 (mm)"):
        t.add_column(c, justify="right")
    for label in ("before", "after"):
        s = out[label]
        t.add_row(label, f"{s['rms_f_mm']:.4f}", f"{s['rms_eps1_mm']:.4f}", f"{s['rms_eps2_mm']:.4f}")
    console.print(t)
    summary = json.loads(Path(out["outputs"]["summary"].path).read_text())
    console.print(f"1.96 sigma epsilon-2: one part in {summary['one_part_in_1p96_sigma']:.0f} of the "
                  f"{summary['volume_diagonal_mm']:.0f} mm volume diagonal ({summary['volume_diagonal_source']})")
    for d in out["diagnostics"]:
        err_console.print(f"[yellow]{d['kind']}[/]: {d['message']}", highlight=False)
    console.print(f"written: {', '.join(str(Path(r.path).relative_to(run)) for r in out['outputs'].values())}")
