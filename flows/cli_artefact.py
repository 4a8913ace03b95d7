"""``fringecal artefact``: engineering checks of the artefact (thesis chapter 3).

Utilities that answer at once (no Prefect): truss forces and sag under gravity,
rigidity, gravity-sag and thermal corrections of the CMM coordinates, CTE from a
cooling log, moisture diffusion and expansion, and the reproducibility of rod
lengths. Defaults are the thesis's artefact and data in ``configs/thesis``.
"""

from __future__ import annotations

import functools
import json
from pathlib import Path
from typing import Optional

import numpy as np
import typer
from rich.table import Table

from fringecal.flows.common import UserInputError, console, guarded
from fringecal.flows.help import CONTEXT, example

TRUSS_EXAMPLE = "fringecal artefact truss --out forces.csv"
app = typer.Typer(no_args_is_help=True, context_settings=CONTEXT, epilog=example(TRUSS_EXAMPLE),
                  help="Artefact engineering: truss, rigidity, sag, thermal, moisture, consistency.")

THESIS_SUPPORTS = "5:xyz,1:yz,14:z"


def _thesis(name: str) -> Path:
    from fringecal.config import thesis_dir

    return thesis_dir() / name


def _engineering(fn):
    """Bad engineering input (supports, mechanisms, configs, unknown ids) -> one message, status 2."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        from fringecal.config import ConfigError
        from fringecal.engineering.errors import EngineeringInputError

        try:
            return fn(*args, **kwargs)
        except (EngineeringInputError, ConfigError, KeyError) as err:
            raise UserInputError(err.args[0] if isinstance(err, KeyError) else str(err)) from None

    return guarded(wrapper)


def _vector(text: str, name: str) -> np.ndarray:
    try:
        v = np.array([float(p) for p in text.split(",")])
    except ValueError:
        raise UserInputError(f"{name}: expected three comma-separated numbers like 0,0,-1, got {text!r}") from None
    if v.shape != (3,) or not np.all(np.isfinite(v)) or not np.linalg.norm(v) > 0:
        raise UserInputError(f"{name}: expected three finite numbers, not all zero, like 0,0,-1; got {text!r}")
    return v


def _supports(value: str, node_ids):
    from fringecal.engineering.supports import parse_supports, supports_from_table
    from fringecal.schemas import SupportsTable, read_table

    if value.lower().endswith(".csv"):
        return supports_from_table(read_table(value, SupportsTable), node_ids)
    return parse_supports(value, node_ids)


def _json(obj) -> None:
    def default(o):
        if isinstance(o, (np.floating, np.integer, np.bool_)):
            return o.item()
        if isinstance(o, np.ndarray):
            return o.tolist()
        if isinstance(o, Path):
            return str(o)
        raise TypeError(type(o).__name__)

    print(json.dumps(obj, indent=2, default=default))


def _print_table(df, title: str, fmt: dict | None = None) -> None:
    fmt = fmt or {}
    t = Table(title=title)
    for c in df.columns:
        t.add_column(str(c), justify="right")
    for row in df.itertuples(index=False):
        t.add_row(*[(fmt.get(c, "{:.4f}").format(v) if isinstance(v, (float, np.floating)) else str(v))
                    for c, v in zip(df.columns, row)])
    console.print(t)


def _load_structure(artefact: Path, rods: Path):
    from fringecal.artefact import load_artefact, load_rods

    art = load_artefact(artefact)
    return art, load_rods(rods, art)


ARTEFACT = typer.Option(None, "--artefact", "-a", help="Artefact definition CSV (default: thesis CMM set 2).")
RODS = typer.Option(None, "--rods", help="Rods CSV (default: thesis table 3-11).")
MATERIALS = typer.Option(None, "--materials", "-m", help="Materials YAML (default: thesis materials.yaml).")
JSON = typer.Option(False, "--json", help="Print the result as JSON.")


@app.command("truss", epilog=example(TRUSS_EXAMPLE))
@_engineering
def truss(
    artefact: Optional[Path] = ARTEFACT,
    rods: Optional[Path] = RODS,
    materials: Optional[Path] = MATERIALS,
    supports: str = typer.Option(THESIS_SUPPORTS, "--supports", "-s", help="Supports 'node:axes,...' (3-2-1) or a supports CSV (sphere_id, nx, ny, nz)."),
    gravity: str = typer.Option("0,0,-1", "--gravity", "-g", help="Gravity direction in the artefact frame."),
    rod_end_load_n: Optional[float] = typer.Option(None, "--rod-end-load-n", help="Prescribed load per rod end (N) along gravity, instead of the masses."),
    node_load_n: Optional[float] = typer.Option(None, "--node-load-n", help="Prescribed load per node (N) along gravity, instead of the masses."),
    out: Path = typer.Option(..., "--out", "-o", help="Member forces CSV (sphere_a, sphere_b, force_n, stress_mpa)."),
    displacements: Optional[Path] = typer.Option(None, "--displacements", help="Displacements CSV (default: <out>_displacements.csv)."),
    as_json: bool = JSON,
):
    """Member forces (tension +), stresses, displacements and reactions under gravity (section 3.4)."""
    from fringecal.engineering import Truss, load_materials, mass_loads, solve_truss, uniform_loads
    from fringecal.flows.validate import number, output_file
    from fringecal.schemas import TrussDisplacementsTable, TrussForcesTable, write_table

    number(rod_end_load_n, "--rod-end-load-n", unit="N")
    number(node_load_n, "--node-load-n", unit="N")
    output_file(out, "--out")
    output_file(displacements, "--displacements")
    art, rod_table = _load_structure(artefact or _thesis("artefact_cmm2.csv"), rods or _thesis("rods.csv"))
    mat = load_materials(materials)
    g = _vector(gravity, "--gravity")
    t = Truss.from_artefact(art, rod_table, mat, source=str(rods or _thesis("rods.csv")))
    sup = _supports(supports, t.node_ids)
    if rod_end_load_n is None and node_load_n is None:
        gl = mass_loads(t, art.diameters, mat, g)
        loads, load_case = gl.forces_n, {"kind": "masses", "total_mass_kg": gl.total_mass_kg,
                                         "masses": gl.masses.to_dict("records")}
    else:
        loads = uniform_loads(t, g, node_load_n or 0.0, rod_end_load_n or 0.0)
        load_case = {"kind": "prescribed", "node_load_n": node_load_n or 0.0, "rod_end_load_n": rod_end_load_n or 0.0}
    sol = solve_truss(t, sup, loads)
    forces, disp = sol.forces_table(), sol.displacements_table()
    displacements = displacements or out.with_name(out.stem + "_displacements.csv")
    write_table(forces, out, TrussForcesTable)
    write_table(disp, displacements, TrussDisplacementsTable)
    tmax, tname = sol.max_tension()
    i = int(np.argmin(sol.forces_n))
    summary = {
        "supports": sup.describe(), "gravity": (g / np.linalg.norm(g)).tolist(), "load_case": load_case,
        "total_load_n": float(np.linalg.norm(loads.sum(axis=0))),
        "max_tension_n": tmax, "max_tension_member": tname,
        "max_compression_n": float(sol.forces_n[i]), "max_compression_member": t.member_names[i],
        "magnet_rating_n": mat.magnet.pull_off_rating_n,
        "magnet_safety_factor": sol.magnet_safety_factor(mat.magnet.pull_off_rating_n),
        "max_displacement_um": float(disp["d_mm"].max() * 1e3),
        "max_displacement_node": str(disp["sphere_id"].iloc[int(disp["d_mm"].argmax())]),
        "reactions": sol.reactions_table().to_dict("records"),
        "forces": str(out), "displacements": str(displacements),
    }
    if as_json:
        _json({**summary, "member_forces": forces.to_dict("records"), "node_displacements": disp.to_dict("records")})
        return
    _print_table(forces, f"member forces -> {out}", {"length_mm": "{:.3f}", "force_n": "{:+.2f}", "stress_mpa": "{:+.4f}"})
    d_um = disp.assign(**{c: disp[c] * 1e3 for c in ("dx_mm", "dy_mm", "dz_mm", "d_mm")})
    d_um.columns = ["sphere_id", "dx_um", "dy_um", "dz_um", "d_um"]
    _print_table(d_um, f"displacements -> {displacements}", {c: "{:+.2f}" for c in d_um.columns})
    _print_table(sol.reactions_table(), "reactions", {"reaction_n": "{:+.2f}", "nx": "{:.3f}", "ny": "{:.3f}", "nz": "{:.3f}"})
    console.print(f"load: {load_case['kind']}, total {summary['total_load_n']:.2f} N; supports {summary['supports']}")
    console.print(f"max tension {tmax:+.2f} N ({tname}), max compression {summary['max_compression_n']:+.2f} N "
                  f"({summary['max_compression_member']}); magnet safety factor {summary['magnet_safety_factor']:.2f} "
                  f"against {mat.magnet.pull_off_rating_n} N; max displacement {summary['max_displacement_um']:.2f} um "
                  f"(node {summary['max_displacement_node']})")


@app.command("rigidity", epilog=example("fringecal artefact rigidity"))
@_engineering
def rigidity(
    artefact: Optional[Path] = ARTEFACT,
    rods: Optional[Path] = RODS,
    seed: int = typer.Option(0, "--seed", help="Seed of the random (generic) configurations."),
    as_json: bool = JSON,
):
    """Maxwell-Laman count, infinitesimal and generic rigidity, redundant rods and flexes (section 3.4.1)."""
    from fringecal.engineering import analyse_rigidity

    art, rod_table = _load_structure(artefact or _thesis("artefact_cmm2.csv"), rods or _thesis("rods.csv"))
    members = np.column_stack([art.index(rod_table["sphere_a"]), art.index(rod_table["sphere_b"])])
    rep = analyse_rigidity(art.centres, members, art.ids, rod_table["rod_id"], seed=seed)
    s = rep.summary()
    if as_json:
        _json(s)
        return
    excess = s["maxwell_excess"]
    console.print(f"{s['n_nodes']} spheres, {s['n_members']} rods; Maxwell-Laman E = 3N - 6 = "
                  f"{s['maxwell_required_members']}: " + ("met" if excess == 0 else
                                                          f"{abs(excess)} rod(s) {'too many' if excess > 0 else 'too few'}"))
    console.print(f"rank of the rigidity matrix: {s['rank']} at the coordinates, {s['rank_generic']} generic, "
                  f"{s['required_rank']} needed")
    verdict = ("minimally rigid" if rep.minimally_rigid else "rigid, over-braced" if rep.infinitesimally_rigid
               else "NOT rigid (a mechanism)")
    console.print(f"infinitesimally rigid: {rep.infinitesimally_rigid}, generically rigid: {rep.generically_rigid} "
                  f"-> {verdict}")
    if rep.redundant_members:
        console.print(f"{s['n_self_stresses']} self-stress(es); redundant rods (any one can go): "
                      f"{', '.join(rep.redundant_members)}")
    if rep.flexible_nodes:
        console.print(f"{s['n_flexes']} flex(es) relative to the rigid body {{{', '.join(rep.rigid_bodies[0])}}}; "
                      f"spheres that move: {', '.join(rep.flexible_nodes)}")


@app.command("sag", epilog=example("fringecal artefact sag --use-gravity 0,-1,0 --out artefact_sag.csv"))
@_engineering
def sag(
    artefact: Optional[Path] = ARTEFACT,
    rods: Optional[Path] = RODS,
    materials: Optional[Path] = MATERIALS,
    cmm_supports: str = typer.Option(THESIS_SUPPORTS, "--cmm-supports", help="Supports during the CMM measurement."),
    cmm_gravity: str = typer.Option("0,0,-1", "--cmm-gravity", help="Gravity in the artefact frame on the CMM."),
    use_supports: Optional[str] = typer.Option(None, "--use-supports", help="Supports in use (default: as on the CMM)."),
    use_gravity: str = typer.Option(..., "--use-gravity", help="Gravity in the artefact frame in use."),
    keep_rigid: bool = typer.Option(False, "--keep-rigid", help="Keep the rigid-motion part of the correction."),
    out: Path = typer.Option(..., "--out", "-o", help="Corrected artefact CSV."),
    table: Optional[Path] = typer.Option(None, "--table", help="Per-sphere displacement table CSV."),
    as_json: bool = JSON,
):
    """Move the CMM sphere centres by the gravity sag between the CMM and the use condition."""
    from fringecal.engineering import SupportCondition, gravity_sag_correction, load_materials
    from fringecal.flows.validate import output_file
    from fringecal.schemas import ArtefactTable, TrussDisplacementsTable, write_table

    output_file(out, "--out")
    output_file(table, "--table")
    art, rod_table = _load_structure(artefact or _thesis("artefact_cmm2.csv"), rods or _thesis("rods.csv"))
    cmm = SupportCondition(_supports(cmm_supports, art.ids), _vector(cmm_gravity, "--cmm-gravity"))
    use = SupportCondition(_supports(use_supports or cmm_supports, art.ids), _vector(use_gravity, "--use-gravity"))
    res = gravity_sag_correction(art, rod_table, load_materials(materials), cmm, use, remove_rigid=not keep_rigid)
    write_table(res.artefact.to_frame(), out, ArtefactTable)
    if table is not None:
        write_table(res.table, table, TrussDisplacementsTable)
    summary = {"cmm": cmm.describe(), "use": use.describe(), "rigid_motion_removed": not keep_rigid,
               "max_correction_um": res.max_correction_mm * 1e3, "out": str(out),
               "table": None if table is None else str(table)}
    if as_json:
        _json({**summary, "spheres": res.table.to_dict("records")})
        return
    cols = ["sphere_id", "dx_mm", "dy_mm", "dz_mm", "d_mm"]
    t_um = res.table[cols].assign(**{c: res.table[c] * 1e3 for c in cols[1:]})
    t_um.columns = ["sphere_id", "dx_um", "dy_um", "dz_um", "d_um"]
    _print_table(t_um, f"sag correction -> {out}", {c: "{:+.3f}" for c in t_um.columns})
    console.print(f"CMM: {summary['cmm']}\nuse: {summary['use']}\nlargest correction {summary['max_correction_um']:.2f} um")


@app.command("cte", epilog=example("fringecal artefact cte --log configs/thesis/thermal_log_table3-5.csv"))
@_engineering
def cte(
    log: Path = typer.Option(..., "--log", "-l", help="Cooling log CSV (time_s, temperature_c, length_mm)."),
    reference_c: float = typer.Option(20.0, "--reference-c", help="Reference temperature for the length."),
    as_json: bool = JSON,
):
    """CTE from a cooling log: regression of length on temperature, with its standard uncertainty."""
    from fringecal.engineering import CteFit
    from fringecal.flows.validate import number
    from fringecal.schemas import ThermalLogTable, read_table

    number(reference_c, "--reference-c", ge=-273.15, unit="C")
    fit = CteFit.from_log(read_table(log, ThermalLogTable), reference_c)
    s = {"log": str(log), **fit.summary()}
    if as_json:
        _json(s)
        return
    console.print(f"{fit.n} points: slope {s['slope_um_per_c']:.4f} +- {s['u_slope_um_per_c']:.4f} um/C, "
                  f"L({reference_c:g} C) = {fit.length_ref_mm:.4f} mm, residual RMS {s['rms_um']:.2f} um")
    console.print(f"CTE = {fit.cte_per_c:.3e} +- {fit.u_cte_per_c:.2e} per C (standard uncertainty)")


@app.command("thermal", epilog=example("fringecal artefact thermal --temperature-c 23.4 --out artefact_23C.csv"))
@_engineering
def thermal(
    artefact: Optional[Path] = ARTEFACT,
    temperature_c: float = typer.Option(..., "--temperature-c", "-t", help="Measurement temperature."),
    cte_per_c: float = typer.Option(1.9e-6, "--cte", help="Effective CTE per deg C (thesis 1.9e-6)."),
    u_cte_per_c: float = typer.Option(0.0, "--u-cte", help="Standard uncertainty of the CTE (added to u_mm)."),
    reference_c: float = typer.Option(20.0, "--reference-c", help="Temperature of the CMM coordinates."),
    centre: Optional[str] = typer.Option(None, "--centre", help="Fixed point x,y,z of the scaling (default: centroid)."),
    out: Path = typer.Option(..., "--out", "-o", help="Compensated artefact CSV."),
    as_json: bool = JSON,
):
    """Scale the CMM coordinates from the reference to the measurement temperature."""
    from fringecal.artefact import load_artefact
    from fringecal.engineering import compensate_temperature
    from fringecal.flows.validate import number, output_file
    from fringecal.schemas import ArtefactTable, write_table

    number(temperature_c, "--temperature-c", ge=-273.15, unit="C")
    number(cte_per_c, "--cte", unit="per C")
    number(u_cte_per_c, "--u-cte", ge=0, unit="per C")
    number(reference_c, "--reference-c", ge=-273.15, unit="C")
    output_file(out, "--out")
    art = load_artefact(artefact or _thesis("artefact_cmm2.csv"))
    c = None
    if centre is not None:
        try:
            c = [float(p) for p in centre.split(",")]
            assert len(c) == 3 and all(np.isfinite(c))
        except (ValueError, AssertionError):
            raise UserInputError(f"--centre: expected x,y,z, got {centre!r}") from None
    res = compensate_temperature(art, temperature_c, cte_per_c, reference_c, c, u_cte_per_c=u_cte_per_c)
    write_table(res.to_frame(), out, ArtefactTable)
    move = np.linalg.norm(res.centres - art.centres, axis=1)
    s = {"temperature_c": temperature_c, "reference_c": reference_c, "cte_per_c": cte_per_c,
         "scale": 1 + cte_per_c * (temperature_c - reference_c), "max_move_um": float(move.max() * 1e3),
         "diagonal_change_um": (res.diagonal_mm - art.diagonal_mm) * 1e3, "out": str(out)}
    if as_json:
        _json(s)
        return
    console.print(f"scaled by {s['scale']:.9f} ({temperature_c:g} C vs {reference_c:g} C, CTE {cte_per_c:.3g}/C): "
                  f"spheres move up to {s['max_move_um']:.2f} um, diagonal changes {s['diagonal_change_um']:+.2f} um -> {out}")


@app.command("moisture", epilog=example("fringecal artefact moisture --series uptake.csv --thickness-mm 2.8"))
@_engineering
def moisture(
    series: Path = typer.Option(..., "--series", help="Uptake CSV: time_s and mass_g or moisture_pct."),
    thickness_mm: float = typer.Option(..., "--thickness-mm", help="h of eq. 3-22 (a wall exposed on one side: 2 x wall)."),
    dry_mass_g: Optional[float] = typer.Option(None, "--dry-mass-g", help="Dry mass (default: the first mass)."),
    m0_pct: Optional[float] = typer.Option(None, "--m0-pct", help="Content before the step (default: at t = 0 if present, else 0)."),
    m_inf_pct: Optional[float] = typer.Option(None, "--m-inf-pct", help="M_inf for the early-time slope (default: farthest observed, eq. 3-19)."),
    as_json: bool = JSON,
):
    """Diffusion coefficient and equilibrium uptake: early sqrt(t) slope (eq. 3-24) and full Fickian fit (eq. 3-22)."""
    from fringecal.engineering import EarlyTimeDiffusion, FickianFit, moisture_content_pct
    from fringecal.flows.validate import number, positive
    from fringecal.schemas import MoistureUptakeTable, read_table

    positive(thickness_mm, "--thickness-mm", "mm")
    positive(dry_mass_g, "--dry-mass-g", "g")
    number(m0_pct, "--m0-pct", unit="%")
    number(m_inf_pct, "--m-inf-pct", unit="%")
    df = read_table(series, MoistureUptakeTable).sort_values("time_s")
    t = df["time_s"].to_numpy(float)
    if "moisture_pct" in df:
        m, dry_note = df["moisture_pct"].to_numpy(float), None
    elif "mass_g" in df:
        dry = float(df["mass_g"].iloc[0]) if dry_mass_g is None else dry_mass_g
        m = moisture_content_pct(df["mass_g"].to_numpy(float), dry)
        dry_note = dry
    else:
        raise UserInputError(f"{series}: needs a mass_g or a moisture_pct column")
    m0 = (float(m[0]) if t[0] == 0 else 0.0) if m0_pct is None else m0_pct
    full = FickianFit.from_estimate(t, m, thickness_mm, m0)
    early = EarlyTimeDiffusion.from_estimate(t, m, thickness_mm, m_inf_pct, m0)
    early_fitted = EarlyTimeDiffusion.from_estimate(t, m, thickness_mm, full.m_inf_pct, m0, full.u_m_inf_pct)
    s = {"series": str(series), "n": int(t.size), "thickness_mm": thickness_mm, "dry_mass_g": dry_note, "m0_pct": m0,
         "early_time": {"D_m2_s": early.D_mm2_s * 1e-6, "u_D_m2_s": early.u_D_mm2_s * 1e-6,
                        "m_inf_pct": early.m_inf_pct, "n_points": early.n_points},
         "early_time_fitted_m_inf": {"D_m2_s": early_fitted.D_mm2_s * 1e-6, "u_D_m2_s": early_fitted.u_D_mm2_s * 1e-6,
                                     "n_points": early_fitted.n_points},
         "full_fit": {"D_m2_s": full.D_mm2_s * 1e-6, "u_D_m2_s": full.u_D_mm2_s * 1e-6, "m_inf_pct": full.m_inf_pct,
                      "u_m_inf_pct": full.u_m_inf_pct, "correlation": full.correlation, "rms_pct": full.rms_pct}}
    if as_json:
        _json(s)
        return
    e, ef, f = s["early_time"], s["early_time_fitted_m_inf"], s["full_fit"]
    console.print(f"{s['n']} points, h = {thickness_mm} mm, M0 = {m0:.4f} %"
                  + (f", dry mass {dry_note} g" if dry_note is not None else ""))
    console.print(f"early sqrt(t) slope (eq. 3-24), M_inf = {e['m_inf_pct']:.4f} %: D = {e['D_m2_s']:.3e} +- "
                  f"{e['u_D_m2_s']:.1e} m^2/s ({e['n_points']} points)")
    console.print(f"early sqrt(t) slope with the fitted M_inf: D = {ef['D_m2_s']:.3e} +- {ef['u_D_m2_s']:.1e} m^2/s")
    console.print(f"full Fickian fit (eq. 3-22): D = {f['D_m2_s']:.3e} +- {f['u_D_m2_s']:.1e} m^2/s, "
                  f"M_inf = {f['m_inf_pct']:.4f} +- {f['u_m_inf_pct']:.4f} %, residual RMS {f['rms_pct']:.2e} %")


@app.command("cme", epilog=example("fringecal artefact cme --mass-change-pct 0.25"))
@_engineering
def cme(
    lengths: Optional[Path] = typer.Option(None, "--lengths", help="Length record CSV (time_h, length_mm); default thesis table 3-6."),
    mass_change_pct: float = typer.Option(..., "--mass-change-pct", help="Moisture mass change over the same step, percent of dry mass."),
    as_json: bool = JSON,
):
    """Coefficient of moisture expansion (eq. 3-17) from a length record and a mass change."""
    from fringecal.engineering import LengthChange, moisture_expansion_coefficient
    from fringecal.flows.validate import number
    from fringecal.schemas import HumidityLengthsTable, read_table

    number(mass_change_pct, "--mass-change-pct", nonzero=True, unit="%")
    path = lengths or _thesis("humidity_lengths_table3-6.csv")
    df = read_table(path, HumidityLengthsTable)
    ch = LengthChange.from_lengths(df["time_h"], df["length_mm"])
    s = {"lengths": str(path), "n": ch.n, "length_mm": ch.length_start_mm, "range_um": ch.range_mm * 1e3,
         "change_um": ch.change_mm * 1e3, "sd_um": ch.sd_mm * 1e3, "mass_change_pct": mass_change_pct,
         "cme_per_pct_from_range": moisture_expansion_coefficient(ch.range_mm, ch.length_start_mm, mass_change_pct),
         "cme_per_pct_from_change": moisture_expansion_coefficient(ch.change_mm, ch.length_start_mm, mass_change_pct)}
    if as_json:
        _json(s)
        return
    console.print(f"{ch.n} lengths of {ch.length_start_mm:.4f} mm: range {s['range_um']:.2f} um, end - start "
                  f"{s['change_um']:+.2f} um, sd {s['sd_um']:.2f} um")
    console.print(f"CME (eq. 3-17) with dM = {mass_change_pct} %: {s['cme_per_pct_from_range']:.2e} per % from the range, "
                  f"{s['cme_per_pct_from_change']:.2e} per % from end - start")


@app.command("consistency", epilog=example("fringecal artefact consistency --out rods_consistency.csv"))
@_engineering
def consistency(
    single: Optional[Path] = typer.Option(None, "--single", help="Rods measured singly (default: thesis table 3-11)."),
    assembled: Optional[Path] = typer.Option(None, "--assembled", help="Rods in the assembled structure (default: table 3-12)."),
    coords: Optional[list[Path]] = typer.Option(None, "--coords", help="Artefact coordinate sets (repeatable; default: table 3-13 sets 1 and 2)."),
    out: Optional[Path] = typer.Option(None, "--out", "-o", help="Per-rod table CSV."),
    as_json: bool = JSON,
):
    """Rod lengths singly vs assembled vs from coordinates (section 3.7): per-rod differences, RMS, worst rods."""
    from fringecal.artefact import load_artefact, load_rods
    from fringecal.engineering import artefact_from_rod_lengths, rod_length_consistency
    from fringecal.flows.validate import output_file
    from fringecal.schemas import RodConsistencyTable, write_table

    output_file(out, "--out")
    coords = coords or [_thesis("artefact_cmm1.csv"), _thesis("artefact_cmm2.csv")]
    arts = {}
    for p in coords:
        art = load_artefact(p)
        arts[art.name.replace("artefact_", "")] = art
    ref = list(arts.values())[-1]
    single_t = load_rods(single or _thesis("rods.csv"), ref)
    asm = load_rods(assembled or _thesis("rods_assembled.csv"), ref)
    rep = rod_length_consistency(single_t, asm, arts)
    rebuilt, dev = artefact_from_rod_lengths(ref, single_t)
    if out is not None:
        write_table(rep.rods, out, RodConsistencyTable)
    recon = {"reference": ref.name, "max_um": float(dev["d_mm"].max() * 1e3),
             "rms_um": float(np.sqrt((dev["d_mm"] ** 2).mean()) * 1e3),
             "worst_sphere": str(dev["sphere_id"].iloc[int(dev["d_mm"].argmax())])}
    if as_json:
        _json({"comparisons": rep.comparisons.to_dict("records"), "from_single_lengths": recon,
               "rods": rep.rods.to_dict("records")})
        return
    cols = ["rod_id", "sphere_a", "sphere_b", "single_mm", "assembled_mm"] + \
        [c for c in rep.rods.columns if c.startswith("coords_") and c.endswith("_mm") and "minus" not in c] + \
        [c for c in rep.rods.columns if c.endswith("_minus_single_um")]
    _print_table(rep.rods[cols], "rod lengths" + (f" -> {out}" if out else ""),
                 {c: ("{:+.1f}" if c.endswith("_um") else "{:.3f}") for c in cols})
    _print_table(rep.comparisons, "comparisons (um)", {c: "{:+.1f}" for c in rep.comparisons.columns})
    console.print(f"coordinates rebuilt from the single-rod lengths vs {recon['reference']} (best fit): "
                  f"RMS {recon['rms_um']:.1f} um, max {recon['max_um']:.1f} um (sphere {recon['worst_sphere']})")
