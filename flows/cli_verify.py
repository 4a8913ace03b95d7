"""``fringecal verify``: VDI/VDE 2634 evaluations of exported measurements."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Optional

import typer
from rich.table import Table

from fringecal.flows.common import UserInputError, console, guarded
from fringecal.flows.help import CONTEXT, example

BALLBAR_EXAMPLE = ("fringecal verify ballbar --centres configs/thesis/ballbar_verification_table6-9.csv "
                   "--reference-length-mm 1015.65 --volume-diagonal-mm 2872.3 --mpe-mm 0.2")
app = typer.Typer(no_args_is_help=True, context_settings=CONTEXT, epilog=example(BALLBAR_EXAMPLE),
                  help="Verification per VDI/VDE 2634 (parts 2 and 3).")


@app.command("ballbar", epilog=example(BALLBAR_EXAMPLE))
@guarded
def ballbar(
    centres: Optional[Path] = typer.Option(None, "--centres", help="Sphere centres CSV with spheres A and B per "
                                           "measurement, or a run's tables/ballbar_centres.csv (per position)."),
    run: Optional[Path] = typer.Option(None, "--run", "-r", help="A verified run directory: its ball-bar centres "
                                       "(tables/ballbar_centres.csv) and, by default, its bar's CMM length."),
    reference_length_mm: Optional[float] = typer.Option(None, "--reference-length-mm", "-L",
                                                        help="Calibrated centre distance (default with --run: "
                                                             "the run's ballbar.csv)."),
    volume_diagonal_mm: Optional[float] = typer.Option(None, "--volume-diagonal-mm", "-D", help="Measurement volume diagonal."),
    mpe_mm: Optional[float] = typer.Option(None, "--mpe-mm", help="Maximum permissible length error."),
    certificate_u_mm: float = typer.Option(0.0, "--certificate-u-mm", help="Expanded uncertainty of the reference length (certificate)."),
    certificate_k: float = typer.Option(2.0, "--certificate-k", help="Coverage factor of the certificate value."),
    coverage_factor: float = typer.Option(1.96, "--k", help="Coverage factor of the stated uncertainty."),
    as_json: bool = typer.Option(False, "--json", help="Print the result as JSON."),
):
    """Length error of a ball-bar per position: mean, max |error|, one part in N of the diagonal.

    Exit status 0, or 3 when a length error exceeds --mpe-mm (FAIL), 2 on bad input.
    """
    from fringecal.flows.validate import number, positive
    from fringecal.schemas import BallbarCentresTable, SphereCentresTable, read_any_table
    from fringecal.verification.lengths import ballbar_lengths, evaluate_ballbar

    given = reference_length_mm
    centres, reference_length_mm = _ballbar_inputs(centres, run, reference_length_mm)
    positive(reference_length_mm, "--reference-length-mm", "mm")
    positive(volume_diagonal_mm, "--volume-diagonal-mm", "mm")
    positive(mpe_mm, "--mpe-mm", "mm")
    number(certificate_u_mm, "--certificate-u-mm", ge=0, unit="mm")
    positive(certificate_k, "--certificate-k")
    positive(coverage_factor, "--k")
    table = read_any_table(centres, SphereCentresTable, BallbarCentresTable)
    lengths = ballbar_lengths(table, str(centres))
    from fringecal.flows.validate import same_unit

    same_unit(float(lengths.length_mm.mean()), reference_length_mm,
              "--reference-length-mm" if given is not None else "the run's ballbar.csv: reference length")
    result = evaluate_ballbar(lengths.length_mm, reference_length_mm, lengths.measurement, mpe_mm,
                              volume_diagonal_mm, certificate_u_mm, certificate_k, coverage_factor)
    failed = mpe_mm is not None and not result.passed  # exit status 3 after the result is printed
    if as_json:
        print(json.dumps(result.to_dict(), indent=2))
        if failed:
            raise typer.Exit(3)
        return
    t = Table(title=f"ball-bar, reference {reference_length_mm:.4f} mm")
    for c in ("position", "length (mm)", "error (um)", "pass"):
        t.add_column(c, justify="right")
    for r in result.positions.itertuples():
        t.add_row(str(r.measurement), f"{r.length_mm:.4f}", f"{r.error_mm * 1000:+.1f}",
                  "-" if mpe_mm is None else "yes" if r._4 else "[red]no[/]")
    console.print(t)
    console.print(f"mean length {result.mean_length_mm:.4f} mm "
                  f"(error {1000 * (result.mean_length_mm - reference_length_mm):+.1f} um), "
                  f"max |error| {result.max_abs_error_mm * 1000:.1f} um")
    if result.one_part_in is not None:
        console.print(f"max |error| = one part in {result.one_part_in:,.0f} of the {volume_diagonal_mm:.0f} mm diagonal")
    console.print(result.uncertainty.sentence())
    if mpe_mm is not None:
        console.print("[green]PASS[/]" if result.passed else "[red]FAIL[/]")
    if failed:
        raise typer.Exit(3)


def _ballbar_inputs(centres: Optional[Path], run: Optional[Path], length: Optional[float]):
    """The centres table and the reference length: given, or the run's (--run)."""
    if run is None:
        if centres is None or length is None:
            raise UserInputError("give --centres CSV and --reference-length-mm L, or --run RUN_DIR")
        return centres, length
    from fringecal.flows.validate import input_folder
    from fringecal.rundir import RunDir

    rd = RunDir(input_folder(run, "--run", "run directory"))
    if centres is None:
        if not rd.ballbar_centres.exists():
            raise UserInputError(f"--run {run}: no {rd.ballbar_centres.path.relative_to(rd.root)}: the run "
                                 "measured no ball-bar (run its verify step first)")
        centres = rd.ballbar_centres.path
    if length is None:
        if not rd.ballbar.exists():
            raise UserInputError(f"--run {run}: no {rd.ballbar.path.name}; give --reference-length-mm")
        length = _bar_length(rd.ballbar.load())
    return centres, length


