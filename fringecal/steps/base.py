"""What a pipeline step is: a declaration and one entry point over the run directory.

A step (one module in :mod:`fringecal.steps`, after OpenSfM's ``actions``) is a
subclass of :class:`Step` that declares

* ``name``: how the flow, the command line and the records call it;
* ``settings``: the parts of the run configuration it uses, as dotted paths
  (``"extraction"``, ``"simulate.acquisition.render"``); the step sees only these
  (:class:`Settings`), so an undeclared setting is an error, not a silent cache bug;
* ``locations``: settings that say *where* inputs are (a data set folder, a rig
  file): the step may read them, but they are not keyed, because the files they
  point at are keyed by content through :meth:`Step.reads`;
* ``modules``: fringecal modules whose source it runs besides its own (imports are
  followed automatically, :func:`fringecal.digests.module_files`);
* :meth:`Step.items`: the instances it runs (one per measurement, or the single
  ``""``);
* :meth:`Step.reads` and :meth:`Step.writes`: the files of one instance, run
  directory files (:class:`fringecal.rundir.RunFile`), external files (``Path``),
  rows of a table (:class:`Rows`) or plain values (:class:`Value`);

and implements :meth:`Step.run`. Its cache key (:mod:`fringecal.steps.keys`) is
built from exactly these declarations.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any, ClassVar, Union

from fringecal.fringe.ripple import ripple_document, scanner_ripple
from fringecal.rundir import RunDir, RunFile, TableFile
from fringecal.schemas import read_csv_text

__all__ = ["Step", "Rows", "Value", "Settings", "StepError", "DataProblem", "Read", "store_row", "store_fields",
           "black_boxes_only", "scanner_ripple_read", "phase_ripple_document",
           "stores_of_kind", "save_or_remove", "black_box_scanners", "stores_of"]


class StepError(RuntimeError):
    """A step broke its declaration (an output it promised is missing)."""


class DataProblem(ValueError):
    """The data cannot give what a step needs (a scanner that never sees three spheres
    with the reference scanner); the message names the need and the data. Raised in a
    running flow, it ends the command with that one line and status 2, as bad input."""


@dataclass(frozen=True)
class Rows:
    """The rows of a table whose columns equal ``where`` (keyed by those rows only).

    A per-measurement step that needs one row of a run-wide table (the pose its
    measurement was rendered at) declares ``Rows(rd.truth.poses, {"measurement": "3"})``
    and reruns only when that row changes.
    """

    table: TableFile
    where: dict = field(default_factory=dict)

    def load(self):
        """The selected rows, validated by the table's schema."""
        return self._select(self.table.load())

    def text(self) -> list[dict]:
        """The selected rows as the file's text (what a key digests: no parsing, no
        validation, so keys stay cheap)."""
        return self._select(_raw_table(self.table.path)).to_dict("records")

    def _select(self, df):
        for col, value in self.where.items():
            df = df[df[col].astype(str) == str(value)]
        return df.reset_index(drop=True)


@lru_cache(maxsize=64)
def _raw_csv(path: str, size: int, mtime_ns: int):
    return read_csv_text(path)


def _raw_table(path: Path):
    st = Path(path).stat()
    return _raw_csv(str(path), st.st_size, st.st_mtime_ns)


@dataclass(frozen=True)
class Value:
    """Something a step reads that is not a file, keyed by its JSON value (e.g. the
    list of stacks a data set holds, which no single file records)."""

    label: str
    value: Any


Read = Union[RunFile, Path, Rows, Value]


class Settings:
    """The declared parts of a run configuration; anything else raises AttributeError.

    >>> from fringecal.run.config import RunConfig
    >>> s = Settings(RunConfig(), ("bundle.gamma1", "extraction"))
    >>> s.bundle.gamma1, type(s.extraction).__name__
    (1.0, 'ExtractionConfig')
    >>> s.bundle.gamma2
    Traceback (most recent call last):
    ...
    AttributeError: setting 'bundle.gamma2' was not declared by the step
    """

    def __init__(self, obj, paths, locations=(), _prefix: tuple[str, ...] = ()):
        self._obj = obj
        self._paths = tuple(tuple(p.split(".")) for p in paths)
        self._locations = tuple(tuple(p.split(".")) for p in locations)
        self._prefix = _prefix

    def __getattr__(self, name: str):
        if name.startswith("_"):
            raise AttributeError(name)
        path = self._prefix + (name,)
        declared = self._paths + self._locations
        if path in declared:
            return getattr(self._obj, name)
        if any(p[:len(path)] == path for p in declared):
            return Settings(getattr(self._obj, name), [".".join(p) for p in self._paths],
                            [".".join(p) for p in self._locations], path)
        raise AttributeError(f"setting {'.'.join(path)!r} was not declared by the step")

    def keyed(self) -> dict[str, Any]:
        """Declared path -> value (JSON), the settings part of a cache key."""
        out = {}
        for path in self._paths:
            value = self._obj
            for part in path[len(self._prefix):]:
                value = getattr(value, part)
            out[".".join(path)] = value.model_dump(mode="json") if hasattr(value, "model_dump") else \
                (str(value) if isinstance(value, Path) else value)
        return out


