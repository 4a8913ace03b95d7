"""The run report: one self-contained HTML page a metrologist can hand to a customer.

:func:`write_report` reads only files of the run directory, each through its
:class:`~fringecal.rundir.RunDir` accessor (the manifest, the artefact and ball-bar,
the acquisition, hexapod, labelling, link and DLT tables, the calibration, the
bundle summary, the residual tables and histograms, the verification, the
acceptance test of VDI/VDE 2634 parts 2 and 3 and, for a simulated run, the
evaluation against the truth), and renders what is there: a
missing optional file (the evaluation of a run of a recorded data set, which has
no truth; the verification of a run without ball-bar recordings) gives its section
a "not available" note, a malformed one a "could not be shown" note naming the file
and the error; neither stops the page. When and by which command the run executed,
and how long its steps took, describe one execution rather than the run's results:
they are passed in (``execution``, ``timings``) or, when the page is rewritten
later, taken from the run's summary. Images are embedded as base64 PNG, the style
sheet is inline, there is no JavaScript, and every string read from a file is
HTML-escaped. The page is written atomically (:meth:`fringecal.rundir.TextFile.save`).
"""

from __future__ import annotations

import base64
import hashlib
import html
import io
import math
import re
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import pandas as pd

from .rundir import RunDir, RunFile
from .sensor import PARAM_NAMES

__all__ = ["NO_TRUTH", "render_report", "write_report"]

#: What the page says where a run of a recorded data set has no truth to compare with.
NO_TRUTH = "absent, as for a run of a recorded data set (no truth)"

_PARAM_LABELS = {"x0": "x<sub>0</sub>", "y0": "y<sub>0</sub>", "z0": "z<sub>0</sub>", "omega": "&omega;",
                 "phi": "&phi;", "kappa": "&kappa;", "xi_h": "&xi;<sub>H</sub>", "eta_h": "&eta;<sub>H</sub>",
                 "c": "c", "k1": "k<sub>1</sub>", "k2": "k<sub>2</sub>", "k3": "k<sub>3</sub>",
                 "p1": "p<sub>1</sub>", "p2": "p<sub>2</sub>"}
_PARAM_UNITS = {"x0": "mm", "y0": "mm", "z0": "mm", "omega": "rad", "phi": "rad", "kappa": "rad",
                "xi_h": "mm", "eta_h": "mm", "c": "mm", "k1": "mm<sup>-2</sup>", "k2": "mm<sup>-4</sup>",
                "k3": "mm<sup>-6</sup>", "p1": "mm<sup>-1</sup>", "p2": "mm<sup>-1</sup>"}

_CSS = """
body{font:14px/1.45 system-ui,-apple-system,"Segoe UI",Helvetica,Arial,sans-serif;color:#1d2329;
 max-width:1100px;margin:0 auto;padding:1.5em 2em 4em}
h1{font-size:1.7em;margin:.2em 0}h2{border-bottom:2px solid #d0d7de;padding-bottom:.2em;margin-top:2em}
h3{margin:1.3em 0 .4em}
table{border-collapse:collapse;margin:.4em 0 1em;font-variant-numeric:tabular-nums}
th,td{border:1px solid #d0d7de;padding:.25em .6em;text-align:right;vertical-align:top}
th{background:#f3f5f7}td.l,th.l{text-align:left}
table.kv th{text-align:left;font-weight:600;width:18em}table.kv td{text-align:left}
.badge{display:inline-block;padding:.25em .9em;border-radius:.3em;font-weight:700;color:#fff;
 letter-spacing:.05em;font-size:1.1em}
.pass{background:#1a7f37}.fail{background:#cf222e}.none{background:#6e7781}
td.pass,td.fail{color:#fff;text-align:center;font-weight:600}
td.warn{text-align:center;font-weight:600}
.note{background:#f6f8fa;border-left:4px solid #8c959f;padding:.4em .8em;color:#57606a}
.warn{background:#fff8c5;border-left:4px solid #bf8700;padding:.4em .8em}
.meta{color:#57606a}.fixed{color:#6e7781}code,pre{font-size:.92em}
pre{background:#f6f8fa;padding:.8em;overflow-x:auto}
.figs img{max-width:100%;border:1px solid #d0d7de;margin:.3em 0}
.key{display:flex;flex-wrap:wrap;gap:.8em;margin:1em 0}
.key div{border:1px solid #d0d7de;border-radius:.3em;padding:.5em .9em;min-width:10em}
.key b{display:block;font-size:1.25em}
nav a{margin-right:1em}
@media print{nav{display:none}h2{page-break-after:avoid}table{page-break-inside:avoid}}
"""


# -- small helpers ----------------------------------------------------------------------------
class _Raw(str):
    """HTML built here from escaped parts: not escaped again."""


class _Missing(Exception):
    """An optional input is absent; the section says so instead of failing."""


def _e(x) -> str:
    return x if isinstance(x, _Raw) else html.escape(str(x))


def _finite(x) -> bool:
    return isinstance(x, (int, float, np.integer, np.floating)) and not isinstance(x, bool) and math.isfinite(x)


def _num(x, fmt: str = ".4g", unit: str = "") -> str:
    if not _finite(x):
        return "n/a"
    text = f"{x:{fmt}}"
    if text.startswith("-") and not text.strip("-0.,"):  # no "-0.0"
        text = text[1:]
    return text + (f" {unit}" if unit else "")


def _um(mm, digits: int = 1) -> str:
    return _num(mm * 1000 if _finite(mm) else mm, f".{digits}f", "µm")


def _len(mm) -> str:
    """A length in µm below 1 mm, else in mm."""
    if not _finite(mm):
        return "n/a"
    return _um(mm) if abs(mm) < 1 else _num(mm, ".3f", "mm")


def _urad(rad) -> str:
    return _num(rad * 1e6 if _finite(rad) else rad, ".1f", "µrad")


def _parts(n) -> str:
    return f"1 part in {n:,.0f}" if _finite(n) else "n/a"


def _secs(s) -> str:
    if not _finite(s):
        return "n/a"
    if s < 60:
        return f"{s:.2f} s" if s < 10 else f"{s:.1f} s"
    minutes, seconds = divmod(round(s), 60)
    return f"{s:.1f} s ({minutes} min {seconds} s)"


def _truthy(v) -> bool:
    return v if isinstance(v, bool) else str(v).strip().lower() in ("true", "1", "yes", "pass")


def _pm(value: float, u) -> _Raw:
    """``value ± u`` with u to two significant digits (common power of ten when tiny or huge).

    >>> _pm(52.69678, 0.0121), _pm(-2.3125e-05, 4.955e-06), _pm(694.018, 0.0)
    ('52.697 ± 0.012', '(-2.31 ± 0.50) × 10<sup>-5</sup>', '694.018')
    """
    if not (_finite(u) and u > 0):
        return _Raw(_e(f"{value:.7g}"))
    big = max(abs(value), u)
    p = int(math.floor(math.log10(big)))
    exp = p if (p < -3 or p > 5) else 0
    scale = 10.0 ** exp
    d = max(0, 1 - int(math.floor(math.log10(u / scale))))
    text = f"{value / scale:.{d}f} ± {u / scale:.{d}f}"
    return _Raw(f"({text}) × 10<sup>{exp}</sup>" if exp else text)


def _verdict(ok) -> _Raw:
    if ok is None:
        return _Raw('<span class="badge none">NOT VERIFIED</span>')
    return _Raw(f'<span class="badge {"pass" if ok else "fail"}">{"PASS" if ok else "FAIL"}</span>')


def _table(headers, rows, left: int = 1, cls: str = "") -> str:
    """Rows of cells (escaped unless :class:`_Raw`); the first ``left`` columns align left.
    A cell ``("PASS", "pass")`` is a coloured verdict; a :class:`_Span` covers the same
    column of the following rows, which then leave that cell out."""
    def cell(j, v, tag="td"):
        klass = "l" if j < left else ""
        span = ""
        if isinstance(v, _Span):
            v, klass, span = v.text, "l", f' rowspan="{v.rows}"'
        elif isinstance(v, tuple):
            v, klass = v
        return f"<{tag}{_cls(klass)}{span}>{_e(v)}</{tag}>"

    head = "".join(cell(j, h, "th") for j, h in enumerate(headers))
    body = "\n".join("<tr>" + "".join(cell(j, v) for j, v in enumerate(r)) + "</tr>" for r in rows)
    return f"<table{_cls(cls)}><tr>{head}</tr>\n{body}</table>\n"