def _bar_length(bar) -> float:
    """The CMM distance of a ball-bar's spheres A and B (mm)."""
    return float(((bar.centres[1] - bar.centres[0]) ** 2).sum() ** 0.5)


@app.command("plan", epilog=example("fringecal verify plan --run runs/demo"))
@guarded
def plan(
    run: Path = typer.Option(..., "--run", "-r", help="A calibrated run directory."),
    out: Optional[Path] = typer.Option(None, "--out", "-o", help="Positions CSV to write as well (always "
                                       "written: RUN/tables/ballbar_positions_planned.csv)."),
    per_pair: int = typer.Option(3, "--per-pair", min=0, help="Positions per pair of neighbouring scanners."),
    per_scanner: int = typer.Option(2, "--per-scanner", min=0, help="Positions within each scanner's volume."),
    seed: int = typer.Option(0, "--seed", help="Seed of the random candidates."),
):
    """Plan ball-bar positions for a calibrated rig: every scanner and every pair of
    neighbouring scanners covered, from the calibrated measurement volumes.

    The CSV gives the planned centres of spheres A and B per position in the
    calibration's frame (the reference scanner's) and the scanner each sphere is
    planned for: record each position with those scanners into
    verification/<position>/<scanner>/ of the data set.
    """
    from fringecal.flows.validate import input_folder, output_file
    from fringecal.rundir import RunDir
    from fringecal.verification.plan import plan_positions, positions_table, volumes_from_run

    input_folder(run, "--run", "run directory")
    output_file(out, "--out")
    rd = RunDir(run)
    needed = [rd.calibration, rd.poses_calibrated, rd.control_points, rd.artefact, rd.ballbar]
    missing = [str(f.path) for f in needed if not f.exists()]
    if missing:
        raise FileNotFoundError(f"{run}: not a calibrated run with a ball-bar (missing {', '.join(missing)})")
    bar = rd.ballbar.load()
    length = _bar_length(bar)
    result = plan_positions(rd.calibration.load(), volumes_from_run(rd), length, per_pair, per_scanner, seed=seed)
    if not len(result.positions):  # refused before anything is written: no header-only table
        if not result.uncovered:
            raise UserInputError("--per-pair and --per-scanner are both 0: no ball-bar position to plan")
        raise UserInputError(f"{run}: no ball-bar position fits ({'; '.join(result.uncovered)}): "
                             f"the {length:.1f} mm bar is longer than the measurement volumes allow")
    table = positions_table(result.positions, bar)
    written = [rd.ballbar_positions_planned.save(table)]
    if out is not None:
        from fringecal.schemas import SphereCentresTable, write_table

        written.append(write_table(table, out, SphereCentresTable))
    t = Table(title=f"{len(result.positions)} ball-bar positions ({length:.1f} mm bar)")
    for c in ("position", "A: scanner", "A (mm)", "B: scanner", "B (mm)"):
        t.add_column(c)
    for name, g in table.groupby("measurement", sort=False):
        a, b = g.iloc[0], g.iloc[1]
        xyz = lambda r: f"{r.x_mm:.0f}, {r.y_mm:.0f}, {r.z_mm:.0f}"  # noqa: E731
        t.add_row(name, a.scanner, xyz(a), b.scanner, xyz(b))
    console.print(t)
    console.print(f"neighbouring pairs: {', '.join('-'.join(p) for p in result.pairs) or 'none'}; written to {', '.join(map(str, written))}")
    for why in result.beyond_region:
        console.print(f"warning: outside the observed region: {why}", style="yellow", highlight=False, soft_wrap=True)
    if result.uncovered:
        raise UserInputError(f"no ball-bar position fits {', '.join(result.uncovered)}: the bar is longer than "
                             "those measurement volumes allow")


