"""Ball-bar positions measured from their stores alone (no plan, no truth), checked
against the plan-driven measurement and the true lengths.

Every store is rendered once per module at 320 px with a short fringe sequence (as the
run-flow test): three thesis positions (table 6-9) seen by both scanners, a short bar
wholly inside scanner one's view, and a bar with only one sphere in any view.

Length tolerance at this profile: each centre comes from 120-200 points at 0.2-0.35 mm
RMS on the side of the sphere facing the scanner; over 27 simulated thesis lengths
(9 positions x 3 seeds) the length error had a standard deviation of about 0.1 mm
(largest 0.24 mm), so a single length is checked to 0.3 mm (3 sigma). At 768 px with
the default sequence the same lengths are within 0.03 mm.
"""

import numpy as np
import pandas as pd
import pytest

from fringecal.artefact import Artefact, load_artefact
from fringecal.fringe.measurement import NoFringesError, decode_to_store
from fringecal.fringe.sequence import FringeSequence
from fringecal.rig import load_rig, scaled_rig
from fringecal.simulate import artefact_scene, render_measurement
from fringecal.simulate.config import RenderConfig
from fringecal.spheres.passes import measurement_maps
from fringecal.spheres.robust import RejectionConfig
from fringecal.verification.ballbar import (
    Sighting,
    ballbar_rods,
    cluster_centres,
    frame_along,
    measure_sphere,
    name_clusters,
    thesis_positions,
)
from fringecal.verification.lengths import ballbar_lengths
from fringecal.verification.measure import measure_position, measure_positions

WIDTH = 320
SEQUENCE = FringeSequence((32, 31, 30, 28, 24, 16), 5, ("x", "y"))
REJECTION = RejectionConfig(noise_mm=0.1)  # the run config's extraction default
LENGTH_TOL_MM = 0.3  # 3 sigma of one length at this profile (module docstring)
THESIS = ("bb01", "bb08", "bb09")  # bb08: sphere A 8 px from scanner one's image border at 2048 px
XYZ = ["x_mm", "y_mm", "z_mm"]


def _render(out, scanner, bar: Artefact, T, seed: int):
    """The decoded store, or None where the scanner sees nothing (no store is recorded)."""
    scene = artefact_scene(bar, ballbar_rods(bar), T)
    render = RenderConfig()
    m = render_measurement(scanner, scene, render, np.random.default_rng(seed), SEQUENCE)
    try:
        decode_to_store(m.frames, m.sequence, out, {"scanner": scanner.name}, full_scale=render.max_dn)
    except NoFringesError:
        return None
    return out


@pytest.fixture(scope="module")
def cell(tmp_path_factory, thesis_dir):
    """Stores (position -> scanner -> path) and the true placement of each bar."""
    rig = load_rig(thesis_dir / "sensors_refined_table6-8.csv")
    small = scaled_rig(rig, WIDTH)
    bb = load_artefact(thesis_dir / "ballbar.csv")
    table = pd.read_csv(thesis_dir / "ballbar_verification_table6-9.csv", dtype={"measurement": str})
    positions = [p for p in thesis_positions(table) if p.name in THESIS]
    short = Artefact(("A", "B"), [[0, 0, 0], [350.0, 0, 0]], [50.850, 50.850], name="short bar")
    # artefact sphere A on the right of scanner one's image, B on the left: the data name them the other way
    a = np.array([150.0, 100.0, 40.0])
    T_short = frame_along(a, a + 350.0 * np.array([-0.95, 0.25, -0.18]) / np.linalg.norm([-0.95, 0.25, -0.18]))
    # the bar points away from both scanners: B is far right of scanner one's view
    T_lonely = frame_along([-222.4, 138.9, 10.5], [800.0, 138.9, 10.5])
    bars = {p.name: (bb, p.T_world_ballbar) for p in positions} | {"short": (short, T_short),
                                                                   "lonely": (bb, T_lonely)}
    root = tmp_path_factory.mktemp("ballbar")
    stores = {}
    for i, (name, (bar, T)) in enumerate(bars.items()):
        found = {s.name: _render(root / f"{name}-{s.name}.zarr", s, bar, T, 100 * i + j)
                 for j, s in enumerate(small.scanners)}
        stores[name] = {k: v for k, v in found.items() if v is not None}
    return {"rig": rig, "small": small, "bb": bb, "short": short, "positions": positions, "bars": bars,
            "stores": stores}


def _true_centres(cell, name):
    bar, T = cell["bars"][name]
    return T.to_world(bar.centres[:2])


def _planned_centre(stores, cell, position, sid, scanner) -> dict:
    """The sphere measured with the plan's knowledge: which sphere the scanner sees and
    the true rod axis (:func:`fringecal.verification.ballbar.measure_sphere`), the reference the
    data-driven measurement must match."""
    bb = cell["bb"]
    here, there = position.T_world_ballbar.to_world(bb.centres[:2])[:: 1 if sid == bb.ids[0] else -1]
    sc = cell["small"].scanner(scanner)
    ds, maps, valid = measurement_maps(stores[position.name][scanner], sc)
    ds.close()
    m = measure_sphere(maps, valid, sc.camera, sc.projector, float(bb.radii[0]),
                       (there - here) / np.linalg.norm(there - here), REJECTION)
    return {"position": position.name, "scanner": scanner, "sphere_id": sid, "x_mm": m.centre[0],
            "y_mm": m.centre[1], "z_mm": m.centre[2], "n_points": m.n_points}


