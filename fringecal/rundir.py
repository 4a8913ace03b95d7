"""The run directory: one object that owns every file of a run (docs/architecture.md).

No other module spells a file name of the run directory: steps, the report, the
flow and the command line reach every file through :class:`RunDir`, whose
accessors return typed handles (:class:`TableFile`, :class:`JsonFile`,
:class:`StoreFile`, ...) with ``path``, ``exists()``, ``load()`` and ``save()``
bound to the file's schema and written by the one atomic writer
(:mod:`fringecal.atomic`). Layout::

    RUN_DIR/
      manifest.json              resolved config, its digest, code digest, package versions, input digests
      summary.json               the run's figures, step timings, each step's key and outputs
      report.html                one self-contained page for the customer
      artefact.csv, rods.csv     the artefact the run used (CMM table with corrections), its rods
      ballbar.csv                the verification ball-bar (CMM table, spheres A and B)
      calibration.xml/.json      the calibrated sensors with uncertainties
      bundle_summary.json, verification.json, evaluation.json (simulated runs)
      acceptance.json            the acceptance test (VDI/VDE 2634 parts 2 and 3); acceptance_standards.json
      calibration_covariance.npz the adjustment's covariance and its sensitivity to the artefact
      crossval.json, crossval_halves.npz  cross-validation of the calibration over two halves
      measurements/<id>.zarr     acquisition stores, one per (measurement, scanner) or (position, scanner);
                                 immutable once complete
      maps/<id>.zarr             derived maps of a measurement: x, y, z, eps1, candidate regions
      labels/<id>.zarr           sphere labels of a measurement's pixels
      tables/*.csv               every table of every step (schema-checked), per-measurement
                                 tables in tables/<name>/<id>.csv
      figures/*.png              residual histograms
      truth/                     simulated runs only: true sensors, poses and ground-truth maps,
                                 read by the simulator and the evaluation step, nothing else
      .steps/<step>/<item>.json  what each step computed from what (key and output digests)
      .digests/, .prefect/       digest cache, Prefect's cached task results
      .in_progress.json          while a run writes the directory: who (pid, start), since when
                                 (left behind by an interrupted run; :mod:`fringecal.run.resume`)
      .in_progress.lock          locked by the process writing the directory (one run at a time)
      fringecal.log              what Prefect and fringecal logged, tracebacks included (appended)

A store id is ``<measurement>-<scanner>`` (e.g. ``1-scanner1``) for the artefact and
``<position>-<scanner>`` (e.g. ``bb01-scanner2``) for the ball-bar.

:meth:`RunDir.temporary` gives a throw-away run directory for tests.
"""

from __future__ import annotations

import hashlib
import json
import platform
import shutil
import sys
import tempfile
from contextlib import contextmanager
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path
from typing import Iterator

import pandas as pd

from fringecal import atomic
from fringecal.names import OutsideFolderError

__all__ = ["RunDir", "RunFile", "TableFile", "JsonFile", "TextFile", "StoreFile", "ArtefactFile", "RigFile",
           "RodsFile", "CalibrationFile", "ArraysFile", "TruthDir", "measurement_id", "package_versions"]

_PACKAGES = ("fringecal", "numpy", "scipy", "numba", "zarr", "xarray", "pandas", "pandera",
             "opencv-python-headless", "prefect", "matplotlib", "pydantic")


def measurement_id(group: str, scanner: str) -> str:
    """``<measurement>-<scanner>``, e.g. ``1-scanner1``.

    >>> measurement_id("bb01", "scanner2")
    'bb01-scanner2'
    """
    return f"{group}-{scanner}"


def package_versions() -> dict[str, str]:
    out = {"python": sys.version.split()[0], "platform": platform.platform()}
    for name in _PACKAGES:
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            out[name] = "not installed"
    return out


