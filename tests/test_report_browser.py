"""report.html in a real browser: headless Chromium loads it without console messages,
its in-page links and embedded PNGs hold in the DOM it parsed, and ``fringecal report
--pdf`` prints it to a multi-page A4 PDF whose first page is the whole certificate.

Skipped when ``chromium`` is not on PATH (Debian: ``apt-get install chromium``); the
page-one test also needs ``pdftotext`` (Debian: ``apt-get install poppler-utils``) to
read the PDF's text per page. The run directory is the small one of
tests/test_report.py (a real bundle adjustment of simulated thesis control points)
with the identity block of its certificate test; each Chromium call gets its own
profile folder, so the test runs beside any other Chromium on the machine.
"""

import base64
import re
import shutil
import struct
import subprocess

import pytest
from test_report import IDENTITY, SCANNERS, TIMINGS, _config, _manifest, base_run  # noqa: F401  (module-scoped run)
from typer.testing import CliRunner

from fringecal.report import write_report
from fringecal.rundir import RunDir

CHROMIUM = shutil.which("chromium")
PDFTOTEXT = shutil.which("pdftotext")
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
def certified(base_run, tmp_path_factory):  # noqa: F811
    """The run with its certificate's identity block (a copy: the module's run stays as built)."""
    rd = RunDir(tmp_path_factory.mktemp("certified") / "run")
    shutil.copytree(base_run.root, rd.root)
    config = _config(simulate={"acquisition": {"camera_width_px": 512}}, certificate=IDENTITY)
    rd.manifest.save(_manifest(config, "simulated", {"configs/thesis/artefact_cmm2.csv": "ab" * 32}))
    return rd


@pytest.fixture(scope="module")
def report(certified):
    return write_report(certified, TIMINGS)


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
    assert ids[:11] == ["certificate", "rig", "timing", "results", "scanners", "residuals", "crossval",
                        "verification", "acceptance", "truth", "provenance"]
    targets = re.findall(r'\bhref="#([^"]*)"', dom)
    assert len(targets) == 10 and set(targets) <= set(ids)
    assert not re.findall(r'\bhref="(?!#)', dom)
    images = re.findall(r'<img [^>]*src="data:image/png;base64,([^"]+)"', dom)
    # histograms, ball-bar plot, each scanner's two maps and its observed regions
    assert len(images) == 3 + 3 * len(SCANNERS)
    for encoded in images:
        width, height = _png_size(base64.b64decode(encoded, validate=True))
        assert width >= 400 and height >= 200
    assert len(re.findall(r"<img\b", dom)) == len(images)


def _page_text(pdf, page: int) -> str:
    res = subprocess.run([PDFTOTEXT, "-f", str(page), "-l", str(page), "-layout", str(pdf), "-"],
                         capture_output=True, text=True, check=True, timeout=60)
    return re.sub(r"[ \t]+", " ", res.stdout)


@pytest.mark.skipif(PDFTOTEXT is None, reason="pdftotext is not on PATH (apt-get install poppler-utils)")
def test_report_pdf_page_one_is_the_whole_certificate(certified, tmp_path):
    """``fringecal report --pdf``: an A4 PDF of several pages; page one holds the identity
    fields, the verdict, the verdict table and the approval, and page two none of them."""
    from fringecal.flows.cli import app

    pdf = tmp_path / "certificate.pdf"
    res = CliRunner().invoke(app, ["report", "--run", str(certified.root), "--pdf", str(pdf)])
    assert res.exit_code == 0, res.output
    assert f"PDF written: {pdf}" in res.output.replace("\n", "")
    data = pdf.read_bytes()
    assert data.startswith(b"%PDF-") and not list(tmp_path.glob(".certificate.pdf.*"))
    pages = re.findall(rb"/Type\s*/Page(?![a-zA-Z])", data)
    assert len(pages) > 1
    boxes = {tuple(round(float(v)) for v in m.split()[2:]) for m in re.findall(rb"/MediaBox\s*\[([^\]]*)\]", data)}
    assert boxes == {A4_PT}
    one, two = _page_text(pdf, 1), _page_text(pdf, 2)
    number = re.search(r"Certificate No\. (FC-[0-9A-F]{4}-[0-9A-F]{4}-[0-9A-F]{4})", one)
    assert number and number.group(1) in certified.report.load()
    for field in ("Customer Acme Aero GmbH", "Cell hall 3, wing jig", "Place Bremen", "Operator R. Tarvaz",
                  "scanner1: serial FP-0042", "CMM-2026-117 (2026-10-02, PTB)", "air 20.4 °C"):
        assert field in one, field
    assert "Calibration certificate ACCEPTED" in one and "Verdict: ACCEPTED" in one
    assert re.search(r"Quality parameter scanner1 scanner2 MPE", one)
    assert re.search(r"ball-bar lengths of the.*47\.0 µm \(U 50\.0 µm\).*conformance, 9 pos\.",
                     one, re.S)
    assert "CMM certificate" in one and "Approved by" in one and "Name: Q. Manager" in one
    assert "page 1 of" in one
    assert "Rig and artefact" in two
    for item in ("Certificate No.", "Customer", "Quality parameter", "Approved by"):
        assert item not in two, item
