"""``fringecal hexapod``: kinematics, workspace, planning, control and drift of the
Stewart platform (thesis chapter 4). Poses on the command line are
``px,py,pz,alpha,beta,gamma`` in mm and degrees; JSON output is in mm and rad
(plus degrees where named ``_deg``)."""

from __future__ import annotations

import functools
import json
from pathlib import Path
from typing import Optional

import numpy as np
import typer

from fringecal.flows.common import UserInputError, console, err_console, fail, guarded
from fringecal.flows.help import CONTEXT, example

IK_EXAMPLE = "fringecal hexapod ik --pose 150,-100,900,1,0,-2"
app = typer.Typer(no_args_is_help=True, add_completion=False, context_settings=CONTEXT, epilog=example(IK_EXAMPLE),
                  help="Stewart-platform hexapod (thesis ch. 4): kinematics, workspace, plan, move, drift.")

CONFIG_HELP = "Hexapod YAML (default: configs/hexapod/thesis_platform.yaml)."


def _guarded(fn):
    """Bad input or a refused target: one message, status 2. A controller fault: status 1.

    The hexapod package is imported when the command runs, not when the CLI loads,
    so that other commands do not pay for it.
    """

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        from fringecal.hexapod import ForwardKinematicsError, HexapodFault, TargetRejected

        inner = guarded(fn, extra=(TargetRejected, ForwardKinematicsError, ValueError), passing=(HexapodFault,))
        try:
            return inner(*args, **kwargs)
        except HexapodFault as err:
            fail(f"hexapod fault ({err.kind}): {err}", code=1)

    return wrapper


def _numbers(text: str, n: int, what: str) -> np.ndarray:

    try:
        v = np.array([float(x) for x in text.replace(" ", "").split(",")])
    except ValueError:
        raise UserInputError(f"{what}: expected {n} comma-separated numbers, got {text!r}") from None
    if v.shape != (n,) or not np.all(np.isfinite(v)):
        raise UserInputError(f"{what}: expected {n} comma-separated finite numbers, got {text!r}")
    return v


def _pose(text: str, what: str = "--pose") -> np.ndarray:
    v = _numbers(text, 6, f"{what} (px,py,pz in mm, alpha,beta,gamma in deg)")
    return np.concatenate([v[:3], np.radians(v[3:])])


def _config(path: Optional[Path]):
    from fringecal.hexapod import load_hexapod_config

    return load_hexapod_config(path)


def _pose_dict(pose) -> dict:
    p = np.asarray(pose, float)
    return {"px_mm": p[0], "py_mm": p[1], "pz_mm": p[2], "alpha_rad": p[3], "beta_rad": p[4], "gamma_rad": p[5],
            "alpha_deg": np.degrees(p[3]), "beta_deg": np.degrees(p[4]), "gamma_deg": np.degrees(p[5])}


def _pose_text(pose) -> str:
    p = np.asarray(pose, float)
    return (f"px {p[0]:.4f} mm, py {p[1]:.4f} mm, pz {p[2]:.4f} mm, alpha {np.degrees(p[3]):.5f} deg, "
            f"beta {np.degrees(p[4]):.5f} deg, gamma {np.degrees(p[5]):.5f} deg")


def _legs_report(config, pose) -> dict:
    from fringecal.hexapod.planning import counts_from_lengths
    from fringecal.hexapod.workspace import check_poses, describe_violations

    chk = check_poses(config, pose)
    return {
        "pose": _pose_dict(pose),
        "legs": [{"leg": i + 1, "length_mm": float(chk.lengths_mm[i]), "stroke_mm": float(chk.strokes_mm[i]),
                  "counts": int(c), "base_joint_deg": float(np.degrees(chk.base_angles_rad[i])),
                  "top_joint_deg": float(np.degrees(chk.top_angles_rad[i]))}
                 for i, c in enumerate(counts_from_lengths(config, chk.lengths_mm))],
        "in_workspace": bool(chk.ok),
        "violations": describe_violations(config, chk),
    }


def _print_legs(report: dict, title: str):
    from rich.table import Table


    t = Table(title=title)
    for c in ("leg", "length mm", "stroke mm", "counts", "base joint deg", "top joint deg"):
        t.add_column(c, justify="right")
    for leg in report["legs"]:
        t.add_row(str(leg["leg"]), f"{leg['length_mm']:.4f}", f"{leg['stroke_mm']:.4f}", str(leg["counts"]),
                  f"{leg['base_joint_deg']:.2f}", f"{leg['top_joint_deg']:.2f}")
    console.print(t)
    if report["in_workspace"]:
        console.print("inside the workspace")
    else:
        err_console.print("[yellow]outside the workspace:[/] " + "; ".join(report["violations"]), highlight=False)


