"""``fringecal decode``: fringe frame folders -> measurement stores."""

from __future__ import annotations

import json
from pathlib import Path

import typer
from pydantic import ValidationError

from fringecal.flows.common import UserInputError, console, guarded


def _measurements(frames: Path, out: Path) -> tuple[list[Path], list[Path]]:
    """One folder with sequence.yaml -> one store at ``out``; a folder of such folders
    -> ``out/<name>.zarr`` each."""
    from fringecal.fringe.importer import SEQUENCE_FILE

    if not frames.is_dir():
        raise UserInputError(f"{frames}: no such folder")
    if (frames / SEQUENCE_FILE).exists():
        return [frames], [out]
    dirs = sorted(d for d in frames.iterdir() if (d / SEQUENCE_FILE).is_file())
    if not dirs:
        raise UserInputError(f"{frames}: neither a measurement folder ({SEQUENCE_FILE} and frames) "
                             f"nor a folder of measurement folders")
    from fringecal.names import check_name, confined

    return dirs, [confined(out, f"{check_name(d.name, 'measurement folder', str(frames))}.zarr") for d in dirs]


def _store_size(dirs: list[Path], store_frames: bool) -> float:
    """Roughly the bytes of the stores: six maps of four bytes per pixel (tau_x, tau_y,
    modulation, phase error, texture, valid), and the frames when kept, before compression."""
    from fringecal.fringe.importer import read_stack_spec

    total = 0.0
    for d in dirs:
        spec, _, _ = read_stack_spec(d)
        pixels = spec.width_px * spec.height_px
        total += 24 * pixels + (spec.sequence.n_frames * pixels * spec.dtype.itemsize if store_frames else 0)
    return total


def _decode(dirs: list[Path], outs: list[Path], settings, store_frames: bool) -> list:
    """Decode each folder into its store, one after the other (each decode uses every core).

    Directly, unless a Prefect server is configured: then as the decode flow on it,
    whose cache skips folders decoded before with the same frames and settings.
    """
    from fringecal.flows.common import configured_prefect_api, no_prefect_telemetry
    from fringecal.tasks.refs import ref_for

    if configured_prefect_api():
        no_prefect_telemetry()
        from fringecal.flows.decode_flow import decode_flow

        return decode_flow([str(d) for d in dirs], [str(o) for o in outs], settings.model_dump(), store_frames)
    from fringecal.fringe.measurement import decode_folder

    refs = []
    for d, o in zip(dirs, outs, strict=True):
        frames = ref_for(d, "frames")
        decode_folder(d, o, settings, attrs={"frames_digest": frames.digest}, store_frames=store_frames)
        refs.append(ref_for(o, "store"))
    return refs


def _ripple_cell(ripple: dict | None) -> str:
    """'corrected 182.1 (Z 6.4e+06)' or 'none seen (Z 1.2)' per orientation."""
    if not ripple:
        return "-"
    return " / ".join(f"{'corrected' if r['applied'] else 'none seen'} {1000 * r['excess_rms_rad']:.1f} "
                      f"(Z {r['z']:.3g})" for r in ripple.values())


@guarded
def decode_command(
    frames: Path = typer.Option(..., "--frames", "-f",
                                help="Measurement folder (sequence.yaml + one PNG/TIFF per frame, or frames.npy), "
                                     "or a folder of measurement folders."),
    out: Path = typer.Option(..., "--out", "-o",
                             help="Store to write (M.zarr); a folder of <name>.zarr stores for several measurements."),
    min_modulation: float = typer.Option(0.02, help="Valid pixels: modulation >= this fraction of full scale."),
    max_phase_error: float = typer.Option(0.3, help="Valid pixels: RMS residual of the tau fit <= this (rad)."),
    phase_ripple: str = typer.Option("auto", help="Phase ripple the N-step sequence leaves (projector gamma, camera "
                                                  "response, step errors): auto = correct where the data show it, "
                                                  "always, off."),
    store_frames: bool = typer.Option(False, "--store-frames", help="Also keep the raw frames in the store."),
    as_json: bool = typer.Option(False, "--json", help="Print the result as JSON."),
):
    """Decode fringe image stacks into zarr stores (tau_x, tau_y, modulation, phase error, texture, valid)."""
    from fringecal.fringe.decode import DecodeSettings
    from fringecal.fringe.importer import check_levels, check_stack
    from fringecal.store import open_store

    try:
        settings = DecodeSettings(min_modulation=min_modulation, max_phase_error=max_phase_error,
                                  phase_ripple=phase_ripple)
    except ValidationError as err:
        raise UserInputError("; ".join(f"--{e['loc'][0].replace('_', '-')}: {e['msg']}" for e in err.errors()))
    from fringecal.flows.validate import input_folder, output_folder

    input_folder(frames, "--frames", "measurement folder")
    output_folder(out, "--out")
    dirs, outs = _measurements(frames, out)
    for d in dirs:  # names, sequence.yaml, the schedule and every frame's header before any decoding
        check_stack(d)
    for d in dirs:  # then one frame per orientation of each: dark or over-exposed stacks
        check_levels(d)
    from fringecal.flows.common import needs_space

    needs_space(out, lambda: _store_size(dirs, store_frames), f"decoding {len(dirs)} stack(s)")
    refs = _decode(dirs, outs, settings, store_frames)
    rows = []
    for d, ref in zip(dirs, refs):
        attrs = open_store(ref.path).attrs
        rows.append({"frames": str(d), "store": ref.path, "digest": ref.digest,
                     "scanner": attrs.get("scanner"), "measurement": attrs.get("measurement"), **attrs["summary"]})
    if as_json:
        print(json.dumps({"stores": rows}, indent=2))
        return
    from rich.table import Table

    t = Table(title=f"decoded -> {out}")
    for col in ("frames", "store", "valid %", "median phase error x / y (mrad)", "phase ripple x / y (mrad, Z)"):
        t.add_column(col)
    for r in rows:
        errs = [r.get(f"median_phase_error_{o}_rad") for o in "xy"]
        t.add_row(r["frames"], r["store"], f"{100 * r['valid_fraction']:.1f}",
                  " / ".join("-" if e is None else f"{1000 * e:.1f}" for e in errs),
                  _ripple_cell(r.get("phase_ripple")))
    console.print(t)
