"""The documentation site: ``mkdocs build --strict`` passes, every page of the nav is
built, the validation page is generated from ``benchmarks/results/*.json``, the
contracts page lists the columns of every table model of ``schemas/tables.py``, and
every ``fringecal`` command and option on the user-facing pages exists."""

from __future__ import annotations

import inspect
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from docs_hooks import benchmark_summary as bs

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"


def _load(name: str) -> dict:
    return json.loads((RESULTS / name).read_text())


def _rows(summary) -> dict[str, str]:
    return {r.path: r.value for r in summary.rows}


def test_measure_summary_reads_the_file():
    doc = _load("measure.json")
    s = bs.summarise(RESULTS / "measure.json")
    rows = _rows(s)
    assert (s.benchmark, s.script, s.command) == ("measure", "benchmarks/measure.py", doc["command"])
    assert (s.date, s.date_source) == (doc["conditions"]["date"], "recorded") == ("2026-11-27T06:14:43+00:00",
                                                                                   "recorded")
    assert rows["median_wall_s"] == f"{doc['median_wall_s']:.4g}" == "9.204"
    assert rows["points"] == f"{doc['points']:,}" == "1,619,964"
    assert rows["walls_s"] == ", ".join(f"{w:.4g}" for w in doc["walls_s"])
    assert rows["runs.0.phases_s.triangulate"] == f"{doc['runs'][0]['phases_s']['triangulate']:.4g}"
    assert "2 CPUs" in s.machine and f"{doc['conditions']['load_average_start'][0]:.2f}" in s.machine
    assert s.timed_command == doc["timed_command"]
    assert s.records == ["`runs` (3 items)"]


def test_coverage_summary_reads_the_file():
    doc = _load("coverage_realistic.json")
    s = bs.summarise(RESULTS / "coverage_realistic.json")
    rows = _rows(s)
    assert rows["summary.coverage"] == f"{doc['summary']['coverage']:.4g}" == "0.9533"
    assert rows["summary.n_lengths"] == str(doc["summary"]["n_lengths"]) == "150"
    assert doc["summary"]["seeds_failed"] == [] and doc["summary"]["credible"] is True
    assert s.outside == []  # inside 0.93-0.97: nothing to explain
    assert rows["summary.rms_z"] == f"{doc['summary']['rms_z']:.4g}"
    assert (s.date, s.date_source) == (doc["conditions"]["date"], "recorded")
    assert s.script == "benchmarks/length_coverage.py" and s.command == doc["command"]
    assert len(s.rows) <= bs.MAX_ROWS and "seeds" not in rows


def test_coverage_summary_of_an_old_file_says_what_it_lacks(tmp_path):
    """The realistic coverage JSON of 2026-11-23 (before the bootstrap bias correction,
    kept in tests/data): no date, the script's old name, another output file, a rerun."""
    results = tmp_path / "benchmarks" / "results"
    results.mkdir(parents=True)
    (results.parent / "length_coverage.py").write_text((ROOT / "benchmarks" / "length_coverage.py").read_text())
    path = results / "coverage_realistic.json"
    path.write_text((Path(__file__).parent / "data" / "coverage_realistic_2026-11-23.json").read_text())
    s = bs.summarise(path)
    rows = _rows(s)
    assert rows["summary.coverage"] == "0.9116" and rows["summary.credible"] == "no"
    assert s.date_source == "file modified"
    assert s.script == "benchmarks/length_coverage.py"
    assert any("benchmarks/coverage.py" in n and "length_coverage.py" in n for n in s.notes)
    assert any("/tmp/cov8/coverage_realistic.json" in n for n in s.notes)
    assert any(n.startswith("Partly rerun (seeds 1, 14, 20") for n in s.notes)


