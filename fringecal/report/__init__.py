"""The run report: one self-contained HTML page a metrologist can hand to a customer.

:func:`write_report` reads only files of the run directory, each through its
:class:`~fringecal.rundir.RunDir` accessor (the manifest, the artefact and ball-bar,
the acquisition, hexapod, labelling, link and DLT tables, the calibration, the
bundle summary, the residual tables and histograms, the cross-validation, the
verification, the acceptance test of VDI/VDE 2634 parts 2 and 3 and, for a simulated
run, the evaluation against the truth), and renders what is there: a missing
optional file (the evaluation of a run of a recorded data set, which has no truth;
the verification of a run without ball-bar recordings) gives its section a "not
available" note, a malformed one a "could not be shown" note naming the file and the
error; neither stops the page. When and by which command the run executed, and how
long its steps took, describe one execution rather than the run's results: they are
passed in (``execution``, ``timings``) or, when the page is rewritten later, taken
from the run's summary. The page is written atomically
(:meth:`fringecal.rundir.TextFile.save`).

The package is layered:

* :mod:`.rundata` reads the run directory (:class:`~.rundata.RunData`) and turns a
  missing or malformed file into a note (:func:`~.rundata.guard`);
* :mod:`.sections` builds each section's context from it (numbers written by
  :mod:`.formatting`, tables by :mod:`.tables`, plots by :mod:`.figures`);
* ``templates/`` holds the jinja2 templates, one per section under ``base.html.j2``,
  and the style sheet ``report.css`` (screen and print, A4), autoescaped so that every
  string read from a file is HTML-escaped; :mod:`.page` renders and writes the page.

Images are embedded as base64 PNG, the style sheet is inline, there is no
JavaScript.
"""

from fringecal.report.page import render_report, write_report
from fringecal.report.rundata import NO_TRUTH

__all__ = ["NO_TRUTH", "render_report", "write_report"]
