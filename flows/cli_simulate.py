"""``fringecal simulate``: a simulated rig written as a recorded data set."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from fringecal.flows.common import UserInputError, console, guarded
from fringecal.flows.progress import HELP as PROGRESS_HELP


@guarded
def simulate_command(
    out: Path = typer.Option(..., "--out", "-o", help="Data set folder to write (must not exist)."),
    config: Optional[Path] = typer.Option(None, "--config", "-c", help="Run config YAML with a simulate section "
                                          "(default: configs/run_thesis.yaml, the thesis rig)."),
    fmt: str = typer.Option("png", "--format", help="Frame files: png (16-bit, lossless) or tif."),
    truth: Optional[Path] = typer.Option(None, "--truth", help="Folder for the truth (default: <out>-truth); the "
                                         "data set does not reference it."),
    workers: int = typer.Option(2, "--workers", min=1, help="Stacks rendered at a time."),
    progress: Optional[str] = typer.Option(None, "--progress", help=PROGRESS_HELP),
):
    """Render the simulated rig's measurements and write them as a recorded data set
    (the layout `fringecal run --dataset` reads, as a real cell would fill it)."""
    from fringecal.flows import progress as shown
    from fringecal.flows.cli_run import check_simulation, reporter_for, validate_run_config

    reporter = reporter_for(progress, console)
    reporter.say(f"fringecal simulate: checking {config or 'configs/run_thesis.yaml (the thesis rig)'}; "
                 f"the data set goes to {out}")
    from fringecal.simulate.export import write_dataset
    from fringecal.simulate.source import acquisition_table, load_simulated_rig, object_plans

    if fmt not in ("png", "tif"):
        raise UserInputError(f"--format must be png or tif, not {fmt!r}")
    from fringecal.flows.validate import input_file, new_folder

    truth = truth or out.with_name(out.name + "-truth")
    new_folder(out, "--out")
    new_folder(truth, "--truth")
    input_file(config, "--config", "run config YAML file")
    cfg = validate_run_config(config)
    if cfg.source != "simulated":
        raise UserInputError(f"{config}: has no simulate section (it names a data set)")
    depths = cfg.acceptance.specification.depth_range_mm
    check_simulation(cfg.simulate, depths)
    sr = load_simulated_rig(cfg.simulate, depths)
    plans = object_plans(cfg.simulate, sr.truth, sr.built, sr.rods, sr.hardware)
    for plan in plans:
        reporter.say(f"object {plan.spec.name} ({plan.spec.kind}): recorded by {', '.join(plan.recorders)}")
        for line in plan.describe_skipped():
            reporter.say(line)
    n = len(acquisition_table(sr)) + sum(len(p.recorders) for p in plans)
    from fringecal.flows.common import needs_space
    from fringecal.simulate.export import remove_interrupted_exports

    for folder, size in remove_interrupted_exports(out.absolute().parent, truth.absolute().parent):
        reporter.say(f"removed {folder} ({size / 1e6:.0f} MB), left by an interrupted fringecal simulate")
    w = cfg.simulate.acquisition.camera_width_px
    needs_space(out.absolute().parent, n * 100 * w * w * 2, "the data set (16-bit frames, about 100 per stack)")
    with reporter.running():
        shown.step("render image stacks", n)
        write_dataset(cfg, out, truth, fmt, workers, on_stack=lambda _: shown.advance("render image stacks"))
    console.print(f"data set: {out}\ntruth (not part of the data set): {truth}\n"
                  f"calibrate it with: fringecal run --dataset {out} --out runs/{out.name}")
