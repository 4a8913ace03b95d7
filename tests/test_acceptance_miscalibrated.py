"""A rig deliberately miscalibrated -- scanner 2's camera principal distance off by
0.05 % -- fails E and SD of the acceptance test, while the calibrated rig passes them.

The world: the thesis rig simulated as the default demo does (ideal profile, all
twelve poses, the default fringe sequence) at 640 px, ball-bar positions 1, 4 and 9 of
thesis table 6-9 and two dumbbell positions per scanner. At this size the calibrated
rig measures SD and E to 14-34 um with U of 45-47 um (measured 2026-11-26), so the
default limits of 100 um are met with their uncertainty (|value| + U at most 80 um); at
320-480 px U alone is 100-350 um and no verdict could be proven. The miscalibrated rig is the
calibration with one parameter changed, measuring the same stores: the 0.05 % of c
moves scanner 2's points by 0.15-0.36 mm at 2.5 m (0.06-0.14 mm over a 500 mm
dumbbell), which the verdicts must show as proven non-conformance.
"""

import numpy as np
import pytest
import yaml

from fringecal.acceptance.document import acceptance_document
from fringecal.acceptance.standards import AcceptanceStandards
from fringecal.run.config import load_run_config
from fringecal.run.summary import manifest
from fringecal.rundir import RunDir
from fringecal.simulate.small_thesis import write_small_thesis_config
from fringecal.steps import run_pipeline
from fringecal.steps.acceptance import acceptance_stores
from fringecal.steps.verify import ballbar_stores
from fringecal.verification.verify import verify_ballbar

pytestmark = pytest.mark.slow  # whole runs: the fast tier (-m "not slow") leaves this module out


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory):
    d = tmp_path_factory.mktemp("miscalibrated")
    path = write_small_thesis_config(d, width=640, poses=tuple(range(1, 13)), positions=(1, 4, 9),
                                     acceptance={"sphere": 0, "dumbbell": 2, "flat": 0})
    doc = yaml.safe_load(path.read_text())
    del doc["simulate"]["acquisition"]["sequence"]          # the default sequence, as the demo
    path.write_text(yaml.safe_dump(doc))
    cfg = load_run_config(path)
    rd = RunDir(d / "run").create()
    rd.manifest.save(manifest(cfg))
    run_pipeline(rd, cfg, workers=2, until="acceptance")
    return rd, cfg


def parameters(rd, cfg, rig) -> dict:
    """The acceptance test of ``rig``, its ball-bar (E) measured with ``rig`` too."""
    covariance = rd.covariance.load()
    _, fails, result, budget = verify_ballbar(ballbar_stores(rd), rig, rd.ballbar.load(), cfg.extraction.rejection,
                                              cfg.verification, rd.bundle_summary.load()["volume_diagonal_mm"],
                                              covariance)
    verification = {"calibrated": result.to_dict(), "uncertainty": budget}
    doc, _ = acceptance_document(rig, AcceptanceStandards(**rd.acceptance_standards.load()), cfg.acceptance,
                                 cfg.extraction.rejection, cfg.verification.uncertainty, covariance,
                                 acceptance_stores(rd), verification)
    return {(p["name"], p["scanner"]): p for p in doc["parameters"]}


def test_principal_distance_off_by_0_05_percent_fails_e_and_sd(calibrated):
    rd, cfg = calibrated
    rig = rd.calibration.load()
    good = parameters(rd, cfg, rig)
    assert {k: p["verdict"] for k, p in good.items()} == {
        ("SD", "scanner1"): "conformance", ("SD", "scanner2"): "conformance", ("E", "cell"): "conformance"}
    # the step's own document says the same as the re-measured one
    step = {(p["name"], p["scanner"]): p["verdict"] for p in rd.acceptance.load()["parameters"]}
    assert step == {k: p["verdict"] for k, p in good.items()}

    params = rig.params.copy()
    camera = [s.name for s in rig.sensors].index(rig.scanner("scanner2").camera.name)
    params[camera, 8] *= 1.0005
    bad = parameters(rd, cfg, rig.with_params(params))
    assert bad[("E", "cell")]["verdict"] == "non-conformance"
    assert bad[("SD", "scanner2")]["verdict"] == "non-conformance"
    assert bad[("SD", "scanner1")]["verdict"] == "conformance"     # scanner 1 is untouched
    assert bad[("SD", "scanner1")]["measured_mm"] == good[("SD", "scanner1")]["measured_mm"]
    for key in (("E", "cell"), ("SD", "scanner2")):
        assert abs(bad[key]["measured_mm"]) - bad[key]["U_mm"] > cfg.acceptance.limits.SD
        assert np.isfinite(bad[key]["U_mm"])
