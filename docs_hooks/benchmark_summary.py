"""Summaries of the benchmarks' JSON results for the generated validation page.

Pure Python (standard library only): :func:`summarise` turns one JSON file of
``benchmarks/results/`` into a :class:`Summary` (what produced it, when, on which
machine, and a table of figures) and :func:`page` renders summaries as Markdown.

Figures come from three sources, in this order:

* the known keys of the benchmark named by the file's ``"benchmark"`` entry
  (:data:`KNOWN`), with readable labels;
* every top-level scalar (number, true/false, short text) not shown yet;
* for a benchmark without known keys, every numeric leaf of nested objects with
  its JSON path (lists of records are counted, not flattened).

At most :data:`MAX_ROWS` rows are kept; a summary says how many were left out. A new
benchmark therefore appears with its top-level and nested figures without any edit
here; adding it to :data:`KNOWN` only gives it labels and an order.

A figure that states its credible range (an object holding ``credible_range`` beside
the figure, e.g. ``summary.coverage``) and lies outside it must say why in one line:
the file's top-level ``credible_range_why``, written by whoever ran it (as ``rerun.why``
is). The page shows that line beside the figure and in the overview;
:attr:`Summary.unexplained` lists the figures without one (the build hook warns, so a
strict build fails).
"""

from __future__ import annotations

import datetime as _dt
import json
import math
import re
from dataclasses import dataclass, field
from pathlib import Path

__all__ = ["Row", "Summary", "KNOWN", "MAX_ROWS", "CREDIBLE_FIGURES", "WHY_KEY", "fmt", "lookup", "outside_credible",
           "summarise", "page"]

#: Most rows of figures per benchmark.
MAX_ROWS = 24

#: Known keys per benchmark name: (JSON path, label). A path is dotted; integers index lists.
KNOWN: dict[str, tuple[tuple[str, str], ...]] = {
    "coverage": (
        ("summary.coverage", "coverage: lengths whose error is within U"),
        ("summary.credible_range", "credible range of the coverage"),
        ("summary.credible", "coverage credible"),
        ("summary.nominal", "nominal coverage (k = 2)"),
        ("summary.n_lengths", "lengths"),
        ("summary.n_not_covered", "lengths not covered"),
        ("summary.binomial_se", "binomial standard error"),
        ("summary.seed_cluster_se", "standard error over seeds"),
        ("summary.seeds_run", "seeds run"),
        ("summary.seeds_ok", "seeds completed"),
        ("summary.seeds_failed", "seeds failed"),
        ("summary.mean_U_mm", "mean U (mm)"),
        ("summary.rms_z", "RMS z = error / u"),
        ("summary.max_abs_z", "largest abs(z)"),
        ("summary.rms_error_vs_true_mm", "RMS error against the true length (mm)"),
        ("summary.mean_error_vs_true_mm", "mean error against the true length (mm)"),
        ("summary.seconds_per_seed_median", "median seconds per seed"),
        ("wall_seconds", "wall time (s)"),
        ("profile", "simulation profile"),
        ("width_px", "camera width (px)"),
        ("poses", "thesis poses"),
        ("ballbar_positions", "ball-bar positions"),
    ),
    "probing_size_bias": (
        ("far_mean_P_S_orthogonal_mm", "mean P_S of the far positions, orthogonal fit (mm)"),
        ("far_mean_P_S_along_rays_mm", "mean P_S of the far positions, fit along the rays (mm)"),
        ("repeated_P_S_orthogonal.mean_mm", "repeated position: mean P_S, orthogonal fit (mm)"),
        ("repeated_P_S_orthogonal.sem_mm", "its standard error (mm)"),
        ("repeated_P_S_along_rays.mean_mm", "repeated position: mean P_S, fit along the rays (mm)"),
        ("repeated_P_S_along_rays.sem_mm", "its standard error (mm)"),
        ("repeated_P_S_along_rays.sd_mm", "scatter of P_S over the draws (mm)"),
        ("repeated_mean_u_along_rays_mm", "mean stated u of the diameter, fit along the rays (mm)"),
        ("noise_free_P_S_along_rays_mm", "P_S rendered without noise (mm)"),
        ("repeated_points_mean_distance_from_true_sphere_mm", "points' mean distance from the true sphere (mm)"),
        ("noise_rms_along_rays_mm", "point noise along the camera rays, RMS (mm)"),
        ("noise_rms_across_rays_mm", "point noise across the camera rays, RMS (mm)"),
        ("repeated_depth_mm", "depth of the repeated position (mm)"),
        ("draws", "noise draws"),
        ("far_positions", "far positions"),
    ),
    "measure": (
        ("median_wall_s", "median wall time of the command (s)"),
        ("walls_s", "wall time of each repeat (s)"),
        ("points", "points in the cloud"),
        ("stores", "stores read"),
        ("width_px", "camera width (px)"),
        ("valid_fraction_mean", "mean fraction of valid pixels"),
        ("ply_bytes", "PLY size (bytes)"),
        ("runs.0.phases_s.triangulate", "triangulation, first repeat (s)"),
        ("setup_s", "setting up the inputs (s)"),
        ("numba_cache", "numba cache"),
    ),
}

