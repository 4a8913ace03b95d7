"""The recorded data set: a folder a metrologist fills from real scanners.

A recorded data set is the input of a real calibration cell. :meth:`DataSet.open`
checks it completely and cheaply -- it reads YAML, CSV, folder listings, zarr metadata
and the header of every frame file (:func:`~fringecal.fringe.importer.check_stack`:
empty, truncated, colour, wrong size or bit depth), never a pixel or a chunk -- so that
a broken data set stops with one clear message before any heavy work starts;
:meth:`DataSet.check_frames` adds the checks that need pixels (dark or over-exposed
stacks) from one decoded frame per orientation of each stack. The layout is the
contract::

    DATASET/
      dataset.yaml            name, reference_scanner; optional description, temperature_c,
                              artefact_corrections, processing (overrides of the run config's
                              decode, extraction, control_points, bundle, verification and
                              acceptance sections), certificate (the report's identity block:
                              customer, cell, place, date, operator, scanner serial numbers,
                              the artefact's, ball-bar's and acceptance objects' certificates,
                              temperatures, approver; :class:`~fringecal.acceptance.identity.CertificateIdentity`);
                              unknown keys are errors
      artefact.csv            CMM table: sphere_id, x_mm, y_mm, z_mm, diameter_mm[, u_mm]
                              (at least 3 spheres)
      rods.csv                optional: rod_id, sphere_a, sphere_b, length_mm (rods masked
                              in the second pass; every sphere must be in artefact.csv)
      sensors_prior.csv       each scanner's own calibration in its own frame (sensor-parameter
                              table with width_px, height_px, width_mm, height_mm per sensor)
      poses_planned.csv       optional: measurement, tx_mm, ty_mm, tz_mm, omega_rad, phi_rad,
                              kappa_rad (one row per measurement folder, no more, no fewer)
      hexapod_moves.csv       optional: the hexapod's log of a live acquisition
                              (fringecal.schemas.HexapodMovesTable, :mod:`fringecal.acquisition.live`);
                              every row names a measurement folder
      measurements/<measurement>/<scanner>/        image stack: sequence.yaml + frames
                                                   (see :mod:`fringecal.fringe.importer`)
      measurements/<measurement>/<scanner>.zarr    or a decoded store with tau_x, tau_y, valid
                                                   and attrs["sequence"] (see :mod:`fringecal.store`)
      measurements/<measurement>/<scanner>.ply     or a black-box scanner's point cloud: x, y, z in
                                                   mm in its own frame (:mod:`fringecal.scancloud`;
                                                   ``.e57`` with the optional pye57)
      verification/ballbar.csv                     optional folder: the ball-bar's CMM table
                                                   (artefact table, exactly spheres A and B)
      verification/<position>/<scanner>/           image stacks (or <scanner>.zarr) of the ball-bar
                                                   at each position; any subset of the scanners
                                                   (length measurement error E)
      verification/acceptance/standards.yaml       the certificates of the acceptance test's objects
                                                   (VDI/VDE 2634 parts 2 and 3):
                                                   :class:`~fringecal.acceptance.standards.AcceptanceStandards`
                                                   with optional ``sphere``, ``dumbbell``, ``flat``
      verification/acceptance/sphere/<position>/<scanner>/    stacks (or <scanner>.zarr) of the
                                                   sphere (probing errors P_F and P_S)
      verification/acceptance/dumbbell/<position>/<scanner>/  of the dumbbell (sphere-spacing error SD)
      verification/acceptance/flat/<position>/<scanner>/      of the flat (flatness measurement error F)
      objects/<name>/<scanner>/                    optional, not read: measurements of objects to
                                                   measure with the calibration (``fringecal measure``;
                                                   :mod:`fringecal.simulate.objects` writes them), one
                                                   stack (or <scanner>.zarr) per scanner that saw it

A *measurement* is one artefact pose seen by every scanner: every measurement folder
holds a stack for every scanner of ``sensors_prior.csv`` and a cloud for every
black-box scanner. The stack of (measurement
``m``, scanner ``s``) has the id ``f"{m}-{s}"`` (:attr:`StackSource.id`). A *position*
is one placement of the ball-bar or of an acceptance object; its stack of scanner ``s``
has the id ``f"{position}-{s}"``.

Decisions
---------
- ``objects/`` (:data:`OBJECTS_DIR`) is not part of the calibration: :meth:`DataSet.open`
  neither lists nor checks it, and no run step reads it or keys on it. Every other
  folder at the top level is ignored too; only the files and folders above are read.
- Entries whose name starts with ``.`` are ignored everywhere (editor and OS files, and
  the hidden temporary folders that :mod:`fringecal.store` writes before a rename).
- Regular files in ``measurements/``, in a measurement or position folder and in
  ``verification/`` (besides ``ballbar.csv``) are ignored: notes and logs may sit next
  to the data. Every sub-folder, in contrast, must be a measurement, position or
  scanner stack.
- A stack becomes the run's store ``<measurement>-<scanner>`` (or ``<position>-<scanner>``),
  so a position may not share a measurement's name (``1`` and ``1``; name positions
  e.g. ``bb1``); such collisions are refused with both folders named.
- Measurement and position names sort naturally (``"2"`` before ``"10"``); stacks within
  one are in the order of the scanners in ``sensors_prior.csv``.
- Every stack (calibration, ball-bar and acceptance) must use the same fringe sequence.
- A calibration stack must have its camera's format of ``sensors_prior.csv``. A
  ball-bar or acceptance stack may have another pixel count over the same sensor
  (binning), but must keep the camera's aspect ratio within one pixel.
- ``dataset.yaml`` problems raise :class:`DataSetError` with the message of
  :func:`fringecal.config.load_yaml_model` (file and key path). Table problems
  (:class:`fringecal.schemas.TableError`), frame-folder problems
  (:class:`~fringecal.fringe.importer.FrameStackError`) and store problems
  (:class:`~fringecal.store.StoreError`) propagate unchanged: they already name the
  file, line and column. All of them are ``ValueError``.

Black-box scanners (point clouds)
---------------------------------
- A scanner whose files are clouds (``<scanner>.ply``, ``<scanner>.e57``) is a
  *black-box* scanner: it needs no row in ``sensors_prior.csv`` (which may be absent
  when every scanner is a black box); it is the reference scanner only when every
  scanner is a black box. A scanner of
  ``sensors_prior.csv`` gives image stacks or stores, never clouds; a scanner gives
  clouds everywhere or nowhere (both refused naming the file).
- Clouds sit where stacks sit: in measurement folders, ball-bar position folders and
  acceptance position folders; black-box scanners are listed after the modelled ones,
  in name order.
- :meth:`DataSet.open` reads each cloud's header (a vertex element with x, y, z, a
  ``units`` comment other than mm refused, at least one vertex);
  :meth:`DataSet.check_frames` reads every point: NaN or infinite coordinates and a
  cloud spanning less than half the artefact's smallest sphere (a cloud in metres)
  are refused naming the file (:func:`fringecal.scancloud.read_scanner_cloud`).
- A swapped cloud (another scanner's file) is not decidable from the file: the
  labelling's consistency check refuses it (``inconsistent``) when the scanners are
  linked.

Verification and acceptance
---------------------------
- ``verification/`` may hold the ball-bar (``ballbar.csv`` and position folders), the
  acceptance test (``acceptance/``), or both. Position folders need ``ballbar.csv``;
  ``ballbar.csv`` needs at least one position folder (a certificate without
  measurements is an incomplete data set, not a skipped test: remove it to skip E).
  A verification folder holding only ``acceptance/`` has no ball-bar
  (:attr:`DataSet.ballbar` is None).
- ``acceptance`` is a reserved name in ``verification/``, never a ball-bar position; a
  position spelt like it in another case (``Acceptance``) is refused as a likely typo.
- ``acceptance/`` needs ``standards.yaml`` and at least one test folder; its only
  sub-folders are the test folders ``sphere``, ``dumbbell`` and ``flat`` (any other is
  refused, naming the allowed ones); regular files besides ``standards.yaml`` are
  ignored, as elsewhere. A test folder needs at least one position folder, a position
  folder at least one scanner stack (any subset of the scanners: each stack is one
  measurement of the object by that scanner, evaluated on its own), and a test folder
  with positions needs its object's certificate in ``standards.yaml``. A certificate
  without a test folder is allowed: the certificate file may describe every object of
  the laboratory, and an object without positions is simply not tested.
- A stack directly inside a test folder (``sphere/scanner1/`` with ``sequence.yaml``,
  or ``sphere/scanner1.zarr``) is refused: stacks go in ``<test>/<position>/<scanner>/``.
- Acceptance stacks are :class:`StackSource` of kind ``"sphere"``, ``"dumbbell"`` or
  ``"flat"`` with the position as group; they are listed test by test (sphere,
  dumbbell, flat: the order of the guideline's parameters P, SD, F), positions in
  natural order, scanners in rig order.
- A position name stands for one placement of one object: it is used once in the whole
  ``verification/`` folder (ball-bar and the three tests), and store ids stay unique
  over the whole data set (measurements, ball-bar and acceptance stacks); both
  refusals name the two folders.
- ``standards.yaml`` errors (unknown keys, a missing or non-positive value) raise
  :class:`DataSetError` with the message of :func:`fringecal.config.load_yaml_model`.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Literal, Optional

from fringecal.acceptance.identity import CertificateIdentity
from fringecal.acceptance.standards import (
    STANDARDS_FILE,
    DumbbellStandard,
    FlatStandard,
    SphereStandard,
    load_standards,
)
from fringecal.artefact import load_artefact, load_rods
from fringecal.config import ConfigError, StrictModel, load_yaml_model
from fringecal.engineering.corrections import ArtefactCorrections
from fringecal.fringe.importer import SEQUENCE_FILE, check_levels, check_stack
from fringecal.fringe.sequence import FringeSequence, SequenceError
from fringecal.names import name_problem
from fringecal.rig import Rig, load_rig
from fringecal.scancloud import CLOUD_SUFFIXES, CloudFileError, check_cloud_header, read_scanner_cloud
from fringecal.schemas import HexapodMovesTable, PosePlanTable, TableError, read_table
from fringecal.store import store_attributes, verify_store

__all__ = [
    "DATASET_FILE", "ARTEFACT_FILE", "RODS_FILE", "SENSORS_PRIOR_FILE", "POSES_PLANNED_FILE",
    "HEXAPOD_MOVES_FILE", "MEASUREMENTS_DIR", "VERIFICATION_DIR", "OBJECTS_DIR", "BALLBAR_FILE", "STORE_SUFFIX",
    "STORE_VARIABLES",
    "BALLBAR_SPHERES", "ACCEPTANCE_DIR", "ACCEPTANCE_TESTS", "STANDARDS_FILE", "DataSetError", "ProcessingOverrides",
    "DatasetConfig", "StackSource", "DataSet", "natural_key",
]

DATASET_FILE = "dataset.yaml"
ARTEFACT_FILE = "artefact.csv"
RODS_FILE = "rods.csv"
SENSORS_PRIOR_FILE = "sensors_prior.csv"
POSES_PLANNED_FILE = "poses_planned.csv"
HEXAPOD_MOVES_FILE = "hexapod_moves.csv"
MEASUREMENTS_DIR = "measurements"
VERIFICATION_DIR = "verification"
#: measurements of objects to measure with the calibration (not read by the calibration)
OBJECTS_DIR = "objects"
BALLBAR_FILE = "ballbar.csv"
STORE_SUFFIX = ".zarr"
#: variables a decoded store must hold
STORE_VARIABLES = ("tau_x", "tau_y", "valid")
#: sphere ids of the ball-bar
BALLBAR_SPHERES = ("A", "B")
#: the acceptance test's folder inside ``verification/`` (a reserved name there)
ACCEPTANCE_DIR = "acceptance"
#: its test folders, in the order they are listed; each is also the stacks' kind and
#: the object's key in ``standards.yaml``
ACCEPTANCE_TESTS = ("sphere", "dumbbell", "flat")
_STANDARD_MODELS = {"sphere": SphereStandard, "dumbbell": DumbbellStandard, "flat": FlatStandard}
MIN_SPHERES = 3


class DataSetError(ValueError):
    """A data set that cannot be processed; the message starts with the offending file or folder."""


class ProcessingOverrides(StrictModel):
    """Per-data-set settings, kept as plain mappings here; they are validated when
    merged into the run configuration."""

    decode: Optional[dict] = None
    extraction: Optional[dict] = None
    control_points: Optional[dict] = None
    bundle: Optional[dict] = None
    verification: Optional[dict] = None
    acceptance: Optional[dict] = None


class DatasetConfig(StrictModel):
    """The contents of ``dataset.yaml``."""

    name: str
    reference_scanner: str
    description: Optional[str] = None
    temperature_c: Optional[float] = None
    artefact_corrections: Optional[ArtefactCorrections] = None
    processing: ProcessingOverrides = ProcessingOverrides()
    certificate: Optional[CertificateIdentity] = None


@dataclass(frozen=True)
class StackSource:
    """One stack: a (measurement or verification position, scanner) pair.

    Attributes
    ----------
    kind : {"artefact", "ballbar", "sphere", "dumbbell", "flat"}
        Calibration measurement, ball-bar position or acceptance-test position (the
        test folder's name).
    group : str
        Measurement name (its folder) or position name.
    scanner : str
    path : Path
        The frame folder or the ``.zarr`` store.
    format : {"frames", "store", "cloud"}
    width_px, height_px : int
        Image size (from ``sequence.yaml`` or the store's array metadata); 0 for a cloud.
    sequence : FringeSequence or None
        None for a cloud.
    """

    kind: Literal["artefact", "ballbar", "sphere", "dumbbell", "flat"]
    group: str
    scanner: str
    path: Path
    format: Literal["frames", "store", "cloud"]
    width_px: int
    height_px: int
    sequence: Optional[FringeSequence]

    @property
    def id(self) -> str:
        """Store id ``"<group>-<scanner>"``."""
        return f"{self.group}-{self.scanner}"

    @property
    def sequence_source(self) -> Path:
        """The file that defines the sequence and size: ``sequence.yaml`` or the store."""
        return self.path / SEQUENCE_FILE if self.format == "frames" else self.path


@dataclass(frozen=True)
class DataSet:
    """A validated recorded data set (see the module notes for the layout).

    ``verification`` holds the ball-bar's stacks, ``acceptance`` those of the acceptance
    test's objects (kinds ``sphere``, ``dumbbell``, ``flat``) and ``acceptance_standards``
    the path of their ``standards.yaml`` (None without ``verification/acceptance/``).
    """

    root: Path
    config: DatasetConfig
    artefact: Path
    rods: Optional[Path]
    sensors_prior: Optional[Path]
    poses_planned: Optional[Path]
    ballbar: Optional[Path]
    scanners: tuple[str, ...]
    measurements: tuple[StackSource, ...]
    verification: tuple[StackSource, ...]
    hexapod_moves: Optional[Path] = None
    acceptance_standards: Optional[Path] = None
    acceptance: tuple[StackSource, ...] = ()
    black_boxes: tuple[str, ...] = ()
    min_sphere_diameter_mm: float = 0.0

    @classmethod
    def open(cls, root) -> "DataSet":
        """Open and validate the data set in ``root`` without decoding any pixel (every
        frame file's header is read: :func:`~fringecal.fringe.importer.check_stack`).

        Raises
        ------
        DataSetError, fringecal.schemas.TableError, FrameStackError, StoreError
            All ``ValueError``; the message starts with the offending file or folder.
        """
        root = Path(root).expanduser().absolute()
        config = _load_config(root)
        artefact_path = _required_file(root / ARTEFACT_FILE, "the artefact's CMM table")
        artefact = load_artefact(artefact_path)
        if len(artefact) < MIN_SPHERES:
            raise DataSetError(f"{artefact_path}: {len(artefact)} sphere(s); an artefact needs at least "
                               f"{MIN_SPHERES}")
        rods = _optional_file(root / RODS_FILE)
        if rods is not None:
            load_rods(rods, artefact)
        black_boxes = _black_boxes(root)
        prior_path = root / SENSORS_PRIOR_FILE
        if black_boxes and not prior_path.exists():
            prior, rig = None, None
        else:
            prior = _required_file(prior_path, "each scanner's prior calibration")
            rig = _load_prior(prior, root / DATASET_FILE, config.reference_scanner, black_boxes)
        rig = _Scanners(rig, black_boxes, prior or prior_path)
        if config.reference_scanner not in rig.names:
            raise DataSetError(f"{root / DATASET_FILE}: reference_scanner {config.reference_scanner!r} is not a "
                               f"scanner of the data set (scanners: {', '.join(rig.names)})")
        if rig.modelled and config.reference_scanner not in rig.modelled:
            raise DataSetError(f"{root / DATASET_FILE}: reference_scanner {config.reference_scanner!r} is a black "
                               f"box; with modelled scanners ({', '.join(rig.modelled)}) the reference is one of them")
        measurements = _open_measurements(root / MEASUREMENTS_DIR, rig, rig.prior)
        poses = _optional_file(root / POSES_PLANNED_FILE)
        if poses is not None:
            _check_planned(poses, root / MEASUREMENTS_DIR, measurements)
        moves = _optional_file(root / HEXAPOD_MOVES_FILE)
        if moves is not None:
            _check_moves(moves, root / MEASUREMENTS_DIR, measurements)
        ballbar, verification, standards, acceptance = _open_verification(root / VERIFICATION_DIR, rig, rig.prior)
        _check_sequences(measurements + verification + acceptance)
        _check_unique_ids(measurements + verification + acceptance)
        _check_unique_positions(verification + acceptance)
        return cls(root, config, artefact_path, rods, prior, poses, ballbar, rig.names, measurements,
                   verification, moves, standards, acceptance, black_boxes,
                   float(2 * min(load_artefact(artefact_path).radii)))

    def stacks(self) -> tuple[StackSource, ...]:
        """Every stack: measurements, then ball-bar positions, then acceptance positions."""
        return self.measurements + self.verification + self.acceptance

    def check_frames(self, threads: int | None = None) -> None:
        """Decode the first frame of each orientation of every frame stack and refuse a
        dark or over-exposed one (:func:`~fringecal.fringe.importer.check_levels`), and
        check every decoded store's content against its digests
        (:func:`~fringecal.store.verify_store`: a flipped byte is named); the first
        problem in :meth:`stacks` order is raised. 2 of 98 frames per stack: a small part
        of decoding, run before it (``fringecal run --dataset``)."""
        from concurrent.futures import ThreadPoolExecutor

        def cloud(path):
            read_scanner_cloud(path, self.min_sphere_diameter_mm / 2)

        checks = {"frames": check_levels, "store": verify_store, "cloud": cloud}
        jobs = [(checks[s.format], s.path) for s in self.stacks()]
        with ThreadPoolExecutor(max_workers=threads or _cores()) as pool:
            futures = [pool.submit(check, path) for check, path in jobs]
            errors = [e for e in (f.exception() for f in futures) if e is not None]
        if errors:
            raise errors[0]

    def measurement_names(self) -> list[str]:
        """Measurement names in natural order."""
        return _groups(self.measurements)

    def position_names(self) -> list[str]:
        """Ball-bar position names in natural order (empty without them)."""
        return _groups(self.verification)

    def acceptance_position_names(self, test: str) -> list[str]:
        """Position names of one acceptance test (``"sphere"``, ``"dumbbell"`` or
        ``"flat"``) in natural order (empty when the test was not measured)."""
        if test not in ACCEPTANCE_TESTS:
            raise ValueError(f"no acceptance test {test!r}; the tests are {', '.join(ACCEPTANCE_TESTS)}")
        return _groups(s for s in self.acceptance if s.kind == test)


def natural_key(name: str) -> tuple:
    """Sort key ordering digit runs by value: ``"2"`` before ``"10"``.

    >>> sorted(["10", "2", "b1", "1", "a10", "a9"], key=natural_key)
    ['1', '2', '10', 'a9', 'a10', 'b1']
    """
    parts = re.split(r"(\d+)", name)
    return tuple((0, int(p), "") if p.isdigit() else (1, 0, p) for p in parts if p), name


# -- files -------------------------------------------------------------------

def _load_config(root: Path) -> DatasetConfig:
    if not root.exists():
        raise DataSetError(f"{root}: no such data set folder")
    if not root.is_dir():
        raise DataSetError(f"{root}: not a folder; a data set is a folder holding {DATASET_FILE}")
    path = root / DATASET_FILE
    if not path.is_file():
        raise DataSetError(f"{path}: missing; a data set folder needs {DATASET_FILE} (name, reference_scanner)")
    try:
        return load_yaml_model(path, DatasetConfig)
    except ConfigError as err:
        raise DataSetError(str(err)) from err


def _required_file(path: Path, what: str) -> Path:
    if not path.is_file():
        raise DataSetError(f"{path}: missing; a data set needs {path.name} ({what})")
    return path


def _optional_file(path: Path) -> Optional[Path]:
    if path.exists() and not path.is_file():
        raise DataSetError(f"{path}: not a file")
    return path if path.exists() else None


def _load_prior(path: Path, config_path: Path, reference: str, black_boxes: tuple = ()) -> Rig:
    try:
        rig = load_rig(path)
    except TableError:
        raise
    except ValueError as err:
        raise DataSetError(f"{path}: {err}") from None
    names = [s.name for s in rig.scanners]
    if reference not in names and reference not in black_boxes:
        raise DataSetError(f"{config_path}: reference_scanner {reference!r} is not a scanner of {path} "
                           f"(scanners: {', '.join(names)})")
    return rig


class _Scanners:
    """The scanners of a data set: the modelled ones of ``sensors_prior.csv`` (``rig``,
    None without the file) in its order, then the black-box scanners in name order."""

    def __init__(self, rig: Optional[Rig], black_boxes: tuple, prior: Path):
        self.rig, self.black_boxes, self.prior = rig, tuple(black_boxes), prior
        self.modelled = tuple(s.name for s in rig.scanners) if rig is not None else ()
        self.names = self.modelled + tuple(b for b in self.black_boxes if b not in self.modelled)


def _cloud_scanner(entry: Path) -> Optional[str]:
    """The scanner of a cloud file's name (``scanner2.ply`` -> ``scanner2``), else None."""
    if not entry.is_file() or entry.name.startswith("."):
        return None
    suffix = entry.suffix.lower()
    return entry.name[: -len(suffix)] if suffix in CLOUD_SUFFIXES else None


def _black_boxes(root: Path) -> tuple[str, ...]:
    """Names of the scanners that give clouds anywhere in ``measurements/`` and
    ``verification/`` (their groups' files), in natural order."""
    found = set()
    for top in (root / MEASUREMENTS_DIR, root / VERIFICATION_DIR):
        if not top.is_dir():
            continue
        for pattern in ("*/*", f"{ACCEPTANCE_DIR}/*/*/*"):
            for entry in top.glob(pattern):
                if (scanner := _cloud_scanner(entry)) is not None:
                    found.add(scanner)
    return tuple(sorted(found, key=natural_key))


def _cores() -> int:
    import os

    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def _entries(folder: Path) -> list[Path]:
    """Visible sub-folders in natural order (hidden entries and regular files ignored);
    each name must be one safe path component (it becomes part of a run's store names)."""
    found = sorted((p for p in folder.iterdir() if not p.name.startswith(".") and p.is_dir()),
                   key=lambda p: natural_key(p.name))
    for p in found:
        if (problem := name_problem(p.name)) is not None:
            raise DataSetError(f"{p}: folder name: {problem}; rename the folder")
    return found


def _groups(sources: Iterable[StackSource]) -> list[str]:
    return list(dict.fromkeys(s.group for s in sources))


# -- stacks ------------------------------------------------------------------

def _scan_group(folder: Path, rig: _Scanners, prior: Path) -> dict[str, tuple[Path, str]]:
    """Stacks of one measurement or position folder: scanner -> (path, format), rig order."""
    known = list(rig.modelled)
    found: dict[str, tuple[Path, str]] = {}
    for entry in sorted(folder.iterdir(), key=lambda p: natural_key(p.name)):
        scanner = _cloud_scanner(entry)
        if scanner is None:
            continue
        if (problem := name_problem(scanner)) is not None:
            raise DataSetError(f"{entry}: file name: {problem}; rename the file")
        if scanner in known:
            raise DataSetError(f"{entry}: a point cloud of scanner {scanner!r}, which has a prior calibration "
                               f"in {prior}: a scanner gives image stacks or stores, or clouds (a black box, "
                               "without a row in sensors_prior.csv), not both")
        if scanner in found:
            raise DataSetError(f"{folder}: ambiguous: two clouds of scanner {scanner!r} ({found[scanner][0].name} "
                               f"and {entry.name}); keep one")
        found[scanner] = (entry, "cloud")
    for entry in _entries(folder):
        is_store = entry.name.endswith(STORE_SUFFIX)
        scanner = entry.name[: -len(STORE_SUFFIX)] if is_store else entry.name
        if scanner in rig.black_boxes:
            raise DataSetError(f"{entry}: {'a decoded store' if is_store else 'frames'} of scanner {scanner!r}, "
                               "which gives point clouds elsewhere: a scanner gives clouds everywhere or nowhere")
        if scanner not in known:
            kind = "a decoded store" if is_store else "frames"
            raise DataSetError(f"{entry}: {kind} but no prior calibration: scanner {scanner!r} is not in {prior} "
                               f"(scanners: {', '.join(known)})")
        if scanner in found:
            names = sorted([found[scanner][0].name, entry.name], key=len)
            raise DataSetError(f"{folder}: ambiguous: scanner {scanner!r} is given both as frame folder "
                               f"{names[0]}/ and as store {names[1]}; keep one")
        found[scanner] = (entry, "store" if is_store else "frames")
    return {s: found[s] for s in rig.names if s in found}


def _read_source(kind: str, group: str, scanner: str, path: Path, fmt: str) -> StackSource:
    if fmt == "cloud":
        try:
            check_cloud_header(path)
        except CloudFileError as err:
            raise DataSetError(str(err)) from None
        return StackSource(kind, group, scanner, path, "cloud", 0, 0, None)
    if fmt == "frames":
        spec, _, _ = check_stack(path)
        return StackSource(kind, group, scanner, path, "frames", spec.width_px, spec.height_px, spec.sequence)
    width, height, sequence = _store_metadata(path)
    return StackSource(kind, group, scanner, path, "store", width, height, sequence)


def _store_metadata(path: Path) -> tuple[int, int, FringeSequence]:
    """Image width, height and sequence of a decoded store, from its metadata alone."""
    attrs = store_attributes(path)
    missing = [v for v in STORE_VARIABLES if not (path / v / "zarr.json").is_file()]
    if missing:
        raise DataSetError(f"{path}: decoded store without variable(s) {missing}; a data set store needs "
                           f"{list(STORE_VARIABLES)}")
    sizes = {v: _array_size(path, v) for v in STORE_VARIABLES}
    if len(set(sizes.values())) > 1:
        shown = ", ".join(f"{v} {w}x{h}" for v, (w, h) in sizes.items())
        raise DataSetError(f"{path}: variables of different sizes ({shown})")
    try:
        sequence = FringeSequence.from_dict(attrs["sequence"])
    except KeyError:
        raise DataSetError(f"{path}: no 'sequence' attribute (orientations, fringe_counts, n_steps)") from None
    except (SequenceError, TypeError, ValueError) as err:
        raise DataSetError(f"{path}: invalid 'sequence' attribute ({err})") from None
    return (*sizes[STORE_VARIABLES[0]], sequence)


def _array_size(store: Path, name: str) -> tuple[int, int]:
    """(width, height) of a 2-D array of a store: dims ("v", "u") or (rows, columns)."""
    meta_path = store / name / "zarr.json"
    try:
        meta = json.loads(meta_path.read_text())
        shape = [int(n) for n in meta["shape"]]
    except (ValueError, KeyError, TypeError, UnicodeDecodeError) as err:
        raise DataSetError(f"{meta_path}: corrupt array metadata ({err})") from None
    if len(shape) != 2:
        raise DataSetError(f"{store}: variable {name!r} has shape {shape}; expected an image (v, u)")
    dims = meta.get("dimension_names") or ["v", "u"]
    size = dict(zip(dims, shape))
    return size.get("u", shape[1]), size.get("v", shape[0])


# -- measurements ------------------------------------------------------------

def _open_measurements(folder: Path, rig: _Scanners, prior: Path) -> tuple[StackSource, ...]:
    if not folder.is_dir():
        raise DataSetError(f"{folder}: missing; a data set needs {MEASUREMENTS_DIR}/<measurement>/<scanner>/")
    groups = {m.name: _scan_group(m, rig, prior) for m in _entries(folder)}
    if not groups:
        raise DataSetError(f"{folder}: no measurement folder; expected {MEASUREMENTS_DIR}/<measurement>/<scanner>/")
    _check_complete(folder, groups, rig, prior)
    sources = tuple(_read_source("artefact", m, s, path, fmt)
                    for m, stacks in groups.items() for s, (path, fmt) in stacks.items())
    for src in sources:
        _check_size(src, rig, prior)
    return sources


def _check_complete(folder: Path, groups: dict, rig: _Scanners, prior: Path) -> None:
    """Every measurement holds a stack of every scanner (rule: one pose seen by all)."""
    seen: dict[str, Path] = {}
    for stacks in groups.values():
        for s, (path, _) in stacks.items():
            seen.setdefault(s, path)
    for m, stacks in groups.items():
        if not stacks:
            raise DataSetError(f"{folder / m}: measurement folder without scanner stacks (expected folders or "
                               f"{STORE_SUFFIX} stores named after the scanners of {prior.name})")
        for s in seen:
            if s not in stacks:
                raise DataSetError(f"{folder / m}: no stack of scanner {s!r}, which other measurements have "
                                   f"(e.g. {seen[s]}); every measurement needs every scanner")
    for s in rig.modelled:
        if s not in seen:
            raise DataSetError(f"{prior}: scanner {s!r} has no frames in any measurement folder of {folder}")


def _check_size(src: StackSource, rig: _Scanners, prior: Path) -> None:
    if src.format == "cloud":
        return
    camera = rig.rig.scanner(src.scanner).camera
    W, H = camera.format.width_px, camera.format.height_px
    w, h = src.width_px, src.height_px
    where = f"{src.sequence_source}: image is {w}x{h} px"
    cam = f"camera {camera.name!r} of scanner {src.scanner!r} in {prior} is {W}x{H} px"
    if src.kind == "artefact":
        if (w, h) != (W, H):
            raise DataSetError(f"{where}, but {cam}")
    elif abs(w - h * W / H) > 1 and abs(h - w * H / W) > 1:
        raise DataSetError(f"{where}, not the aspect ratio of the sensor within one pixel: {cam} "
                           f"(binning keeps the aspect ratio: {W}x{H} / 2 = {W // 2}x{H // 2})")


def _check_sequences(sources: tuple[StackSource, ...]) -> None:
    sources = tuple(s for s in sources if s.format != "cloud")
    if not sources:
        return
    first = sources[0]
    for src in sources[1:]:
        a, b = first.sequence, src.sequence
        if a != b:
            diff = [f"{what} {x} vs {y}" for what, x, y in (
                ("fringe counts", a.fringe_counts, b.fringe_counts), ("steps", a.n_steps, b.n_steps),
                ("orientations", a.orientations, b.orientations)) if x != y]
            raise DataSetError(f"{src.sequence_source}: fringe sequence differs from {first.sequence_source} "
                               f"({'; '.join(diff)}); every stack must use the same sequence")


def _check_unique_ids(sources: tuple[StackSource, ...]) -> None:
    """Every stack becomes the store ``<group>-<scanner>`` of a run: no two may share it
    (a position named like a measurement, or names whose hyphens make them collide)."""
    seen: dict[str, StackSource] = {}
    for src in sources:
        other = seen.setdefault(src.id, src)
        if other is not src:
            raise DataSetError(f"{src.path}: its store id {src.id!r} is also that of {other.path}; rename the "
                               "measurement or position folder")


def _check_planned(path: Path, folder: Path, sources: tuple[StackSource, ...]) -> None:
    planned = list(read_table(path, PosePlanTable)["measurement"])
    names = _groups(sources)
    for m in planned:
        if m not in names:
            raise DataSetError(f"{path}: planned measurement {m!r} has no measurement folder {folder / m}")
    for m in names:
        if m not in planned:
            raise DataSetError(f"{folder / m}: measurement folder has no planned pose in {path}")


def _check_moves(path: Path, folder: Path, sources: tuple[StackSource, ...]) -> None:
    names = _groups(sources)
    for m in read_table(path, HexapodMovesTable)["measurement"]:
        if m not in names:
            raise DataSetError(f"{path}: hexapod move of measurement {m!r}, which has no measurement folder "
                               f"{folder / m}")


# -- verification --------------------------------------------------------------

def _open_verification(folder: Path, rig: _Scanners, prior: Path
                       ) -> tuple[Optional[Path], tuple[StackSource, ...], Optional[Path], tuple[StackSource, ...]]:
    """(ballbar.csv, ball-bar stacks, standards.yaml, acceptance stacks) of ``verification/``."""
    if not folder.exists():
        return None, (), None, ()
    if not folder.is_dir():
        raise DataSetError(f"{folder}: not a folder")
    visible = [p for p in folder.iterdir() if not p.name.startswith(".")]
    if not visible:
        raise DataSetError(f"{folder}: empty verification folder; it needs {BALLBAR_FILE} and at least one "
                           f"position folder, or {ACCEPTANCE_DIR}/ (remove it when there is no verification)")
    acceptance_dir = folder / ACCEPTANCE_DIR
    if acceptance_dir.exists() and not acceptance_dir.is_dir():
        raise DataSetError(f"{acceptance_dir}: not a folder; {ACCEPTANCE_DIR!r} is reserved in {VERIFICATION_DIR}/ "
                           f"for the acceptance test ({STANDARDS_FILE} and {', '.join(ACCEPTANCE_TESTS)} folders)")
    positions = [p for p in _entries(folder) if p.name != ACCEPTANCE_DIR]
    ballbar, ballbar_sources = None, ()
    if positions or (folder / BALLBAR_FILE).exists() or not acceptance_dir.is_dir():
        ballbar, ballbar_sources = _open_ballbar(folder, positions, rig, prior)
    standards, acceptance = (None, ())
    if acceptance_dir.is_dir():
        standards, acceptance = _open_acceptance(acceptance_dir, rig, prior)
    return ballbar, ballbar_sources, standards, acceptance


def _open_ballbar(folder: Path, positions: list[Path], rig: _Scanners, prior: Path
                  ) -> tuple[Path, tuple[StackSource, ...]]:
    ballbar = _required_file(folder / BALLBAR_FILE, "the ball-bar's CMM table, spheres A and B")
    spheres = load_artefact(ballbar)
    if sorted(spheres.ids) != list(BALLBAR_SPHERES):
        raise DataSetError(f"{ballbar}: a ball-bar has exactly two spheres with ids "
                           f"{' and '.join(BALLBAR_SPHERES)}; found {list(spheres.ids)}")
    for p in positions:
        if p.name.casefold() == ACCEPTANCE_DIR:
            raise DataSetError(f"{p}: a ball-bar position named like the reserved acceptance folder; name the "
                               f"acceptance test's folder {ACCEPTANCE_DIR!r} (lower case) or rename the position")
    groups = {p.name: _scan_group(p, rig, prior) for p in positions}
    if not groups:
        raise DataSetError(f"{folder}: no position folder; expected {VERIFICATION_DIR}/<position>/<scanner>/")
    for p, stacks in groups.items():
        if not stacks:
            raise DataSetError(f"{folder / p}: position folder without scanner stacks (expected folders or "
                               f"{STORE_SUFFIX} stores named after the scanners of {prior.name})")
    sources = tuple(_read_source("ballbar", p, s, path, fmt)
                    for p, stacks in groups.items() for s, (path, fmt) in stacks.items())
    for src in sources:
        _check_size(src, rig, prior)
    return ballbar, sources


def _open_acceptance(folder: Path, rig: _Scanners, prior: Path) -> tuple[Path, tuple[StackSource, ...]]:
    """``standards.yaml`` and the stacks of ``verification/acceptance/``."""
    tests = ", ".join(f"{t}/" for t in ACCEPTANCE_TESTS)
    if not any(not p.name.startswith(".") for p in folder.iterdir()):
        raise DataSetError(f"{folder}: empty acceptance folder; it needs {STANDARDS_FILE} and at least one of the "
                           f"test folders {tests} (remove it when there is no acceptance test)")
    path = folder / STANDARDS_FILE
    if path.exists() and not path.is_file():
        raise DataSetError(f"{path}: not a file")
    if not path.exists():
        raise DataSetError(f"{path}: missing; {folder} needs {STANDARDS_FILE}, the certificates of its test "
                           f"objects ({', '.join(ACCEPTANCE_TESTS)})")
    try:
        standards = load_standards(path)
    except ConfigError as err:
        raise DataSetError(str(err)) from err
    found = {}
    for entry in _entries(folder):
        if entry.name not in ACCEPTANCE_TESTS:
            raise DataSetError(f"{entry}: unknown acceptance test folder; the test folders are {tests} "
                               f"({VERIFICATION_DIR}/{ACCEPTANCE_DIR}/<test>/<position>/<scanner>/)")
        found[entry.name] = entry
    if not found:
        raise DataSetError(f"{folder}: no test folder; expected one or more of {tests} with "
                           f"<position>/<scanner>/ stacks")
    sources: list[StackSource] = []
    for test in (t for t in ACCEPTANCE_TESTS if t in found):
        sources += _open_test(found[test], test, standards, path, rig, prior)
    for src in sources:
        _check_size(src, rig, prior)
    return path, tuple(sources)


def _open_test(folder: Path, test: str, standards, standards_path: Path, rig: _Scanners, prior: Path
               ) -> list[StackSource]:
    """The stacks of one test folder (``sphere``, ``dumbbell`` or ``flat``)."""
    positions = _entries(folder)
    if not positions:
        raise DataSetError(f"{folder}: no position folder; expected {ACCEPTANCE_DIR}/{test}/<position>/<scanner>/ "
                           f"(remove the folder when the {test} was not measured)")
    if getattr(standards, test) is None:
        required = [k for k, f in _STANDARD_MODELS[test].model_fields.items() if f.is_required()]
        raise DataSetError(f"{standards_path}: no certificate {test!r}, but {folder} holds {len(positions)} "
                           f"position folder(s); add the key {test!r} ({', '.join(required)}, ...) or remove "
                           "the folder")
    sources = []
    for p in positions:
        if p.name.endswith(STORE_SUFFIX) or (p / SEQUENCE_FILE).exists():
            raise DataSetError(f"{p}: a stack directly in the test folder; stacks go in "
                               f"{ACCEPTANCE_DIR}/{test}/<position>/<scanner>/")
        stacks = _scan_group(p, rig, prior)
        if not stacks:
            raise DataSetError(f"{p}: position folder without scanner stacks (expected folders or "
                               f"{STORE_SUFFIX} stores named after the scanners of {prior.name})")
        sources += [_read_source(test, p.name, s, path, fmt) for s, (path, fmt) in stacks.items()]
    return sources


def _check_unique_positions(sources: tuple[StackSource, ...]) -> None:
    """A position name stands for one placement of one object: one folder in the whole
    ``verification/`` (ball-bar and acceptance tests)."""
    seen: dict[str, Path] = {}
    for src in sources:
        folder = src.path.parent
        other = seen.setdefault(src.group, folder)
        if other != folder:
            raise DataSetError(f"{folder}: position name {src.group!r} is also that of {other}; a position names "
                               "one placement of one object: rename one of them")
