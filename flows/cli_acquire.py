"""``fringecal acquire``: fill a data set with a real hexapod and real scanners
(:mod:`fringecal.acquisition.live`; no Prefect: it drives hardware step by step)."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer
from rich.markup import escape

from fringecal.flows.common import UserInputError, console, fail, guarded, user_errors

CAPTURE_HELP = ("Capture command template, run once per (measurement, scanner), e.g. "
                "'vendor-scan --scanner {scanner} --out {out}'. Placeholders: {measurement}, {scanner}, {out} "
                "(the folder to write the image stack into), {dataset}. Needed unless --dry-run.")


@guarded
def acquire_command(
    dataset: Path = typer.Option(..., "--dataset", "-d", help="Data set folder with dataset.yaml, artefact.csv, "
                                 "sensors_prior.csv and poses_planned.csv (measurements/ is filled)."),
    hexapod: str = typer.Option(..., "--hexapod", help="The hexapod controller's serial port (/dev/ttyUSB0) or a "
                                "pyserial URL (hexsim://name?... for the simulated box)."),
    capture: Optional[str] = typer.Option(None, "--capture", help=CAPTURE_HELP),
    hexapod_config: Optional[Path] = typer.Option(None, "--hexapod-config", help="Hexapod YAML with placement and "
                                                  "mounting (default: configs/hexapod/thesis_platform.yaml)."),
    timeout: float = typer.Option(120.0, "--timeout", min=0.1, help="Seconds from starting a capture until its "
                                  "image stack must be complete."),
    retries: int = typer.Option(0, "--retries", min=0, help="Further attempts of a failed capture at the same pose."),
    settle: float = typer.Option(1.0, "--settle", min=0.0, help="Seconds to wait after each move before capturing."),
    dry_run: bool = typer.Option(False, "--dry-run", help="Only query the controller (identify, read the encoders) "
                                 "and check every planned move; move nothing, capture nothing, write nothing."),
):
    """Move the artefact to each planned pose and capture every scanner's image stack;
    rerun to resume. Exit status: 0 done, 1 hexapod, 2 bad input (nothing moved),
    3 capture, 130 interrupted."""
    from fringecal.acquisition.live import EXIT_HEXAPOD, EXIT_INPUT, AcquisitionError
    from fringecal.acquisition.live_capture import CaptureTemplateError
    from fringecal.flows.validate import number
    from fringecal.hexapod import ForwardKinematicsError, HexapodFault, TargetRejected

    try:
        number(timeout, "--timeout", gt=0, unit="s")
        number(settle, "--settle", ge=0, unit="s")
        if dry_run:
            _dry_run(dataset, hexapod, capture, hexapod_config)
        else:
            _acquire(dataset, hexapod, capture, hexapod_config, timeout, retries, settle)
    except AcquisitionError as err:
        fail(escape(str(err)), err.status)
    except HexapodFault as err:
        fail(escape(f"hexapod fault ({err.kind}): {err}"), EXIT_HEXAPOD)
    except user_errors() + (TargetRejected, CaptureTemplateError, ForwardKinematicsError) as err:
        fail(escape(str(err)), EXIT_INPUT)


def _say(line: str) -> None:
    console.print(line, markup=False, highlight=False)


def _acquire(dataset, hexapod, capture, hexapod_config, timeout, retries, settle) -> None:
    from fringecal.acquisition.live import acquire, prepare, stop_on_signals

    if capture is None:
        raise UserInputError("--capture is needed (or --dry-run to only check)")
    plan = prepare(dataset, hexapod_config, capture)
    todo = plan.survey.todo()
    _say(f"{plan.root}: {len(plan.planned) - len(todo)} of {len(plan.planned)} measurements complete, "
         f"{len(todo)} to acquire with scanners {', '.join(plan.cameras)}")
    with stop_on_signals() as stop:
        ds = acquire(plan, hexapod, timeout, retries, settle, stop, report=_say)
    log = f"; hexapod log {ds.hexapod_moves}" if ds.hexapod_moves else ""
    _say(f"data set complete: {len(ds.measurement_names())} measurements x {len(ds.scanners)} scanners{log}")
    _say(f"calibrate it with: fringecal run --dataset {ds.root} --out runs/{ds.root.name}")


def _dry_run(dataset, hexapod, capture, hexapod_config) -> None:
    from rich.table import Table

    from fringecal.acquisition.live import EXIT_INPUT, prepare
    from fringecal.acquisition.live_dryrun import dry_run

    plan = prepare(dataset, hexapod_config, capture)
    rep = dry_run(plan, hexapod)
    _say(f"hexapod at {rep.url}: {rep.identity}; encoders {rep.counts.tolist()} "
         f"{'BUSY' if rep.busy else 'IDLE'}")
    if rep.artefact_pose is not None:
        p = rep.artefact_pose.params
        _say(f"artefact now at T_world_artefact t = ({p[0]:.3f}, {p[1]:.3f}, {p[2]:.3f}) mm, "
             f"angles ({p[3]:.6f}, {p[4]:.6f}, {p[5]:.6f}) rad")
    t = Table(title=f"dry run: {plan.root}")
    for c in ("measurement", "status", "missing scanners", "check"):
        t.add_column(c)
    for r in rep.rows:
        check = "-" if r.status == "complete" else (escape(r.problem) if r.problem else "ok")
        t.add_row(escape(r.measurement), r.status, escape(", ".join(r.missing)), check)
    console.print(t)
    for s in rep.stale:
        _say(f"stale staging folder (a real run removes it): {s}")
    problems = rep.problems()
    if problems:
        fail(escape(f"dry run: {len(problems)} problem(s) would stop the acquisition: " + "; ".join(problems)),
             EXIT_INPUT)
    _say(f"dry run ok: nothing moved, nothing captured; {len(plan.survey.todo())} measurement(s) to acquire")