class _Span:
    """A cell spanning ``rows`` rows (a note standing for a whole column)."""

    def __init__(self, text, rows: int):
        self.text, self.rows = text, max(1, int(rows))


def _column_note(rows: list[list], text) -> list[list]:
    """``rows`` with one more column: ``text`` once, spanning all of them."""
    return [r + [_Span(text, len(rows))] if i == 0 else list(r) for i, r in enumerate(rows)]


def _cls(name: str) -> str:
    return f' class="{name}"' if name else ""


def _kv(pairs) -> str:
    rows = "\n".join(f"<tr><th>{_e(k)}</th><td>{_e(v)}</td></tr>" for k, v in pairs if v is not None)
    return f'<table class="kv">{rows}</table>\n'


def _note(text) -> str:
    return f'<p class="note">{_e(text)}</p>\n'


def _warn(text) -> str:
    return f'<p class="warn">{_e(text)}</p>\n'


def _img(png: bytes, alt: str) -> str:
    return f'<img alt="{_e(alt)}" src="data:image/png;base64,{base64.b64encode(png).decode("ascii")}">'


def _pass_cell(v) -> tuple:
    ok = _truthy(v)
    return ("PASS" if ok else "FAIL", "pass" if ok else "fail")


# -- reading the run directory ---------------------------------------------------------------
class _Run:
    """The run directory as the report reads it: every file through its RunDir accessor,
    each loaded once; a missing file raises :class:`_Missing`, a malformed one ValueError."""

    def __init__(self, rd: RunDir):
        self.rd = rd
        self.root = rd.root
        self._loaded: dict[str, tuple[bool, object]] = {}

    def load(self, f: RunFile, *args):
        if not f.exists():
            raise _Missing(f"{f.rel} is not in the run directory")
        if f.rel not in self._loaded:
            try:
                self._loaded[f.rel] = (True, f.load(*args))
            except (ValueError, KeyError, OSError) as err:
                self._loaded[f.rel] = (False, err)
        ok, value = self._loaded[f.rel]
        if not ok:
            raise value
        return value

    def json(self, f: RunFile) -> dict:
        doc = self.load(f)
        if not isinstance(doc, dict):
            raise ValueError(f"{f.rel}: not a JSON object")
        return doc

    def maybe_json(self, f: RunFile) -> dict | None:
        try:
            return self.json(f)
        except (_Missing, ValueError, KeyError, OSError):
            return None

    def table(self, f: RunFile) -> pd.DataFrame:
        return self.load(f)

    def manifest(self) -> dict:
        return self.maybe_json(self.rd.manifest) or {}

    def config(self) -> dict:
        cfg = self.manifest().get("config")
        return cfg if isinstance(cfg, dict) else {}

    def name(self) -> str:
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
        except (_Missing, ValueError, KeyError, OSError):
            pass
        cfg = self.config()
        if cfg.get("dataset"):
            return "dataset"
        return "simulated" if cfg.get("simulate") else None

    def evaluation(self) -> dict:
        """The evaluation against the truth (``rd.evaluation``); its absence explained
        (a run of a recorded data set has no truth)."""
        f = self.rd.evaluation
        if not f.exists():
            if self.source() == "simulated":
                raise _Missing(f"{f.rel} is not in the run directory: this simulated run has not been evaluated "
                               f"against its truth")
            raise _Missing(f"{f.rel} is {NO_TRUTH}")
        return self.json(f)

    def no_truth(self) -> str:
        """What a "true parameters" cell says when there is no evaluation to fill it."""
        f = self.rd.evaluation
        if f.exists():
            return f"could not be read (see the {f.rel} note under Simulation truth)"
        return NO_TRUTH if self.source() != "simulated" else f"not available ({f.rel} is not in the run directory)"

    def clean(self, message: str) -> str:
        """An error message with the run directory's absolute path left out."""
        root = str(self.root)
        return message.replace(root + "/", "").replace(root, self.root.name)


def _guard(fn, run: _Run, *args) -> str:
    try:
        return fn(run, *args)
    except _Missing as why:
        return _note(f"Not available: {why}.")
    except (ValueError, KeyError, TypeError, AttributeError, IndexError) as err:
        # a malformed file: say which, keep the rest of the page
        return _warn(f"Could not be shown: {type(err).__name__}: {run.clean(str(err))}")


def _section(anchor: str, title: str, fn, run: _Run, *args) -> str:
    return f'<section id="{anchor}">\n<h2>{_e(title)}</h2>\n{_guard(fn, run, *args)}</section>\n'


def _numeric(df: pd.DataFrame) -> pd.DataFrame:
    """A table loaded as text (no schema) with its numeric columns as numbers."""
    out = df.copy()
    for col in out.columns:
        try:
            out[col] = pd.to_numeric(out[col])
        except (ValueError, TypeError):
            pass
    return out


def _execution(run: _Run, execution: dict | None) -> dict:
    """When and by which command the run executed: passed in, else from the summary."""
    if execution:
        return dict(execution)
    summ = run.maybe_json(run.rd.summary) or {}
    return {k: summ[k] for k in ("created_utc", "command") if summ.get(k) is not None}


# -- sections ---------------------------------------------------------------------------------
def _status(run: _Run):
    """PASS/FAIL of the ball-bar verification, None when the run is not verified.
    Only ``rd.verification`` decides (the summary may be of an earlier execution)."""
    ver = run.maybe_json(run.rd.verification)
    if ver and isinstance(ver.get("calibrated"), dict) and "pass" in ver["calibrated"]:
        return _truthy(ver["calibrated"]["pass"])
    return None


def _key_figures(run: _Run) -> str:
    bs = run.maybe_json(run.rd.bundle_summary) or {}
    ver = (run.maybe_json(run.rd.verification) or {}).get("calibrated")
    ver = ver if isinstance(ver, dict) else {}
    items = []
    eps2 = (bs.get("after") or {}).get("rms_eps2_mm")
    if _finite(eps2):
        items.append(("RMS ε<sub>2</sub> after adjustment", _um(eps2)))
    n = bs.get("one_part_in_1p96_sigma")
    if _finite(n):
        items.append(("calibration accuracy (1.96 σ of ε<sub>2</sub>)", _parts(n)))
    if _finite(ver.get("max_abs_error_mm")):
        items.append(("ball-bar max |length error|", _um(ver["max_abs_error_mm"])))
        if _finite(ver.get("volume_diagonal_mm")):
            items.append(("ball-bar max error of the volume diagonal",
                          _parts(ver["volume_diagonal_mm"] / ver["max_abs_error_mm"] if ver["max_abs_error_mm"] else
                                 float("inf"))))
    if _finite(ver.get("mpe_mm")):
        items.append(("maximum permissible error", _um(ver["mpe_mm"])))
    if not items:
        return ""
    return '<div class="key">' + "".join(f"<div>{label}<b>{_e(v)}</b></div>" for label, v in items) + "</div>\n"


_SOURCES = {"simulated": "simulated rig", "dataset": "recorded data set"}


def _source_text(run: _Run) -> str:
    src = run.source()
    cfg = run.config()
    if src == "dataset" and cfg.get("dataset"):
        return f"recorded data set {cfg['dataset']}"
    if src == "simulated" and isinstance(cfg.get("simulate"), dict) and cfg["simulate"].get("rig"):
        return f"simulated rig {cfg['simulate']['rig']}"
    return _SOURCES.get(src, "not recorded")