def _inside(root: Path, rel: str) -> str:
    """``rel`` if it names a place inside the run directory (relative, no ``..``, no
    empty part): every path of a run is built from names (measurement, scanner), and
    none may lead a write out of the run directory."""
    parts = rel.split("/")
    if rel.startswith("/") or any(p in ("", ".", "..") or "\\" in p for p in parts):
        raise OutsideFolderError(f"{root / rel}: would be written outside the run directory {root}; "
                                 "a name in the path is not one folder or file name")
    return rel


# -- typed files ------------------------------------------------------------------------

@dataclass(frozen=True)
class RunFile:
    """One file or folder of a run directory.

    ``optional`` files may legitimately be absent (a data set without rods); a step
    that declares one as an output removes it when it has nothing to write.
    """

    root: Path
    rel: str
    optional: bool = False

    @property
    def path(self) -> Path:
        return self.root / self.rel

    def exists(self) -> bool:
        return self.path.exists()

    def remove(self) -> None:
        if self.path.is_dir():
            shutil.rmtree(self.path)
        else:
            self.path.unlink(missing_ok=True)

    def __fspath__(self) -> str:
        return str(self.path)


@dataclass(frozen=True)
class TableFile(RunFile):
    """A CSV table validated by a :mod:`schemas` model on load and save.

    An empty table is written as its schema's header and loads as an empty frame.
    """

    schema: type | None = None

    def load(self) -> pd.DataFrame:
        from fringecal.schemas import read_csv_text, validate_table  # lazy: pandera loads when a table is read

        df = read_csv_text(self.path)
        if df.empty or self.schema is None:
            return df
        return validate_table(df, self.schema, str(self.path))

    def save(self, df: pd.DataFrame) -> Path:
        from fringecal.schemas import write_table  # lazy: pandera loads when a table is read

        if df.empty and self.schema is not None:
            cols = list(df.columns) or list(self.schema.to_schema().columns)
            return write_table(pd.DataFrame(columns=cols), self.path)
        return write_table(df, self.path, self.schema)


@dataclass(frozen=True)
class ArtefactFile(RunFile):
    """An artefact definition (:class:`fringecal.artefact.Artefact`)."""

    def load(self):
        from fringecal.artefact import load_artefact  # lazy: pandera loads when a table is read

        return load_artefact(self.path)

    def save(self, artefact) -> Path:
        from fringecal.schemas import ArtefactTable, write_table  # lazy: pandera loads when a table is read

        return write_table(artefact.to_frame(), self.path, ArtefactTable)


@dataclass(frozen=True)
class RodsFile(RunFile):
    """The artefact's rods (checked against the artefact's spheres on load)."""

    def load(self, artefact=None) -> pd.DataFrame:
        from fringecal.artefact import load_rods  # lazy: pandera loads when a table is read

        return load_rods(self.path, artefact)

    def save(self, rods: pd.DataFrame) -> Path:
        from fringecal.schemas import RodsTable, write_table  # lazy: pandera loads when a table is read

        return write_table(rods, self.path, RodsTable)


@dataclass(frozen=True)
class RigFile(RunFile):
    """A sensor-parameter table (:class:`fringecal.rig.Rig`)."""

    def load(self, reference: str | None = None):
        from fringecal.rig import load_rig  # lazy: pandera loads when a table is read

        return load_rig(self.path, reference=reference)

    def save(self, rig) -> Path:
        from fringecal.schemas import SensorParametersTable, write_table  # lazy: pandera loads when a table is read

        return write_table(rig.to_frame(), self.path, SensorParametersTable)


@dataclass(frozen=True)
class JsonFile(RunFile):
    def load(self) -> dict:
        try:
            return json.loads(self.path.read_text(encoding="utf-8"))
        except json.JSONDecodeError as err:
            raise ValueError(f"{self.path}: not valid JSON ({err})") from None

    def save(self, doc) -> Path:
        return atomic.write_json(self.path, doc)


@dataclass(frozen=True)
class TextFile(RunFile):
    def load(self) -> str:
        return self.path.read_text(encoding="utf-8")

    def save(self, text: str) -> Path:
        return atomic.write_text(self.path, text)


