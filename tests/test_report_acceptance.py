"""The report's acceptance section (VDI/VDE 2634 parts 2 and 3): the certificate
table, the decision under ISO 14253-1, the positions figure and the raw values.

The run directory is minimal: a hand-made two-scanner calibration (its pinholes are
the truth of the figure's markers), the objects' certificates and an
``acceptance.json`` made by :func:`fringecal.acceptance.evaluate.certificate` from
values chosen here, so every number and verdict on the page is known beforehand.
"""

import base64
import html
import re
from html.parser import HTMLParser

import numpy as np
import pandas as pd
import pytest

from fringecal.acceptance.evaluate import VALUE_COLUMNS, certificate
from fringecal.acceptance.standards import AcceptanceLimits, AcceptanceStandards
from fringecal.report import figures, render_report, write_report
from fringecal.report.sections.certificate import observed_line
from fringecal.report.sections.placements import placement
from fringecal.rig import Rig, Scanner
from fringecal.rundir import RunDir
from fringecal.sensor import Sensor, SensorFormat
from fringecal.steps.report import report_inputs

TITLE = "Acceptance test (VDI/VDE 2634 parts 2 and 3)"
PINHOLES = {"scanner1": (700.0, -210.0, 2590.0), "scanner2": (-710.0, -220.0, 2700.0)}
STANDARDS = AcceptanceStandards(sphere={"diameter_mm": 127.0},
                                dumbbell={"length_mm": 500.0, "diameter_mm": 50.8},
                                flat={"length_mm": 700.0, "width_mm": 120.0})
NAN = float("nan")

#: (test, parameter, position, scanner, value_mm, U_mm, n_points, n_excluded)
VALUES = [("sphere", "P_F", "sphere-1-01", "scanner1", 0.120, 0.0023, 5000, 15),
          ("sphere", "P_S", "sphere-1-01", "scanner1", 0.030, 0.004, 5000, 15),
          ("sphere", "P_F", "sphere-1-02", "scanner1", 0.150, 0.0023, 4000, 12),
          ("sphere", "P_S", "sphere-1-02", "scanner1", -0.045, 0.004, 4000, 12),
          ("dumbbell", "SD", "dumbbell-1-01", "scanner1", 0.020, 0.030, 0, 0),
          ("dumbbell", "SD", "dumbbell-1-02", "scanner1", -0.050, 0.030, 0, 0),
          ("flat", "F", "flat-1-01", "scanner1", 0.210, 0.004, 9000, 27),
          ("ballbar", "E", "bb01", "cell", 0.030, 0.020, 0, 0),
          ("ballbar", "E", "bb02", "cell", -0.040, NAN, 0, 0)]  # no budget: U unknown

#: The certificate table as the page must show it, given VALUES and the default limits.
EXPECTED = [["P_F probing error form", "scanner1", "2", "150.0 µm", "500.0 µm", "2.3 µm", "conformance"],
            ["P_S probing error size", "scanner1", "2", "-45.0 µm", "100.0 µm", "4.0 µm", "conformance"],
            ["SD sphere-spacing error", "scanner1", "2", "-50.0 µm", "100.0 µm", "30.0 µm", "conformance"],
            ["E length measurement error", "cell", "2", "-40.0 µm", "100.0 µm", "n/a", "uncertainty zone"],
            ["F flatness measurement error", "scanner1", "1", "210.0 µm", "500.0 µm", "4.0 µm", "conformance"]]

#: T_world_<object> of the three placed objects (kappa = pi/2 turns local x onto world y).
POSITIONS = [{"measurement": "sphere-1-01", "test": "sphere", "scanner": "scanner1", "tx_mm": 100.0, "ty_mm": 50.0,
              "tz_mm": -300.0, "omega_rad": 0.0, "phi_rad": 0.0, "kappa_rad": 0.0},
             {"measurement": "dumbbell-1-01", "test": "dumbbell", "scanner": "scanner1", "tx_mm": 100.0,
              "ty_mm": -50.0, "tz_mm": -400.0, "omega_rad": 0.0, "phi_rad": 0.0, "kappa_rad": np.pi / 2},
             {"measurement": "flat-1-01", "test": "flat", "scanner": "scanner1", "tx_mm": 0.0, "ty_mm": 0.0,
              "tz_mm": -500.0, "omega_rad": 0.0, "phi_rad": 0.0, "kappa_rad": 0.0}]


def _rig() -> Rig:
    def sensor(name, role, pinhole):
        return Sensor(name, role, SensorFormat(1400, 1050, 19.0, 14.3),
                      [*pinhole, -3.04, -0.26, 3.14, 0.0, 0.0, 50.0, 0, 0, 0, 0, 0])

    return Rig(tuple(Scanner(n, sensor(f"C{i}", "camera", p), sensor(f"P{i}", "projector", np.add(p, (-900, 0, 50))))
                     for i, (n, p) in enumerate(PINHOLES.items(), start=1)), "scanner1")


