"""The report page: the run directory's files read into each section's context and
rendered with the package's jinja2 templates (autoescaped), then written atomically."""

from __future__ import annotations

from datetime import datetime, timezone
from functools import lru_cache
from pathlib import Path

import jinja2

from fringecal import __version__
from fringecal.report.rundata import RunData, Shown, guard
from fringecal.report.sections import (
    SECTIONS,
    acceptance,
    certificate,
    crossval,
    provenance,
    residuals,
    results,
    rig,
    scanners,
    timing,
    truth,
    verification,
)
from fringecal.rundir import RunDir

__all__ = ["render_report", "write_report"]


@lru_cache(maxsize=1)
def environment() -> jinja2.Environment:
    """The templates of ``fringecal/report/templates``: every value HTML-escaped unless
    it is :class:`~markupsafe.Markup`, and an undefined name an error, not an empty string."""
    return jinja2.Environment(loader=jinja2.PackageLoader("fringecal.report", "templates"), autoescape=True,
                              undefined=jinja2.StrictUndefined, trim_blocks=True, lstrip_blocks=True,
                              keep_trailing_newline=True)


def _run_dir(run_dir) -> RunDir:
    return run_dir if isinstance(run_dir, RunDir) else RunDir(run_dir)


def _bodies(run: RunData, timings: dict | None, execution: dict, compile_seconds: dict | None) -> dict[str, Shown]:
    """Each section's context (or its note or warning), by anchor."""
    builders = {"rig": (rig.build,), "timing": (timing.build, timings, compile_seconds), "results": (results.build,),
                "scanners": (scanners.build,), "residuals": (residuals.build,), "crossval": (crossval.build,),
                "verification": (verification.build,), "acceptance": (acceptance.build,), "truth": (truth.build,),
                "provenance": (provenance.build, execution)}
    bodies = {}
    for s in SECTIONS:
        build, *args = builders[s.anchor]
        bodies[s.anchor] = guard(build, run, *args)
    return bodies


def render_report(run_dir, timings: dict | None = None, execution: dict | None = None,
                  generated: str | None = None, compile_seconds: dict | None = None) -> str:
    """The report page of ``run_dir`` (a :class:`~fringecal.rundir.RunDir` or a path)
    as an HTML string; see :func:`write_report`. ``generated`` (UTC) defaults to now."""
    rd = _run_dir(run_dir)
    markers = (rd.manifest, rd.summary, rd.bundle_summary, rd.calibration)
    if not any(f.path.is_file() for f in markers):
        raise FileNotFoundError(f"{rd.root} is not a run directory: none of "
                                f"{', '.join(f.rel for f in markers)} is there")

    run = RunData(rd)
    generated = generated or datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M:%S")
    execution = run.execution(execution)
    bodies = _bodies(run, timings, execution, compile_seconds)
    return environment().get_template("base.html.j2").render(
        name=run.name(), run_dir=run.root.name, version=__version__, generated=generated,
        certificate=certificate.build(run, generated, execution),
        sections=[(s, bodies[s.anchor]) for s in SECTIONS])


def write_report(run_dir, timings: dict | None = None, execution: dict | None = None,
                 compile_seconds: dict | None = None) -> Path:
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
    compile_seconds : step name -> seconds of those timings numba spent compiling
        kernels (a first run on the machine); without it, as the summary recorded

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
    return rd.report.save(render_report(rd, timings, execution, compile_seconds=compile_seconds))