def test_unknown_benchmark_falls_back_to_json_paths(tmp_path):
    results = tmp_path / "benchmarks" / "results"
    results.mkdir(parents=True)
    doc = {"benchmark": "new_one", "median_s": 0.4123456, "phases": {"read_s": 0.11, "deep": {"x_mm": 12345.6}},
           "label": "short", "runs": [{"s": 1}, {"s": 2}], "load_average_start": [1.0, 2.0, 3.0],
           "extra": {f"v{i}": float(i) for i in range(2 * bs.MAX_ROWS)}}
    (results / "new_one.json").write_text(json.dumps(doc))
    (tmp_path / "benchmarks" / "new_one.py").write_text('doc = {"benchmark": "new_one"}\n')
    s = bs.summarise(results / "new_one.json")
    rows = _rows(s)
    assert s.script == "benchmarks/new_one.py" and s.command is None
    assert rows["median_s"] == "0.4123" and rows["phases.read_s"] == "0.11"
    assert rows["phases.deep.x_mm"] == "12,346" and rows["label"] == "short"
    assert s.records == ["`runs` (2 items)"] and "load_average_start" not in rows
    assert len(s.rows) == bs.MAX_ROWS and s.omitted == len(doc["extra"]) + 4 - bs.MAX_ROWS
    text = bs.page([s])
    assert "| phases.deep.x_mm | 12,346 | `phases.deep.x_mm` |" in text
    assert f"{s.omitted} more figures are in the file." in text


def _nav_pages(nav) -> list[str]:
    out = []
    for item in nav:
        value = next(iter(item.values())) if isinstance(item, dict) else item
        out += _nav_pages(value) if isinstance(value, list) else [value]
    return out


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    out = tmp_path_factory.mktemp("site")
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1"}
    proc = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(out)],
                          cwd=ROOT, capture_output=True, text=True, env=env, timeout=120, check=False)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    return out


def test_every_nav_page_is_built(site):
    nav = yaml.safe_load((ROOT / "mkdocs.yml").read_text())["nav"]
    pages = _nav_pages(nav)
    assert {"index.md", "guide.md", "contracts.md", "validation.md"} <= set(pages)
    on_disk = {p.name for p in (ROOT / "docs").glob("*.md")}
    assert on_disk <= set(pages), f"pages missing from the nav: {on_disk - set(pages)}"
    for page in pages:
        html = site / ("index.html" if page == "index.md" else f"{page[:-3]}/index.html")
        assert html.is_file(), page


def test_validation_page_shows_the_benchmarks(site):
    html = (site / "validation" / "index.html").read_text()
    measure = _load("measure.json")
    coverage = _load("coverage_ideal.json")
    assert measure["conditions"]["date"] in html
    assert f"{measure['median_wall_s']:.4g}" in html and f"{measure['points']:,}" in html
    assert f"{coverage['summary']['coverage']:.4g}" in html  # 0.9467
    for path in sorted(RESULTS.glob("*.json")):  # one section per file, e.g. id="measurejson"
        anchor = re.sub(r"[^\w-]", "", path.name.lower())
        assert f'id="{anchor}"' in html, path.name


def test_every_figure_outside_its_credible_range_says_why(site, tmp_path):
    """Item of the validation page: a coverage outside 0.93-0.97 carries its file's one-line
    why, on the page and in the overview; a file without one is caught."""
    html = (site / "validation" / "index.html").read_text()
    for path in sorted(RESULTS.glob("*.json")):
        s = bs.summarise(path)
        assert s.unexplained == [], s.unexplained
        for line in s.outside:
            assert line.split(": ", 1)[1] != "not explained"
            assert html.count("outside its credible range") >= 1
    for name in ("coverage_4poses_ideal.json", "coverage_4poses_realistic.json"):  # 0.967, 0.944: inside
        assert bs.summarise(RESULTS / name).outside == [], name
    assert bs.summarise(RESULTS / "coverage_realistic.json").outside == []  # 0.966: inside
    ideal = bs.summarise(RESULTS / "coverage_ideal.json")  # 0.980: above, and says why
    assert ideal.outside == [f"summary.coverage 0.98 is outside its credible range 0.93-0.97: "
                             f"{_load('coverage_ideal.json')['credible_range_why']}"]
    bare = tmp_path / "results" / "c.json"
    bare.parent.mkdir()
    bare.write_text('{"benchmark": "coverage", "summary": {"coverage": 0.83, "credible_range": [0.93, 0.97]}}')
    s = bs.summarise(bare, tmp_path)
    assert s.unexplained == ["c.json: summary.coverage = 0.83 is outside its credible range 0.93-0.97 and the file "
                             "says no why (credible_range_why)"]
    assert "**outside its credible range**" in bs.page([s])


