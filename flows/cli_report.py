"""``fringecal report --run RUN_DIR [--pdf OUT.pdf]``: (re)write the report of an
existing run, and print it to an A4 PDF."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from fringecal.flows.common import UserInputError, console, fail, guarded


@guarded
def report_command(
    run: Path = typer.Option(..., "--run", "-r", help="Run directory written by `fringecal run` "
                             "(or `fringecal calibrate`)."),
    pdf: Optional[Path] = typer.Option(None, "--pdf", help="Also print the report to this PDF (A4, the "
                                       "certificate on page one) with headless Chromium."),
):
    """Write RUN_DIR/report.html from the files in the run directory (nothing is recomputed).

    Step timings come from summary.json; sections whose files are missing say so.
    With --pdf the page is printed to A4 by headless Chromium (chromium on PATH, or
    FRINGECAL_CHROMIUM); without Chromium the command says what to install (exit 2).
    """
    from fringecal.flows.validate import output_file
    from fringecal.report import write_report
    from fringecal.report.pdf import PdfEngineMissing, PdfError, print_pdf, require_chromium

    if not run.is_dir():
        raise UserInputError(f"{run}: no such run directory")
    if pdf is not None:
        output_file(pdf, "--pdf")
        try:
            require_chromium()  # before any work: without Chromium nothing is written
        except PdfEngineMissing as err:
            raise UserInputError(f"--pdf {pdf}: {err}") from None
    path = write_report(run)
    console.print(f"report written: {path}", highlight=False, soft_wrap=True)
    if pdf is not None:
        try:
            print_pdf(path, pdf)
        except PdfError as err:
            fail(f"--pdf {pdf}: {err}", 1)
        console.print(f"PDF written: {pdf}", highlight=False, soft_wrap=True)