def _header(run: _Run, generated: str, execution: dict) -> str:
    digest = str(run.manifest().get("config_digest") or "n/a")
    meta = _kv([("Run directory", run.root.name), ("Data source", _source_text(run)),
                ("Run started (UTC)", execution.get("created_utc") or "not recorded"),
                ("Configuration digest", _Raw(f"<code>{_e(digest[:16])}</code>")),
                ("Report written (UTC)", generated)])
    return (f"<header><h1>Multi-scanner calibration report: {_e(run.name())} {_verdict(_status(run))}</h1>\n"
            f'<p class="meta">Fringe-projection scanners calibrated into one global frame with a '
            f"CMM-measured sphere artefact (fringecal).</p>\n{meta}{_key_figures(run)}</header>\n")


def _rig_part(run: _Run) -> str:
    rig = run.load(run.rd.calibration)
    rows = []
    for sc in rig.scanners:
        for s in sc.sensors:
            f = s.format
            rows.append([sc.name + (" (reference)" if sc.name == rig.reference else ""), s.name, s.role,
                         f"{f.width_px} × {f.height_px} px", f"{f.width_mm:g} × {f.height_mm:g} mm",
                         _um(f.width_mm / f.width_px, 2)])
    return (f"<p>{len(rig.scanners)} scanner(s), {len(rig.sensors)} sensors; the reference scanner "
            f"<b>{_e(rig.reference)}</b> defines the world frame.</p>\n"
            + _table(["Scanner", "Sensor", "Role", "Format", "Image size", "Pixel pitch"], rows, left=3))


def _artefact_part(run: _Run) -> str:
    rd = run.rd
    art = run.load(rd.artefact)
    d = art.distance_matrix()
    try:
        n_rods = f"{len(run.load(rd.rods, art))}"
    except _Missing:
        n_rods = "none recorded for this run"
    except ValueError as err:
        n_rods = f"could not be read: {run.clean(str(err))}"
    try:
        bar = run.load(rd.ballbar)
        length = float(np.linalg.norm(bar.centres[1] - bar.centres[0])) if len(bar) >= 2 else float("nan")
        ballbar = (f"spheres {', '.join(bar.ids)}, diameters {', '.join(f'{x:.3f}' for x in bar.diameters)} mm, "
                   f"centre distance {_num(length, '.4f', 'mm')} (CMM)")
    except _Missing as why:
        ballbar = str(why) if rd.verification.exists() else "none in this run (the calibration is not verified)"
    except ValueError as err:
        ballbar = f"could not be read: {run.clean(str(err))}"
    bs = run.maybe_json(rd.bundle_summary) or {}
    diag = bs.get("volume_diagonal_mm")
    return _kv([("Spheres", f"{len(art)} (diameters {art.diameters.min():.3f} to {art.diameters.max():.3f} mm)"),
                ("Rods", n_rods),
                ("Largest sphere distance", _num(float(d.max()), ".1f", "mm")),
                ("Sphere-centre bounding-box diagonal", _num(art.diagonal_mm, ".1f", "mm")),
                ("Centre uncertainty (CMM, per coordinate)",
                 _um(float(art.u.max())) if art.u.max() > 0 else "not given"),
                ("Measurement-volume diagonal",
                 f"{_num(diag, '.1f', 'mm')} ({bs.get('volume_diagonal_source', 'source not recorded')})"
                 if _finite(diag) else None),
                ("Verification ball-bar", ballbar)])


def _acquisition_part(run: _Run) -> str:
    rd = run.rd
    src = run.source()
    cfg = run.config()
    sim = cfg.get("simulate") if isinstance(cfg.get("simulate"), dict) else {}
    width = (sim.get("acquisition") or {}).get("camera_width_px")
    pairs = [("Data source", _source_text(run)),
             ("Simulated camera resolution", f"{width} px wide" if src == "simulated" and width else None)]
    try:
        acq = run.table(rd.acquisition)
        art = acq[acq["kind"] == "artefact"]
        bar = acq[acq["kind"] == "ballbar"]
        pairs.append(("Measurements (artefact pose × scanner)",
                      f"{len(art)} from {art['pose'].nunique()} artefact poses and {art['scanner'].nunique()} "
                      f"scanner(s)"))
        pairs.append(("Ball-bar recordings (position × scanner)",
                      f"{len(bar)} from {bar['pose'].nunique()} positions" if len(bar) else
                      "none (the calibration is not verified)"))
        external = acq[acq["source"].astype(str) != "simulated"]
        if len(external):
            pairs.append(("Read from the data set", f"{len(external)} image stacks or stores"))
        elif len(acq):
            pairs.append(("Rendered by the simulator", f"{len(acq)} stores"))
    except _Missing as why:
        bs = run.maybe_json(rd.bundle_summary) or {}
        pairs.append(("Artefact poses in the adjustment", bs.get("n_measurements")))
        pairs.append(("Acquisition table", f"not available: {why}"))
    except (ValueError, KeyError) as err:  # a malformed table: named, the hexapod part still shown
        return _kv(pairs) + _warn(f"Could not be shown: {type(err).__name__}: {run.clean(str(err))}") \
            + _guard(_hexapod_part, run)
    return _kv(pairs) + _guard(_hexapod_part, run)


def _hexapod_part(run: _Run) -> str:
    try:
        poses = run.table(run.rd.hexapod_moves)
    except _Missing as why:
        if run.source() == "dataset":
            return _note("Hexapod: the data set's artefact poses were not moved by a hexapod here (its "
                         "measurements were recorded before this run), so there are no planned and reached "
                         "poses to compare.")
        return _note(f"Hexapod moves not available: {why}.")
    used = bool(poses["hexapod"].map(_truthy).any())
    t, r = poses["translation_error_mm"].astype(float), poses["rotation_error_rad"].astype(float)
    html_ = _kv([("Hexapod", "used to move the artefact" if used else "not used (poses set directly)"),
                 ("Planned vs reached pose", f"translation error max {_um(t.max())}, RMS "
                  f"{_um(float(np.sqrt(np.mean(t ** 2))))}; rotation error max {_urad(r.max())}")])
    rows = [[p.measurement, _um(p.translation_error_mm), _urad(p.rotation_error_rad),
             f"{p.tx_mm:.3f}, {p.ty_mm:.3f}, {p.tz_mm:.3f}"] for p in poses.itertuples()]
    return html_ + ("<details><summary>Planned vs reached pose per artefact pose</summary>\n"
                    + _table(["Pose", "Translation error", "Rotation error", "Reached t (mm)"], rows)
                    + "</details>\n")


def _processing_part(run: _Run) -> str:
    rd = run.rd
    out = []
    try:
        lab = run.table(rd.label_outcomes)
        ok = lab[lab["status"] == "labelled"]
        out.append(f"<p>Sphere labelling: {len(ok)} of {len(lab)} measurements labelled.</p>\n")
        bad = lab[lab["status"] != "labelled"]
        if len(bad):
            out.append(_table(["Measurement", "Scanner", "Reason"],
                              [[r.measurement, r.scanner, "; ".join(str(x) for x in (r.reason, r.message)
                                                                      if pd.notna(x) and str(x))]
                               for r in bad.itertuples()],
                              left=3))
    except _Missing as why:
        out.append(_note(f"Labelling outcomes not available: {why}."))
    out.append(_guard(_links_part, run))
    out.append(_guard(_dlt_part, run))
    return "".join(out)


def _links_part(run: _Run) -> str:
    try:
        links = run.table(run.rd.scanner_links)
    except _Missing:
        return ""
    return "<h3>Scanner links (start values)</h3>\n" + _table(
        ["Scanner", "Linked to", "Via", "Measurements", "Translation spread", "Rotation spread"],
        [[r.scanner, r.reference, r.via, r.n_measurements, _len(r.translation_spread_mm),
          _urad(r.rotation_spread_rad)] for r in links.itertuples()], left=3)


def _dlt_part(run: _Run) -> str:
    try:
        dlt = _numeric(run.table(run.rd.dlt))
    except _Missing:
        return ""
    return "<h3>Start values by DLT</h3>\n" + _table(
        ["Sensor", "Points", "Reprojection RMS", "Method"],
        [[r.sensor, r.n_points, _um(r.reprojection_rms_mm, 2), r.method] for r in dlt.itertuples()])


