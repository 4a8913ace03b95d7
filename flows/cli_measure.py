"""``fringecal measure``: one measurement of every scanner -> one registered point cloud.

No Prefect: a measurement is seconds of work and answers at once.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Optional

import typer

from fringecal.flows.common import UserInputError, console, err_console, guarded


def _settings(decimate: int, max_eps1_mm: Optional[float], uncertainty: bool):
    from fringecal.measure import MeasureSettings

    try:
        return MeasureSettings(decimate, max_eps1_mm, uncertainty)
    except ValueError as err:
        raise UserInputError(f"--{str(err).split()[0].replace('_', '-')}: {err}") from None


def _print(summary: dict) -> None:
    from rich.table import Table

    t = Table(title=f"{summary['points']:,} points -> {summary['out']}")
    for col in ("scanner", "points", "RMS eps1 (um)", "median u (um)", "stores"):
        t.add_column(col, justify="right" if col not in ("scanner", "stores") else "left")
    for name, s in summary["scanners"].items():
        u = "-" if s["u_mm_median"] is None else f"{1000 * s['u_mm_median']:.1f}"
        t.add_row(name, f"{s['points']:,}", f"{1000 * s['eps1_rms_mm']:.1f}", u, str(len(s["sources"])))
    console.print(t)
    console.print(f"uncertainty: {summary['uncertainty']}")
    _print_observed_region(summary["observed_region"])
    if summary["overlap"]:
        o = Table(title="overlap: distance of one scanner's points from the other's surface")
        for col in ("points of", "from surface of", "n", "mean (um)", "RMS (um)", "95 % |d| (um)"):
            o.add_column(col, justify="right")
        for r in summary["overlap"]:
            o.add_row(r["of"], r["to"], f"{r['n_points']:,}", f"{1000 * r['mean_mm']:+.1f}",
                      f"{1000 * r['rms_mm']:.1f}", f"{1000 * r['p95_abs_mm']:.1f}")
        console.print(o)
    elif len(summary["measurements"]) == 1:
        console.print("overlap: no two scanners see the same surface")
    if summary.get("spheres") is not None:
        _print_spheres(summary["spheres"], summary["datum"])
    console.print(f"{summary['seconds']['total']:.1f} s")


def _print_observed_region(region: dict) -> None:
    """One warning line per store with points outside the calibration's observed region;
    a note when the calibration records no region for some sensors."""
    for r in region["stores"]:
        if r["outside"]:
            err_console.print(f"[yellow]warning: {r['store']}: {r['outside']:,} of {r['points']:,} points "
                              f"({100 * r['fraction']:.1f} %) lie outside the region of the image planes the "
                              "calibration observed (flagged in outside_observed_region)[/]", soft_wrap=True)
    if region["unknown"]:
        console.print(f"observed region: not recorded in the calibration file for {', '.join(region['unknown'])}; "
                      "their points are not flagged")
    elif not region["points_outside"]:
        console.print("observed region: every point lies inside the region the calibration observed")


def _um(value) -> str:
    return "-" if value is None or value != value else f"{1000 * value:.1f}"


def _print_spheres(spheres: dict, datum: str) -> None:
    from rich.table import Table

    t = Table(title=f"spheres of {spheres['nominal']}: centres, u of the position ({datum} frame)")
    for col in ("measurement", "sphere", "scanner", "x (mm)", "y (mm)", "z (mm)", "u (um)", "points",
                "outside observed region"):
        t.add_column(col, justify="left" if col in ("measurement", "sphere", "scanner") else "right")
    for r in spheres["fitted"]:
        outside = r.get("n_outside_observed_region")
        t.add_row(r["measurement"], r["sphere"], r["scanner"], f"{r['x_mm']:.3f}", f"{r['y_mm']:.3f}",
                  f"{r['z_mm']:.3f}", _um(r["u_position_mm"]), f"{r['n_points']:,}",
                  "not known" if outside is None else f"{outside:,}")
    console.print(t if spheres["fitted"] else "spheres: none found (none seen whole enough by any scanner)")
    if spheres["distances"]:
        d = Table(title="distances between sphere centres, each with its own u (what a CMM compares)")
        for col in ("measurement", "from", "to", "distance (mm)", "u (um)", "of it model error (um)",
                    "bias subtracted (um)"):
            d.add_column(col, justify="left" if col in ("measurement", "from", "to") else "right")
        for r in spheres["distances"]:
            d.add_row(r["measurement"], f"{r['sphere_a']} ({r['scanner_a']})", f"{r['sphere_b']} ({r['scanner_b']})",
                      f"{r['distance_mm']:.4f}", _um(r["u_mm"]), _um(r.get("model_error_mm")),
                      _um(r.get("bias_mm")))
        console.print(d)


def _cloud_size(folders: list[Path], decimate: int) -> float:
    """Roughly the bytes of the cloud: per camera pixel kept, about 40 bytes (x, y, z as
    float64, pixel, scanner, eps1, modulation, u), from the folders' stacks and stores."""
    from fringecal.fringe.importer import read_stack_spec
    from fringecal.store import open_store

    pixels = 0
    for folder in folders:
        for entry in Path(folder).iterdir():
            try:
                if entry.suffix == ".zarr":
                    pixels += int(open_store(entry)["valid"].size)
                elif entry.is_dir():
                    spec, _, _ = read_stack_spec(entry)
                    pixels += spec.width_px * spec.height_px
            except ValueError:
                continue
    return 40.0 * pixels / decimate**2


