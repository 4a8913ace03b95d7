"""The run directory as the report reads it: every file through its
:class:`~fringecal.rundir.RunDir` accessor, each loaded once.

A missing file raises :class:`Missing`, which a section (or a part of one) shows as a
"Not available" note; a malformed file raises the error its loader raised, shown as a
"Could not be shown" warning naming the file (:func:`guard`).
"""

from __future__ import annotations

from dataclasses import dataclass

import pandas as pd

from fringecal.acceptance.verdict import run_verdict, unreadable
from fringecal.rundir import RunDir, RunFile

__all__ = ["NO_TRUTH", "SOURCES", "Missing", "RunData", "Shown", "failure", "guard", "numeric"]

#: What the page says where a run of a recorded data set has no truth to compare with.
NO_TRUTH = "absent, as for a run of a recorded data set (no truth)"

#: How the page names the data source of the manifest.
SOURCES = {"simulated": "simulated rig", "dataset": "recorded data set"}


class Missing(Exception):
    """An optional input is absent; the section says so instead of failing."""


class RunData:
    """The files of one run directory, loaded on first use.

    Parameters
    ----------
    rd : the run directory
    """

    def __init__(self, rd: RunDir):
        self.rd = rd
        self.root = rd.root
        self._loaded: dict[str, tuple[bool, object]] = {}

    def load(self, f: RunFile, *args):
        """The content of ``f`` (its loader's result, e.g. a frame or a rig).

        Raises
        ------
        Missing
            ``f`` is not in the run directory.
        ValueError, KeyError, OSError
            ``f`` is malformed (the same error at every later call).
        """
        if not f.exists():
            raise Missing(f"{f.rel} is not in the run directory")
        if f.rel not in self._loaded:
            try:
                self._loaded[f.rel] = (True, f.load(*args))
            except (ValueError, KeyError, OSError) as err:
                self._loaded[f.rel] = (False, err)
        ok, value = self._loaded[f.rel]
        if not ok:
            raise value
        return value

    def calibration_file(self):
        """The calibration read whole, with its covariances
        (:class:`fringecal.calibration.file.Calibration`); loaded once."""
        from fringecal.calibration.file import read_calibration  # lazy: numba loads when a calibration is read

        f = self.rd.calibration
        if not f.exists():
            raise Missing(f"{f.rel} is not in the run directory")
        key = f.rel + "#whole"
        if key not in self._loaded:
            try:
                self._loaded[key] = (True, read_calibration(f.path))
            except (ValueError, KeyError, OSError) as err:
                self._loaded[key] = (False, err)
        ok, value = self._loaded[key]
        if not ok:
            raise value
        return value

    def json(self, f: RunFile) -> dict:
        """A JSON file that must hold an object."""
        doc = self.load(f)
        if not isinstance(doc, dict):
            raise ValueError(f"{f.rel}: not a JSON object")
        return doc

    def maybe_json(self, f: RunFile) -> dict | None:
        """A JSON object, or None when the file is missing or malformed."""
        try:
            return self.json(f)
        except (Missing, ValueError, KeyError, OSError):
            return None

    def table(self, f: RunFile) -> pd.DataFrame:
        """A table of the run directory (schema-checked by its accessor)."""
        return self.load(f)

    def manifest(self) -> dict:
        """The manifest, empty when missing or malformed."""
        return self.maybe_json(self.rd.manifest) or {}

    def config(self) -> dict:
        """The resolved run configuration recorded in the manifest."""
        cfg = self.manifest().get("config")
        return cfg if isinstance(cfg, dict) else {}

    def simulation(self) -> dict:
        """The configuration's ``simulate`` settings (empty for a recorded data set)."""
        sim = self.config().get("simulate")
        return sim if isinstance(sim, dict) else {}

    def name(self) -> str:
        """The run's name: the configuration's, else the directory's."""
        return str(self.config().get("name") or self.root.name)

    def source(self) -> str | None:
        """``"simulated"``, ``"dataset"`` or None (not recorded)."""
        src = self.manifest().get("source")
        if src in ("simulated", "dataset"):
            return src
        try:
            kinds = set(self.table(self.rd.acquisition)["source"].astype(str))
            if kinds:
                return "simulated" if kinds == {"simulated"} else "dataset"
        except (Missing, ValueError, KeyError, OSError):
            pass
        cfg = self.config()
        if cfg.get("dataset"):
            return "dataset"
        return "simulated" if cfg.get("simulate") else None

    def source_text(self) -> str:
        """The data source in words, with the data set's folder or the rig's name."""
        src = self.source()
        cfg = self.config()
        if src == "dataset" and cfg.get("dataset"):
            return f"recorded data set {cfg['dataset']}"
        if src == "simulated" and self.simulation().get("rig"):
            return f"simulated rig {self.simulation()['rig']}"
        return SOURCES.get(src, "not recorded")

    def evaluation(self) -> dict:
        """The evaluation against the truth; its absence explained (a run of a
        recorded data set has no truth)."""
        f = self.rd.evaluation
        if not f.exists():
            if self.source() == "simulated":
                raise Missing(f"{f.rel} is not in the run directory: this simulated run has not been evaluated "
                              f"against its truth")
            raise Missing(f"{f.rel} is {NO_TRUTH}")
        return self.json(f)

    def no_truth(self) -> str:
        """What a "true parameters" cell says when there is no evaluation to fill it."""
        f = self.rd.evaluation
        if f.exists():
            return f"could not be read (see the {f.rel} note under Simulation truth)"
        return NO_TRUTH if self.source() != "simulated" else f"not available ({f.rel} is not in the run directory)"

    def verdict(self) -> dict:
        """The run's verdict (:func:`fringecal.acceptance.verdict.run_verdict`) from
        ``verification.json`` and ``acceptance.json``, as the summary records it. Only
        these files decide (the summary may be of an earlier execution); one that
        exists but cannot be read proves nothing, so the run is then not accepted."""
        docs = []
        for f in (self.rd.verification, self.rd.acceptance):
            doc = self.maybe_json(f) if f.exists() else None
            if f.exists() and doc is None:
                return unreadable(f.rel)
            docs.append(doc)
        try:
            return run_verdict(*docs)
        except (KeyError, TypeError, ValueError) as err:
            return unreadable(f"{self.rd.verification.rel} or {self.rd.acceptance.rel} ({type(err).__name__}: {err})")

    def execution(self, execution: dict | None) -> dict:
        """When and by which command the run executed: passed in, else from the summary."""
        if execution:
            return dict(execution)
        summary = self.maybe_json(self.rd.summary) or {}
        return {k: summary[k] for k in ("created_utc", "command") if summary.get(k) is not None}

    def clean(self, message: str) -> str:
        """An error message with the run directory's absolute path left out."""
        root = str(self.root)
        return message.replace(root + "/", "").replace(root, self.root.name)


@dataclass(frozen=True)
class Shown:
    """What a section, or a part of one, shows: its template context, or instead a
    note (an input is missing) or a warning (an input is malformed)."""

    context: object = None
    note: str | None = None
    warning: str | None = None


def failure(run: RunData, err: Exception) -> str:
    """The warning for a malformed file: the error, without the machine's paths."""
    return f"Could not be shown: {type(err).__name__}: {run.clean(str(err))}"


def guard(build, run: RunData, *args) -> Shown:
    """``build(run, *args)`` as a :class:`Shown`; a missing or malformed input gives a
    note or a warning instead, and the rest of the page is still written."""
    try:
        return Shown(build(run, *args))
    except Missing as why:
        return Shown(note=f"Not available: {why}.")
    except (ValueError, KeyError, TypeError, AttributeError, IndexError) as err:
        return Shown(warning=failure(run, err))


def numeric(df: pd.DataFrame) -> pd.DataFrame:
    """A table loaded as text (no schema) with its numeric columns as numbers."""
    out = df.copy()
    for col in out.columns:
        try:
            out[col] = pd.to_numeric(out[col])
        except (ValueError, TypeError):
            pass
    return out