class Step:
    """Base class of a pipeline step (see the module notes)."""

    name: ClassVar[str]
    title: ClassVar[str] = ""  # progress and report label; defaults to the name
    settings: ClassVar[tuple[str, ...]] = ()
    locations: ClassVar[tuple[str, ...]] = ()
    modules: ClassVar[tuple[str, ...]] = ()

    def view(self, cfg) -> Settings:
        return Settings(cfg, self.settings, self.locations)

    def items(self, rd: RunDir, cfg: Settings) -> list[str]:
        """Instances of the step; ``[""]`` for a step that runs once."""
        return [""]

    def reads(self, rd: RunDir, cfg: Settings, item: str) -> list[Read]:
        raise NotImplementedError

    def writes(self, rd: RunDir, cfg: Settings, item: str) -> list[RunFile]:
        raise NotImplementedError

    def run(self, rd: RunDir, cfg: Settings, item: str, **context) -> None:
        raise NotImplementedError

    @property
    def label(self) -> str:
        return self.title or self.name

    @classmethod
    def module_names(cls) -> tuple[str, ...]:
        return (cls.__module__,) + tuple(cls.modules)


def save_or_remove(file, content) -> None:
    """Save an optional output, or remove it when there is nothing (None) to save: a
    rerun must not leave an earlier run's file behind."""
    if content is None:
        file.remove()
    else:
        file.save(content)


# -- the acquisition table, which every per-store step starts from ------------------------

def store_row(rd: RunDir, measurement: str) -> Rows:
    """The acquisition-table row of one store (what a per-store step reads of the table)."""
    return Rows(rd.acquisition, {"measurement": measurement})


def store_fields(rd: RunDir, measurement: str) -> dict[str, str]:
    """That row as text: ``measurement, kind, pose, scanner, store, source``."""
    return store_row(rd, measurement).text()[0]


def stores_of_kind(rd: RunDir, kind: str) -> list[str]:
    """Ids of the run's ``artefact`` (calibration) or ``ballbar`` stores, in table order."""
    table = _raw_table(rd.acquisition.path)
    return list(table.loc[table["kind"] == kind, "measurement"])


def scanner_ripple_read(rd: RunDir, scanner: str, sequence) -> "Value":
    """What a stack of ``scanner`` decoded after its calibration stacks reads of them:
    the scanner's phase ripple (:func:`fringecal.fringe.ripple.scanner_ripple` of
    :meth:`RunDir.phase_ripple_fits`), keyed by value, so that calibration stacks rendered
    or decoded again change its key only if that ripple changes (on a cell without one:
    never)."""
    ripple = scanner_ripple(rd.phase_ripple_fits(scanner), sequence)
    return Value(f"phase ripple of {scanner}", {o: r.to_dict(sequence) for o, r in sorted(ripple.items())})


def phase_ripple_document(rd: RunDir) -> dict:
    """scanner -> orientation -> the phase ripple of every scanner whose calibration stacks
    were corrected (:func:`fringecal.fringe.ripple.ripple_document`): what
    ``calibration.json`` carries; empty on a cell without one."""
    if not rd.acquisition.exists():
        return {}
    table = _raw_table(rd.acquisition.path)
    scanners = dict.fromkeys(table.loc[table["kind"] == "artefact", "scanner"])
    out = {s: ripple_document(rd.phase_ripple_fits(s)) for s in scanners}
    return {s: doc for s, doc in out.items() if doc}


def black_box_scanners(rd: RunDir) -> list[str]:
    """Scanners of the acquisition table without a prior calibration: the black boxes,
    whose stores are point clouds (in table order); none in a run directory without an
    acquisition table (one written for ``fringecal calibrate`` from control points)."""
    if not rd.acquisition.exists():
        return []
    table = _raw_table(rd.acquisition.path)
    modelled = set(_raw_table(rd.sensors_prior.path)["scanner"]) if rd.sensors_prior.exists() else set()
    return [s for s in dict.fromkeys(table["scanner"]) if s not in modelled]


def black_boxes_only(rd: RunDir) -> bool:
    """Whether the run's rig is black boxes only: an acquisition table of black boxes and
    no prior calibration (a run directory without an acquisition table, one written for
    ``fringecal calibrate`` from control points, is not)."""
    return not rd.sensors_prior.exists() and bool(black_box_scanners(rd))


def stores_of(rd: RunDir, kind: str, black_box: bool) -> list[str]:
    """Ids of the ``kind`` stores of the black-box scanners (``black_box``) or of the
    modelled ones, in table order."""
    table = _raw_table(rd.acquisition.path)
    boxes = set(black_box_scanners(rd))
    sel = (table["kind"] == kind) & (table["scanner"].isin(boxes) == black_box)
    return list(table.loc[sel, "measurement"])
