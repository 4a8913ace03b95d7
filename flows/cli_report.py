"""``fringecal report --run RUN_DIR``: (re)write the report of an existing run."""

from __future__ import annotations

from pathlib import Path

import typer

from fringecal.flows.common import UserInputError, console, guarded


@guarded
def report_command(
    run: Path = typer.Option(..., "--run", "-r", help="Run directory written by `fringecal run` "
                             "(or `fringecal calibrate`)."),
):
    """Write RUN_DIR/report.html from the files in the run directory (nothing is recomputed).

    Step timings come from summary.json; sections whose files are missing say so.
    """
    from fringecal.report import write_report

    if not run.is_dir():
        raise UserInputError(f"{run}: no such run directory")
    path = write_report(run)
    console.print(f"report written: {path}", highlight=False, soft_wrap=True)
