"""The run report: one self-contained HTML page a metrologist can hand to a customer.

:func:`write_report` reads only files inside the run directory (``manifest.json``,
``summary.json``, ``bundle_summary.json``, ``calibration.json``, ``verification.json``,
``truth.json``, ``artefact.csv``, ``tables/*.csv``, ``figures/*.png``) and renders what
is there: a missing optional file (``truth.json`` of a real run, say) gives its section
a "not available" note, a malformed one a "could not be shown" note naming the error;
neither stops the page. Images are embedded as base64 PNG, the style sheet is inline,
there is no JavaScript, and every string read from a file is HTML-escaped.
"""

from __future__ import annotations

import base64
import hashlib
import html
import io
import json
import math
import re
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import pandas as pd

from .rundir import RunDir
from .sensor import PARAM_NAMES

__all__ = ["write_report"]

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
    A cell ``("PASS", "pass")`` is a coloured verdict."""
    def cell(j, v, tag="td"):
        klass = "l" if j < left else ""
        if isinstance(v, tuple):
            v, klass = v
        return f"<{tag}{_cls(klass)}>{_e(v)}</{tag}>"

    head = "".join(cell(j, h, "th") for j, h in enumerate(headers))
    body = "\n".join("<tr>" + "".join(cell(j, v) for j, v in enumerate(r)) + "</tr>" for r in rows)
    return f"<table{_cls(cls)}><tr>{head}</tr>\n{body}</table>\n"


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
    def __init__(self, root: Path):
        self.rd = RunDir(root)
        self.root = self.rd.root
        self._json: dict[str, dict] = {}

    def json(self, name: str) -> dict:
        path = self.root / name
        if not path.is_file():
            raise _Missing(f"{name} is not in the run directory")
        if name not in self._json:
            try:
                self._json[name] = json.loads(path.read_text(encoding="utf-8"))
            except json.JSONDecodeError as err:
                raise ValueError(f"{name}: not valid JSON ({err})") from None
        return self._json[name]

    def maybe_json(self, name: str) -> dict | None:
        try:
            return self.json(name)
        except (_Missing, ValueError):
            return None

    def table(self, name: str, model=None) -> pd.DataFrame:
        from schemas import read_table

        path = self.rd.table(name)
        if not path.is_file():
            raise _Missing(f"tables/{name}.csv is not in the run directory")
        return read_table(path, model) if model is not None else pd.read_csv(path, dtype={"sensor": str})

    def file(self, rel: str) -> Path:
        path = self.root / rel
        if not path.is_file():
            raise _Missing(f"{rel} is not in the run directory")
        return path

    def rig(self):
        from .calibration_file import read_calibration_json

        return read_calibration_json(self.file("calibration.json"))

    def config(self) -> dict:
        return (self.maybe_json("manifest.json") or {}).get("config") or {}


def _guard(fn, *args) -> str:
    try:
        return fn(*args)
    except _Missing as why:
        return _note(f"Not available: {why}.")
    except (ValueError, KeyError) as err:  # a malformed file: say which, keep the rest of the page
        return _warn(f"Could not be shown: {type(err).__name__}: {err}")


def _section(anchor: str, title: str, fn, *args) -> str:
    return f'<section id="{anchor}">\n<h2>{_e(title)}</h2>\n{_guard(fn, *args)}</section>\n'


# -- sections ---------------------------------------------------------------------------------
def _status(run: _Run):
    ver = run.maybe_json("verification.json")
    if ver and isinstance(ver.get("calibrated"), dict) and "pass" in ver["calibrated"]:
        return _truthy(ver["calibrated"]["pass"])
    summ = (run.maybe_json("summary.json") or {}).get("verification") or {}
    return _truthy(summ["pass"]) if "pass" in summ else None


def _key_figures(run: _Run) -> str:
    bs = run.maybe_json("bundle_summary.json") or {}
    summ = run.maybe_json("summary.json") or {}
    ver = (run.maybe_json("verification.json") or {}).get("calibrated") or summ.get("verification") or {}
    items = []
    eps2 = summ.get("rms_eps2_mm_after", (bs.get("after") or {}).get("rms_eps2_mm"))
    if _finite(eps2):
        items.append(("RMS ε<sub>2</sub> after adjustment", _um(eps2)))
    n = summ.get("one_part_in", bs.get("one_part_in_1p96_sigma"))
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


def _header(run: _Run, generated: str) -> str:
    man = run.maybe_json("manifest.json") or {}
    name = run.config().get("name") or run.root.name
    digest = str(man.get("config_digest") or "n/a")
    meta = _kv([("Run directory", run.root.name), ("Created (UTC)", man.get("created_utc", "n/a")),
                ("Configuration digest", _Raw(f"<code>{_e(digest[:16])}</code>")),
                ("Report written (UTC)", generated)])
    return (f"<header><h1>Multi-scanner calibration report: {_e(name)} {_verdict(_status(run))}</h1>\n"
            f'<p class="meta">Fringe-projection scanners calibrated into one global frame with a '
            f"CMM-measured sphere artefact (fringecal).</p>\n{meta}{_key_figures(run)}</header>\n")


def _rig_part(run: _Run) -> str:
    rig = run.rig()
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
    from .artefact import load_artefact

    art = load_artefact(run.file("artefact.csv"))
    d = art.distance_matrix()
    rods = run.root / "rods.csv"
    n_rods = f"{len(pd.read_csv(rods))}" if rods.is_file() else "not recorded in the run directory"
    bs = run.maybe_json("bundle_summary.json") or {}
    diag = bs.get("volume_diagonal_mm")
    return _kv([("Spheres", f"{len(art)} (diameters {art.diameters.min():.3f} to {art.diameters.max():.3f} mm)"),
                ("Rods", n_rods),
                ("Largest sphere distance", _num(float(d.max()), ".1f", "mm")),
                ("Sphere-centre bounding-box diagonal", _num(art.diagonal_mm, ".1f", "mm")),
                ("Centre uncertainty (CMM, per coordinate)",
                 _um(float(art.u.max())) if art.u.max() > 0 else "not given"),
                ("Measurement-volume diagonal",
                 f"{_num(diag, '.1f', 'mm')} ({bs.get('volume_diagonal_source', 'source not recorded')})"
                 if _finite(diag) else None)])


def _acquisition_part(run: _Run) -> str:
    acq_cfg = run.config().get("acquisition") or {}
    pairs = [("Camera resolution", f"{acq_cfg['camera_width_px']} px wide" if "camera_width_px" in acq_cfg else None)]
    try:
        acq = run.table("acquisition")
        pairs.append(("Measurements (pose × scanner)",
                      f"{len(acq)} from {acq['pose'].nunique()} artefact poses and {acq['scanner'].nunique()} "
                      f"scanner(s); median valid pixel fraction {acq['valid_fraction'].median():.2f}"))
    except _Missing:
        summ = run.maybe_json("summary.json") or run.maybe_json("bundle_summary.json") or {}
        pairs.append(("Artefact poses in the adjustment", summ.get("n_measurements")))
    html_ = _kv(pairs)
    try:
        from schemas import AcquiredPosesTable

        poses = run.table("acquisition_poses", AcquiredPosesTable)
    except _Missing as why:
        return html_ + _note(f"Hexapod and pose plan not available: {why}.")
    used = bool(poses["hexapod"].any())
    t, r = poses["translation_error_mm"], poses["rotation_error_rad"]
    html_ += _kv([("Hexapod", "used to move the artefact" if used else "not used (poses set directly)"),
                  ("Planned vs reached pose", f"translation error max {_um(t.max())}, RMS "
                   f"{_um(float(np.sqrt(np.mean(t ** 2))))}; rotation error max {_urad(r.max())}")])
    rows = [[p.measurement, _um(p.translation_error_mm), _urad(p.rotation_error_rad),
             f"{p.tx_mm:.3f}, {p.ty_mm:.3f}, {p.tz_mm:.3f}"] for p in poses.itertuples()]
    return html_ + ("<details><summary>Planned vs reached pose per artefact pose</summary>\n"
                    + _table(["Pose", "Translation error", "Rotation error", "Reached t (mm)"], rows)
                    + "</details>\n")


def _processing_part(run: _Run) -> str:
    from schemas import LabelOutcomesTable, ScannerLinksTable

    out = []
    try:
        lab = run.table("label_outcomes", LabelOutcomesTable)
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
    try:
        links = run.table("scanner_links", ScannerLinksTable)
        out.append("<h3>Scanner links (start values)</h3>\n" + _table(
            ["Scanner", "Linked to", "Via", "Measurements", "Translation spread", "Rotation spread"],
            [[r.scanner, r.reference, r.via, r.n_measurements, _len(r.translation_spread_mm),
              _urad(r.rotation_spread_rad)] for r in links.itertuples()], left=3))
    except _Missing:
        pass
    try:
        dlt = run.table("dlt")
        out.append("<h3>Start values by DLT</h3>\n" + _table(
            ["Sensor", "Points", "Reprojection RMS", "Method"],
            [[r.sensor, r.n_points, _um(r.reprojection_rms_mm, 2), r.method] for r in dlt.itertuples()]))
    except _Missing:
        pass
    return "".join(out)


def _timings(run: _Run, timings: dict | None) -> str:
    source = "this run"
    if not timings:
        summ = run.maybe_json("summary.json") or {}
        timings = summ.get("timings") or {k: summ[k] for k in ("bundle_seconds", "total_seconds") if k in summ}
        source = "summary.json"
    if not timings:
        raise _Missing("no step timings were passed in and summary.json records none")
    steps = {str(k).removesuffix("_seconds"): float(v) for k, v in timings.items() if _finite(v)}
    total = steps.pop("total") if "total" in steps else sum(steps.values())
    rows = [[k, _secs(v), f"{100 * v / total:.0f} %" if total > 0 else ""] for k, v in steps.items()]
    rows.append([_Raw("<b>total</b>"), _Raw(f"<b>{_secs(total)}</b>"), ""])
    return _table(["Step", "Wall time", "Share"], rows) + f'<p class="meta">Timings from {source}.</p>\n'


def _results(run: _Run) -> str:
    bs = run.json("bundle_summary.json")
    truth = run.maybe_json("truth.json") or {}
    before, after = bs["before"], bs["after"]
    rows = []
    for key, label in (("rms_f_mm", "F (objective, eq. 2-24)"),
                       ("rms_eps1_mm", "ε<sub>1</sub> (ray closest approach)"),
                       ("rms_eps2_mm", "ε<sub>2</sub> (distance to the CMM sphere)")):
        floor = truth.get(key.replace("_mm", "_mm_true_params"))
        rows.append([_Raw(label), _len(before[key]), _len(after[key]), _len(floor)])
    sig = bs.get("sigma_mm") or {}
    dof = bs.get("degrees_of_freedom") or {}
    out = _table(["RMS over control points", "start values", "after adjustment", "true parameters (simulation)"]
                 if truth else ["RMS over control points", "start values", "after adjustment"],
                 [r if truth else r[:3] for r in rows])
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
                ("Condition number (scaled normal matrix)", _num(bs.get("condition_number"), ".2e"))])
    notes = [(d.get("severity", ""), d.get("kind", ""), d.get("message", "")) for d in bs.get("diagnostics", [])]
    notes += [("warning", "weak direction", w) for w in bs.get("weak_directions", [])]
    notes += [("warning", "dropped measurement", f"{d.get('measurement')}: {d.get('reason')}")
              for d in bs.get("dropped_measurements", [])]
    out += "<h3>Warnings and diagnoses</h3>\n"
    out += _table(["Severity", "Kind", "Message"], notes, left=3) if notes else _note("None: the adjustment "
                                                                                      "raised no warning.")
    return out


def _parameters(run: _Run) -> str:
    rig = run.rig()
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
    corr = run.json("bundle_summary.json")["correlation"]
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
    from schemas import MeasurementResidualsTable, SphereResidualsTable

    figs = []
    for name, label in (("eps1_hist", "ε1 histogram"), ("eps2_hist", "ε2 histogram")):
        try:
            figs.append(_img(run.file(f"figures/{name}.png").read_bytes(), label))
        except _Missing as why:
            figs.append(_note(f"Not available: {why}."))
    out = ('<p>Histograms of ε<sub>1</sub> and ε<sub>2</sub> over all control points at the start values and '
           'after the adjustment (as thesis figures 6-10 and 6-11).</p>\n'
           f'<div class="figs">{"".join(figs)}</div>\n')

    def per_measurement():
        t = run.table("residuals_per_measurement", MeasurementResidualsTable)
        t = t.iloc[sorted(range(len(t)), key=lambda i: _natural(t["measurement"].iloc[i]))]
        return _table(["Measurement", "Scanners", "Points", "Spheres", "RMS ε1", "RMS ε2", "Mean ε2",
                       "RMS ε2 at start"],
                      [[r.measurement, r.scanners, r.n_points, r.n_spheres, _um(r.rms_eps1_mm), _um(r.rms_eps2_mm),
                        _um(r.mean_eps2_mm), _len(r.rms_eps2_start_mm)] for r in t.itertuples()], left=2)

    def per_sphere(show: int = 10, most: int = 300):
        t = run.table("residuals_per_sphere", SphereResidualsTable).sort_values("rms_eps2_mm", ascending=False)
        heads = ["Measurement", "Scanner", "Sphere", "Points", "RMS ε1", "RMS ε2", "Mean ε2", "Max |ε2|"]
        rows = [[r.measurement, r.scanner, r.sphere_id, r.n_points, _um(r.rms_eps1_mm), _um(r.rms_eps2_mm),
                 _um(r.mean_eps2_mm), _um(r.max_abs_eps2_mm)] for r in t.itertuples()]
        html_ = (f"<p>{len(rows)} sphere images; the worst by RMS ε<sub>2</sub> first.</p>\n"
                 + _table(heads, rows[:show], left=3))
        if len(rows) > show:
            title = f"All {len(rows)} sphere images" if len(rows) <= most else \
                f"The worst {most} of {len(rows)} sphere images (all in tables/residuals_per_sphere.csv)"
            html_ += f"<details><summary>{title}</summary>\n" + _table(heads, rows[:most], left=3) + "</details>\n"
        return html_

    out += "<h3>Per measurement</h3>\n" + _guard(per_measurement)
    out += "<h3>Per sphere image</h3>\n" + _guard(per_sphere)
    return out


def _natural(s) -> list:
    """Sort key putting measurement "2" before "10"."""
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


def _verification(run: _Run) -> str:
    ver = run.json("verification.json")
    cal, true = ver["calibrated"], ver.get("true")
    scheme = {"thesis9": "nine positions as thesis section 6.9.3", "vdi7": "the seven positions of VDI/VDE 2634"}
    where = scheme.get(ver.get("scheme"), ver.get("scheme", "scheme not recorded"))
    out = (f"<p>Ball-bar length measurement error per VDI/VDE 2634 ({_e(where)}): "
           f"the calibrated centre distance of the bar's two spheres against its certified length, "
           f"each position judged against the maximum permissible error (MPE). "
           f"Result: {_verdict(_truthy(cal['pass']))}</p>\n")
    out += _kv([("Reference (certified) length", _num(cal["reference_length_mm"], ".4f", "mm")),
                ("Mean measured length", _num(cal["mean_length_mm"], ".4f", "mm")),
                ("Mean error", _um(cal.get("mean_error_mm"))),
                ("Max |length error|", f"{_um(cal['max_abs_error_mm'])} = {_parts(cal.get('one_part_in'))} of the "
                                       f"{_num(cal.get('volume_diagonal_mm'), '.1f', 'mm')} volume diagonal"),
                ("MPE", _um(cal.get("mpe_mm")) if _finite(cal.get("mpe_mm")) else "none set"),
                ("With the true parameters (simulation)",
                 f"max |error| {_um(true['max_abs_error_mm'])}; calibrated / true = "
                 f"{cal['max_abs_error_mm'] / true['max_abs_error_mm']:.2f}" if true and true.get("max_abs_error_mm")
                 else None)])
    true_by = {str(p["measurement"]): p for p in (true or {}).get("positions", [])}
    rows = []
    for p in cal["positions"]:
        row = [p["measurement"], _num(p["length_mm"], ".4f", "mm"), _um(p["error_mm"]), _pass_cell(p["pass"])]
        if true:
            t = true_by.get(str(p["measurement"]))
            row += [_um(t["error_mm"]), _pass_cell(t["pass"])] if t else ["n/a", ""]
        rows.append(row)
    heads = ["Position", "Length", "Error", "Pass"] + (["Error (true parameters)", "Pass"] if true else [])
    out += _table(heads, rows)
    out += f'<div class="figs">{_img(_ballbar_png(cal, true), "ball-bar length error per position")}</div>\n'
    out += _gum(cal)
    fails = ver.get("failures") or []
    if fails:
        out += "<h3>Positions that could not be measured</h3>\n" + _table(
            ["Parameters", "Position", "Sphere", "Reason"],
            [[f.get("rig"), f.get("measurement"), f.get("sphere_id"), f.get("reason")] for f in fails], left=4)
    return out


def _truth(run: _Run) -> str:
    try:
        truth = run.json("truth.json")
    except _Missing:
        raise _Missing("truth.json is absent, as for a real (not simulated) run: no true parameters to "
                       "compare with") from None
    bs = run.maybe_json("bundle_summary.json") or {}
    after = bs.get("after") or {}
    summ = run.maybe_json("summary.json") or {}
    floor = (summ.get("truth") or {}).get("verification_max_abs_error_true_params_mm")
    out = ("<p>The simulator knows every true parameter: the errors of the calibrated sensors, and the "
           "residual floor (the same control points evaluated with the true sensors and poses, set by noise).</p>\n")
    out += _kv([("Max sensor position error", _um(truth.get("max_position_error_mm"))),
                ("Max sensor angle error", _urad(truth.get("max_angle_error_rad"))),
                ("RMS ε1: calibrated / true parameters",
                 f"{_um(after.get('rms_eps1_mm'))} / {_um(truth.get('rms_eps1_mm_true_params'))}"),
                ("RMS ε2: calibrated / true parameters",
                 f"{_um(after.get('rms_eps2_mm'))} / {_um(truth.get('rms_eps2_mm_true_params'))}"),
                ("Ball-bar max |error| with the true parameters", _um(floor) if _finite(floor) else None)])
    rows = [[s.get("sensor"), _um(s.get("position_error_mm")), _urad(s.get("angle_error_rad")),
             _um(s.get("c_error_mm")), _num(s.get("max_sigma_ratio_position_angles_c"), ".2f")]
            for s in truth.get("sensors", [])]
    if rows:
        out += _table(["Sensor", "Position error", "Max angle error", "c error",
                       "max |error| / u (position, angles, c)"], rows)
    return out


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _provenance(run: _Run) -> str:
    import yaml

    out = []
    files = [(n, _Raw(f"<code>{_sha256(run.root / n)}</code>")) for n in ("calibration.xml", "calibration.json")
             if (run.root / n).is_file()]
    try:
        man = run.json("manifest.json")
    except _Missing as why:
        return _kv(files) + _note(f"Not available: {why}.")
    out.append(_kv([("Configuration digest (SHA-256)", _Raw(f"<code>{_e(man.get('config_digest', 'n/a'))}</code>")),
                    ("Created (UTC)", man.get("created_utc")),
                    ("Command", _Raw(f"<code>{_e(man.get('command', ''))}</code>")),
                    *files]))
    vers = man.get("versions") or {}
    out.append("<h3>Software</h3>\n" + _table(["Package", "Version"], sorted(vers.items()), left=2))
    inputs = man.get("inputs") or {}
    if inputs:
        out.append("<h3>Inputs</h3>\n" + _table(
            ["Input", "Path", "SHA-256"],
            [[k, v.get("path", ""), _Raw(f"<code>{_e(v.get('sha256', ''))}</code>")] for k, v in inputs.items()],
            left=3))
    cfg = man.get("config")
    if cfg is not None:
        text = yaml.safe_dump(cfg, sort_keys=False, allow_unicode=True, default_flow_style=False)
        out.append(f"<details><summary>Resolved configuration</summary>\n<pre>{_e(text)}</pre></details>\n")
    return "".join(out)


_SECTIONS = [("rig", "Rig and artefact"), ("timing", "Timing"), ("results", "Calibration results"),
             ("parameters", "Sensor parameters"), ("residuals", "Residuals"),
             ("verification", "Verification (ball-bar)"), ("truth", "Simulation truth"),
             ("provenance", "Provenance")]


def _rig_section(run: _Run) -> str:
    return ("<h3>Scanners</h3>\n" + _guard(_rig_part, run) + "<h3>Artefact</h3>\n" + _guard(_artefact_part, run)
            + "<h3>Acquisition</h3>\n" + _guard(_acquisition_part, run)
            + "<h3>Labelling and start values</h3>\n" + _guard(_processing_part, run))


def render_report(run_dir: Path, timings: dict | None = None, generated: str | None = None) -> str:
    """The report page of ``run_dir`` as an HTML string (see :func:`write_report`)."""
    run = _Run(Path(run_dir))
    if not any((run.root / n).is_file() for n in ("manifest.json", "summary.json", "bundle_summary.json",
                                                  "calibration.json")):
        raise FileNotFoundError(f"{run.root} is not a run directory: none of manifest.json, summary.json, "
                                f"bundle_summary.json, calibration.json is there")
    generated = generated or datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M:%S")
    bodies = {"rig": (_rig_section, run), "timing": (_timings, run, timings), "results": (_results, run),
              "parameters": (_parameters, run), "residuals": (_residuals, run),
              "verification": (_verification, run), "truth": (_truth, run), "provenance": (_provenance, run)}
    nav = "<nav>" + "".join(f'<a href="#{a}">{_e(t)}</a>' for a, t in _SECTIONS) + "</nav>\n"
    sections = "".join(_section(a, t, *bodies[a]) for a, t in _SECTIONS)
    name = run.config().get("name") or run.root.name
    from . import __version__

    return (f'<!DOCTYPE html>\n<html lang="en">\n<head>\n<meta charset="utf-8">\n'
            f"<title>Calibration report: {_e(name)}</title>\n<style>{_CSS}</style>\n</head>\n<body>\n"
            f"{_header(run, generated)}{nav}{sections}"
            f'<footer class="meta"><p>Written by fringecal {_e(__version__)} on {_e(generated)} UTC from the files '
            f"of the run directory {_e(run.root.name)}.</p></footer>\n</body>\n</html>\n")


def write_report(run_dir: Path, timings: dict | None = None) -> Path:
    """Write ``run_dir/report.html``: one self-contained page describing the run.

    Parameters
    ----------
    run_dir : the run directory (DESIGN.md storage); only files inside it are read
    timings : step name -> wall seconds of the run that produced it (``"total"`` is
        the whole run); without it the timings recorded in ``summary.json`` are shown

    Returns
    -------
    The path of the report, written atomically (temporary name, then rename).
    """
    path = RunDir(run_dir).report
    text = render_report(run_dir, timings)
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(text, encoding="utf-8")
    tmp.replace(path)
    return path
