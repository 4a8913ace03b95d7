"""``fringecal export opencv`` and ``fringecal import opencv``: calibrations to and from
OpenCV (:mod:`fringecal.interop`). They answer at once: no Prefect."""

from __future__ import annotations

import json
from pathlib import Path
from typing import List, Optional

import typer
from rich.table import Table

from fringecal.flows.common import UserInputError, console, guarded
from fringecal.flows.help import CONTEXT, example

EXPORT_EXAMPLE = "fringecal export opencv --calibration configs/thesis/sensors_refined_table6-8.csv --out cv"
IMPORT_EXAMPLE = "fringecal import opencv --stereo cv/scanner1.yml --stereo cv/scanner2.yml --out sensors_prior.csv"
export_app = typer.Typer(no_args_is_help=True, context_settings=CONTEXT, epilog=example(EXPORT_EXAMPLE),
                         help="Export a calibration to other software.")
import_app = typer.Typer(no_args_is_help=True, context_settings=CONTEXT, epilog=example(IMPORT_EXAMPLE),
                         help="Import calibrations from other software.")


def _opencv_errors():
    from fringecal.interop.opencv_storage import OpenCVFileError

    return (OpenCVFileError,)


def _read_rig(path: Path, option: str):
    """The rig of a calibration file or sensor table, and its sensors' observed regions
    (none from a table)."""
    from fringecal.calibration.file import read_calibration
    from fringecal.flows.validate import calibration_file
    from fringecal.rig import load_rig

    path = calibration_file(path, option)
    if not path.is_file():
        raise UserInputError(f"{path}: no such file")
    suffix = path.suffix.lower()
    if suffix == ".csv":
        return load_rig(path), {}
    if suffix not in (".json", ".xml"):
        raise UserInputError(f"{path}: expected a calibration .json or .xml (a run's calibration file) or a "
                             f"sensor-parameter .csv (e.g. a data set's sensors_prior.csv)")
    cal = read_calibration(path)
    return cal.rig, cal.observed_regions


def _size(text: Optional[str], option: str) -> Optional[tuple[int, int]]:
    if text is None:
        return None
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise UserInputError(f"{option}: expected WIDTHxHEIGHT in pixels like 2048x2048, got {text!r}") from None
    if w < 2 or h < 2:
        raise UserInputError(f"{option}: at least 2x2 pixels, got {text!r}")
    return w, h


def _print(rows: list[dict], title: str, as_json: bool, extra: dict) -> None:
    """JSON of ``extra`` and ``rows``, or a table of the rows (files listed below it)."""
    if as_json:
        print(json.dumps({**extra, "sensors": rows}, indent=2))
        return
    t = Table(title=title)
    cols = [c for c in rows[0] if c != "file"]
    for c in cols:
        t.add_column(c, justify="right")
    for r in rows:
        t.add_row(*[f"{r[c]:.3g}" if isinstance(r[c], float) else str(r[c]) for c in cols])
    console.print(t)
    for f in dict.fromkeys(r["file"] for r in rows):
        console.print(f"  {f}", highlight=False, soft_wrap=True)


@export_app.command("opencv", epilog=example(EXPORT_EXAMPLE))
def export_opencv(
    run: Optional[Path] = typer.Option(None, "--run", "-r", help="A calibrated run directory: export its "
                                       "calibration (calibration.json)."),
    calibration: Optional[Path] = typer.Option(None, "--calibration", help="calibration.json or .xml of a run (or "
                                               "the run directory), or a sensor-parameter CSV (e.g. a data set's "
                                               "sensors_prior.csv)."),
    out: Path = typer.Option(..., "--out", "-o", help="Folder for <scanner>.yml (created if missing)."),
    as_json: bool = typer.Option(False, "--json", help="Print the result as JSON."),
):
    """One OpenCV FileStorage YAML per scanner (cv2.stereoCalibrate layout: cameraMatrix1/2,
    distCoeffs1/2, R, T, plus each sensor's world pose and, from a run's calibration, its
    observed region as a hull in pixels); prints each sensor's model
    difference to fringecal's projection in pixels. A sensor with a correction field gets
    OpenCV's 14-coefficient model fitted by least squares, and the worst difference says
    whether it fits (at most 0.01 px) or approximates."""
    guarded(_export, extra=_opencv_errors())(run, calibration, out, as_json)