@guarded
def measure_command(
    run: Optional[Path] = typer.Option(None, "--run", "-r", help="A calibrated run directory: measure with its "
                                       "calibration (calibration.json)."),
    calibration: Optional[Path] = typer.Option(None, "--calibration",
                                               help="Calibration file (a run's calibration.json; .xml has no "
                                                    "covariance), or a run directory."),
    frames: Optional[list[Path]] = typer.Option(None, "--frames", "-f",
                                                help="Measurement folder: one frame folder per scanner, named after "
                                                     "it (repeat for several measurements)."),
    stores: Optional[list[Path]] = typer.Option(None, "--stores", "-s",
                                                help="Measurement folder: one decoded store <scanner>.zarr per "
                                                     "scanner (repeat for several measurements)."),
    out: Path = typer.Option(..., "--out", "-o", help="Cloud to write: CLOUD.ply (binary PLY) or CLOUD.zarr."),
    decimate: int = typer.Option(1, "--decimate", help="Keep every n-th pixel in rows and columns."),
    max_eps1_mm: Optional[float] = typer.Option(None, "--max-eps1-mm",
                                                help="Drop points whose two rays pass farther apart (mm)."),
    uncertainty: bool = typer.Option(True, "--uncertainty/--no-uncertainty",
                                     help="Per-point standard uncertainty from the calibration's covariance."),
    datum: str = typer.Option("rig", "--datum",
                              help="u_mm relative to the frame the sensors realise ('rig') or to the calibration's "
                                   "own world frame, the reference camera as given ('calibration')."),
    spheres: Optional[Path] = typer.Option(None, "--spheres",
                                           help="CSV of nominal spheres (sphere_id, x_mm, y_mm, z_mm, radius_mm; "
                                                "centres within 15 mm): fit each, state its position's u and every "
                                                "distance between two with its own u."),
    as_json: bool = typer.Option(False, "--json", help="Print the summary as JSON."),
):
    """Triangulate every valid pixel of every scanner in the global frame into one point cloud
    (per point: scanner, camera pixel, eps1, modulation, standard uncertainty, and whether its camera pixel
    or projector phases lie outside the region the calibration observed)."""
    from fringecal.flows.validate import calibration_file, input_folder, output_file, output_folder
    from fringecal.measure import MeasurementSourceError
    from fringecal.measure.run import measure_folder

    if (run is None) == (calibration is None):
        raise UserInputError("give the calibration as --run RUN_DIR or as --calibration FILE (not both, not none)")
    calibration = calibration_file(run, "--run") if run is not None else calibration_file(calibration, "--calibration")
    if bool(frames) == bool(stores):
        raise UserInputError("give measurement folders either as --frames DIR or as --stores DIR (not both, not none)")
    for folder in frames or stores:
        input_folder(folder, "--frames" if frames else "--stores", "measurement folder")
    (output_folder if out.suffix.lower() == ".zarr" else output_file)(out, "--out")
    settings = _settings(decimate, max_eps1_mm, uncertainty)
    kind, folders = ("frames", frames) if frames else ("stores", stores)
    from fringecal.flows.common import needs_space

    needs_space(out, lambda: _cloud_size(folders, decimate), "the point cloud")
    try:
        summary = measure_folder(calibration, folders, kind, out, settings, datum=datum, spheres=spheres)
    except MeasurementSourceError as err:
        raise UserInputError(str(err)) from None
    if as_json:
        print(json.dumps(summary, indent=2))
        return
    if summary["uncertainty"].startswith("none"):
        err_console.print(f"[yellow]{calibration}: no covariance in the calibration file; u_mm is NaN[/]")
    _print(summary)