@dataclass(frozen=True)
class BytesFile(RunFile):
    def load(self) -> bytes:
        return self.path.read_bytes()

    def save(self, data: bytes) -> Path:
        return atomic.write_bytes(self.path, data)


@dataclass(frozen=True)
class ArraysFile(RunFile):
    """Named numpy arrays (``.npz``, no pickles)."""

    def load(self) -> dict:
        import numpy as np

        with np.load(self.path, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}

    def save(self, arrays: dict) -> Path:
        import io

        import numpy as np

        buf = io.BytesIO()
        np.savez(buf, **arrays)
        return atomic.write_bytes(self.path, buf.getvalue())


@dataclass(frozen=True)
class StoreFile(RunFile):
    """A zarr v3 measurement store (:mod:`fringecal.store`)."""

    def exists(self) -> bool:
        from fringecal.store import is_complete  # lazy: zarr and xarray load when a store is opened

        return is_complete(self.path)

    def open(self):
        from fringecal.store import open_store  # lazy: zarr and xarray load when a store is opened

        return open_store(self.path)

    def attrs(self) -> dict:
        from fringecal.store import store_attributes  # lazy: zarr and xarray load when a store is opened

        return store_attributes(self.path)

    def save(self, ds) -> Path:
        from fringecal.store import write_store  # lazy: zarr and xarray load when a store is opened

        return write_store(self.path, ds)


@dataclass(frozen=True)
class CalibrationFile(RunFile):
    """The calibration as JSON (``rel``) with its XML twin (same name, ``.xml``).

    Every writer of a run's calibration goes through :meth:`save` (or, writing it with
    other files all or nothing, :meth:`document` and :meth:`write`): both files are made
    from one document, so the XML carries each sensor's observed region whenever the
    JSON does, and a calibration saved with its regions never loses them."""

    @property
    def xml(self) -> RunFile:
        return RunFile(self.root, str(Path(self.rel).with_suffix(".xml")))

    def load(self):
        from fringecal.calibration.file import read_calibration_json  # lazy: numba loads when a calibration is read

        return read_calibration_json(self.path)

    @staticmethod
    def document(rig, metadata: dict | None = None, *, observed_regions: dict | None = None,
                 black_boxes: dict | None = None, **blocks) -> dict:
        """The calibration document of ``rig``: ``metadata``, each sensor's region of
        ``observed_regions`` (sensor name -> ObservedRegion), ``black_boxes`` and the
        blocks of :func:`fringecal.calibration.file.rig_to_dict` (covariances,
        provenance, sensor_model, replicas, phase_ripple)."""
        from fringecal.calibration.file import rig_to_dict  # lazy: numba loads when a calibration is read

        doc = rig_to_dict(rig, metadata, observed_regions=observed_regions, **blocks)
        if black_boxes is not None:
            doc["black_boxes"] = black_boxes
        return doc

    @staticmethod
    def write(doc: dict, json_path, xml_path) -> None:
        """Write a :meth:`document` to ``json_path`` and its XML to ``xml_path`` (the
        temporary paths of an all-or-nothing write)."""
        from fringecal.calibration.file import calibration_texts  # lazy: numba loads when a calibration is read

        for path, text in zip((json_path, xml_path), calibration_texts(doc)):
            Path(path).write_text(text, encoding="utf-8")

    def save(self, rig, metadata: dict | None = None, **kw) -> Path:
        """Write the calibration of ``rig`` (JSON and XML, both or neither); ``kw`` as
        :meth:`document`, ``observed_regions`` included."""
        doc = self.document(rig, metadata, **kw)
        with atomic.atomic_paths([self.path, self.xml.path]) as (tmp_json, tmp_xml):
            self.write(doc, tmp_json, tmp_xml)
        return self.path


# -- the run directory -------------------------------------------------------------------