def _export(run: Optional[Path], calibration: Optional[Path], out: Path, as_json: bool) -> None:
    from fringecal.flows.validate import output_folder
    from fringecal.interop.opencv import FIT_TOLERANCE_PX
    from fringecal.interop.opencv_storage import write_rig

    if (run is None) == (calibration is None):
        raise UserInputError("give the calibration as --run RUN_DIR or as --calibration FILE (not both, not none)")
    output_folder(out, "--out")
    option, calibration = ("--run", run) if run is not None else ("--calibration", calibration)
    rig, regions = _read_rig(calibration, option)
    try:
        written = write_rig(rig, out, regions=regions)
    except ValueError as err:  # a lens model that folds over inside the format
        raise UserInputError(f"{calibration}: {err}") from None
    models = [(name, path, m) for name, (path, cam, prj) in written.items() for m in (cam, prj)]
    fitted = [m for _, _, m in models if m.fitted]  # sensors with a correction field: OpenCV's model is fitted
    rows = [{"scanner": name, "sensor": m.name, "role": m.role, "image_px": f"{m.image_size[0]}x{m.image_size[1]}",
             "worst_px": m.worst_px, "rms_px": m.rms_px, **({"model": m.verdict} if fitted else {}), "file": str(path)}
            for name, path, m in models]
    extra = {"calibration": str(calibration), "out": str(out)}
    if fitted:
        extra.update(fit_tolerance_px=FIT_TOLERANCE_PX, notes=[m.statement for m in fitted])
    _print(rows, "OpenCV model vs fringecal's projection (pixels), written to:", as_json, extra)
    if fitted and not as_json:
        for m in fitted:
            console.print(m.statement, highlight=False, soft_wrap=True)


@import_app.command("opencv", epilog=example(IMPORT_EXAMPLE))
def import_opencv(
    stereo: List[Path] = typer.Option(..., "--stereo", "-s", help="A stereo calibration (cv2.FileStorage YAML/XML: "
                                      "cameraMatrix1 = camera, cameraMatrix2 = projector, R, T); one per scanner."),
    scanner: Optional[List[str]] = typer.Option(None, "--scanner", help="Scanner name of each --stereo, in order "
                                                "(default: the file's 'scanner' key, else its stem)."),
    out: Path = typer.Option(..., "--out", "-o", help="Prior table to write (a data set's sensors_prior.csv), or a "
                             "calibration file (.json, with its .xml twin) that also keeps each sensor's observed "
                             "region (observedHullPx1/2)."),
    reference: Optional[str] = typer.Option(None, "--reference", help="Reference scanner (default: the first)."),
    camera_size: Optional[str] = typer.Option(None, "--camera-size", help="Camera WIDTHxHEIGHT px where a file "
                                              "has no imageSize1."),
    projector_size: Optional[str] = typer.Option(None, "--projector-size", help="Projector WIDTHxHEIGHT px where "
                                                 "a file has no imageSize2."),
    camera_width_mm: Optional[float] = typer.Option(None, "--camera-width-mm", help="Camera format width (mm) where "
                                                    "a file has no sensorSizeMm1 (default 15.1, the thesis's)."),
    projector_width_mm: Optional[float] = typer.Option(None, "--projector-width-mm", help="Projector format width "
                                                       "(mm) where a file has no sensorSizeMm2 (default 19.0)."),
    as_json: bool = typer.Option(False, "--json", help="Print the result as JSON."),
):
    """Each scanner's prior calibration in its own frame (camera at the origin) from
    OpenCV stereo calibrations, written as a data set's sensors_prior.csv, or as a
    calibration file (--out NAME.json, and NAME.xml) that keeps the observed region of
    each sensor whose file has one (fringecal export opencv writes it)."""
    guarded(_import, extra=_opencv_errors())(stereo, scanner or [], out, reference, camera_size, projector_size,
                                             camera_width_mm, projector_width_mm, as_json)


