"""Checks of command-line inputs, run at the top of a command before any work.

Numbers must be finite (click reads ``nan`` and ``inf`` as floats) and inside their
physical range; input paths must be the right kind (a file, a folder); output paths
must not be an existing thing of the other kind and must lie in a folder this process
can write into -- checked by creating and removing a hidden probe file there, which
also catches read-only file systems and the root user on ``/proc``. Every check
raises :class:`~fringecal.flows.common.UserInputError` naming the option and the value, so a
``@guarded`` command prints one line and exits with status 2 having written nothing.

Table files are checked by :func:`fringecal.schemas.read_table` (missing file, folder, bytes
that are not UTF-8, cells; with file, line and column) and config files by
:func:`fringecal.config.read_yaml_mapping`; the checks here are for the options.
"""

from __future__ import annotations

import math
import os
import tempfile
from pathlib import Path
from typing import Optional

from fringecal.flows.common import UserInputError

__all__ = ["number", "positive", "whole", "input_file", "input_folder", "output_file", "output_folder",
           "new_folder", "calibration_file", "apart", "same_unit"]


def number(value: Optional[float], option: str, *, gt: Optional[float] = None, ge: Optional[float] = None,
           le: Optional[float] = None, nonzero: bool = False, unit: str = "") -> Optional[float]:
    """``value`` if finite and within the bounds given (None passes: an option not given)."""
    if value is None:
        return None
    v = float(value)
    if not math.isfinite(v):
        raise UserInputError(f"{option}: must be a finite number{f' ({unit})' if unit else ''}, got {value}")
    unit = f" {unit}" if unit else ""
    if gt is not None and not v > gt:
        raise UserInputError(f"{option}: must be greater than {gt:g}{unit}, got {value:g}")
    if ge is not None and not v >= ge:
        raise UserInputError(f"{option}: must be at least {ge:g}{unit}, got {value:g}")
    if le is not None and not v <= le:
        raise UserInputError(f"{option}: must be at most {le:g}{unit}, got {value:g}")
    if nonzero and v == 0:
        raise UserInputError(f"{option}: must not be 0")
    return v


def positive(value: Optional[float], option: str, unit: str = "") -> Optional[float]:
    """A finite number > 0 (a length, a limit, a coverage factor), or None."""
    return number(value, option, gt=0, unit=unit)


def whole(value: Optional[int], option: str, minimum: int = 1) -> Optional[int]:
    """A whole number >= ``minimum`` (a count of workers, positions), or None."""
    if value is None:
        return None
    if value < minimum:
        raise UserInputError(f"{option}: must be at least {minimum}, got {value}")
    return value


def input_file(path: Optional[Path], option: str, what: str = "file") -> Optional[Path]:
    """An existing file to read (not a folder)."""
    if path is None:
        return None
    path = Path(path)
    if path.is_dir():
        raise UserInputError(f"{option} {path}: is a folder; expected a {what}")
    if not path.exists():
        raise UserInputError(f"{option} {path}: file not found")
    return path


def input_folder(path: Optional[Path], option: str, what: str = "folder") -> Optional[Path]:
    """An existing folder to read (not a file)."""
    if path is None:
        return None
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise UserInputError(f"{option} {path}: is a file; expected a {what}")
    if not path.is_dir():
        raise UserInputError(f"{option} {path}: no such {what}")
    return path


def calibration_file(path: Path, option: str) -> Path:
    """A calibration file to read (its reader checks it), or a run directory, which stands
    for its calibration.json. A run's calibration file must be what its step wrote (its
    content digest against the step's record: a damaged or edited file is refused)."""
    path = Path(path)
    from fringecal.rundir import RunDir, RunFile  # lazy: pandas loads only when a run's file is read
    from fringecal.steps.keys import check_unchanged  # lazy: as above

    if not path.is_dir():
        if path.is_file() and RunDir(path.parent).step_records():
            check_unchanged(RunDir(path.parent), [RunFile(path.parent, path.name)])
        return path
    cal = RunDir(path).calibration.path
    if not cal.is_file():
        raise UserInputError(f"{option} {path}: a folder without {cal.name}; expected a calibrated run "
                             "directory (fringecal run) or a calibration file")
    check_unchanged(RunDir(path), [RunDir(path).calibration])
    return cal