def acceptance_table(doc: dict) -> Table:
    """The certificate of ``acceptance.json`` as a rich table."""
    colour = {"conformance": "green", "non-conformance": "red", "uncertainty zone": "yellow"}
    t = Table(title="acceptance test, VDI/VDE 2634 parts 2 and 3 (decision rule ISO 14253-1, "
                    f"k = {doc['coverage_factor']:g})")
    for c in ("test", "scanner", "positions", "measured (um)", "limit (um)", "U (um)", "verdict"):
        t.add_column(c, justify="left" if c in ("test", "scanner", "verdict") else "right",
                     no_wrap=c in ("test", "verdict"))
    for p in doc["parameters"]:
        limit = "-" if p["mpe_mm"] is None else f"{p['mpe_mm'] * 1000:.0f}"
        u = p["U_mm"]
        c = colour.get(p["verdict"], "white")
        t.add_row(p["name"], p["scanner"], str(p["positions"]), f"{p['measured_mm'] * 1000:+.1f}",
                  limit, "-" if u != u else f"{u * 1000:.1f}", f"[{c}]{p['verdict']}[/]")
    t.caption = "P_F probing error form, P_S probing error size, SD sphere-spacing error, " \
        "E length measurement error, F flatness measurement error"
    return t


@app.command("acceptance", epilog=example("fringecal verify acceptance --run runs/demo"))
@guarded
def acceptance(
    run: Path = typer.Option(..., "--run", "-r", help="A calibrated run directory (fringecal run)."),
    config: Optional[Path] = typer.Option(None, "--config", "-c", help="Run config YAML (default: the run's "
                                          "manifest); its acceptance section sets limits and rules."),
    as_json: bool = typer.Option(False, "--json", help="Print acceptance.json instead of the table."),
):
    """The acceptance test of a calibrated cell: P_F, P_S, SD, E and F per VDI/VDE 2634
    parts 2 and 3, each against its limit with its uncertainty and the ISO 14253-1
    verdict (runs the run's acceptance step if its result is not current).

    Exit status 0 when the cell is accepted (every limited parameter's conformance
    proven), 3 when it is not, 2 on bad input.
    """
    from fringecal.flows.cli_step import run_config_of
    from fringecal.flows.validate import input_file, input_folder
    from fringecal.rundir import RunDir
    from fringecal.steps import get_step, run_step

    input_folder(run, "--run", "run directory")
    input_file(config, "--config", "run config YAML file")
    rd = RunDir(run)
    cfg = run_config_of(run, config)
    if not rd.calibration.exists():
        raise UserInputError(f"{run}: not a calibrated run (no {rd.calibration.path.name}); run `fringecal run` first")
    step = get_step("acceptance")
    run_step(step, rd, cfg, "")
    if not rd.acceptance.exists():
        raise UserInputError(f"{run}: no acceptance test: the run has no acceptance measurements and no verified "
                             "ball-bar (or acceptance.enabled is false)")
    doc = rd.acceptance.load()
    if as_json:
        print(json.dumps(doc, indent=2))
    else:
        console.print(acceptance_table(doc))
        for f in doc["failures"]:
            console.print(f"[yellow]not measured[/]: {f['test']} {f['position']} ({f['scanner']}): {f['reason']}")
        console.print("[green]ACCEPTED[/] (conformance proven for every parameter)" if doc["accepted"] else
                      "[red]NOT ACCEPTED[/] (a parameter is outside its limit or inside the uncertainty zone)")
    if not doc["accepted"]:
        raise typer.Exit(3)