def _doc(values=VALUES, limits=None, failures=None, positions=POSITIONS) -> dict:
    table = pd.DataFrame(values, columns=VALUE_COLUMNS)
    return certificate(table, limits or AcceptanceLimits(), 2.0, 0.003, list(PINHOLES), failures, positions)


@pytest.fixture
def rd(tmp_path):
    rd = RunDir(tmp_path / "run").create()
    rd.calibration.save(_rig())
    rd.acceptance_standards.save(STANDARDS.model_dump(mode="json"))
    return rd


def _section(page: str) -> str:
    m = re.search(r'<section id="acceptance">(.*?)</section>', page, re.S)
    assert m
    return m.group(1)


def _page(rd: RunDir, doc: dict | None) -> str:
    if doc is not None:
        rd.acceptance.save(doc)
    return render_report(rd, generated="2026-01-02 03:04:05")


def _rows(html_: str) -> list[list[str]]:
    """The cells (text) of the first table's body rows."""
    table = html_.split("<table>", 1)[1].split("</table>", 1)[0]
    return [[re.sub(r"<[^>]+>", "", c) for c in re.findall(r"<td[^>]*>(.*?)</td>", r, re.S)]
            for r in re.findall(r"<tr>(<td.*?)</tr>", table, re.S)]


class _Nesting(HTMLParser):
    VOID = {"meta", "img", "br", "hr", "link", "input", "wbr"}

    def __init__(self):
        super().__init__()
        self.stack, self.errors = [], []

    def handle_starttag(self, tag, attrs):
        if tag not in self.VOID:
            self.stack.append(tag)

    def handle_endtag(self, tag):
        if not self.stack or self.stack[-1] != tag:
            self.errors.append(tag)
        else:
            self.stack.pop()


def test_certificate_table_shows_each_parameter(rd):
    page = _page(rd, _doc())
    assert page.index('id="verification"') < page.index('id="acceptance"') < page.index('id="truth"')
    assert f'<a href="#acceptance">{TITLE}</a>' in page and f"<h2>{TITLE}</h2>" in page
    section = _section(page)
    assert _rows(section) == EXPECTED
    assert "<th>U (k = 2)</th>" in section
    assert section.count('<td class="pass">conformance</td>') == 4
    assert section.count('<td class="warn">uncertainty zone</td>') == 1
    # E's U is unknown at bb02: conformance not proven, though every value is within its MPE
    assert '<span class="badge fail">NOT ACCEPTED</span> under ISO 14253-1' in section
    assert "conformance not proven for E (cell): uncertainty zone" in section
    assert "coverage factor k = 2; 0.3 % of the points" in section
    assert "The simple comparison (every value within its MPE, uncertainty not considered) would accept" in section
    assert "Could not be shown" not in page
    nesting = _Nesting()
    nesting.feed(page)
    assert nesting.errors == [] and nesting.stack == []


def test_accepted_cell_has_no_simple_comparison_note(rd):
    values = [v if v[2] != "bb02" else (*v[:5], 0.020, 0, 0) for v in VALUES]
    doc = _doc(values)
    assert doc["accepted"] and doc["within_mpe"]
    section = _section(_page(rd, doc))
    assert '<span class="badge pass">ACCEPTED</span>' in section and "NOT ACCEPTED" not in section
    assert "conformance proven for every limited parameter" in section
    assert "simple comparison" not in section
    assert section.count('<td class="pass">conformance</td>') == 5


def test_non_conformance_is_marked(rd):
    # P_S at sphere-1-02: |0.130| - 0.004 > 0.1 mm, proven outside its MPE; F is not limited
    values = [v if (v[1], v[2]) != ("P_S", "sphere-1-02") else (*v[:4], 0.130, *v[5:]) for v in VALUES]
    doc = _doc(values, AcceptanceLimits(F=None))
    assert not doc["accepted"] and not doc["within_mpe"]
    section = _section(_page(rd, doc))
    rows = {r[0]: r for r in _rows(section)}
    assert rows["P_S probing error size"][3:] == ["130.0 µm", "100.0 µm", "4.0 µm", "non-conformance"]
    assert rows["F flatness measurement error"][3:] == ["210.0 µm", "not limited", "4.0 µm", "not limited"]
    assert section.count('<td class="fail">non-conformance</td>') == 1
    assert '<span class="badge fail">NOT ACCEPTED</span>' in section
    assert "P_S (scanner1): non-conformance, E (cell): uncertainty zone" in section
    assert "simple comparison" not in section  # it does not accept the cell either