def _timings(run: _Run, timings: dict | None) -> str:
    source = "this run"
    if not timings:
        summ = run.maybe_json(run.rd.summary) or {}
        timings = dict(summ.get("timings") or {})
        if not timings and _finite(summ.get("bundle_seconds")):
            timings["bundle"] = summ["bundle_seconds"]
        if timings and _finite(summ.get("total_seconds")):
            timings["total"] = summ["total_seconds"]
        source = f"{run.rd.summary.rel} (recorded when the run executed)"
    if not timings:
        raise _Missing(f"no step timings were passed in and {run.rd.summary.rel} records none")
    steps = {str(k).removesuffix("_seconds"): float(v) for k, v in timings.items() if _finite(v)}
    total = steps.pop("total") if "total" in steps else sum(steps.values())
    rows = [[k, _secs(v), f"{100 * v / total:.0f} %" if total > 0 else ""] for k, v in steps.items()]
    rows.append([_Raw("<b>total</b>"), _Raw(f"<b>{_secs(total)}</b>"), ""])
    return _table(["Step", "Wall time", "Share"], rows) + f'<p class="meta">Timings from {_e(source)}.</p>\n'


def _results(run: _Run) -> str:
    bs = run.json(run.rd.bundle_summary)
    try:
        truth = run.evaluation()
    except (_Missing, ValueError):
        truth = None
    before, after = bs["before"], bs["after"]
    rows = []
    for key, label in (("rms_f_mm", "F (objective, eq. 2-24)"),
                       ("rms_eps1_mm", "ε<sub>1</sub> (ray closest approach)"),
                       ("rms_eps2_mm", "ε<sub>2</sub> (distance to the CMM sphere)")):
        row = [_Raw(label), _len(before[key]), _len(after[key])]
        if truth is not None:
            row.append(_len(truth.get(key.replace("_mm", "_mm_true_params"))))
        rows.append(row)
    if truth is None:
        rows = _column_note(rows, run.no_truth())
    sig = bs.get("sigma_mm") or {}
    dof = bs.get("degrees_of_freedom") or {}
    out = _table(["RMS over control points", "start values", "after adjustment", "true parameters (simulation)"],
                 rows)
    out += _kv([("Calibration accuracy", f"{_parts(bs.get('one_part_in_1p96_sigma'))} of the "
                 f"{_num(bs.get('volume_diagonal_mm'), '.1f', 'mm')} volume diagonal (1.96 × RMS ε2, 95 %)"),
                ("Control points", f"{bs.get('n_control_points', 'n/a')} in {bs.get('n_measurements', 'n/a')} "
                 f"artefact poses"),
                ("Free parameters / degrees of freedom",
                 f"{bs.get('n_free_parameters', 'n/a')} / {dof.get('total', 'n/a')}"),
                ("Weights γ1, γ2; robust loss",
                 f"{', '.join(map(str, bs.get('gamma', [])))}; {bs.get('robust_loss', 'n/a')}"),
                ("Iterations (evaluations)", f"{bs.get('iterations', 'n/a')} ({bs.get('evaluations', 'n/a')})"),
                ("Converged", f"{'yes' if bs.get('converged') else 'NO'}: {bs.get('message', '')}"),
                ("Start values used", bs.get("start")),
                ("σ per term (ε1, ε2); σ0",
                 f"{_um(sig.get('alpha1'))}, {_um(sig.get('alpha2'))}; {_um(sig.get('sigma0'))}"),
                ("Condition number (scaled normal matrix)", _num(bs.get("condition_number"), ".2e")),
                ("Adjustment wall time", _secs(bs["bundle_seconds"]) if _finite(bs.get("bundle_seconds")) else None)])
    notes = [(d.get("severity", ""), d.get("kind", ""), d.get("message", "")) for d in bs.get("diagnostics", [])]
    notes += [("warning", "weak direction", w) for w in bs.get("weak_directions", [])]
    notes += [("warning", "dropped measurement", f"{d.get('measurement')}: {d.get('reason')}")
              for d in bs.get("dropped_measurements", [])]
    out += "<h3>Warnings and diagnoses</h3>\n"
    out += _table(["Severity", "Kind", "Message"], notes, left=3) if notes else _note("None: the adjustment "
                                                                                      "raised no warning.")
    return out


def _parameters(run: _Run) -> str:
    rig = run.load(run.rd.calibration)
    u = rig.uncertainty
    out = ['<p>Refined values with standard uncertainties (k = 1) from the adjustment; parameters held '
           'fixed are marked. Angles per thesis eq. 2-6; distortion of the ideal image coordinates.</p>\n']
    k = 0
    for sc in rig.scanners:
        idx = list(range(k, k + len(sc.sensors)))
        k += len(sc.sensors)
        rows = []
        for j, p in enumerate(PARAM_NAMES):
            cells = [_Raw(_PARAM_LABELS[p]), _Raw(_PARAM_UNITS[p])]
            for i in idx:
                v = float(rig.sensors[i].params[j])
                if rig.free[i, j]:
                    cells.append(_pm(v, None if u is None else float(u[i, j])))
                else:
                    cells.append(_Raw(f'<span class="fixed">{_e(f"{v:.7g}")} (fixed)</span>'))
            rows.append(cells)
        heads = ["Parameter", "Unit"] + [f"{s.name} ({s.role})" for s in sc.sensors]
        out.append(f"<h3>Scanner {_e(sc.name)}</h3>\n" + _table(heads, rows, left=2))
    out.append("<h3>Strongest correlations</h3>\n" + _guard(_correlations, run))
    return "".join(out)


def _correlations(run: _Run, k: int = 10) -> str:
    corr = run.json(run.rd.bundle_summary)["correlation"]
    names = list(corr["names"])
    m = np.asarray(corr["matrix"], float)
    iu = np.triu_indices(len(names), 1)
    r = m[iu]
    sensor = np.array([not n.startswith("pose[") for n in names])
    both = sensor[iu[0]] & sensor[iu[1]]
    top = np.flatnonzero(both)[np.argsort(-np.abs(r[both]), kind="stable")[:k]]
    rows = [[names[iu[0][t]], names[iu[1][t]], f"{r[t]:+.4f}"] for t in top]
    n_high = int((np.abs(r) > 0.99).sum())
    return (_table(["Parameter", "Parameter", "Correlation"], rows, left=2)
            + f"<p>{n_high} pair(s) of adjusted parameters, artefact poses included, correlate by more than "
              f"0.99 in magnitude.</p>\n")


def _residuals(run: _Run) -> str:
    rd = run.rd
    figs = []
    for term, label in (("eps1", "ε1 histogram"), ("eps2", "ε2 histogram")):
        try:
            figs.append(_img(run.load(rd.histogram(term)), label))
        except _Missing as why:
            figs.append(_note(f"Not available: {why}."))
    out = ('<p>Histograms of ε<sub>1</sub> and ε<sub>2</sub> over all control points at the start values and '
           'after the adjustment (as thesis figures 6-10 and 6-11).</p>\n'
           f'<div class="figs">{"".join(figs)}</div>\n')

    def per_measurement(run: _Run):
        t = run.table(rd.residuals_per_measurement)
        t = t.iloc[sorted(range(len(t)), key=lambda i: _natural(t["measurement"].iloc[i]))]
        return _table(["Measurement", "Scanners", "Points", "Spheres", "RMS ε1", "RMS ε2", "Mean ε2",
                       "RMS ε2 at start"],
                      [[r.measurement, r.scanners, r.n_points, r.n_spheres, _um(r.rms_eps1_mm), _um(r.rms_eps2_mm),
                        _um(r.mean_eps2_mm), _len(r.rms_eps2_start_mm)] for r in t.itertuples()], left=2)

    def per_sphere(run: _Run, show: int = 10, most: int = 300):
        f = rd.residuals_per_sphere
        t = run.table(f).sort_values("rms_eps2_mm", ascending=False)
        heads = ["Measurement", "Scanner", "Sphere", "Points", "RMS ε1", "RMS ε2", "Mean ε2", "Max |ε2|"]
        rows = [[r.measurement, r.scanner, r.sphere_id, r.n_points, _um(r.rms_eps1_mm), _um(r.rms_eps2_mm),
                 _um(r.mean_eps2_mm), _um(r.max_abs_eps2_mm)] for r in t.itertuples()]
        html_ = (f"<p>{len(rows)} sphere images; the worst by RMS ε<sub>2</sub> first.</p>\n"
                 + _table(heads, rows[:show], left=3))
        if len(rows) > show:
            title = f"All {len(rows)} sphere images" if len(rows) <= most else \
                f"The worst {most} of {len(rows)} sphere images (all in {_e(f.rel)})"
            html_ += f"<details><summary>{title}</summary>\n" + _table(heads, rows[:most], left=3) + "</details>\n"
        return html_

    out += "<h3>Per measurement</h3>\n" + _guard(per_measurement, run)
    out += "<h3>Per sphere image</h3>\n" + _guard(per_sphere, run)
    return out