def _dump(obj):
    print(json.dumps(obj, indent=2, default=lambda o: o.item() if hasattr(o, "item") else str(o)))


@app.command(epilog=example(IK_EXAMPLE))
@_guarded
def ik(
    pose: str = typer.Option(..., "--pose", "-p", help="px,py,pz,alpha,beta,gamma (mm, deg)."),
    config: Optional[Path] = typer.Option(None, "--config", "-c", help=CONFIG_HELP),
    as_json: bool = typer.Option(False, "--json", help="Print JSON."),
):
    """Inverse kinematics: six leg lengths, strokes and encoder counts for a platform pose."""
    cfg = _config(config)
    rep = _legs_report(cfg, _pose(pose))
    if as_json:
        _dump(rep)
    else:
        _print_legs(rep, f"inverse kinematics: {_pose_text(_pose(pose))}")


@app.command(epilog=example("fringecal hexapod fk --counts 4495,8620,7031,5418,6998,5810"))
@_guarded
def fk(
    lengths: Optional[str] = typer.Option(None, "--lengths", help="Six leg lengths l1,...,l6 (mm, joint to joint)."),
    counts: Optional[str] = typer.Option(None, "--counts", help="Six encoder counts c1,...,c6."),
    start: Optional[str] = typer.Option(None, "--start", help="Start pose for the solve (mm, deg); default home."),
    config: Optional[Path] = typer.Option(None, "--config", "-c", help=CONFIG_HELP),
    as_json: bool = typer.Option(False, "--json", help="Print JSON."),
):
    """Forward kinematics: the platform pose for six leg lengths or encoder counts."""
    from fringecal.hexapod import forward_kinematics
    from fringecal.hexapod.planning import lengths_from_counts

    cfg = _config(config)
    if (lengths is None) == (counts is None):
        raise UserInputError("give exactly one of --lengths or --counts")
    L = _numbers(lengths, 6, "--lengths") if lengths is not None else lengths_from_counts(cfg, _numbers(counts, 6, "--counts"))
    x0 = _pose(start, "--start") if start else cfg.home_pose.vector
    sol = forward_kinematics(cfg.platform, L, x0)
    rep = _legs_report(cfg, sol.poses)
    rep.update(iterations=sol.iterations, residual_mm=sol.residual_mm)
    if as_json:
        _dump(rep)
    else:

        console.print(f"pose: {_pose_text(sol.poses)}  ({sol.iterations} iterations, "
                      f"residual {sol.residual_mm:.1e} mm)", highlight=False)
        _print_legs(rep, "legs")


@app.command(epilog=example("fringecal hexapod workspace --limit-mm 200"))
@_guarded
def workspace(
    limit_mm: float = typer.Option(250.0, "--limit-mm", help="Translation to test along px, py, pz (mm)."),
    limit_deg: float = typer.Option(10.0, "--limit-deg", help="Rotation to test about alpha, beta, gamma (deg)."),
    config: Optional[Path] = typer.Option(None, "--config", "-c", help=CONFIG_HELP),
    as_json: bool = typer.Option(False, "--json", help="Print JSON."),
):
    """Reach from the home pose along each pose coordinate, with the constraint that limits it."""
    from fringecal.flows.validate import positive
    from fringecal.hexapod import reach_report
    from fringecal.hexapod.workspace import cube_reach

    positive(limit_mm, "--limit-mm", "mm")
    positive(limit_deg, "--limit-deg", "deg")
    cfg = _config(config)
    cube = cube_reach(cfg, limit_mm)
    rows = []
    for r in reach_report(cfg, limit_mm, limit_deg):
        ang = r.axis in ("alpha", "beta", "gamma")
        f = np.degrees if ang else (lambda v: v)
        rows.append({"axis": r.axis, "unit": "deg" if ang else "mm", "lower": float(f(r.lower)),
                     "upper": float(f(r.upper)), "limit": float(f(r.limit)),
                     "lower_limited_by": r.lower_by, "upper_limited_by": r.upper_by,
                     "reaches_limit": r.reaches_limit})
    if as_json:
        _dump({"home_pose": _pose_dict(cfg.home_pose.vector), "axes": rows,
               "cube": {"half_mm": cube.half_mm, "inside": cube.inside, "largest_half_mm": cube.largest_half_mm,
                        "worst_offset_mm": cube.worst_offset_mm, "limited_by": cube.limited_by}})
        return
    from rich.table import Table


    t = Table(title=f"reach from the home pose (target +-{limit_mm:g} mm, +-{limit_deg:g} deg)")
    for c in ("axis", "lower", "upper", "limited below by", "limited above by"):
        t.add_column(c)
    for r in rows:
        t.add_row(r["axis"], f"{r['lower']:.3f} {r['unit']}", f"{r['upper']:.3f} {r['unit']}",
                  r["lower_limited_by"] or "-", r["upper_limited_by"] or "-")
    console.print(t)
    if cube.inside:
        console.print(f"combined translations: the whole +-{limit_mm:g} mm cube is inside the workspace")
    else:
        off = ", ".join(f"{v:+.1f}" for v in cube.worst_offset_mm)
        console.print(f"combined translations: the +-{limit_mm:g} mm cube is not; the largest cube about home is "
                      f"+-{cube.largest_half_mm:.2f} mm, beyond which the offset ({off}) mm breaks: "
                      f"{cube.limited_by}", highlight=False)


