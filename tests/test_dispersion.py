"""The scatter of sphere centres between spheres against their fits' stated uncertainty
(fringecal.spheres.dispersion), on simulated control points of the thesis rig (every 10 px,
phase noise for an epsilon-1 RMS of 45 um), measured with the true rig (nothing absorbed by
an adjustment, so kappa is 1 when the fits' covariance says all there is).

Truth: the artefact the control points were simulated on. Offsets of 0.15 mm per coordinate
(several times a fit's lateral u) added to its spheres and left out of the table the
dispersion is computed against raise kappa well above 1; the same table stating 0.15 mm as
its u brings it back to 1.
"""

import numpy as np
import pytest

from fringecal.artefact import Artefact
from fringecal.calibration.model import BundleProblem
from fringecal.simulate.control_points import simulate_control_points, thesis_truth
from fringecal.spheres.dispersion import sighting_dispersion

OFFSET_MM = 0.15


def _problem(rig, table: Artefact, sim, poses) -> BundleProblem:
    return BundleProblem.from_tables(rig, table, sim.control_points, poses)


@pytest.fixture(scope="module")
def world():
    rig, art, poses = thesis_truth()
    rng = np.random.default_rng(7)
    built = Artefact(art.ids, art.centres + rng.normal(0, OFFSET_MM, art.centres.shape), art.diameters,
                     np.zeros(len(art.ids)), art.name)
    exact = simulate_control_points(rig, art, poses, spacing_px=10, rng=3)
    moved = simulate_control_points(rig, built, poses, spacing_px=10, rng=3)
    return rig, art, poses, exact, moved


def _exact_table(art: Artefact, u: float) -> Artefact:
    return Artefact(art.ids, art.centres, art.diameters, np.full(len(art.ids), u), art.name)


def test_fits_that_say_all_there_is_give_kappa_one(world):
    rig, art, poses, exact, _ = world
    d = sighting_dispersion(_problem(rig, _exact_table(art, 0.0), exact, poses), rig)
    assert set(d) == {"scanner1", "scanner2"}
    for s in d.values():
        assert s.dof > 40 and s.views >= 10
        # kappa^2 is chi^2 / dof: within 3 standard deviations sqrt(2 / dof) of 1
        assert abs(s.kappa**2 - 1) < 3 * np.sqrt(2 / s.dof), s


def test_sightings_moved_beyond_their_fits_raise_kappa_unless_the_table_states_it(world):
    rig, art, poses, _, moved = world
    hidden = sighting_dispersion(_problem(rig, _exact_table(art, 0.0), moved, poses), rig)
    stated = sighting_dispersion(_problem(rig, _exact_table(art, OFFSET_MM), moved, poses), rig)
    for name in ("scanner1", "scanner2"):
        assert hidden[name].kappa > 2.0, hidden[name]
        assert abs(stated[name].kappa**2 - 1) < 3 * np.sqrt(2 / stated[name].dof), stated[name]


def test_the_verification_scales_only_by_a_scatter_above_the_fits():
    from fringecal.steps.verify import fit_factors
    from fringecal.verification.settings import VerificationConfig

    summary = {"sighting_dispersion": {"scanner1": {"kappa": 0.86}, "scanner2": {"kappa": 1.3}}}
    assert fit_factors(summary, VerificationConfig()) == {"scanner1": 1.0, "scanner2": 1.3}
    off = VerificationConfig(uncertainty={"sphere_scatter": False})
    assert fit_factors(summary, off) == {} and fit_factors({}, VerificationConfig()) == {}


def test_a_scaled_fit_scales_its_covariance_not_its_points():
    from fringecal.verification.budget import SightingModel, SightingPoints
    from fringecal.verification.uncertainty import scaled_fit

    rig = thesis_truth()[0]
    pts = SightingPoints(rig.scanners[0], 0, np.zeros((3, 2)), np.zeros((3, 2)), np.zeros(3), 25.0, 0.02)
    m = scaled_fit(SightingModel(pts, np.ones((3, 28)), np.diag([1.0, 2.0, 3.0])), 1.5)
    assert np.allclose(m.C_fit, np.diag([2.25, 4.5, 6.75])) and m.points.rms_mm == pytest.approx(0.02)
    assert np.array_equal(m.J, np.ones((3, 28)))