#: Keys of a figure that an object's ``credible_range`` judges.
CREDIBLE_FIGURES = ("coverage", "value")
#: The top-level key saying why a figure lies outside its credible range.
WHY_KEY = "credible_range_why"

#: Top-level keys shown in the header of a summary, not among its figures.
_META = {"benchmark", "command", "timed_command", "date", "created_utc", "cpu_count", "python",
         "threads", "load_average_start", "load_average_end", "code_digest_start",
         "code_digest_end", "complete", "stopped", "code_changed_during_run", "rerun", "smoke", "commit",
         "numba_cache_at_start", WHY_KEY}
_DATE_KEYS = ("date", "created_utc", "timestamp")
_SHORT_TEXT = 40
_SHORT_LIST = 8


@dataclass(frozen=True)
class Row:
    """One figure: its label, its formatted value and its JSON path."""

    label: str
    value: str
    path: str


@dataclass
class Summary:
    """What one benchmark JSON file says.

    Attributes
    ----------
    file : str
        The file's name, e.g. ``measure.json``.
    benchmark : str
        The ``"benchmark"`` entry, else the file's stem.
    command : str or None
        The command recorded in the JSON, if any.
    timed_command : str or None
        The command it timed, if recorded (``"timed_command"``).
    script : str or None
        The script under ``benchmarks/`` that writes this benchmark, if found.
    date : str
        When it ran (``YYYY-MM-DD HH:MM``).
    date_source : str
        ``"recorded"`` (from the JSON) or ``"file modified"`` (the file's mtime).
    machine : str
        CPU count, Python version, threads and load averages, as recorded.
    notes : list of str
        Completeness, code changes during the run, reruns.
    rows : list of Row
        The figures, at most :data:`MAX_ROWS`.
    omitted : int
        Figures left out by the row limit.
    records : list of str
        Top-level lists of records (e.g. ``"`seeds` (50 items)"``), not flattened.
    outside : list of str
        One line per figure outside its credible range, with why.
    unexplained : list of str
        The figures outside their credible range that the file does not explain.
    """

    file: str
    benchmark: str
    command: str | None
    timed_command: str | None
    script: str | None
    date: str
    date_source: str
    machine: str
    notes: list[str] = field(default_factory=list)
    rows: list[Row] = field(default_factory=list)
    omitted: int = 0
    records: list[str] = field(default_factory=list)
    outside: list[str] = field(default_factory=list)
    unexplained: list[str] = field(default_factory=list)


def _is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _is_scalar(value) -> bool:
    if isinstance(value, bool) or _is_number(value):
        return True
    if isinstance(value, str):
        return len(value) <= _SHORT_TEXT
    return isinstance(value, list) and len(value) <= _SHORT_LIST and all(
        _is_number(v) or isinstance(v, str) for v in value)