@app.command(epilog=example("fringecal hexapod plan --out plan.csv --commands moves.txt"))
@_guarded
def plan(
    poses: Optional[Path] = typer.Option(None, "--poses", help="Artefact poses T_world_artefact (PosePlanTable CSV); "
                                         "default: the thesis's table 6-1."),
    grid: bool = typer.Option(False, "--grid", help="Plan the thesis's nominal grid (section 6.9.1: lateral 0/100/200 mm "
                              "at stand-offs 2000/2330/2670/3000 mm) from the first pose instead."),
    station_per_standoff: bool = typer.Option(False, "--station-per-standoff", help="With --grid: roll the base to a "
                                              "new station for every stand-off, centred on that row of poses."),
    config: Optional[Path] = typer.Option(None, "--config", "-c", help=CONFIG_HELP),
    out: Optional[Path] = typer.Option(None, "--out", "-o", help="Write the plan table (HexapodPlanTable CSV)."),
    commands: Optional[Path] = typer.Option(None, "--commands", help="Write the reachable moves as a command file."),
    as_json: bool = typer.Option(False, "--json", help="Print JSON."),
):
    """Artefact poses -> platform poses -> leg lengths -> encoder counts, with reachability."""
    from fringecal.config import thesis_dir
    from fringecal.flows.validate import output_file
    from fringecal.hexapod import HexapodRig
    from fringecal.hexapod.driver import write_command_file
    from fringecal.hexapod.planning import COUNT_COLUMNS, frames_from_table, plan_with_stations, thesis_grid
    from fringecal.schemas import HexapodPlanTable, PosePlanTable, read_table, write_table

    output_file(out, "--out")
    output_file(commands, "--commands")
    cfg = _config(config)
    source = poses or thesis_dir() / "poses_scanner1_table6-1.csv"
    table = read_table(source, PosePlanTable)
    if station_per_standoff and not grid:
        raise UserInputError("--station-per-standoff needs --grid")
    if grid:
        table = thesis_grid(frames_from_table(table)[0])
    if station_per_standoff:
        result, _ = plan_with_stations(cfg, table, "standoff_mm")
    else:
        result = HexapodRig.from_config(cfg).plan(table)
    if out:
        write_table(result, out, HexapodPlanTable)
    ok = result[result.reachable]
    if commands:
        write_command_file(commands, ok[COUNT_COLUMNS].to_numpy(),
                           [f"measurement {m}" for m in ok.measurement])
    if as_json:
        _dump({"n_poses": len(result), "n_reachable": int(result.reachable.sum()),
               "plan": result.to_dict("records")})
        return
    from rich.table import Table


    t = Table(title=f"plan for {source}{' (nominal grid)' if grid else ''}: "
                    f"{len(ok)} of {len(result)} poses reachable")
    for c in ("meas.", "station", "px mm", "py mm", "pz mm", "gamma deg", "counts", "limits"):
        t.add_column(c)
    for r in result.itertuples(index=False):
        t.add_row(r.measurement, r.station, f"{r.px_mm:.1f}", f"{r.py_mm:.1f}", f"{r.pz_mm:.1f}",
                  f"{np.degrees(r.gamma_rad):.2f}", " ".join(str(getattr(r, c)) for c in COUNT_COLUMNS),
                  "ok" if r.reachable else r.limits)
    console.print(t)