def test_thesis_positions_agree_with_the_plan_and_the_true_length(cell):
    stores = {name: cell["stores"][name] for name in THESIS}
    # the rig at the thesis's 2048 px: each camera is rescaled to its store's 320 px
    rows, failures = measure_positions(stores, cell["rig"], cell["bb"], REJECTION)
    assert failures.empty, failures.to_dict("records")
    assert list(rows.columns[:9]) == ["position", "scanner", "sphere_id", "x_mm", "y_mm", "z_mm", "radius_mm",
                                      "rms_mm", "n_points"]
    # each scanner sees exactly one sphere: scanner one A, scanner two B (rig order)
    assert rows.groupby(["position", "scanner"]).size().eq(1).all()
    assert dict(zip(rows.scanner, rows.sphere_id)) == {"scanner1": "A", "scanner2": "B"}
    assert len(rows) == 2 * len(THESIS) and (rows.radius_mm == 25.425).all()

    plan = pd.DataFrame([_planned_centre(stores, cell, p, sid, scanner)
                         for p in cell["positions"] for sid, scanner in p.scanner_of.items()])
    m = rows.merge(plan, on=["position", "scanner", "sphere_id"], suffixes=("", "_plan"))
    assert len(m) == len(rows)
    # same points, same fit: the measured rod axis differs from the planned one by < 1 mrad
    np.testing.assert_allclose(m[XYZ].to_numpy(), m[[f"{c}_plan" for c in XYZ]].to_numpy(), atol=0.001)
    assert (m.n_points == m.n_points_plan).all()

    lengths = ballbar_lengths(rows)
    assert lengths.measurement.tolist() == list(THESIS)
    np.testing.assert_allclose(lengths.length_mm, 1015.650, atol=LENGTH_TOL_MM)
    one, _ = measure_position(stores["bb01"], cell["rig"], cell["bb"], REJECTION, "bb01")
    pd.testing.assert_frame_equal(one, rows[rows.position == "bb01"].reset_index(drop=True))


def test_short_bar_in_one_scanner_is_named_left_to_right(cell):
    rows, failures = measure_position(cell["stores"]["short"], cell["small"], cell["short"], REJECTION, "short")
    assert rows.scanner.tolist() == ["scanner1", "scanner1"] and rows.sphere_id.tolist() == ["A", "B"]
    truth = _true_centres(cell, "short")
    # A is the sphere further left in scanner one's image: the artefact's B
    np.testing.assert_allclose(rows[XYZ].to_numpy(), truth[::-1], atol=LENGTH_TOL_MM)
    assert list(cell["stores"]["short"]) == ["scanner1"] and failures.empty  # scanner two sees nothing
    length = ballbar_lengths(rows).length_mm[0]
    assert length == pytest.approx(350.0, abs=LENGTH_TOL_MM)


def test_one_visible_sphere_is_a_failure_naming_the_position(cell):
    assert list(cell["stores"]["lonely"]) == ["scanner1"]
    rows, failures = measure_position(cell["stores"]["lonely"], cell["rig"], cell["bb"], REJECTION, "lonely")
    assert rows.empty and list(rows.columns[:3]) == ["position", "scanner", "sphere_id"]
    last = failures.iloc[-1]
    assert last.position == "lonely" and last.scanner == "" and last.sphere_id == ""
    assert "'lonely'" in last.reason and "1 sphere found, seen by scanner1" in last.reason
    with pytest.raises(ValueError, match="position 'lonely'.*'scanner9'"):
        measure_position({"scanner9": cell["stores"]["lonely"]["scanner1"]}, cell["rig"], cell["bb"], REJECTION,
                          "lonely")


def test_a_sphere_seen_by_two_scanners_gives_a_length_per_pair():
    rows = pd.DataFrame({"position": ["p1", "p1", "p1", "p2", "p2"],
                         "scanner": ["s1", "s2", "s2", "s1", "s2"],
                         "sphere_id": ["A", "A", "B", "A", "B"],
                         "x_mm": [0.0, 0.02, 1000.0, 0.0, 0.0], "y_mm": [0.0] * 5,
                         "z_mm": [0.0, 0.0, 0.0, 0.0, 500.0]})
    lengths = ballbar_lengths(rows)
    assert lengths.measurement.tolist() == ["p1:s1/s2", "p1:s2/s2", "p2"]
    np.testing.assert_allclose(lengths.length_mm, [1000.0, 999.98, 500.0])
    assert lengths.scanner_a.tolist() == ["s1", "s2", "s1"] and lengths.position.tolist() == ["p1", "p1", "p2"]
    # the plan-driven tables (``measurement``) behave the same
    old = ballbar_lengths(rows.rename(columns={"position": "measurement"}))
    assert old.measurement.tolist() == lengths.measurement.tolist()


def _sighting(scanner, radius, column):
    return Sighting(scanner, np.zeros(3), radius, 0.1, 500, column, None, None)


def test_naming_rules():
    assert cluster_centres([[0, 0, 0], [1000, 0, 0], [10, 0, 0]], 25.4).tolist() == [0, 1, 0]
    alike = Artefact(("A", "B"), [[0, 0, 0], [1000.0, 0, 0]], [50.85, 50.85])
    seen = [_sighting("s2", 25.0, 100.0), _sighting("s2", 25.0, 50.0), _sighting("s1", 25.0, 900.0)]
    assert name_clusters(seen, [0, 1, 0], alike, ["s1", "s2"]) == {0: "A", 1: "B"}  # first scanner in rig order
    assert name_clusters(seen[:2], [0, 1], alike, ["s1", "s2"]) == {1: "A", 0: "B"}  # then further left
    distinct = Artefact(("A", "B"), [[0, 0, 0], [1000.0, 0, 0]], [50.0, 40.0])
    seen = [_sighting("s1", 20.2, 50.0), _sighting("s2", 24.7, 900.0), _sighting("s1", 24.9, 400.0)]
    assert name_clusters(seen, [0, 1, 1], distinct, ["s1", "s2"]) == {1: "A", 0: "B"}  # by fitted radius