def fmt(value) -> str:
    """A value as the page shows it.

    Floats keep four significant digits, numbers from 10,000 up have their thousands
    separated, lists are joined with commas, true/false become yes/no.

    >>> fmt(0.9466666666666667), fmt(13.18888042600156), fmt(3717.4062304)
    ('0.9467', '13.19', '3717')
    >>> fmt(1619964), fmt(2048), fmt(True), fmt([0.93, 0.97]), fmt([])
    ('1,619,964', '2048', 'yes', '0.93, 0.97', 'none')
    """
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, int):
        return f"{value:,}" if abs(value) >= 10_000 else str(value)
    if isinstance(value, float):
        if not math.isfinite(value):
            return str(value)
        return f"{value:,.0f}" if abs(value) >= 1e4 else f"{value:.4g}"
    if isinstance(value, list):
        return ", ".join(fmt(v) for v in value) if value else "none"
    return str(value)


def lookup(doc, path: str):
    """The value at a dotted JSON ``path`` of ``doc`` (integers index lists), or None.

    >>> lookup({"runs": [{"s": 1.5}]}, "runs.0.s"), lookup({"a": 1}, "a.b")
    (1.5, None)
    """
    value = doc
    for part in path.split("."):
        if isinstance(value, dict) and part in value:
            value = value[part]
        elif isinstance(value, list) and part.isdigit() and int(part) < len(value):
            value = value[int(part)]
        else:
            return None
    return value


def outside_credible(doc, prefix: str = "") -> list[tuple[str, object, list]]:
    """(path, value, range) of every figure outside the credible range stated beside it.

    >>> outside_credible({"summary": {"coverage": 0.833, "credible_range": [0.93, 0.97]}})
    [('summary.coverage', 0.833, [0.93, 0.97])]
    >>> outside_credible({"summary": {"coverage": 0.95, "credible_range": [0.93, 0.97]}})
    []
    """
    out = []
    if not isinstance(doc, dict):
        return out
    rng = doc.get("credible_range")
    if isinstance(rng, list) and len(rng) == 2 and all(_is_number(v) for v in rng):
        for key in CREDIBLE_FIGURES:
            value = doc.get(key)
            if _is_number(value) and not rng[0] <= value <= rng[1]:
                out.append((f"{prefix}{key}", value, rng))
    for key, value in doc.items():
        if isinstance(value, dict):
            out += outside_credible(value, f"{prefix}{key}.")
    return out


def _leaves(doc: dict, prefix: str = ""):
    """(path, value, False) for every scalar below ``doc``, (path, count, True) for every
    list of records (objects), which is counted rather than flattened."""
    for key, value in doc.items():
        path = f"{prefix}.{key}" if prefix else str(key)
        if isinstance(value, dict):
            yield from _leaves(value, path)
        elif isinstance(value, list) and value and all(isinstance(v, dict) for v in value):
            yield path, len(value), True
        elif _is_scalar(value):
            yield path, value, False


def _rows(doc: dict, name: str) -> tuple[list[Row], int, list[str]]:
    rows, seen, records = [], set(), []
    for path, label in KNOWN.get(name, ()):
        value = lookup(doc, path)
        if value is not None and _is_scalar(value):
            rows.append(Row(label, fmt(value), path))
            seen.add(path)
    top = {k: v for k, v in doc.items() if k not in _META}
    for path, value, is_records in _leaves(top):
        nested = "." in path
        if is_records:
            if not nested:
                records.append(f"`{path}` ({value} items)")
        elif (not nested and path not in seen  # a top-level scalar
              or nested and name not in KNOWN and _is_number(value)):  # generic: numeric leaves
            rows.append(Row(path, fmt(value), path))
    return rows[:MAX_ROWS], max(0, len(rows) - MAX_ROWS), records


def _machine(doc: dict) -> str:
    parts = []
    if "cpu_count" in doc:
        parts.append(f"{doc['cpu_count']} CPUs")
    if "python" in doc:
        parts.append(f"Python {doc['python']}")
    if isinstance(doc.get("threads"), dict):
        parts.append("threads " + ", ".join(f"{k}={v}" for k, v in doc["threads"].items()))
    loads = [f"{fmt([round(x, 2) for x in doc[key]])} {when}"
             for key, when in (("load_average_start", "at the start"), ("load_average_end", "at the end"))
             if isinstance(doc.get(key), list)]
    if loads:
        parts.append("load average (1, 5, 15 min) " + ", ".join(loads))
    if doc.get("commit"):
        parts.append(f"commit {doc['commit']}")
    if doc.get("numba_cache_at_start"):
        parts.append(f"numba's kernel cache {doc['numba_cache_at_start']} at the start")
    return "; ".join(parts) if parts else "not recorded"