def _natural(s) -> list:
    """Sort key putting measurement "2" before "10".

    >>> sorted(["10", "2", "bb01"], key=_natural)
    ['2', '10', 'bb01']
    """
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", str(s))]


def _ballbar_png(cal: dict, true: dict | None) -> bytes:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    pos = [str(p["measurement"]) for p in cal["positions"]]
    err = np.array([p["error_mm"] for p in cal["positions"]], float) * 1000
    fig = Figure(figsize=(8.5, 3.4), dpi=100)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    x = np.arange(len(pos))
    w = 0.38 if true else 0.6
    ax.bar(x - (w / 2 if true else 0), err, w, label="calibrated parameters", color="tab:blue")
    if true:
        by = {str(p["measurement"]): p["error_mm"] * 1000 for p in true["positions"]}
        ax.bar(x + w / 2, [by.get(p, np.nan) for p in pos], w, label="true parameters", color="tab:gray")
    if _finite(cal.get("mpe_mm")):
        for s in (1, -1):
            ax.axhline(s * cal["mpe_mm"] * 1000, color="tab:red", ls="--", lw=1,
                       label="± MPE" if s == 1 else None)
    ax.axhline(0, color="k", lw=0.6)
    ax.set_xticks(x, pos)
    ax.set_xlabel("ball-bar position")
    ax.set_ylabel("length error (µm)")
    ax.legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.2), ncol=3, frameon=False)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    return buf.getvalue()


def _gum(cal: dict) -> str:
    g = cal.get("uncertainty") or {}
    if not g:
        return _note("No uncertainty statement recorded.")
    k = g.get("coverage_factor")
    return (f"<p><b>Uncertainty statement (GUM).</b> Mean measured length {_num(cal['mean_length_mm'], '.4f', 'mm')} "
            f"± {_um(g.get('expanded_mm'))} (expanded uncertainty U, coverage factor k = {_num(k, 'g')}, about 95 % "
            f"coverage). Combined standard uncertainty u<sub>c</sub> = {_um(g.get('u_combined_mm'), 2)} from type A "
            f"u<sub>A</sub> = {_um(g.get('u_type_a_mm'), 2)} (standard deviation of the mean over "
            f"{_e(g.get('n_repeats'))} positions) and type B u<sub>B</sub> = {_um(g.get('u_type_b_mm'), 2)} "
            f"(artefact calibration certificate).</p>\n")


_ISO = {"conformance": "conformance proven", "non-conformance": "non-conformance proven",
        "uncertainty zone": "inside the uncertainty zone"}


def _length_budget(unc: dict | None, mpe_mm) -> str:
    """Each length's expanded uncertainty and ISO 14253-1 verdict, and the budget."""
    if not unc:
        return _note("No task-specific uncertainty recorded for the lengths (a run from before the budget "
                     "existed, or without the adjustment's covariance).")
    k = unc["coverage_factor"]
    out = (f"<h3>Uncertainty of each length and the decision rule (ISO 14253-1)</h3>\n<p>Every length carries "
           f"its own expanded uncertainty U (k = {_num(k, 'g')}) propagated from the calibration's covariance, "
           f"the artefact's CMM uncertainty and temperature, the sphere fits' own noise and the bar's "
           f"certificate and temperature. Conformance with the MPE is shown only when |error| + U is inside it; "
           f"non-conformance only when |error| - U exceeds it; otherwise the length lies in the uncertainty "
           f"zone.</p>\n")
    rows = []
    for e in unc["lengths"]:
        mc = e.get("monte_carlo")
        mc_cell = "not run" if mc is None else (f"{_um(mc['u_mc_mm'], 2)} ({mc['ratio']:.2f} x linear; "
                                                f"{'agrees' if mc['agree'] else 'DOES NOT AGREE'})")
        rows.append([e["measurement"], _um(e["error_mm"]), _um(e["u_mm"], 2), _um(e["U_mm"]),
                     mc_cell, _ISO.get(e["iso14253"], e["iso14253"]),
                     ("yes", "pass") if e["covered"] else ("NO: not covered by the budget", "fail")])
    out += _table(["Length", "Error", "u (linear)", "U", "u (Monte Carlo, JCGM 101)", "ISO 14253-1",
                   "|error| <= U"], rows, left=1)
    if unc["not_covered"]:
        out += _warn(f"Length error beyond its expanded uncertainty at {', '.join(unc['not_covered'])}: an error "
                     "source the uncertainty budget does not hold (for example an artefact whose scale differs "
                     "from its CMM table, or lens behaviour outside the sensor model). With k = 2 about one "
                     "length in twenty exceeds U by chance; more than that means the budget is incomplete.")
    mc = unc.get("monte_carlo")
    if mc is not None and not mc["all_agree"]:
        out += _warn(f"The Monte Carlo propagation does not confirm the linear one at {', '.join(mc['disagree'])} "
                     "(JCGM 101 clause 8): quote the Monte Carlo interval there.")
    b = unc.get("budget") or {}
    if b:
        worst = b["largest_error"]
        out += (f"<h3>Uncertainty budget</h3>\n<p>Standard uncertainty contributions (µm), as RMS over the "
                f"{len(unc['lengths'])} lengths and at the length of largest error ({_e(worst['measurement'])}, "
                f"error {_um(worst['error_mm'])}, U {_um(worst['U_mm'])}).</p>\n")
        out += _table(["Contribution", "RMS over lengths", f"At {worst['measurement']}"],
                      [[t, _um(b["rms_mm"][t], 2), _um(worst["budget_mm"][t], 2)] for t in b["terms"]]
                      + [["combined u", _um(float(np.sqrt(sum(v ** 2 for v in b["rms_mm"].values()))), 2),
                          _um(worst["u_mm"], 2)]], left=1)
    return out


_SCHEMES = {"thesis9": "placed as in thesis section 6.9.3", "vdi7": "placed after the scheme of VDI/VDE 2634"}


def _true_ballbar(run: _Run) -> tuple[dict | None, str]:
    """The ball-bar measured with the true sensors (``rd.evaluation``), or why there is none."""
    try:
        ev = run.evaluation()
    except (_Missing, ValueError):
        return None, run.no_truth()
    true = ev.get("verification_true_params")
    if not isinstance(true, dict) or not isinstance(true.get("positions"), list):
        return None, f"not evaluated ({run.rd.evaluation.rel} has no ball-bar measured with the true sensors)"
    return true, ""