class TruthDir:
    """``RUN_DIR/truth``: what only a simulated run knows (read by the simulator and by
    the evaluation step, never by the pipeline). ``fringecal simulate`` writes the same
    layout as a folder of its own beside the data set (``prefix=""``)."""

    def __init__(self, root: Path, prefix: str = "truth/"):
        self.root = Path(root)
        self.prefix = prefix

    def _at(self, cls, rel: str, **kw):
        return cls(self.root, _inside(self.root, f"{self.prefix}{rel}"), **kw)

    @property
    def sensors(self) -> RigFile:
        """The true sensors in the world frame, cameras at the simulated resolution."""
        return self._at(RigFile, "sensors.csv")

    @property
    def artefact(self) -> ArtefactFile:
        """The artefact as built, which the renderer places (the run's ``artefact.csv`` is
        the CMM table the pipeline fits against)."""
        return self._at(ArtefactFile, "artefact.csv")

    @property
    def ballbar(self) -> ArtefactFile:
        """The ball-bar as built, which the renderer places (the run's ``ballbar.csv``
        is its certificate)."""
        return self._at(ArtefactFile, "ballbar.csv")

    @property
    def scanner_frames(self) -> TableFile:
        """``T_world_scanner`` of each scanner's own (prior calibration) frame."""
        return self._at(TableFile, "scanner_frames.csv")

    @property
    def poses(self) -> TableFile:
        """The artefact pose each measurement was rendered at (``T_world_artefact``)."""
        from fringecal.schemas import PosePlanTable  # lazy: pandera loads when a table is read

        return self._at(TableFile, "poses.csv", schema=PosePlanTable)

    @property
    def ballbar_positions(self) -> TableFile:
        """``T_world_ballbar`` of each verification position."""
        from fringecal.schemas import PosePlanTable  # lazy: pandera loads when a table is read

        return self._at(TableFile, "ballbar_positions.csv", schema=PosePlanTable)

    @property
    def acceptance_positions(self) -> TableFile:
        """``T_world_<object>`` of each acceptance-test position (``measurement``: the
        position), with its ``test`` (sphere, dumbbell, flat) and ``scanner``."""
        from fringecal.schemas import PosePlanTable  # lazy: pandera loads when a table is read

        return self._at(TableFile, "acceptance_positions.csv", schema=PosePlanTable)

    @property
    def hexapod_moves(self) -> TableFile:
        """The hexapod's log of a simulated data set (a run keeps it in its tables)."""
        return self._at(TableFile, "hexapod_moves.csv")

    def store(self, measurement: str) -> StoreFile:
        """The renderer's ground-truth maps of one acquisition store."""
        return self._at(StoreFile, f"measurements/{measurement}.zarr")

    def object(self, name: str) -> JsonFile:
        """The truth of a simulated object to measure (``simulate.objects``): its kind,
        ``T_world_object`` and surface (:func:`fringecal.simulate.objects.object_truth`)."""
        return self._at(JsonFile, f"objects/{name}.json")