def _flatten_conditions(doc: dict) -> dict:
    """A result written through ``benchmarks/_common.py`` keeps its conditions (date,
    commit, cores, Python, load averages, numba's cache state) under ``conditions``:
    the header's keys, at the top level."""
    c = doc.get("conditions")
    if not isinstance(c, dict):
        return doc
    out = {k: v for k, v in doc.items() if k != "conditions"}
    for key, new in (("date", "date"), ("cores", "cpu_count"), ("python", "python"), ("commit", "commit"),
                     ("load_average_start", "load_average_start"), ("load_average_end", "load_average_end"),
                     ("numba_cache", "numba_cache_at_start")):
        if key in c:
            out.setdefault(new, c[key])
    return out


def _script(doc: dict, name: str, bench_dir: Path, json_name: str) -> tuple[str | None, list[str]]:
    """The script writing benchmark ``name``, with notes when the recorded command names
    another script or writes another file than ``benchmarks/results/<json_name>``."""
    quoted = r"""["']""" + re.escape(name) + r"""["']"""
    # the name as a JSON key, as the first argument of _common.conditions, or among the
    # script's FORMER_NAMES (a renamed benchmark's older result files)
    tag = re.compile(r"""["']benchmark["']\s*:\s*""" + quoted + r"|conditions\(\s*" + quoted
                     + r"|^FORMER_NAMES\s*=\s*\([^)]*" + quoted, re.M)
    found = sorted(p for p in bench_dir.glob("*.py") if tag.search(p.read_text(encoding="utf-8")))
    if not found and (bench_dir / f"{name}.py").is_file():
        found = [bench_dir / f"{name}.py"]
    script = f"benchmarks/{found[0].name}" if found else None
    named = re.search(r"benchmarks/[\w.-]+\.py", doc.get("command") or "")
    notes = []
    if named and not (bench_dir / Path(named.group(0)).name).is_file():
        now = f"; the script is now `{script}`" if script else ""
        notes.append(f"The recorded command names `{named.group(0)}`, which is no longer in the tree{now}.")
    elif named and script is None:
        script = named.group(0)
    out = re.search(r"--out[= ](\S+)", doc.get("command") or "")
    if out and Path(out.group(1)).as_posix() != f"benchmarks/results/{json_name}":
        notes.append(f"The command wrote `{out.group(1)}`; this file was moved or renamed here afterwards.")
    return script, notes


def _notes(doc: dict) -> list[str]:
    notes = []
    if doc.get("complete") is False:
        notes.append("Incomplete: the benchmark had not finished when this file was written.")
    if doc.get("stopped"):
        notes.append(f"Stopped: {doc['stopped']}.")
    if doc.get("code_changed_during_run") is True:
        notes.append("fringecal's source changed while it ran (its code digests at start and end differ).")
    rerun = doc.get("rerun")
    if isinstance(rerun, dict) and rerun.get("why"):
        seeds = f" (seeds {fmt(rerun['seeds'])})" if isinstance(rerun.get("seeds"), list) else ""
        notes.append(f"Partly rerun{seeds}: {rerun['why']}")
    return notes