def _verification(run: _Run) -> str:
    rd = run.rd
    try:
        ver = run.json(rd.verification)
    except _Missing as why:
        try:
            acq = run.table(rd.acquisition)
            if not (acq["kind"] == "ballbar").any():
                why = _Missing(f"{why}: the run has no ball-bar recordings, so the calibration is not verified")
        except (_Missing, ValueError, KeyError):
            pass
        raise why from None
    cal = ver["calibrated"]
    true, no_true = _true_ballbar(run)
    recorded = ver.get("recorded_by") or {}
    fails = ver.get("failures") or []
    sim = run.config().get("simulate") if isinstance(run.config().get("simulate"), dict) else {}
    scheme = (sim.get("verification") or {}).get("scheme") if run.source() == "simulated" else None
    n_positions = len(recorded) or len({str(p["measurement"]).split(":")[0] for p in cal["positions"]})
    where = f"{n_positions} positions" + (f", {_SCHEMES[scheme]}" if scheme in _SCHEMES else "")
    out = (f"<p>Ball-bar length measurement error per VDI/VDE 2634 ({_e(where)}): "
           f"the calibrated centre distance of the bar's two spheres against its certified length, "
           f"each position judged against the maximum permissible error (MPE). "
           f"Result: {_verdict(_truthy(cal['pass']))}</p>\n")
    ratio = None
    if true is not None and _finite(true.get("max_abs_error_mm")) and true["max_abs_error_mm"] > 0:
        ratio = (f"max |error| {_um(true['max_abs_error_mm'])}; calibrated / true = "
                 f"{cal['max_abs_error_mm'] / true['max_abs_error_mm']:.2f}")
    out += _kv([("Reference (certified) length", _num(cal["reference_length_mm"], ".4f", "mm")),
                ("Mean measured length", _num(cal["mean_length_mm"], ".4f", "mm")),
                ("Mean error", _um(cal.get("mean_error_mm"))),
                ("Max |length error|", f"{_um(cal['max_abs_error_mm'])} = {_parts(cal.get('one_part_in'))} of the "
                                       f"{_num(cal.get('volume_diagonal_mm'), '.1f', 'mm')} volume diagonal"),
                ("MPE", _um(cal.get("mpe_mm")) if _finite(cal.get("mpe_mm")) else "none set"),
                ("Positions", f"{len(recorded)} recorded, {len(cal['positions'])} length(s) measured, "
                              f"{len(fails)} problem(s)" if recorded else None),
                ("With the true parameters (simulation)", ratio if true is not None else no_true)])
    true_by = {str(p.get("measurement")): p for p in (true or {}).get("positions", [])}
    rows = []
    for p in cal["positions"]:
        name = str(p["measurement"])
        scanners = recorded.get(name, recorded.get(name.split(":")[0], []))
        row = [name, ", ".join(map(str, scanners)), _num(p["length_mm"], ".4f", "mm"), _um(p["error_mm"]),
               _pass_cell(p["pass"])]
        if true is not None:
            t = true_by.get(name)
            row += [_um(t["error_mm"]), _pass_cell(t["pass"])] if t else ["not measured", ""]
        rows.append(row)
    heads = ["Position", "Recorded by", "Length", "Error", "Pass"]
    if true is not None:
        heads += ["Error (true parameters)", "Pass (true parameters)"]
    else:
        heads += ["True parameters (simulation)"]
        rows = _column_note(rows, no_true)
    out += _table(heads, rows, left=2)
    out += f'<div class="figs">{_img(_ballbar_png(cal, true), "ball-bar length error per position")}</div>\n'
    out += _gum(cal)
    out += _length_budget(ver.get("uncertainty"), cal.get("mpe_mm"))
    if fails:
        out += "<h3>Positions that could not be measured completely</h3>\n" + _table(
            ["Position", "Scanner", "Sphere", "Reason"],
            [[f.get("position"), f.get("scanner"), f.get("sphere_id"), f.get("reason")] for f in fails], left=4)
    return out


# -- acceptance test (VDI/VDE 2634 parts 2 and 3) ----------------------------------------------
#: ISO 14253-1 verdict of acceptance.json -> CSS class of its cell (not limited: plain).
_ACCEPTANCE_CLASSES = {"conformance": "pass", "non-conformance": "fail", "uncertainty zone": "warn"}

#: Colour of each acceptance object (and of the ball-bar) in the positions figure.
_TEST_COLOURS = {"sphere": "tab:blue", "dumbbell": "tab:orange", "flat": "tab:green", "ballbar": "tab:purple"}


def _acceptance(run: _Run) -> str:
    """The acceptance section: certificate, positions figure, raw values and failures.

    Parameters
    ----------
    run : the run directory as the report reads it

    Returns
    -------
    HTML; a note when the run has no ``acceptance.json``.
    """
    f = run.rd.acceptance
    if not f.exists():
        return _note(f"No acceptance test in this run ({f.rel} is not in the run directory).")
    doc = run.json(f)
    return (_acceptance_certificate(doc)
            + "<h3>Positions in the measurement volume</h3>\n" + _guard(_acceptance_figure, run, doc)
            + "<h3>Values per position</h3>\n" + _acceptance_values(doc))


def _percent(fraction) -> str:
    """A fraction as a percentage.

    >>> _percent(0.003), _percent(None)
    ('0.3 %', 'n/a')
    """
    return _num(100 * fraction if _finite(fraction) else fraction, ".3g", "%")


def _acceptance_verdict(v) -> tuple | str:
    """The verdict cell: coloured as the verification's PASS/FAIL (uncertainty zone: warning)."""
    klass = _ACCEPTANCE_CLASSES.get(str(v))
    return (str(v), klass) if klass else str(v)


def _acceptance_row(p: dict) -> list:
    """One certificate row of a parameter of ``acceptance.json``."""
    mpe = p.get("mpe_mm")
    return [f"{p.get('name')} {p.get('title') or ''}".strip(), p.get("scanner"), p.get("positions"),
            _um(p.get("measured_mm")), _um(mpe) if mpe is not None else "not limited", _um(p.get("U_mm")),
            _acceptance_verdict(p.get("verdict"))]


def _acceptance_certificate(doc: dict) -> str:
    """The certificate table and the decision: accepted or not under ISO 14253-1."""
    params = doc.get("parameters") or []
    k = _num(doc.get("coverage_factor"), "g")
    out = (f"<p>Quality parameters of {_e(doc.get('standard', 'VDI/VDE 2634 parts 2 and 3'))}: P<sub>F</sub>, "
           f"P<sub>S</sub>, SD and F inside each scanner's volume (part 2), E across the cell (part 3). Each is the "
           f"value of largest magnitude over its positions, with that position's expanded uncertainty U "
           f"(k = {_e(k)}), judged position by position against the maximum permissible error (MPE). "
           f"Decision rule: {_e(doc.get('decision_rule', 'ISO 14253-1'))}.</p>\n")
    out += _table(["Test", "Scanner", "Positions", "Measured", "Limit (MPE)", f"U (k = {k})", "Verdict"],
                  [_acceptance_row(p) for p in params], left=2)
    return out + _acceptance_decision(doc, params, k)


def _acceptance_decision(doc: dict, params: list, k: str) -> str:
    """ACCEPTED / NOT ACCEPTED with the settings, and the simple comparison when it differs."""
    accepted = _truthy(doc.get("accepted"))
    badge = f'<span class="badge {"pass" if accepted else "fail"}">{"ACCEPTED" if accepted else "NOT ACCEPTED"}</span>'
    limited = [p for p in params if p.get("mpe_mm") is not None]
    if not limited:
        why = "no parameter has a limit (MPE) to conform to"
    elif accepted:
        why = "conformance proven for every limited parameter"
    else:
        short = [f"{p.get('name')} ({p.get('scanner')}): {p.get('verdict')}" for p in limited
                 if p.get("verdict") != "conformance"]
        why = "conformance not proven for " + (", ".join(short) or "every limited parameter")
    out = (f"<p>The cell is {badge} under ISO 14253-1: {_e(why)} (coverage factor k = {_e(k)}; "
           f"{_e(_percent(doc.get('exclude_fraction')))} of the points of each sphere and flat measurement "
           f"excluded as outliers).</p>\n")
    within = doc.get("within_mpe")
    if within is not None and _truthy(within) != accepted:
        out += _warn(f"The simple comparison (every value within its MPE, uncertainty not considered) would "
                     f"{'accept' if _truthy(within) else 'not accept'} the cell.")
    return out


