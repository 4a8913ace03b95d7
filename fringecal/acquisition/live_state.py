"""What a live acquisition finds on disk and what it records there.

* :func:`survey`: per planned measurement, the scanners whose stack is in place
  (``measurements/<m>/<scanner>/`` or ``<scanner>.zarr``; a visible stack folder is
  complete by construction, since captures are renamed into place whole), and the
  staging folders a killed run left behind. Frame stacks already in place are checked
  cheaply (``sequence.yaml`` and the listing, the camera format, one fringe sequence).
* :class:`MovesLog`: the journal ``.acquire/moves.csv`` (every move, written right after
  the move) and the published ``hexapod_moves.csv`` (:class:`fringecal.schemas.HexapodMovesTable`,
  one row per complete measurement: its last move, and how many moves it took). Both
  are rewritten atomically, so a kill at any point leaves either the old or the new file.
* :func:`acquisition_lock`: one acquirer per data set (``.acquire/lock``, released by
  the kernel if the process dies).
"""

from __future__ import annotations

import fcntl
import os
from contextlib import contextmanager
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Iterator, Optional

import pandas as pd

from fringecal.acquisition.live_capture import is_staging
from fringecal.dataset import HEXAPOD_MOVES_FILE, MEASUREMENTS_DIR, POSES_PLANNED_FILE, STORE_SUFFIX, DataSetError
from fringecal.frames import POSE_COLUMNS
from fringecal.fringe.importer import read_stack_spec
from fringecal.fringe.sequence import FringeSequence
from fringecal.schemas import HexapodMovesTable, read_table, write_table

__all__ = ["ACQUIRE_DIR", "MeasurementState", "Survey", "survey", "MovesLog", "move_row", "acquisition_lock"]

#: hidden folder of the acquirer's own files (journal, lock, capture logs)
ACQUIRE_DIR = ".acquire"


@dataclass(frozen=True)
class MeasurementState:
    """Scanners of one measurement with a stack in place (``present``) and without (``missing``)."""

    name: str
    present: tuple[str, ...]
    missing: tuple[str, ...]

    @property
    def complete(self) -> bool:
        return not self.missing

    @property
    def status(self) -> str:
        """``complete``, ``partial`` or ``pending``."""
        return "complete" if self.complete else "partial" if self.present else "pending"


@dataclass(frozen=True)
class Survey:
    """Every planned measurement's state (plan order), the stale staging folders, and the
    fringe sequence of the first frame stack in place (None when there is none yet)."""

    states: dict[str, MeasurementState]
    stale: tuple[Path, ...]
    sequence: Optional[FringeSequence]
    sequence_source: Optional[Path]

    def todo(self) -> list[str]:
        return [m for m, s in self.states.items() if not s.complete]


def survey(root: Path, measurements: list[str], scanners: dict[str, tuple[int, int]]) -> Survey:
    """Look at ``measurements/`` of the data set ``root``.

    Parameters
    ----------
    root : Path
    measurements : list of str
        Planned measurements, in plan order.
    scanners : dict
        Scanner name -> camera (width_px, height_px), in ``sensors_prior.csv`` order.

    Raises
    ------
    DataSetError, FrameStackError
        A folder that is no planned measurement or no known scanner, or a frame stack in
        place that is not of this data set; the message names the folder.
    """
    folder = root / MEASUREMENTS_DIR
    if folder.exists() and not folder.is_dir():
        raise DataSetError(f"{folder}: not a folder")
    if folder.is_dir():
        for entry in folder.iterdir():
            if entry.is_dir() and not entry.name.startswith(".") and entry.name not in measurements:
                raise DataSetError(f"{entry}: measurement folder has no planned pose in {root / POSES_PLANNED_FILE}")
    states, stale = {}, []
    seq: list = [None, None]
    for m in measurements:
        present = _scan(folder / m, scanners, stale, seq)
        states[m] = MeasurementState(m, tuple(s for s in scanners if s in present),
                                     tuple(s for s in scanners if s not in present))
    return Survey(states, tuple(stale), seq[0], seq[1])


