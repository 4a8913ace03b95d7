"""The ``fringecal`` command line (typer).

Pipeline commands run Prefect flows; small utilities (fitting exported points,
kinematics, ball-bar evaluation) call fringecal directly so they answer at once.
Inputs are validated before a flow starts, so bad input costs no Prefect start-up
and leaves nothing half-written.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import typer

from fringecal.flows.common import UserInputError, console, err_console, guarded
from fringecal.flows.help import CONTEXT, example

app = typer.Typer(add_completion=False, no_args_is_help=True, context_settings=CONTEXT,
                  help="Calibrate fringe-projection scanners into one global frame.",
                  epilog=example("fringecal run --out runs/demo"))


def _print_version(value: bool) -> None:
    if value:
        from fringecal import __version__

        print(f"fringecal {__version__}")
        raise typer.Exit()


@app.callback()
def _options(
    version: bool = typer.Option(False, "--version", callback=_print_version, is_eager=True,
                                 help="Print fringecal's version and exit."),
):
    """Calibrate fringe-projection scanners into one global frame."""


@app.command(epilog=example("fringecal pose --artefact configs/thesis/artefact_cmm2.csv "
                            "--centres configs/thesis/centres_scanner1_table6-3.csv --out poses.csv"))
@guarded
def pose(
    artefact: Path = typer.Option(..., "--artefact", "-a", help="Artefact definition CSV (sphere_id, x_mm, y_mm, z_mm, diameter_mm)."),
    centres: Path = typer.Option(..., "--centres", help="Sphere centres CSV (measurement, scanner, sphere_id, x_mm, y_mm, z_mm)."),
    out: Path = typer.Option(..., "--out", "-o", help="Poses CSV to write."),
    as_json: bool = typer.Option(False, "--json", help="Print the result as JSON."),
):
    """Artefact pose per (measurement, scanner) by SVD against the artefact definition.

    Runs directly (milliseconds of SVD); as a Prefect flow only when a Prefect server
    is configured (PREFECT_API_URL or a profile), so that the run shows there.
    """
    from fringecal.artefact import load_artefact
    from fringecal.flows.common import configured_prefect_api, no_prefect_telemetry
    from fringecal.flows.validate import output_file
    from fringecal.schemas import SphereCentresTable, read_table

    output_file(out, "--out")  # validate every input before anything is written
    art = load_artefact(artefact)
    if len(art) < 3:
        raise UserInputError(f"{artefact}: {len(art)} sphere(s); a pose needs at least 3 spheres of the artefact")
    read_table(centres, SphereCentresTable)

    if configured_prefect_api():
        no_prefect_telemetry()
        from fringecal.flows.pose_flow import pose_flow

        result = pose_flow(str(artefact), str(centres), str(out))
        written, skipped = result["poses"] is not None, result["skipped"]
    else:
        from fringecal.spheres.pose import estimate_poses_file

        result = estimate_poses_file(artefact, centres, out)
        written, skipped = len(result.poses) > 0, result.skipped.to_dict("records")
    if not written:
        reasons = "; ".join(f"{s['measurement']}/{s['scanner']}: {s['reason']}" for s in skipped)
        raise UserInputError(f"{centres}: no group gives a pose ({reasons}); nothing written")
    import pandas as pd

    poses = pd.read_csv(out, dtype={"measurement": str, "scanner": str})
    if as_json:
        print(json.dumps({"poses": poses.to_dict("records"), "skipped": skipped, "out": str(out)}, indent=2))
        return
    from rich.table import Table

    t = Table(title=f"poses -> {out}")
    for c in poses.columns:
        t.add_column(c, justify="right")
    for r in poses.itertuples(index=False):
        t.add_row(*[f"{v:.4f}" if isinstance(v, float) else str(v) for v in r])
    console.print(t)
    for s in skipped:
        err_console.print(f"[yellow]skipped[/] measurement {s['measurement']}, scanner {s['scanner']}: {s['reason']}")


def _register_subcommands():
    """Sub-apps live in flows/cli_<area>.py; they import helpers from this module."""
    from fringecal.flows import (
        cli_acquire,
        cli_artefact,
        cli_decode,
        cli_fit,
        cli_hexapod,
        cli_interop,
        cli_measure,
        cli_report,
        cli_run,
        cli_simulate,
        cli_step,
        cli_verify,
    )

    commands = [
        ("run", cli_run.run_command, "fringecal run --out runs/demo"),
        ("reproduce", cli_run.reproduce_command, "fringecal reproduce --run runs/demo --out runs/demo-again"),
        ("serve", cli_run.serve_command, "fringecal serve --dataset my-example --out runs/nightly --timezone UTC"),
        ("decode", cli_decode.decode_command,
         "fringecal decode --frames my-example/measurements/1/scanner1 --out 1-scanner1.zarr"),
        ("simulate", cli_simulate.simulate_command, "fringecal simulate --out my-example"),
        ("acquire", cli_acquire.acquire_command, "fringecal acquire --dataset my-cell --hexapod /dev/ttyUSB0 --dry-run"),
        ("step", cli_step.step_command, "fringecal step bundle --run runs/demo"),
        ("calibrate", guarded(cli_step.calibrate_command), "fringecal calibrate --run runs/demo"),
        ("report", cli_report.report_command, "fringecal report --run runs/demo"),
        ("measure", cli_measure.measure_command,
         "fringecal measure --run runs/demo --frames my-example/measurements/1 --out artefact-1.ply"),
    ]
    for name, command, line in commands:
        extra = {"context_settings": cli_run.REPRODUCE_CONTEXT} if name == "reproduce" else {}
        app.command(name, epilog=example(line), **extra)(command)
    app.add_typer(cli_verify.app, name="verify")
    app.add_typer(cli_fit.fit_app, name="fit")
    app.add_typer(cli_hexapod.app, name="hexapod")
    app.add_typer(cli_artefact.app, name="artefact")
    app.add_typer(cli_interop.export_app, name="export")
    app.add_typer(cli_interop.import_app, name="import")


if __name__ != "__main__":
    _register_subcommands()


def main():  # pragma: no cover - console entry point
    app()


if __name__ == "__main__":  # pragma: no cover
    # `python -m fringecal.flows.cli`: run the imported module so sub-apps register exactly once.
    from fringecal.flows.cli import main as _main

    sys.exit(_main())