@app.command(epilog=example("fringecal hexapod drift --centres configs/thesis/drift_table4-1.csv --tolerance-um 20"))
@_guarded
def drift(
    centres: Path = typer.Option(..., "--centres", help="Repeated sphere centres (DriftCentresTable CSV)."),
    interval_s: float = typer.Option(120.0, "--interval-s", help="Time between measurements when the CSV has no time_s "
                                     "(section 4.5.2: ~2 min)."),
    scan_s: float = typer.Option(15.0, "--scan-s", help="Duration of one scan (s)."),
    tolerance_um: float = typer.Option(5.0, "--tolerance-um", help="Largest acceptable drift during one scan (um)."),
    as_json: bool = typer.Option(False, "--json", help="Print JSON."),
):
    """Drift after a move: displacements, drift velocity and the drift expected in one scan.

    Exit status 0, or 3 when the drift expected in one scan EXCEEDS --tolerance-um.
    """
    from fringecal.flows.validate import positive
    from fringecal.hexapod.drift import drift_check
    from fringecal.schemas import DriftCentresTable, read_table

    positive(interval_s, "--interval-s", "s")
    positive(scan_s, "--scan-s", "s")
    positive(tolerance_um, "--tolerance-um", "um")
    rep = drift_check(read_table(centres, DriftCentresTable), scan_s, tolerance_um, interval_s)
    if as_json:
        _dump({**rep.summary(), "per_sphere": rep.per_sphere.to_dict("records"), "pairs": rep.pairs.to_dict("records")})
        if not rep.ok:
            raise typer.Exit(3)  # the tolerance is exceeded: the verdict's own status
        return

    for r in rep.per_sphere.itertuples(index=False):
        console.print(f"sphere {r.sphere_id}: mean displacement {r.mean_displacement_um:.1f} um "
                      f"(max {r.max_displacement_um:.1f}), {r.mean_velocity_um_s:.3f} um/s", highlight=False)
    verdict = "within" if rep.ok else "EXCEEDS"
    console.print(f"mean displacement {rep.mean_displacement_um:.1f} um over {rep.mean_interval_s:.0f} s -> "
                  f"{rep.expected_scan_drift_um:.1f} um expected in a {scan_s:g} s scan, {verdict} the "
                  f"{tolerance_um:g} um tolerance", highlight=False)
    if not rep.ok:
        raise typer.Exit(3)


@app.command(epilog=example("fringecal hexapod move --port hexsim://demo --pose 150,-100,900,1,0,-2"))
@_guarded
def move(
    port: str = typer.Option(..., "--port", help="Serial port or URL (/dev/ttyACM0, hexsim://name?...)."),
    pose: Optional[str] = typer.Option(None, "--pose", "-p", help="Target pose px,py,pz,alpha,beta,gamma (mm, deg)."),
    counts: Optional[str] = typer.Option(None, "--counts", help="Target encoder counts c1,...,c6."),
    config: Optional[Path] = typer.Option(None, "--config", "-c", help=CONFIG_HELP),
    as_json: bool = typer.Option(False, "--json", help="Print JSON."),
):
    """Move the platform (all six legs together), verify the encoders and report the pose reached."""
    from fringecal.hexapod import HexapodDriver
    from fringecal.hexapod.kinematics import inverse_kinematics
    from fringecal.hexapod.planning import counts_from_lengths

    cfg = _config(config)
    if (pose is None) == (counts is None):
        raise UserInputError("give exactly one of --pose or --counts")
    if pose is not None:
        target_pose = _pose(pose)
        target = counts_from_lengths(cfg, inverse_kinematics(cfg.platform, target_pose))
    else:
        c = _numbers(counts, 6, "--counts")
        if np.any(c != np.round(c)):
            raise UserInputError(f"--counts must be integers, got {counts!r}")
        target = c.astype(np.int64)
    with HexapodDriver.open(port, cfg) as drv:
        if pose is not None:
            read = drv.move_pose(target_pose)
        else:
            read = drv.move_counts(target)
        reached = drv.pose
    rep = {"port": port, "counts_target": target.tolist(), "counts_read": read.tolist(),
           "pose_reached": _pose_dict(reached)}
    if as_json:
        _dump(rep)
        return

    console.print(f"target counts {target.tolist()}\nread counts   {read.tolist()}\n"
                  f"reached: {_pose_text(reached)}", highlight=False)


@app.command("run-file", epilog=example("fringecal hexapod run-file moves.txt --port hexsim://demo"))
@_guarded
def run_file(
    commands: Path = typer.Argument(..., help="Text file of protocol commands (section 4.5.1)."),
    port: str = typer.Option(..., "--port", help="Serial port or URL."),
    config: Optional[Path] = typer.Option(None, "--config", "-c", help=CONFIG_HELP),
):
    """Check a whole command file against stroke and workspace, then run it line by line."""
    from fringecal.flows.validate import input_file
    from fringecal.hexapod import HexapodDriver

    input_file(commands, "COMMANDS", "command file")
    cfg = _config(config)
    with HexapodDriver.open(port, cfg) as drv:
        results = drv.run_command_file(commands)

    for i, c in enumerate(results, 1):
        console.print(f"move {i}: encoders {c.tolist()}", highlight=False)
