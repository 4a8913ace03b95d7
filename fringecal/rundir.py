"""The run directory: one object that owns every path of a run (DESIGN.md, storage).

Layout::

    RUN_DIR/
      manifest.json            resolved config, its hash, package versions, input digests
      artefact.csv             the artefact definition the run used (copied in)
      measurements/<id>.zarr   one zarr v3 store per measurement (pose x scanner)
      tables/<name>.csv        every table of every step
      figures/<name>.png       report plots
      calibration.xml, calibration.json
      report.html, summary.json

A measurement id is ``<pose>-<scanner>``: the thesis's 24 measurements are 12 artefact
poses seen by two scanners.
"""

from __future__ import annotations

import hashlib
import json
import platform
import sys
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path

__all__ = ["RunDir", "measurement_id", "package_versions", "write_json_atomic", "output_record", "up_to_date"]

_PACKAGES = ("fringecal", "numpy", "scipy", "numba", "zarr", "xarray", "pandas", "pandera",
             "opencv-python-headless", "prefect", "matplotlib", "pydantic")


def measurement_id(pose: str, scanner: str) -> str:
    """``<pose>-<scanner>``, e.g. ``01-scanner1``."""
    return f"{pose}-{scanner}"


def package_versions() -> dict[str, str]:
    out = {"python": sys.version.split()[0], "platform": platform.platform()}
    for name in _PACKAGES:
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            out[name] = "not installed"
    return out


def write_json_atomic(path, obj) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(json.dumps(obj, indent=2, sort_keys=False, default=str) + "\n")
    tmp.replace(path)
    return path


@dataclass(frozen=True)
class RunDir:
    """Paths of one run. Creating the object touches nothing; :meth:`create` makes folders."""

    root: Path

    def __post_init__(self):
        object.__setattr__(self, "root", Path(self.root))

    def create(self) -> "RunDir":
        for d in (self.root, self.measurements_dir, self.tables_dir, self.figures_dir):
            d.mkdir(parents=True, exist_ok=True)
        return self

    @property
    def manifest(self) -> Path:
        return self.root / "manifest.json"

    @property
    def artefact(self) -> Path:
        return self.root / "artefact.csv"

    @property
    def measurements_dir(self) -> Path:
        return self.root / "measurements"

    @property
    def tables_dir(self) -> Path:
        return self.root / "tables"

    @property
    def figures_dir(self) -> Path:
        return self.root / "figures"

    @property
    def calibration_xml(self) -> Path:
        return self.root / "calibration.xml"

    @property
    def calibration_json(self) -> Path:
        return self.root / "calibration.json"

    @property
    def report(self) -> Path:
        return self.root / "report.html"

    @property
    def summary(self) -> Path:
        return self.root / "summary.json"

    def store(self, measurement: str) -> Path:
        return self.measurements_dir / f"{measurement}.zarr"

    def table(self, name: str) -> Path:
        return self.tables_dir / f"{name}.csv"

    def figure(self, name: str) -> Path:
        return self.figures_dir / f"{name}.png"

    def read_manifest(self) -> dict:
        if not self.manifest.exists():
            raise FileNotFoundError(f"{self.root} is not a run directory: {self.manifest.name} is missing")
        return json.loads(self.manifest.read_text())

    @staticmethod
    def config_digest(config: dict) -> str:
        return hashlib.sha256(json.dumps(config, sort_keys=True, default=str).encode()).hexdigest()


def output_record(rd: RunDir, files: dict, stores: list) -> dict:
    """What a later run checks, before any orchestration starts, to know that ``rd`` is
    up to date: content digests of the files, and each store's acquisition digest
    (stores gain variables after acquisition, so not their bytes)."""
    from .store import store_attributes

    return {"files": {str(Path(p).relative_to(rd.root)): d for p, d in files.items()},
            "stores": {str(Path(p).relative_to(rd.root)): store_attributes(p).get("config_digest") for p in stores}}


def up_to_date(run_dir, config_doc: dict) -> dict | None:
    """The summary of ``run_dir`` if it holds a complete run of exactly this config with
    every recorded output unchanged since; None otherwise."""
    from . import __version__
    from .digests import CODE_VERSION, digest_path
    from .store import StoreError, store_attributes

    rd = RunDir(run_dir)
    try:
        manifest = rd.read_manifest()
        summary = json.loads(rd.summary.read_text())
    except (FileNotFoundError, json.JSONDecodeError):
        return None
    if (manifest.get("config_digest") != RunDir.config_digest(config_doc) or "outputs" not in summary
            or manifest.get("code_version") != CODE_VERSION
            or manifest.get("versions", {}).get("fringecal") != __version__):
        return None
    for rel, digest in summary["outputs"]["files"].items():
        p = rd.root / rel
        if not p.exists() or digest_path(p) != digest:
            return None
    for rel, digest in summary["outputs"]["stores"].items():
        try:
            if store_attributes(rd.root / rel).get("config_digest") != digest:
                return None
        except StoreError:
            return None
    return summary
