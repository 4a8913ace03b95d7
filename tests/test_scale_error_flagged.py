"""A scale error of the artefact never passes silently.

The small simulated thesis rig (``write_small_thesis_config``: 4 poses, 320 px) with
ball-bar positions 1 and 9 of table 6-9, rendered without camera noise, once as its table and once with the
rendered artefact 50 ppm larger than its table (a 21 C artefact whose table is at 20 C,
expanding by 50e-6 /K: an artefact measured warm, or a wrong CMM scale). The
calibration takes its scale from the table, so the ball-bar comes out short by
50 ppm of its 1015.65 mm (50.8 um) against the same run unscaled; the budget (table u
factor 0: the simulated artefact is its table except for the scale) does not hold that
error, the lengths are flagged as not covered and the report says so.

Position 4 is left out: at 320 px without noise its sphere A is fitted from 124 points
and the length comes out 15 um short in the unscaled run, twice its noise-only U of
7.5 um: a fit bias of a small sphere image that the budget rightly flags as not
covered, which would blur the contrast this test is about.
"""

from __future__ import annotations

import shutil

import pytest

from fringecal.report import render_report
from fringecal.run.config import load_run_config
from fringecal.run.summary import manifest
from fringecal.rundir import RunDir
from fringecal.simulate.small_thesis import write_small_thesis_config
from fringecal.steps import run_pipeline

pytestmark = pytest.mark.slow  # whole runs: the fast tier (-m "not slow") leaves this module out

SCALE = 50e-6

QUIET = {"simulate": {"acquisition": {"render": {"excess_noise": 0.0, "shot_noise": False, "read_noise_e": 0.0}}},
         "verification": {"uncertainty": {"artefact_u_factor": 0.0, "monte_carlo_draws": 0}}}


def _run(config, root, errors: dict, start: RunDir | None = None):
    cfg = load_run_config(config, overrides={**QUIET, "simulate": {**QUIET["simulate"], "errors": errors}})
    rd = RunDir(shutil.copytree(start.root, root, symlinks=True)) if start else RunDir(root).create()
    rd.manifest.save(manifest(cfg))
    run_pipeline(rd, cfg, workers=2, until="verify")
    return rd


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """The scaled run starts from a copy of the plain one: the artefact's scale keys the
    prepare step, whose as-built tables key what they change (the artefact's stores and
    everything after them, tests/test_simulation_errors.py), so the ball-bar's stores,
    which the scale does not touch, are reused instead of rendered again."""
    d = tmp_path_factory.mktemp("scale")
    config = write_small_thesis_config(d, positions=(1, 9))
    plain = _run(config, d / "plain", {})
    scaled = _run(config, d / "scaled", {"artefact_temperature_c": 21.0, "artefact_cte_per_c": SCALE}, start=plain)
    return plain, scaled


def test_a_50_ppm_artefact_scale_is_flagged_as_not_covered(runs):
    plain, scaled = runs
    p = {e["measurement"]: e for e in plain.verification.load()["uncertainty"]["lengths"]}
    s = scaled.verification.load()["uncertainty"]
    assert len(p) == len(s["lengths"]) == 2
    expected = -SCALE * 1015.65
    for e in s["lengths"]:
        shift = e["length_mm"] - p[e["measurement"]]["length_mm"]
        # same noise-free stores but for the scale: the shift is the scale error, to 15 %
        assert shift == pytest.approx(expected, rel=0.15)
        assert abs(e["error_mm"]) > e["U_mm"] and not e["covered"]
    assert sorted(s["not_covered"]) == sorted(p)
    html = render_report(scaled.root)
    assert "not covered by the budget" in html and "an error source the uncertainty budget does not hold" in html


def test_the_unscaled_run_is_covered(runs):
    plain, _ = runs
    u = plain.verification.load()["uncertainty"]
    assert u["not_covered"] == [] and all(abs(e["error_mm"]) <= e["U_mm"] for e in u["lengths"])
    assert "not covered by the budget" not in render_report(plain.root)