def summarise(path, bench_dir=None) -> Summary:
    """Summarise one benchmark JSON file.

    Parameters
    ----------
    path : str or Path
        A JSON file holding one object (``benchmarks/results/*.json``).
    bench_dir : str or Path, optional
        The folder of the benchmark scripts (default: the JSON folder's parent).

    Returns
    -------
    Summary

    Raises
    ------
    ValueError
        If the file is not valid JSON or does not hold an object.
    """
    path = Path(path)
    bench_dir = Path(bench_dir) if bench_dir is not None else path.resolve().parent.parent
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as err:
        raise ValueError(f"{path}: not valid JSON ({err})") from None
    if not isinstance(doc, dict):
        raise ValueError(f"{path}: a benchmark result is a JSON object, found {type(doc).__name__}")
    doc = _flatten_conditions(doc)
    name = str(doc.get("benchmark") or path.stem)
    recorded = next((str(doc[k]) for k in _DATE_KEYS if doc.get(k)), None)
    if recorded:
        date, source = recorded, "recorded"
    else:
        mtime = _dt.datetime.fromtimestamp(path.stat().st_mtime)
        date, source = mtime.strftime("%Y-%m-%d %H:%M"), "file modified"
    script, script_notes = _script(doc, name, bench_dir, path.name)
    rows, omitted, records = _rows(doc, name)
    why = str(doc.get(WHY_KEY) or "").strip()
    labels = {r.path: r.label for r in rows}
    outside, unexplained = [], []
    for where, value, rng in outside_credible(doc):
        figure = f"{labels.get(where, where)} {fmt(value)}"
        outside.append(f"{figure} is outside its credible range {fmt(rng[0])}-{fmt(rng[1])}: "
                       + (why or "not explained"))
        if not why:
            unexplained.append(f"{path.name}: {where} = {fmt(value)} is outside its credible range "
                               f"{fmt(rng[0])}-{fmt(rng[1])} and the file says no why ({WHY_KEY})")
    return Summary(file=path.name, benchmark=name, command=doc.get("command"),
                   timed_command=doc.get("timed_command"), script=script, date=date,
                   date_source=source, machine=_machine(doc), notes=script_notes + _notes(doc), rows=rows,
                   omitted=omitted, records=records, outside=outside, unexplained=unexplained)


def _cell(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ")


def _section(s: Summary) -> list[str]:
    when = s.date if s.date_source == "recorded" else (
        f"{s.date} (not recorded in the JSON: the file's modification time, which a fresh checkout "
        "sets to the time of the checkout)")
    out = [f"## {s.file}", "", f"* Benchmark: `{s.benchmark}`, script: "
           + (f"`{s.script}`" if s.script else "not found under `benchmarks/`"),
           f"* Date: {when}", f"* Machine: {s.machine}"]
    out += [f"* Outside its credible range: {o}" for o in s.outside]
    out += [f"* Note: {n}" for n in s.notes]
    if s.records:
        out.append("* Per-item records in the file (not shown): " + ", ".join(s.records))
    if s.command:
        out += ["", "Command:", "", "```bash", s.command, "```"]
    else:
        out += ["", "No command is recorded in the JSON" + (f"; `{s.script}` writes it." if s.script else ".")]
    if s.timed_command:
        out += ["", "Timed command:", "", "```bash", s.timed_command, "```"]
    out += ["", "| figure | value | JSON path |", "|---|---|---|"]
    out += [f"| {_cell(r.label)} | {_cell(r.value)} | `{r.path}` |" for r in s.rows]
    if s.omitted:
        out += ["", f"{s.omitted} more figures are in the file."]
    return out + [""]


def page(summaries: list[Summary], source: str = "benchmarks/results") -> str:
    """The Markdown of the validation page for ``summaries`` (one section each)."""
    files = f"{len(summaries)} JSON file{'' if len(summaries) == 1 else 's'}"
    intro = (f"Generated when the site is built from the {files} in `{source}/` by "
             "`docs_hooks/validation.py` (`docs_hooks/benchmark_summary.py` reads them); nothing here is "
             "typed by hand. A benchmark run with `--out benchmarks/results/NAME.json` appears at the "
             "next build. The date is the one the JSON records, else the file's modification time (said so).")
    out = ["# Validation (generated)", "", intro,
           "", "| file | benchmark | date | headline |", "|---|---|---|---|"]
    for s in summaries:
        head = "; ".join(f"{r.label}: {r.value}" for r in s.rows[:2]) or "no figures"
        if s.outside:
            head += "; **outside its credible range**, see below"
        anchor = re.sub(r"[^\w-]", "", s.file.lower())
        date = s.date + ("" if s.date_source == "recorded" else " (file modified)")
        out.append(f"| [{s.file}](#{anchor}) | `{s.benchmark}` | {date} | {_cell(head)} |")
    out.append("")
    for s in summaries:
        out += _section(s)
    return "\n".join(out)
