"""``fringecal acquire``: simulate every measurement of a run configuration."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Optional

import typer

from .common import UserInputError, console, fail, guarded


def check_acquisition_config(config: Path | None):
    """Load and check everything the acquisition reads (run config, rig files, poses,
    hexapod config and reach) before Prefect starts; returns (RunConfig, plans)."""
    from fringecal.acquisition import AcquisitionInputs, plan_acquisition, planned_poses
    from fringecal.runconfig import load_run_config

    cfg = load_run_config(config)
    inputs = AcquisitionInputs.from_run_config(cfg)
    plans = plan_acquisition(cfg, inputs)
    hx = cfg.acquisition.hexapod
    if hx.enabled:
        from fringecal.hexapod import HexapodRig, load_hexapod_config
        from fringecal.hexapod.workspace import check_poses, describe_violations

        rig = HexapodRig.from_config(load_hexapod_config(hx.config))
        for pose, T in planned_poses(plans).items():
            check = check_poses(rig.config, rig.platform_pose_for(T))
            if not check.ok:
                raise UserInputError(f"{cfg.rig}: artefact pose {pose} is out of the hexapod's reach: "
                                     + "; ".join(describe_violations(rig.config, check)))
    return cfg, plans


@guarded
def acquire_command(
    config: Optional[Path] = typer.Option(None, "--config", "-c",
                                          help="Run configuration YAML (default: configs/run_thesis.yaml)."),
    out: Path = typer.Option(..., "--out", "-o", help="Run directory to write (measurements/, tables/)."),
    as_json: bool = typer.Option(False, "--json", help="Print the result as JSON."),
):
    """Simulate the acquisition of a run: move the (simulated) hexapod to each artefact
    pose, render every scanner's fringe frames, decode them into measurement stores."""
    from fringecal.hexapod import HexapodFault, TargetRejected

    try:
        cfg, plans = check_acquisition_config(config)
    except TargetRejected as err:
        raise UserInputError(str(err)) from None
    from flows.acquire_flow import acquire_flow

    try:
        result = acquire_flow(cfg, str(out))
    except TargetRejected as err:
        raise UserInputError(str(err)) from None
    except HexapodFault as err:
        fail(f"hexapod: {err}", code=1)
    import pandas as pd

    table = pd.read_csv(result["measurements"].path, dtype={"measurement": str, "pose": str, "scanner": str})
    poses = pd.read_csv(result["poses"].path, dtype={"measurement": str})
    if as_json:
        print(json.dumps({"run_dir": str(out), "measurements": table.to_dict("records"),
                          "poses": poses.to_dict("records"),
                          "tables": {"measurements": result["measurements"].path, "poses": result["poses"].path}},
                         indent=2, default=str))
        return
    from rich.table import Table

    t = Table(title=f"acquired {len(table)} measurements -> {out}")
    for col in ("measurement", "store", "valid %", "sphere pixels"):
        t.add_column(col)
    for r in table.itertuples(index=False):
        t.add_row(r.measurement, r.store, f"{100 * r.valid_fraction:.1f}", str(r.sphere_pixels))
    console.print(t)
    hexapod = poses[poses["hexapod"]]
    if len(hexapod):
        console.print(f"hexapod: {len(hexapod)} poses, reached within {hexapod['translation_error_mm'].max():.4f} mm "
                      f"and {1e6 * hexapod['rotation_error_rad'].max():.0f} urad of plan")