def test_contracts_page_lists_every_table_model():
    from fringecal.schemas import tables

    models = {name: cls for name, cls in vars(tables).items()
              if inspect.isclass(cls) and issubclass(cls, tables._Base) and cls is not tables._Base
              and cls.__module__ == tables.__name__}

    def columns(cls) -> tuple[set, set]:
        cols = cls.to_schema().columns
        return {n for n, c in cols.items() if c.required}, {n for n, c in cols.items() if not c.required}

    text = (ROOT / "docs" / "contracts.md").read_text()
    sections = dict(re.findall(r"^### `(\w+)`\n(.*?)(?=^#|\Z)", text, flags=re.MULTILINE | re.DOTALL))
    assert set(sections) == set(models)
    for name, body in sections.items():
        line = next(ln for ln in body.splitlines() if ln.startswith("Columns: "))
        parent = re.match(r"Columns: all of \[`(\w+)`\]\(#\w+\), plus ", line)
        required, _, optional = line.removeprefix(parent.group(0) if parent else "Columns: ").partition("; optional: ")
        # a column set by a pattern (a regex field) is written as its pattern
        stated = set(re.findall(r"`([\w\\+]+)`", required)), set(re.findall(r"`([\w\\+]+)`", optional))
        if parent:
            assert issubclass(models[name], models[parent.group(1)]), name
            base = columns(models[parent.group(1)])
            stated = stated[0] | base[0], stated[1] | base[1]
        assert stated == columns(models[name]), name


def test_summary_module_doctests():
    import doctest

    assert doctest.testmod(bs).failed == 0


def _command_segments(text: str) -> list[str]:
    """Every ``fringecal ...`` command in fenced blocks and inline code of a page."""
    blocks = re.findall(r"^```[^\n]*\n(.*?)^```", text, flags=re.MULTILINE | re.DOTALL)
    rest = re.sub(r"^```[^\n]*\n.*?^```", "", text, flags=re.MULTILINE | re.DOTALL)
    lines = [ln for b in blocks for ln in b.replace("\\\n", " ").splitlines()]
    spans = [s.replace("\n", " ") for s in re.findall(r"`([^`]+)`", rest)]
    found = (re.match(r"\s*(fringecal\b[^#;]*)", seg) for seg in lines + spans)
    return [m.group(1) for m in found if m]


@pytest.mark.parametrize("page", ["guide.md", "contracts.md", "index.md"])
def test_commands_on_the_user_pages_exist(page):
    import typer.main

    from fringecal.flows.cli import app

    root = typer.main.get_command(app)
    segments = _command_segments((ROOT / "docs" / page).read_text())
    assert segments, page
    for seg in segments:
        tokens = seg.split()[1:]
        commands = [root]
        while tokens and hasattr(commands[0], "commands") and re.fullmatch(r"[a-z-]+(\|[a-z-]+)*", tokens[0]):
            names = tokens.pop(0).split("|")  # `fit sphere|plane`
            assert all(n in commands[0].commands for n in names), f"{page}: {seg!r}"
            commands = [commands[0].commands[n] for n in names]
        for option in (t.split("=")[0] for t in tokens if t.startswith("--")):
            for command in commands:
                options = {o for p in command.params for o in p.opts + p.secondary_opts} | {"--help"}
                assert option in options, f"{page}: {seg!r}"
