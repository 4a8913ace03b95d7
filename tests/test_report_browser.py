"""report.html in a real browser: headless Chromium loads it without console messages,
its in-page links and embedded PNGs hold in the DOM it parsed, and it prints to a
multi-page A4 PDF.

Skipped when ``chromium`` is not on PATH (Debian: ``apt-get install chromium``). The
run directory is the small one of tests/test_report.py (a real bundle adjustment of
simulated thesis control points); each Chromium call gets its own profile folder,
so the test runs beside any other Chromium on the machine.
"""

import base64
import re
import shutil
import struct
import subprocess

import pytest
from test_report import TIMINGS, base_run  # noqa: F401  (the module-scoped run fixture)

from fringecal.report import write_report

CHROMIUM = shutil.which("chromium")
pytestmark = pytest.mark.skipif(CHROMIUM is None, reason="chromium is not on PATH (apt-get install chromium)")

#: A4 in PostScript points (210 x 297 mm), as Chromium writes the MediaBox.
A4_PT = (595.0, 842.0)


def _chromium(tmp_path, *args: str) -> subprocess.CompletedProcess:
    """Run headless Chromium with its own profile; stdout and stderr as text."""
    cmd = [CHROMIUM, "--headless", "--disable-gpu", "--no-sandbox", "--no-first-run",
           f"--user-data-dir={tmp_path / 'chromium-profile'}", *args]
    res = subprocess.run(cmd, check=False, capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr[-2000:]
    return res


def _console(stderr: str) -> list[str]:
    """The page's console messages among Chromium's own log lines."""
    return [line for line in stderr.splitlines() if ":CONSOLE" in line]


def _dom(tmp_path, url: str) -> tuple[str, list[str]]:
    """The DOM Chromium built from ``url`` and the console messages of loading it."""
    res = _chromium(tmp_path, "--enable-logging=stderr", "--v=0", "--dump-dom", url)
    return res.stdout, _console(res.stderr)


def _png_size(data: bytes) -> tuple[int, int]:
    """Width and height from a PNG's signature and IHDR chunk."""
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and data[12:16] == b"IHDR"
    return struct.unpack(">II", data[16:24])


@pytest.fixture(scope="module")
def report(base_run):  # noqa: F811
    return write_report(base_run, TIMINGS)


def test_the_console_check_sees_messages(tmp_path):
    """The check below is not vacuous: a page that logs and fails is caught."""
    bad = tmp_path / "bad.html"
    bad.write_text('<!DOCTYPE html><p>x</p><script>console.error("logged"); notDefined();</script>')
    _, console = _dom(tmp_path, bad.as_uri())
    assert any('"logged"' in m for m in console) and any("ReferenceError" in m for m in console)


def test_page_loads_without_console_messages_and_its_links_and_images_hold(report, tmp_path):
    dom, console = _dom(tmp_path, report.as_uri())
    assert console == []
    ids = re.findall(r'\bid="([^"]+)"', dom)
    assert ids[:10] == ["rig", "timing", "results", "parameters", "residuals", "crossval", "verification",
                        "acceptance", "truth", "provenance"]
    targets = re.findall(r'\bhref="#([^"]*)"', dom)
    assert len(targets) == 10 and set(targets) <= set(ids)
    assert not re.findall(r'\bhref="(?!#)', dom)
    images = re.findall(r'<img [^>]*src="data:image/png;base64,([^"]+)"', dom)
    assert len(images) == 3  # two histograms and the ball-bar plot
    for encoded in images:
        width, height = _png_size(base64.b64decode(encoded, validate=True))
        assert width >= 400 and height >= 200
    assert len(re.findall(r"<img\b", dom)) == 3


def test_page_prints_to_a_multi_page_a4_pdf(report, tmp_path):
    pdf = tmp_path / "report.pdf"
    _chromium(tmp_path, f"--print-to-pdf={pdf}", "--no-pdf-header-footer", report.as_uri())
    data = pdf.read_bytes()
    assert data.startswith(b"%PDF-")
    pages = re.findall(rb"/Type\s*/Page(?![a-zA-Z])", data)
    assert len(pages) > 1
    boxes = {tuple(round(float(v)) for v in m.split()[2:]) for m in
             re.findall(rb"/MediaBox\s*\[([^\]]*)\]", data)}
    assert boxes == {A4_PT}