def _scan(mf: Path, scanners: dict, stale: list, seq: list) -> set[str]:
    if not mf.exists():
        return set()
    if not mf.is_dir():
        raise DataSetError(f"{mf}: not a folder; a measurement folder holds one stack per scanner")
    found: dict[str, Path] = {}
    for entry in sorted(mf.iterdir()):
        if is_staging(entry):
            stale.append(entry)
            continue
        scanner = entry.name.removesuffix(STORE_SUFFIX)
        if entry.name.startswith("."):
            continue
        if not entry.is_dir():
            if entry.name in scanners:  # the stack's folder will be renamed onto this name
                raise DataSetError(f"{entry}: a file where the stack of scanner {entry.name!r} belongs; move it away")
            continue
        if scanner not in scanners:
            raise DataSetError(f"{entry}: scanner {scanner!r} is not in sensors_prior.csv (scanners: "
                               f"{', '.join(scanners)})")
        if scanner in found:
            raise DataSetError(f"{mf}: ambiguous: scanner {scanner!r} is given both as {found[scanner].name}/ "
                               f"and as {entry.name}/; keep one")
        found[scanner] = entry
        if entry.name.endswith(STORE_SUFFIX):
            continue  # a decoded store; DataSet.open checks it once the data set is complete
        spec, _, _ = read_stack_spec(entry)
        if (spec.width_px, spec.height_px) != scanners[scanner]:
            w, h = scanners[scanner]
            raise DataSetError(f"{entry}: images are {spec.width_px}x{spec.height_px} px, but the camera of scanner "
                               f"{scanner!r} in sensors_prior.csv is {w}x{h} px")
        if seq[0] is None:
            seq[0], seq[1] = spec.sequence, entry
        elif spec.sequence != seq[0]:
            raise DataSetError(f"{entry}: fringe sequence {spec.sequence.to_dict()} differs from "
                               f"{seq[0].to_dict()} of {seq[1]}; every stack must use the same sequence")
    return set(found)


def move_row(measurement: str, move, tolerance: tuple[float, float]) -> dict:
    """One journal row for an :class:`~fringecal.hexapod.ArtefactMove` (HexapodMovesTable columns)."""
    row = {"measurement": measurement, **dict(zip(POSE_COLUMNS, map(float, move.reached.params)))}
    row.update({f"planned_{c}": float(v) for c, v in zip(POSE_COLUMNS, move.planned.params)})
    row.update(translation_error_mm=move.translation_error_mm, rotation_error_rad=move.rotation_error_rad,
               hexapod=True)
    row.update({f"counts_{i + 1}": int(c) for i, c in enumerate(move.counts_read)})
    row.update(tolerance_mm=float(tolerance[0]), tolerance_rad=float(tolerance[1]), moves=1,
               time_utc=datetime.now(timezone.utc).isoformat(timespec="milliseconds"))
    return row


class MovesLog:
    """The journal of every move and the published ``hexapod_moves.csv`` of a data set."""

    def __init__(self, root: Path):
        self.journal = root / ACQUIRE_DIR / "moves.csv"
        self.published = root / HEXAPOD_MOVES_FILE

    def _journal(self) -> pd.DataFrame:
        if not self.journal.is_file():
            return pd.DataFrame()
        try:
            return pd.read_csv(self.journal, dtype={"measurement": str, "time_utc": str})
        except (ValueError, pd.errors.ParserError) as err:
            raise DataSetError(f"{self.journal}: unreadable move journal ({err})") from None

    def record(self, row: dict) -> None:
        """Append one move to the journal (atomic rewrite)."""

        write_table(pd.concat([self._journal(), pd.DataFrame([row])], ignore_index=True), self.journal)

    def publish(self, complete: list[str]) -> Optional[Path]:
        """Write ``hexapod_moves.csv``: per complete measurement (in ``complete``'s order) its
        last journalled move with the number of moves; rows already published for a complete
        measurement that the journal does not hold are kept. Returns the path, or None when
        there is no row to write."""

        journal = self._journal()
        rows: dict[str, dict] = {}
        if self.published.is_file():
            for r in read_table(self.published, HexapodMovesTable).to_dict("records"):
                rows[r["measurement"]] = r
        if len(journal):
            counts = journal["measurement"].value_counts()
            for r in journal.groupby("measurement", sort=False).tail(1).to_dict("records"):
                rows[r["measurement"]] = {**r, "moves": int(counts[r["measurement"]])}
        table = [rows[m] for m in complete if m in rows]
        if not table:
            return None
        return write_table(pd.DataFrame(table), self.published, HexapodMovesTable)


@contextmanager
def acquisition_lock(root: Path) -> Iterator[None]:
    """Hold ``.acquire/lock`` of the data set; refuse when another acquirer holds it."""
    path = root / ACQUIRE_DIR / "lock"
    path.parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 32, 0).decode(errors="replace").strip() or "unknown"
            raise DataSetError(f"{root}: another `fringecal acquire` is running on this data set (pid {holder}); "
                               "wait for it or stop it") from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        yield
    finally:
        os.close(fd)
