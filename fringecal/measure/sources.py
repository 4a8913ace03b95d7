"""What ``fringecal measure`` reads: one measurement of the data-set layout.

A measurement folder holds one entry per scanner, named after the scanner as in the
calibration: either a frame folder ``<scanner>/`` (``sequence.yaml`` and the frames,
:mod:`fringecal.fringe.importer`) or a decoded store ``<scanner>.zarr`` (the store
format of a run's ``measurements/``, :mod:`fringecal.store`); a black-box scanner's
entry is its cloud ``<scanner>.ply`` (or ``.e57``) whatever the kind. Every entry is checked
before anything is decoded or triangulated (names, kind, completeness, the camera's
aspect ratio against the calibration), so a bad folder costs nothing.
"""

from __future__ import annotations

from pathlib import Path

from fringecal.fringe.decode import decode
from fringecal.fringe.importer import SEQUENCE_FILE, check_stack, read_frames
from fringecal.fringe.measurement import check_decoded, measurement_dataset
from fringecal.rig import Rig
from fringecal.scancloud import CLOUD_SUFFIXES, check_cloud_header
from fringecal.store import StoreError, is_complete, open_store

__all__ = ["MeasurementSourceError", "measurement_entries", "open_entry"]

STORE_SUFFIX = ".zarr"


class MeasurementSourceError(ValueError):
    """A measurement folder that cannot be measured; the message names the entry."""


def measurement_entries(folder, rig: Rig, kind: str, black_boxes=()) -> dict[str, Path]:
    """Scanner name -> frame folder (``kind="frames"``) or store (``kind="stores"``).

    Entries that are neither (hidden files, notes) are ignored; an entry of the other
    kind, a scanner the calibration does not know, or an empty folder is an error.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise MeasurementSourceError(f"{folder}: {'not a folder' if folder.exists() else 'no such folder'} "
                                     f"(a measurement folder holds one {'frame folder' if kind == 'frames' else 'store'}"
                                     f" per scanner)")
    names = [s.name for s in rig.scanners]
    out = {}
    for entry in sorted(folder.iterdir()):
        if entry.name.startswith("."):
            continue
        if entry.is_file() and entry.suffix.lower() in CLOUD_SUFFIXES:
            scanner = entry.name[:-len(entry.suffix)]
            if scanner not in black_boxes:
                raise MeasurementSourceError(f"{entry}: a point cloud, but scanner {scanner!r} is not a black-box "
                                             f"scanner of the calibration ({', '.join(black_boxes) or 'none'})")
            out[scanner] = entry
            continue
        is_store = entry.name.endswith(STORE_SUFFIX)
        is_frames = entry.is_dir() and not is_store and (entry / SEQUENCE_FILE).is_file()
        if not (is_store or is_frames):
            continue
        scanner = entry.name[:-len(STORE_SUFFIX)] if is_store else entry.name
        if (kind == "frames") != is_frames:
            want = f"frame folders <scanner>/ with {SEQUENCE_FILE}" if kind == "frames" else f"stores <scanner>{STORE_SUFFIX}"
            raise MeasurementSourceError(f"{entry}: a {'store' if is_store else 'frame folder'}, but --{kind} "
                                         f"expects {want}")
        if scanner not in names:
            raise MeasurementSourceError(f"{entry}: scanner {scanner!r} is not in the calibration ({', '.join(names)})")
        out[scanner] = entry
    if not out:
        want = f"<scanner>/ frame folders with {SEQUENCE_FILE}" if kind == "frames" else f"<scanner>{STORE_SUFFIX} stores"
        raise MeasurementSourceError(f"{folder}: no {want} of the calibration's scanners ({', '.join(names)})")
    for scanner, entry in out.items():
        if scanner in black_boxes:
            check_cloud_header(entry)
        else:
            _check_entry(entry, rig.scanner(scanner).camera, kind)
    return out


def _check_entry(entry: Path, camera, kind: str) -> None:
    if kind == "frames":
        spec, _, _ = check_stack(entry)  # every frame's header: empty, truncated, colour, size, depth
        w, h = spec.width_px, spec.height_px
    else:
        if not is_complete(entry):
            raise MeasurementSourceError(f"{entry}: not a complete store (interrupted write or not a fringecal store)")
        try:
            with open_store(entry) as ds:
                missing = [v for v in ("tau_x", "tau_y", "valid", "modulation_x", "modulation_y") if v not in ds]
                h, w = int(ds.sizes.get("v", 0)), int(ds.sizes.get("u", 0))
        except StoreError as err:
            raise MeasurementSourceError(str(err)) from None
        if missing:
            raise MeasurementSourceError(f"{entry}: the store has no {', '.join(missing)} (not a decoded measurement)")
    fmt = camera.format
    if w * fmt.height_px != h * fmt.width_px:
        raise MeasurementSourceError(f"{entry}: {w}x{h} px, but camera {camera.name!r} of the calibration is "
                                     f"{fmt.width_px}x{fmt.height_px} px (not the same sensor, nor binned)")


def open_entry(entry: Path, kind: str, decode_settings=None, scanner_fits=()):
    """The maps of one entry (an opened store, or the frames decoded in memory;
    ``scanner_fits``: as :func:`~fringecal.fringe.decode.decode`)."""
    if kind == "stores":
        return open_store(entry)

    stack = read_frames(entry)
    result = decode(stack.frames, stack.sequence, decode_settings, stack.full_scale, scanner_fits=scanner_fits)
    check_decoded(result, str(entry))
    return measurement_dataset(result, {"source": str(entry)})