def _acceptance_values(doc: dict) -> str:
    """The raw value of every position, then the positions not measured as warnings."""
    def count(n, parameter):
        return int(n) if _finite(n) and (n > 0 or parameter not in ("SD", "E")) else "–"

    rows = [[v.get("test"), v.get("parameter"), v.get("position"), v.get("scanner"), _um(v.get("value_mm")),
             _um(v.get("U_mm")), count(v.get("n_points"), v.get("parameter")),
             count(v.get("n_excluded"), v.get("parameter"))] for v in doc.get("values") or []]
    out = (_table(["Test", "Parameter", "Position", "Scanner", "Value", "U", "Points", "Excluded"], rows, left=4)
           if rows else _note("No value was measured."))
    fails = doc.get("failures") or []
    if fails:
        out += f"<h3>Positions not measured ({len(fails)})</h3>\n" + "".join(
            _warn(f"{f.get('test')} position {f.get('position')}, scanner {f.get('scanner')}: {f.get('reason')}")
            for f in fails)
    return out


def _acceptance_figure(run: _Run, doc: dict) -> str:
    """The positions drawn in the world frame, or a note when none are stated."""
    positions = doc.get("positions") or []
    if not positions:
        return _note(f"No positions to draw: {run.rd.acceptance.rel} states no placements of the objects "
                     "(a recorded data set holds its measurements, not where the objects stood).")
    standards = run.maybe_json(run.rd.acceptance_standards) or {}
    shapes = [s for s in (_placement(p, standards) for p in positions) if s is not None]
    pinholes = _pinholes(run)
    png = _acceptance_png(shapes, pinholes, _ballbar_segments(run))
    frame = f"the reference scanner {_e(pinholes[0][2])}'s frame" if pinholes else "the world frame"
    return (f'<div class="figs">{_img(png, "acceptance test positions in the measurement volume")}</div>\n'
            f'<p class="meta">{len(shapes)} positions as placed (T<sub>world_object</sub> of '
            f"{_e(run.rd.acceptance.rel)}) in {frame} (mm); triangles: the scanners' camera pinholes.</p>\n")


def _placement(row: dict, standards: dict) -> dict | None:
    """One position as world points to draw: ``test``, ``points`` (k, 3) and ``radius``
    (spheres); an object of unknown size is drawn as a point at its frame's origin."""
    from .frames import POSE_COLUMNS, Frame

    try:
        T = Frame.from_params([float(row[c]) for c in POSE_COLUMNS])
    except (KeyError, TypeError, ValueError):
        return None
    if not np.all(np.isfinite(T.params)):
        return None
    test = str(row.get("test"))
    size = standards.get(test) if isinstance(standards.get(test), dict) else {}
    local = np.zeros((1, 3))
    radius = None
    if test == "sphere" and _finite(size.get("diameter_mm")):
        radius = size["diameter_mm"] / 2
    elif test == "dumbbell" and _finite(size.get("length_mm")):
        local = np.array([[0.0, 0.0, 0.0], [size["length_mm"], 0.0, 0.0]])
    elif test == "flat" and _finite(size.get("length_mm")) and _finite(size.get("width_mm")):
        u, v = size["length_mm"] / 2, size["width_mm"] / 2
        local = np.array([[-u, -v, 0.0], [u, -v, 0.0], [u, v, 0.0], [-u, v, 0.0], [-u, -v, 0.0]])
    return {"test": test, "points": T.to_world(local), "radius": radius}


def _pinholes(run: _Run) -> list[tuple]:
    """(scanner, camera pinhole, reference scanner) of the calibration; none without one."""
    try:
        rig = run.load(run.rd.calibration)
    except (_Missing, ValueError, KeyError, OSError):
        return []
    return [(sc.name, np.asarray(sc.camera.pinhole, float), rig.reference) for sc in rig.scanners]


def _ballbar_segments(run: _Run) -> list[np.ndarray]:
    """The ball-bar (E) positions as their sphere centres (mean over the scanners)."""
    try:
        t = _numeric(run.table(run.rd.ballbar_centres))
        mean = t.groupby(["position", "sphere_id"], sort=True)[["x_mm", "y_mm", "z_mm"]].mean()
    except (_Missing, ValueError, KeyError, OSError):
        return []
    return [g.to_numpy(float) for _, g in mean.groupby(level="position", sort=False)]


#: The two views of the positions figure: title, (horizontal, vertical) world axis.
_VIEWS = (("top view", (0, 2)), ("side view", (2, 1)))