def test_uncertainty_given_as_null_is_shown_as_not_available(rd):
    doc = _doc()
    for entry in doc["parameters"] + doc["values"]:
        entry["U_mm"] = None
    section = _section(_page(rd, doc))
    assert [r[5] for r in _rows(section)] == ["n/a"] * len(EXPECTED)
    values = _rows(section.split("<h3>Values per position</h3>")[1])
    assert [r[5] for r in values] == ["n/a"] * len(VALUES)
    assert "Could not be shown" not in section


def test_raw_values_per_position(rd):
    section = _section(_page(rd, _doc()))
    rows = _rows(section.split("<h3>Values per position</h3>")[1])
    assert rows[0] == ["sphere", "P_F", "sphere-1-01", "scanner1", "120.0 µm", "2.3 µm", "5000", "15"]
    assert rows[5] == ["dumbbell", "SD", "dumbbell-1-02", "scanner1", "-50.0 µm", "30.0 µm", "–", "–"]
    assert rows[8] == ["ballbar", "E", "bb02", "cell", "-40.0 µm", "n/a", "–", "–"]
    assert [r[2] for r in rows] == [v[2] for v in VALUES]


def test_figure_is_embedded_with_the_positions_and_pinholes(rd, monkeypatch):
    bar = pd.DataFrame([{"position": "bb01", "scanner": s, "sphere_id": sid, "x_mm": x + d, "y_mm": 0.0,
                         "z_mm": -200.0} for s, d in (("scanner1", -0.1), ("scanner2", 0.1))
                        for sid, x in (("A", -400.0), ("B", 600.0))])
    rd.ballbar_centres.save(bar)
    drawn = {}
    real = figures.acceptance_png

    def spy(shapes, pinholes, bars):
        drawn.update(shapes=shapes, pinholes=pinholes, bars=bars)
        return real(shapes, pinholes, bars)

    monkeypatch.setattr(figures, "acceptance_png", spy)
    section = _section(_page(rd, _doc()))
    images = re.findall(r'src="data:image/png;base64,([^"]+)"', section)
    assert len(images) == 1 and base64.b64decode(images[0]).startswith(b"\x89PNG")
    assert "3 positions as placed" in section and "reference scanner scanner1" in section
    assert [(n, tuple(p)) for n, p, _ in drawn["pinholes"]] == list(PINHOLES.items())
    assert len(drawn["bars"]) == 1
    np.testing.assert_allclose(drawn["bars"][0], [[-400.0, 0.0, -200.0], [600.0, 0.0, -200.0]], atol=1e-9)
    assert [s["test"] for s in drawn["shapes"]] == ["sphere", "dumbbell", "flat"]


def test_objects_are_placed_by_their_frames():
    standards = STANDARDS.model_dump(mode="json")
    sphere, bell, flat = (placement(p, standards) for p in POSITIONS)
    assert sphere["radius"] == 63.5
    np.testing.assert_allclose(sphere["points"], [[100.0, 50.0, -300.0]])
    # sphere A at the origin, B at (500, 0, 0) of a frame turned by kappa = 90 deg
    np.testing.assert_allclose(bell["points"], [[100.0, -50.0, -400.0], [100.0, 450.0, -400.0]], atol=1e-9)
    np.testing.assert_allclose(flat["points"][:4], [[-350.0, -60.0, -500.0], [350.0, -60.0, -500.0],
                                                    [350.0, 60.0, -500.0], [-350.0, 60.0, -500.0]])
    unknown = placement(POSITIONS[1], {})  # no certificate: the frame's origin only
    np.testing.assert_allclose(unknown["points"], [[100.0, -50.0, -400.0]])


def test_a_data_set_without_positions_gets_a_note(rd):
    section = _section(_page(rd, _doc(positions=[])))
    assert "data:image/png" not in section
    assert f"No positions to draw: {rd.acceptance.rel} states no placements of the objects" in section
    assert _rows(section) == EXPECTED  # the certificate is still shown


def test_failures_are_listed_as_warnings(rd):
    failures = [{"test": "flat", "position": "flat-1-02", "scanner": "scanner1", "reason": "too few points"},
                {"test": "sphere", "position": "sphere-1-03", "scanner": "scanner1", "reason": "<b>no fit</b>"}]
    section = _section(_page(rd, _doc(failures=failures)))
    assert "<h3>Positions not measured (2)</h3>" in section
    assert '<p class="warn">flat position flat-1-02, scanner scanner1: too few points</p>' in section
    assert "sphere position sphere-1-03, scanner scanner1: &lt;b&gt;no fit&lt;/b&gt;" in section


def test_a_run_without_acceptance_test_gets_a_note(rd):
    page = write_report(rd).read_text(encoding="utf-8")
    section = _section(page)
    assert f"No acceptance test in this run ({rd.acceptance.rel} is not in the run directory)." in section
    assert "Could not be shown" not in section