def output_file(path: Optional[Path], option: str) -> Optional[Path]:
    """A file to write: not an existing folder, in a folder that exists or can be made, writable."""
    if path is None:
        return None
    path = Path(path)
    if path.is_dir():
        raise UserInputError(f"{option} {path}: is a folder; expected the name of a file to write")
    _writable(path.parent, option, path)
    return path


def output_folder(path: Optional[Path], option: str) -> Optional[Path]:
    """A folder to write into: not an existing file; it, or the folder it will be made in, writable."""
    if path is None:
        return None
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise UserInputError(f"{option} {path}: is a file; expected a folder")
    _writable(path, option, path)
    return path


def new_folder(path: Path, option: str) -> Path:
    """A folder that must not exist yet (nothing is overwritten), in a writable place."""
    path = Path(path)
    if path.exists() or path.is_symlink():
        raise UserInputError(f"{option} {path}: already exists; choose a new folder (nothing is overwritten)")
    _writable(path.parent, option, path)
    return path


def _writable(folder: Path, option: str, target: Path) -> None:
    """``folder`` (made later if missing) can receive files: its nearest existing
    ancestor is a folder in which a probe file can be created."""
    existing = Path(os.path.abspath(folder))
    while not existing.exists():
        if existing.is_symlink():
            raise UserInputError(f"{option} {target}: {existing} is a broken link")
        existing = existing.parent
    if not existing.is_dir():
        raise UserInputError(f"{option} {target}: {existing} is a file, not a folder")
    try:
        fd, probe = tempfile.mkstemp(dir=existing, prefix=".fringecal-write-check-")
    except OSError as err:
        raise UserInputError(f"{option} {target}: cannot write in {existing} "
                             f"({err.strerror or err})") from None
    os.close(fd)
    os.unlink(probe)


def apart(out: Path, option: str, data: Path, what: str = "the data set") -> None:
    """``out`` (a run directory) neither equal to, inside, nor holding the folder ``data``:
    a run inside a data set adds folders its contract refuses (every later run of it
    would stop), and a run around one would treat it as the run's own files."""
    a, b = Path(os.path.realpath(out)), Path(os.path.realpath(data))
    if a == b or b in a.parents:
        raise UserInputError(f"{option} {out}: inside {what} {data}; write the run outside it (it would add files "
                             f"and folders to {what}, which later runs would refuse)")
    if a in b.parents:
        raise UserInputError(f"{option} {out}: holds {what} {data}; write the run to a folder of its own, beside "
                             f"{what}")


#: (factor, unit): a reference length ``factor`` times too small was likely given in ``unit``
_UNITS = ((1000.0, "metres"), (304.8, "feet"), (25.4, "inches"), (10.0, "centimetres"), (1e-3, "micrometres"))


def same_unit(measured_mm: float, reference_mm: float, option: str) -> None:
    """Refuse a reference length that differs from the measured lengths by more than a
    factor of two: no calibration is that wrong, a unit slip or the wrong bar is (a
    reference in metres judged as a failed cell, status 3, misleads); names the likely
    unit."""
    if not (math.isfinite(measured_mm) and measured_mm > 0):
        return
    ratio = measured_mm / reference_mm
    if 0.5 <= ratio <= 2.0:
        return
    guess = next((f"given in {unit}? ({reference_mm * f:.6g} mm)" for f, unit in _UNITS
                  if abs(math.log(ratio / f)) < math.log(1.1)), "the wrong bar or unit?")
    raise UserInputError(f"{option} {reference_mm:g}: the measured lengths average {measured_mm:.6g} mm, "
                         f"{ratio:.4g} times the reference: {guess} An error this large is an input mix-up, not "
                         "a failed cell")