def _acceptance_png(shapes: list[dict], pinholes: list[tuple], bars: list[np.ndarray]) -> bytes:
    """The positions in two views of the world frame (PNG): spheres as circles,
    dumbbells as segments with their spheres, flats as outlines, coloured per test."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.lines import Line2D

    fig = Figure(figsize=(10, 5.2), dpi=100)
    FigureCanvasAgg(fig)
    names = "xyz"
    for j, (title, (h, v)) in enumerate(_VIEWS):
        ax = fig.add_subplot(1, 2, j + 1)
        for s in shapes:
            _draw_shape(ax, s, h, v)
        for pts in bars:
            ax.plot(pts[:, h], pts[:, v], "-o", color=_TEST_COLOURS["ballbar"], lw=1, ms=3, alpha=0.6)
        for i, (name, p, _) in enumerate(pinholes):  # labels staggered: pinholes may coincide in a view
            ax.plot(p[h], p[v], "^", color="k", ms=8)
            ax.annotate(name, (p[h], p[v]), textcoords="offset points", xytext=(6, 6 - 11 * i), fontsize=8)
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_title(f"{title} (world {names[h]}-{names[v]})", fontsize=10)
        ax.set_xlabel(f"world {names[h]} (mm)")
        ax.set_ylabel(f"world {names[v]} (mm)")
        ax.grid(True, lw=0.3)
    tests = [t for t in _TEST_COLOURS if any(s["test"] == t for s in shapes) or (t == "ballbar" and bars)]
    handles = [Line2D([], [], color=_TEST_COLOURS[t], marker="o", label=t) for t in tests]
    if pinholes:
        handles.append(Line2D([], [], color="k", marker="^", ls="", label="camera pinhole"))
    fig.legend(handles=handles, fontsize=8, loc="lower center", ncol=len(handles), frameon=False)
    fig.tight_layout(rect=(0, 0.06, 1, 1))
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    return buf.getvalue()


def _draw_shape(ax, shape: dict, h: int, v: int) -> None:
    """One position in the view of world axes ``h`` (horizontal) and ``v`` (vertical)."""
    from matplotlib.patches import Circle

    colour = _TEST_COLOURS.get(shape["test"], "tab:gray")
    pts = shape["points"]
    if shape["radius"]:
        ax.add_patch(Circle((pts[0, h], pts[0, v]), shape["radius"], fill=False, color=colour, lw=1.2))
        ax.plot(pts[0, h], pts[0, v], "+", color=colour, ms=4)
    elif shape["test"] == "dumbbell" and len(pts) == 2:
        ax.plot(pts[:, h], pts[:, v], "-o", color=colour, lw=1.5, ms=4)
    elif len(pts) > 1:
        ax.plot(pts[:, h], pts[:, v], "-", color=colour, lw=1.2)
    else:
        ax.plot(pts[0, h], pts[0, v], "o", color=colour, ms=4)


def _truth(run: _Run) -> str:
    ev = run.evaluation()
    bs = run.maybe_json(run.rd.bundle_summary) or {}
    after = bs.get("after") or {}
    true_bar = ev.get("verification_true_params")
    floor = true_bar.get("max_abs_error_mm") if isinstance(true_bar, dict) else None
    out = ("<p>The simulator knows every true parameter: the errors of the calibrated sensors, and the "
           "residual floor (the same control points evaluated with the true sensors and poses, set by noise).</p>\n")
    out += _kv([("Max sensor position error", _um(ev.get("max_position_error_mm"))),
                ("Max sensor angle error", _urad(ev.get("max_angle_error_rad"))),
                ("RMS F: calibrated / true parameters",
                 f"{_len(after.get('rms_f_mm'))} / {_len(ev.get('rms_f_mm_true_params'))}"),
                ("RMS ε1: calibrated / true parameters",
                 f"{_um(after.get('rms_eps1_mm'))} / {_um(ev.get('rms_eps1_mm_true_params'))}"),
                ("RMS ε2: calibrated / true parameters",
                 f"{_um(after.get('rms_eps2_mm'))} / {_um(ev.get('rms_eps2_mm_true_params'))}"),
                ("Ball-bar max |error| with the true parameters", _um(floor) if _finite(floor) else None)])
    rows = [[s.get("sensor"), _um(s.get("position_error_mm")), _urad(s.get("angle_error_rad")),
             _um(s.get("c_error_mm")), _num(s.get("max_sigma_ratio_position_angles_c"), ".2f")]
            for s in ev.get("sensors", [])]
    if rows:
        out += _table(["Sensor", "Position error", "Max angle error", "c error",
                       "max |error| / u (position, angles, c)"], rows)
    return out


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _provenance(run: _Run, execution: dict) -> str:
    import yaml

    rd = run.rd
    out = []
    files = [(f.rel, _Raw(f"<code>{_sha256(f.path)}</code>")) for f in (rd.calibration.xml, rd.calibration)
             if f.path.is_file()]
    command = execution.get("command")
    run_facts = [("Run started (UTC)", execution.get("created_utc") or "not recorded"),
                 ("Command", _Raw(f"<code>{_e(command)}</code>") if command else "not recorded")]
    try:
        man = run.json(rd.manifest)
    except _Missing as why:
        return _kv(run_facts + files) + _note(f"Not available: {why}.")
    src = man.get("source")
    out.append(_kv([("Configuration digest (SHA-256)", _Raw(f"<code>{_e(man.get('config_digest', 'n/a'))}</code>")),
                    ("Code digest (fringecal source)", _Raw(f"<code>{_e(man['code_digest'])}</code>")
                     if man.get("code_digest") else None),
                    ("Data source", _SOURCES.get(src, src) if src else None),
                    *run_facts, *files]))
    vers = man.get("versions") or {}
    out.append("<h3>Software</h3>\n" + _table(["Package", "Version"], sorted(vers.items()), left=2))
    inputs = man.get("inputs") or {}
    if inputs:
        rows = []
        for path, digest in inputs.items():
            if isinstance(digest, dict):  # {"path": ..., "sha256": ...}
                path, digest = digest.get("path", path), digest.get("sha256", "")
            rows.append([path, _Raw(f"<code>{_e(digest)}</code>")])
        out.append("<h3>Inputs</h3>\n" + _table(["Input file", "SHA-256"], rows, left=2))
    cfg = man.get("config")
    if cfg is not None:
        text = yaml.safe_dump(cfg, sort_keys=False, allow_unicode=True, default_flow_style=False)
        out.append(f"<details><summary>Resolved configuration</summary>\n<pre>{_e(text)}</pre></details>\n")
    return "".join(out)


def _crossval(run: _Run) -> str:
    """The two half-calibrations compared (``crossval.json``)."""
    cv = run.json(run.rd.crossval)
    if cv.get("verdict") == "not possible":
        return _note(f"Not possible: {cv.get('reason')}")
    out = (f"<p>The measurements split into two halves, each calibrated on its own; both triangulate the same "
           f"control-point observations and their difference is compared with the uncertainty the two "
           f"calibrations state (mean z<sup>2</sup>/3 is 1 when it is right). Verdict: "
           f"<b>{_e(cv['verdict'])}</b>.</p>\n")
    rows = []
    for name, sc in cv["scanners"].items():
        rows.append([name, *(f"{sc[f]['mean_z2_over_3']:.2f} ({_um(sc[f]['rms_difference_mm'])} vs "
                              f"{_um(sc[f]['rms_predicted_mm'])})" for f in ("scanner", "reference", "world")),
                     (sc["verdict"], "pass" if sc["verdict"] == "consistent" else "fail"),
                     _um(sc["model_error_mm"])])
    out += _table(["Scanner", "Own frame: z²/3 (RMS difference vs predicted)", "Aligned on the reference",
                   "World (reported only)", "Verdict", "Model error per half"], rows, left=1)
    par = cv.get("parameters") or {}
    halves = cv.get("halves") or []
    out += _kv([("Halves", "; ".join(f"{len(h['measurements'])} measurements, eps1/eps2 {_um(h['rms_eps1_mm'])} / "
                                     f"{_um(h['rms_eps2_mm'])}" for h in halves) or None),
                ("Largest parameter difference", f"{par.get('parameter')}: {par.get('max_normalised', 0):.1f} times "
                                                 f"its combined uncertainty (RMS over all "
                                                 f"{par.get('rms_normalised', 0):.2f})" if par else None)])
    return out


_SECTIONS = [("rig", "Rig and artefact"), ("timing", "Timing"), ("results", "Calibration results"),
             ("parameters", "Sensor parameters"), ("residuals", "Residuals"),
             ("crossval", "Cross-validation"), ("verification", "Verification (ball-bar)"),
             ("acceptance", "Acceptance test (VDI/VDE 2634 parts 2 and 3)"),
             ("truth", "Simulation truth"), ("provenance", "Provenance")]


def _rig_section(run: _Run) -> str:
    return ("<h3>Scanners</h3>\n" + _guard(_rig_part, run) + "<h3>Artefact</h3>\n" + _guard(_artefact_part, run)
            + "<h3>Acquisition</h3>\n" + _guard(_acquisition_part, run)
            + "<h3>Labelling and start values</h3>\n" + _guard(_processing_part, run))


def _run_dir(run_dir) -> RunDir:
    return run_dir if isinstance(run_dir, RunDir) else RunDir(run_dir)


def render_report(run_dir, timings: dict | None = None, execution: dict | None = None,
                  generated: str | None = None) -> str:
    """The report page of ``run_dir`` (a :class:`~fringecal.rundir.RunDir` or a path)
    as an HTML string; see :func:`write_report`. ``generated`` (UTC) defaults to now."""
    rd = _run_dir(run_dir)
    markers = (rd.manifest, rd.summary, rd.bundle_summary, rd.calibration)
    if not any(f.path.is_file() for f in markers):
        raise FileNotFoundError(f"{rd.root} is not a run directory: none of "
                                f"{', '.join(f.rel for f in markers)} is there")
    run = _Run(rd)
    generated = generated or datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M:%S")
    execution = _execution(run, execution)
    bodies = {"rig": (_rig_section,), "timing": (_timings, timings), "results": (_results,),
              "parameters": (_parameters,), "residuals": (_residuals,), "crossval": (_crossval,),
              "verification": (_verification,),
              "acceptance": (_acceptance,),
              "truth": (_truth,), "provenance": (_provenance, execution)}
    nav = "<nav>" + "".join(f'<a href="#{a}">{_e(t)}</a>' for a, t in _SECTIONS) + "</nav>\n"
    sections = "".join(_section(a, t, bodies[a][0], run, *bodies[a][1:]) for a, t in _SECTIONS)
    from . import __version__

    return (f'<!DOCTYPE html>\n<html lang="en">\n<head>\n<meta charset="utf-8">\n'
            f"<title>Calibration report: {_e(run.name())}</title>\n<style>{_CSS}</style>\n</head>\n<body>\n"
            f"{_header(run, generated, execution)}{nav}{sections}"
            f'<footer class="meta"><p>Written by fringecal {_e(__version__)} on {_e(generated)} UTC from the files '
            f"of the run directory {_e(run.root.name)}.</p></footer>\n</body>\n</html>\n")


def write_report(run_dir, timings: dict | None = None, execution: dict | None = None) -> Path:
    """Write the run's report page: one self-contained HTML page describing the run.

    Parameters
    ----------
    run_dir : the run directory (a :class:`~fringecal.rundir.RunDir` or its path);
        only its files are read
    timings : step name -> wall seconds of the execution that produced the run
        (``"total"``: the whole execution); without it the timings recorded in the
        run's summary are shown
    execution : ``{"created_utc": ..., "command": ...}`` of that execution; without
        it, taken from the run's summary (``fringecal report`` rewriting the page later)

    Returns
    -------
    The path of the report, written atomically: a failed render leaves any previous
    page untouched.

    Raises
    ------
    FileNotFoundError
        ``run_dir`` is not a run directory (none of its manifest, summary, bundle
        summary or calibration is there); nothing is written.
    """
    rd = _run_dir(run_dir)
    text = render_report(rd, timings, execution)
    return rd.report.save(text)