def test_a_malformed_acceptance_file_is_named(rd):
    rd.acceptance.path.write_text('{"parameters": ')
    section = _section(_page(rd, None))
    assert "Could not be shown" in section and rd.acceptance.rel in section


def test_the_report_step_reads_the_acceptance_files(rd):
    rels = {f.rel for f in report_inputs(rd)}
    assert {rd.acceptance.rel, rd.acceptance_standards.rel, rd.ballbar_centres.rel} <= rels


def test_a_black_box_s_transform_and_acceptance_rows_are_shown(rd):
    """A black box (``black_boxes.json``): its origin, angles and scale with their u
    and its 4x4 under Scanners, with its acceptance values; its certificate rows beside
    the modelled scanners', marked."""
    from fringecal.calibration.blackbox import BlackBoxScanner

    cov = np.diag([0.09**2, 0.08**2, 0.43**2, 2e-4**2, 2.5e-4**2, 1.3e-5**2, 3e-5**2])
    box = BlackBoxScanner("box", np.array([1385.21, 7.795, 252.48, 0.001, -0.002, 0.0064, 1.0002]), cov, 0.0305, 48)
    rd.black_boxes.save({"reference": "scanner1", "scale": True, "scanners": [box.to_dict()]})
    values = VALUES + [("sphere", "P_S", "sphere-2-01", "box", 0.058, 0.056, 4000, 12),
                       ("dumbbell", "SD", "dumbbell-2-01", "box", 0.020, 0.055, 0, 0)]
    doc = _doc(values)
    doc["black_boxes"] = ["box"]
    page = _page(rd, doc)
    rows = _rows(_section(page))
    assert rows[2] == ["P_S probing error size", "box (black box)", "1", "58.0 µm", "100.0 µm", "56.0 µm",
                       "uncertainty zone"]  # 58 + 56 um > 100 um, judged as a modelled scanner's
    assert rows[4] == ["SD sphere-spacing error", "box (black box)", "1", "20.0 µm", "100.0 µm", "55.0 µm",
                       "conformance"]
    part = re.search(r"<h3>Black-box scanner box</h3>(.*?)<h3>Strongest", page, re.S).group(1)
    assert "1385.210 ± 0.090" in part and "1.000200 ± 0.000030" in part and "48 sphere centres lie 30.5 µm RMS" in part
    assert f"{box.matrix()[0, 3]:.9g}" in part and f"{box.matrix()[0, 0]:.9g}" in part
    assert "Depths (its frame&#39;s z)" in part and "20.0 µm" in part and "Could not be shown" not in page
    assert rd.black_boxes.rel in {f.rel for f in report_inputs(rd)}


def _certificate_page(page: str) -> str:
    m = re.search(r'<header id="certificate".*?</header>', page, re.S)
    assert m
    return html.unescape(re.sub(r"<[^>]+>", "", m.group(0)))


def test_the_certificate_counts_the_objects_outside_the_observed_region(rd):
    """Per test, the positions partly outside the observed region, the wholly outside
    among them and the largest share, as ``acceptance.json``'s ``observed_region``
    states them (the summary's counts, :func:`fringecal.acceptance.observed.outside_counts`);
    a calibration without regions: "not known", never 0."""
    def obj(test, position, points, outside):
        return {"test": test, "position": position, "points": points, "outside": outside,
                "fraction": None if outside is None else outside / points, "scanners": {}}

    doc = _doc()
    doc["observed_region"] = {"known": True, "objects": [
        obj("sphere", "sphere-1-01", 400, 400), obj("sphere", "sphere-1-02", 500, 60),
        obj("flat", "flat-1-01", 900, 0), obj("dumbbell", "dumbbell-1-01", 300, 0),
        obj("dumbbell", "dumbbell-1-02", 300, 0), obj("ballbar", "bb01", 200, 30), obj("ballbar", "bb02", 100, 100)]}
    page = _certificate_page(_page(rd, doc))
    assert ("Observed region: positions measured partly outside the region of the images the calibration observed, "
            "where its model extrapolates (share of their fits' pixels): spheres 2 of 2 positions (1 wholly, up to "
            "100 %); flats 0 of 1 position; dumbbells 0 of 2 positions; ball-bar (E) 2 of 2 positions (1 wholly, "
            "up to 100 %).") in page
    for o in doc["observed_region"]["objects"]:
        o.update(outside=None, fraction=None)
    doc["observed_region"]["known"] = False
    assert observed_line(doc) == ("not known: the calibration records no region of its images (spheres: 2 "
                                  "positions, flats: 1 position, dumbbells: 2 positions, ball-bar (E): 2 positions)")
    del doc["observed_region"]  # an acceptance.json from before the regions: not known either
    assert observed_line(doc).startswith("not known: acceptance.json does not count them")
    assert observed_line(None) is None  # no acceptance test: no line
