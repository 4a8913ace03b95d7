"""The report as a PDF: ``report.html`` printed to A4 by headless Chromium.

The page's print style sheet (``templates/report.css``) lays it out: the certificate
alone on page one, each scanner on pages of its own, numbered pages. Chromium is the
engine because it is what renders the page on screen too (a Python engine would draw
another layout from the same CSS and is one more dependency); it is looked up on
``PATH`` (:data:`CANDIDATES`) or taken from ``FRINGECAL_CHROMIUM``. Without it,
:class:`PdfEngineMissing` says what to install. Each call gets its own profile folder
and prints to a temporary file renamed into place, so a failed print leaves no
half-written PDF and runs beside any other Chromium.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import tempfile
from pathlib import Path

from fringecal.atomic import temporary_sibling

__all__ = ["CANDIDATES", "PdfError", "PdfEngineMissing", "find_chromium", "require_chromium", "print_pdf",
           "INSTALL_HINT"]

#: Executables tried on PATH, in order.
CANDIDATES = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")
#: What to do without Chromium.
INSTALL_HINT = ("install Chromium (Debian/Ubuntu: apt-get install chromium; elsewhere Chromium or Google Chrome) "
                "or set FRINGECAL_CHROMIUM to its executable; report.html can also be printed from any browser")
#: Chromium's switches for a headless print that touches nothing outside its profile folder.
SWITCHES = ("--headless", "--no-sandbox", "--disable-gpu", "--no-first-run", "--disable-background-networking",
            "--disable-component-update", "--disable-sync", "--no-pdf-header-footer")


class PdfError(RuntimeError):
    """Chromium ran but wrote no PDF."""


class PdfEngineMissing(PdfError):
    """No Chromium to print with; the message says what to install."""


def find_chromium() -> str | None:
    """The Chromium executable: ``FRINGECAL_CHROMIUM`` if set, else the first of
    :data:`CANDIDATES` on PATH; None when there is none."""
    given = os.environ.get("FRINGECAL_CHROMIUM")
    if given:
        return shutil.which(given) or (given if Path(given).is_file() else None)
    return next((p for p in map(shutil.which, CANDIDATES) if p), None)


def require_chromium() -> str:
    """:func:`find_chromium`, or :class:`PdfEngineMissing` saying what to install."""
    chromium = find_chromium()
    if chromium is None:
        where = f"FRINGECAL_CHROMIUM={os.environ['FRINGECAL_CHROMIUM']!r} is not an executable" \
            if os.environ.get("FRINGECAL_CHROMIUM") else f"none of {', '.join(CANDIDATES)} is on PATH"
        raise PdfEngineMissing(f"cannot write a PDF without headless Chromium ({where}): {INSTALL_HINT}")
    return chromium


def print_pdf(html: Path, out: Path, timeout_s: float = 180.0) -> Path:
    """Print the page ``html`` to the PDF ``out`` (A4, as its print style sheet says).

    Raises
    ------
    PdfEngineMissing
        No Chromium is found (nothing is written).
    PdfError
        Chromium failed or wrote no PDF (nothing is written).
    """
    chromium = require_chromium()
    out = Path(out)
    tmp = temporary_sibling(out)
    with tempfile.TemporaryDirectory(prefix="fringecal-chromium-") as profile:
        cmd = [chromium, *SWITCHES, f"--user-data-dir={profile}", f"--print-to-pdf={tmp}",
               Path(html).resolve().as_uri()]
        try:
            res = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s, check=False)
        except subprocess.TimeoutExpired:
            tmp.unlink(missing_ok=True)
            raise PdfError(f"{chromium} did not finish printing {html} within {timeout_s:g} s") from None
    if res.returncode != 0 or not tmp.is_file() or not tmp.read_bytes()[:5] == b"%PDF-":
        tmp.unlink(missing_ok=True)
        tail = (res.stderr or res.stdout or "").strip().splitlines()[-3:]
        raise PdfError(f"{chromium} wrote no PDF of {html} (exit status {res.returncode}"
                       + (f": {' / '.join(tail)}" if tail else "") + ")")
    tmp.replace(out)
    return out