def _import(stereo, names, out, reference, camera_size, projector_size, camera_width_mm, projector_width_mm,
            as_json) -> None:
    from fringecal.interop.opencv_storage import prior_scanner, read_stereo
    from fringecal.rig import Rig
    from fringecal.rundir import CalibrationFile, RigFile

    if names and len(names) != len(stereo):
        raise UserInputError(f"--scanner: {len(names)} name(s) for {len(stereo)} --stereo file(s); give one name per "
                             "file, in the same order, or none")
    from fringecal.flows.validate import output_file, positive

    for option, value in (("--camera-width-mm", camera_width_mm), ("--projector-width-mm", projector_width_mm)):
        positive(value, option, "mm")
    output_file(out, "--out")
    if out.suffix.lower() not in (".csv", ".json", ".xml"):
        raise UserInputError(f"--out {out}: expected a prior table .csv (a data set's sensors_prior.csv) or a "
                             "calibration file .json or .xml (it keeps each sensor's observed region)")
    sizes = {"camera_size": _size(camera_size, "--camera-size"),
             "projector_size": _size(projector_size, "--projector-size")}
    files = [read_stereo(p) for p in stereo]
    from fringecal.names import check_name

    for n in names:  # names become file names: one safe path component each
        check_name(n, "--scanner")
    names = names or [check_name(f.scanner or f.path.stem, "scanner", str(f.path)) for f in files]
    for f in files:
        for sensor in (f.camera_name, f.projector_name):
            if sensor:
                check_name(sensor, "sensor name", str(f.path))
    for i, n in enumerate(names):
        if names.index(n) != i:
            raise UserInputError(f"scanner name {n!r} given twice ({stereo[names.index(n)]} and {stereo[i]}); "
                                 "name them with --scanner")
    scanners, rows, regions = [], [], {}
    for i, (f, name) in enumerate(zip(files, names), 1):
        sc, cam, prj = prior_scanner(f, name, f.camera_name or f"C{i}", f.projector_name or f"P{i}", **sizes,
                                     camera_width_mm=camera_width_mm, projector_width_mm=projector_width_mm)
        scanners.append(sc)
        regions.update({s.name: r for k, s in ((1, sc.camera), (2, sc.projector)) if (r := f.region(k)) is not None})
        rows += [{"scanner": name, "sensor": imp.sensor.name, "role": imp.sensor.role, "worst_px": imp.worst_px,
                  "rms_px": imp.rms_px, "distortion": "fitted" if imp.fitted else "exact", "file": str(f.path)}
                 for imp in (cam, prj)]
    reference = reference or scanners[0].name
    try:
        rig = Rig(tuple(scanners), reference)
    except ValueError as err:  # duplicate sensor names, unknown reference
        raise UserInputError(f"{err}") from None
    if out.suffix.lower() == ".csv":
        RigFile(out.parent, out.name).save(rig)
        kept = "not kept: a sensor table has no place for them; give --out NAME.json to keep them" if regions else None
    else:  # the run directory's writer of a calibration: the JSON and its XML twin, regions in both
        out = CalibrationFile(out.parent, out.with_suffix(".json").name).save(
            rig, {"source": "fringecal import opencv", "files": [str(f.path) for f in files],
                  "frames": "each scanner in its own frame, its camera at the origin"}, observed_regions=regions)
        kept = "kept" if regions else None
    _print(rows, "fringecal model vs OpenCV's projection (pixels), read from:", as_json,
           {"out": str(out), "reference": reference, "observed_regions": sorted(regions), "regions": kept})
    if not as_json:
        console.print(f"prior calibration (reference {reference}): {out}", highlight=False, soft_wrap=True)
        if regions:
            console.print(f"observed regions of {', '.join(regions)}: {kept}", highlight=False, soft_wrap=True)