class RunDir:
    """Every file of one run. Creating the object touches nothing; :meth:`create` makes folders."""

    def __init__(self, root):
        self.root = Path(root)
        self.truth = TruthDir(self.root)

    def __repr__(self) -> str:
        return f"RunDir({str(self.root)!r})"

    def __eq__(self, other) -> bool:
        return isinstance(other, RunDir) and other.root == self.root

    def __hash__(self) -> int:
        return hash(self.root)

    def create(self) -> "RunDir":
        self.root.mkdir(parents=True, exist_ok=True)
        return self

    @classmethod
    @contextmanager
    def temporary(cls) -> Iterator["RunDir"]:
        """A run directory in a temporary folder, removed afterwards (for tests)."""
        with tempfile.TemporaryDirectory(prefix="fringecal-run-") as d:
            yield cls(d).create()

    def _at(self, cls, rel: str, **kw):
        return cls(self.root, _inside(self.root, rel), **kw)

    def _table(self, rel: str, schema_name: str | None, optional: bool = False) -> TableFile:
        from fringecal import schemas  # lazy: pandera loads when a table is read

        return TableFile(self.root, rel, optional, getattr(schemas, schema_name) if schema_name else None)

    # -- provenance and results ------------------------------------------------------
    @property
    def manifest(self) -> JsonFile:
        return self._at(JsonFile, "manifest.json")

    @property
    def summary(self) -> JsonFile:
        return self._at(JsonFile, "summary.json")

    @property
    def report(self) -> TextFile:
        return self._at(TextFile, "report.html")

    def read_manifest(self) -> dict:
        if not self.manifest.exists():
            raise FileNotFoundError(f"{self.root} is not a run directory: {self.manifest.rel} is missing")
        return self.manifest.load()

    @staticmethod
    def config_digest(config: dict) -> str:
        return hashlib.sha256(json.dumps(config, sort_keys=True, default=str).encode()).hexdigest()

    # -- inputs of the run, written by its data source ---------------------------------
    @property
    def artefact(self) -> ArtefactFile:
        return self._at(ArtefactFile, "artefact.csv")

    @property
    def rods(self) -> RodsFile:
        return self._at(RodsFile, "rods.csv", optional=True)

    @property
    def ballbar(self) -> ArtefactFile:
        return self._at(ArtefactFile, "ballbar.csv", optional=True)

    @property
    def sensors_prior(self) -> RigFile:
        """Each modelled scanner's own calibration in its own frame (the reference scanner's
        is the world); absent in a rig of black boxes only."""
        return self._at(RigFile, "tables/sensors_prior.csv", optional=True)

    @property
    def poses_planned(self) -> TableFile:
        """Planned ``T_world_artefact`` per measurement, in any fixed frame."""
        return self._table("tables/poses_planned.csv", "PosePlanTable", optional=True)

    @property
    def acquisition(self) -> TableFile:
        """Every acquisition store of the run: id, kind, measurement or position, scanner, source."""
        return self._table("tables/acquisition.csv", "AcquisitionTable")

    @property
    def hexapod_moves(self) -> TableFile:
        """Planned and reached pose per measurement, with encoder counts (simulated or live hexapod)."""
        return self._table("tables/hexapod_moves.csv", "AcquiredPosesTable", optional=True)

    def store(self, measurement: str) -> StoreFile:
        """The acquisition store of ``measurement`` (a ``<group>-<scanner>`` id)."""
        return self._at(StoreFile, f"measurements/{measurement}.zarr")

    def _store_attributes(self, kind: str | None = None, scanner: str | None = None) -> Iterator[tuple[str, str, dict]]:
        """``(measurement, scanner, attributes)`` of the complete acquisition stores of the
        acquisition table (of ``kind`` and ``scanner`` where given), read from the stores'
        metadata alone; none without an acquisition table. The table is read as text
        (validated when it was written): this runs for every step key that reads it."""
        from fringecal.schemas import read_csv_text  # lazy: pandera loads when a table is read
        from fringecal.store import StoreError, store_attributes  # lazy: as above

        if not self.acquisition.exists():
            return
        table = read_csv_text(self.acquisition.path)
        for m, k, s in zip(table["measurement"], table["kind"], table["scanner"]):
            if (kind is None or k == kind) and (scanner is None or s == scanner):
                try:
                    yield m, s, store_attributes(self.store(m).path)
                except (OSError, StoreError):  # missing or incomplete
                    continue

    def store_summaries(self) -> list[tuple[str, str, dict]]:
        """``(measurement, scanner, summary)`` of every complete acquisition store whose
        attributes hold a ``summary`` (the decoder's; a cloud store of a black box has
        none)."""
        return [(m, s, a["summary"]) for m, s, a in self._store_attributes() if a.get("summary")]

    def phase_ripple_fits(self, scanner: str) -> list[dict]:
        """The phase-ripple fits of ``scanner``'s calibration (``artefact``) stores, their
        decoders' ``phase_ripple_fit`` records: what its stacks too small for a fit of
        their own are corrected with (:func:`fringecal.fringe.ripple.scanner_ripple`)."""
        return [fit for _, _, a in self._store_attributes("artefact", scanner)
                for fit in ((a.get("decoder") or {}).get("phase_ripple_fit") or {}).values()]

    # -- spheres, labels, control points -------------------------------------------------
    def maps(self, measurement: str) -> StoreFile:
        """Point maps x, y, z, eps1 (scanner frame) and candidate regions of a measurement."""
        return self._at(StoreFile, f"maps/{measurement}.zarr")

    def sphere_labels(self, measurement: str) -> StoreFile:
        """Index of the artefact sphere each pixel belongs to (-1: none)."""
        return self._at(StoreFile, f"labels/{measurement}.zarr")

    def fits_first(self, measurement: str) -> TableFile:
        return self._table(f"tables/fits_first/{measurement}.csv", "SphereFitsTable")

    def fits_final(self, measurement: str) -> TableFile:
        return self._table(f"tables/fits_final/{measurement}.csv", "SphereFitsTable")

    def control_points_of(self, measurement: str) -> TableFile:
        return self._table(f"tables/control_points/{measurement}.csv", "ControlPointsTable")

    @property
    def sphere_fits_labelled(self) -> TableFile:
        return self._table("tables/sphere_fits_labelled.csv", "SphereFitsTable")

    @property
    def label_outcomes(self) -> TableFile:
        return self._table("tables/label_outcomes.csv", "LabelOutcomesTable")

    @property
    def sphere_centres(self) -> TableFile:
        return self._table("tables/sphere_centres.csv", "SphereCentresTable")

    @property
    def poses(self) -> TableFile:
        """``T_scanner_artefact`` per (measurement, scanner) from the labelled centres."""
        return self._table("tables/poses.csv", "PosesTable")

    @property
    def poses_skipped(self) -> TableFile:
        return self._table("tables/poses_skipped.csv", None)

    @property
    def scanner_links(self) -> TableFile:
        return self._table("tables/scanner_links.csv", "ScannerLinksTable")

    # -- calibration ---------------------------------------------------------------------------
    @property
    def control_points(self) -> TableFile:
        return self._table("tables/control_points.csv", "ControlPointsTable")

    @property
    def poses_initial(self) -> TableFile:
        return self._table("tables/poses_initial.csv", "PosePlanTable")

    @property
    def sensors_initial(self) -> RigFile:
        return self._at(RigFile, "tables/sensors_initial.csv")

    @property
    def dlt(self) -> TableFile:
        return self._table("tables/dlt.csv", None)

    @property
    def calibration(self) -> CalibrationFile:
        return self._at(CalibrationFile, "calibration.json")

    @property
    def sensors_calibrated(self) -> TableFile:
        return self._table("tables/sensors_calibrated.csv", "CalibratedSensorsTable")

    @property
    def poses_calibrated(self) -> TableFile:
        return self._table("tables/poses_calibrated.csv", "CalibratedPosesTable")

    @property
    def residuals_per_sphere(self) -> TableFile:
        return self._table("tables/residuals_per_sphere.csv", "SphereResidualsTable")

    @property
    def residuals_per_measurement(self) -> TableFile:
        return self._table("tables/residuals_per_measurement.csv", "MeasurementResidualsTable")

    @property
    def residuals_binned(self) -> TableFile:
        """Residuals and control-point counts binned over each camera's and projector's image."""
        return self._table("tables/residuals_binned.csv", "BinnedResidualsTable")

    def histogram(self, term: str) -> BytesFile:
        """``figures/<term>_hist.png`` for ``eps1`` or ``eps2``."""
        return self._at(BytesFile, f"figures/{term}_hist.png")

    @property
    def bundle_summary(self) -> JsonFile:
        return self._at(JsonFile, "bundle_summary.json")

    @property
    def black_boxes(self) -> JsonFile:
        """The black-box scanners' calibration: each one's transform, scale and
        covariance (:meth:`fringecal.calibration.blackbox.BlackBoxResult.to_dict`);
        absent without black boxes."""
        return self._at(JsonFile, "black_boxes.json", optional=True)

    @property
    def black_boxes_export(self) -> TableFile:
        """The simple export: scale and 4x4 T_world_scanner per black-box scanner
        (:func:`fringecal.calibration.blackbox.export_table`); absent without black boxes."""
        return self._table("scanner_transforms.csv", None, optional=True)

    @property
    def covariance(self) -> ArraysFile:
        """The adjustment's covariance and its sensitivity to the artefact
        (:func:`fringecal.calibration.results.covariance_arrays`)."""
        return self._at(ArraysFile, "calibration_covariance.npz")

    @property
    def crossval(self) -> JsonFile:
        """Cross-validation of the calibration (two halves of the measurements)."""
        return self._at(JsonFile, "crossval.json", optional=True)

    @property
    def crossval_halves(self) -> ArraysFile:
        """Each half-calibration's sensor parameters and covariance."""
        return self._at(ArraysFile, "crossval_halves.npz", optional=True)

    # -- verification and evaluation -----------------------------------------------------------
    @property
    def verification(self) -> JsonFile:
        return self._at(JsonFile, "verification.json", optional=True)

    @property
    def ballbar_positions_planned(self) -> TableFile:
        """Ball-bar positions planned from this calibration (``fringecal verify plan``)."""
        return self._table("tables/ballbar_positions_planned.csv", "SphereCentresTable", optional=True)

    @property
    def ballbar_centres(self) -> TableFile:
        return self._table("tables/ballbar_centres.csv", "BallbarCentresTable", optional=True)

    @property
    def evaluation(self) -> JsonFile:
        """Simulated runs: the calibration against the truth."""
        return self._at(JsonFile, "evaluation.json", optional=True)

    @property
    def acceptance_standards(self) -> JsonFile:
        """Certificates of the acceptance test's objects
        (:class:`fringecal.acceptance.standards.AcceptanceStandards` as JSON)."""
        return self._at(JsonFile, "acceptance_standards.json", optional=True)

    @property
    def acceptance(self) -> JsonFile:
        """The acceptance test per VDI/VDE 2634 parts 2 and 3 (:mod:`fringecal.acceptance`)."""
        return self._at(JsonFile, "acceptance.json", optional=True)

    @property
    def acceptance_values(self) -> TableFile:
        """Every acceptance measurement's raw value (one row per position and scanner)."""
        return self._table("tables/acceptance_values.csv", None, optional=True)

    @property
    def ballbar_centres_true(self) -> TableFile:
        return self._table("tables/ballbar_centres_true.csv", "BallbarCentresTable", optional=True)

    # -- bookkeeping -------------------------------------------------------------------------------
    def step_record(self, step: str, item: str) -> JsonFile:
        """What ``step`` computed for ``item`` ('' for one-off steps) and from what."""
        return self._at(JsonFile, f".steps/{step}/{item or '_'}.json")

    def step_records(self) -> list[JsonFile]:
        """Every step record of the run directory (none before its first step ran)."""
        base = self.root / ".steps"
        if not base.is_dir():
            return []
        return [self._at(JsonFile, p.relative_to(self.root).as_posix()) for p in sorted(base.glob("*/*.json"))
                if not p.name.startswith(".")]

    @property
    def log(self) -> RunFile:
        """The run's log file: every line Prefect and fringecal log while a command runs
        the flow, tracebacks included (the terminal shows one line per failure), appended
        run after run."""
        return self._at(RunFile, "fringecal.log")

    @property
    def lock(self) -> RunFile:
        """Held (an exclusive ``flock``) by the one process that runs the flow into this
        directory; released when that process ends, however it ends."""
        return self._at(RunFile, ".in_progress.lock")

    @property
    def in_progress(self) -> JsonFile:
        """Written when a run of this directory starts, removed when it ends; found by the
        next run, it says the last one was interrupted (:mod:`fringecal.run.resume`)."""
        return self._at(JsonFile, ".in_progress.json")

    @property
    def digest_cache_dir(self) -> Path:
        return self.root / ".digests"

    @property
    def prefect_storage(self) -> Path:
        return self.root / ".prefect"

    def relative(self, path) -> str:
        """``path`` relative to the run directory (as recorded in tables and records)."""
        return str(Path(path).resolve().relative_to(self.root.resolve()))
