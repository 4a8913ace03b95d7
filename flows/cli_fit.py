"""``fringecal fit sphere|plane``: fit exported points with the pipeline's own code."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Optional

import typer

from fringecal.flows.common import UserInputError, console, guarded
from fringecal.flows.help import CONTEXT, example

SPHERE_EXAMPLE = "fringecal fit sphere --points configs/thesis/artefact_cmm2.csv"
fit_app = typer.Typer(add_completion=False, no_args_is_help=True, context_settings=CONTEXT,
                      epilog=example(SPHERE_EXAMPLE),
                      help="Fit a sphere or a plane to exported points (columns x_mm, y_mm, z_mm).")

def _input_error(message: str) -> Exception:
    return UserInputError(message)


POINTS_HELP = "CSV of points with columns x_mm, y_mm, z_mm (extra columns ignored)."


def _read_points(path: Path):
    from fringecal.schemas import PointsTable, read_table

    return read_table(path, PointsTable)[["x_mm", "y_mm", "z_mm"]].to_numpy(float)


def _print(result: dict, title: str, as_json: bool):
    if as_json:
        print(json.dumps(result, indent=2))
        return
    from rich.table import Table


    t = Table(title=title, show_header=False)
    for k, v in result.items():
        t.add_row(k, f"{v:.6f}" if isinstance(v, float) else str(v))
    console.print(t)


@fit_app.command("sphere", epilog=example(SPHERE_EXAMPLE))
@guarded
def sphere(
    points: Path = typer.Option(..., "--points", "-p", help=POINTS_HELP),
    radius_mm: Optional[float] = typer.Option(None, "--radius-mm", help="Fix the radius (e.g. the CMM value)."),
    robust: bool = typer.Option(False, "--robust", help="Reject outliers, rods and glints first (RANSAC + trimming)."),
    noise_mm: float = typer.Option(0.02, "--noise-mm", help="Expected point noise for --robust."),
    as_json: bool = typer.Option(False, "--json", help="Print the result as JSON."),
):
    """Least-squares sphere (orthogonal distances), radius free or fixed."""
    from fringecal.flows.validate import positive
    from fringecal.spheres.fit import FitError, SphereModel
    from fringecal.spheres.robust import RejectionConfig, fit_sphere_robust

    positive(radius_mm, "--radius-mm", "mm")
    positive(noise_mm, "--noise-mm", "mm")
    pts = _read_points(points)
    try:
        if robust:
            fit = fit_sphere_robust(pts, radius_mm, expected_radius=radius_mm,
                                    config=RejectionConfig(noise_mm=noise_mm, min_points=4))
            result = fit.summary()
        else:
            result = SphereModel.from_estimate(pts, radius_mm).to_dict()
    except FitError as err:
        raise _input_error(f"{points}: {err}") from None
    _print({"file": str(points), **result}, f"sphere fit of {points}", as_json)


@fit_app.command("plane", epilog=example("fringecal fit plane --points configs/thesis/artefact_cmm2.csv --robust"))
@guarded
def plane(
    points: Path = typer.Option(..., "--points", "-p", help=POINTS_HELP),
    robust: bool = typer.Option(False, "--robust", help="Keep only the dominant plane (RANSAC + trimming)."),
    noise_mm: float = typer.Option(0.02, "--noise-mm", help="Expected point noise for --robust."),
    as_json: bool = typer.Option(False, "--json", help="Print the result as JSON."),
):
    """Total-least-squares plane (orthogonal distances)."""
    from fringecal.flows.validate import positive
    from fringecal.spheres.fit import FitError, PlaneModel
    from fringecal.spheres.robust import fit_plane_robust

    positive(noise_mm, "--noise-mm", "mm")
    pts = _read_points(points)
    try:
        if robust:
            fit = fit_plane_robust(pts, noise_mm=noise_mm)
            result = {**fit.model.to_dict(), "n_rejected": int((~fit.kept).sum())}
        else:
            result = PlaneModel.from_estimate(pts).to_dict()
    except FitError as err:
        raise _input_error(f"{points}: {err}") from None
    _print({"file": str(points), **result}, f"plane fit of {points}", as_json)
