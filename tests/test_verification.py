"""VDI/VDE 2634 evaluations, checked against the thesis's ball-bar verification (table 6-9)."""

import json

import numpy as np
import pandas as pd
import pytest
from typer.testing import CliRunner

from fringecal.flows.cli import app
from fringecal.schemas import SphereCentresTable, TableError, read_table
from fringecal.verification.lengths import (
    GumStatement,
    ballbar_lengths,
    evaluate_ballbar,
    flatness_error,
    one_part_in,
    probing_form_error,
    probing_size_error,
    seven_ballbar_positions,
)

runner = CliRunner()


def test_table_6_9_lengths_and_summary(thesis_dir):
    centres = read_table(thesis_dir / "ballbar_verification_table6-9.csv", SphereCentresTable)
    lengths = ballbar_lengths(centres)
    printed = pd.read_csv(thesis_dir / "ballbar_lengths_table6-9.csv")
    # lengths from the printed coordinates agree with the printed lengths (rounding of 6 coordinates)
    np.testing.assert_allclose(lengths.length_mm, printed.length_mm, atol=0.0011)
    r = evaluate_ballbar(lengths.length_mm, 1015.650, lengths.measurement, mpe_mm=0.2, volume_diagonal_mm=2872.3)
    assert r.mean_length_mm == pytest.approx(1015.612, abs=0.0005)  # thesis: 1015.612 mm
    assert r.max_abs_error_mm == pytest.approx(0.149, abs=0.0011)    # thesis: 149 um
    assert 18_500 < r.one_part_in < 19_500                              # thesis: "one part in 19 000"
    assert r.passed and r.positions["pass"].all()
    failing = evaluate_ballbar(lengths.length_mm, 1015.650, mpe_mm=0.1)
    assert not failing.passed and failing.positions["pass"].sum() == 5


def test_gum_statement():
    g = GumStatement.from_repeats([1.0, 1.2, 0.8, 1.0], certificate_expanded_mm=0.0004, certificate_k=2, coverage_factor=1.96)
    assert g.u_type_a_mm == pytest.approx(np.std([1.0, 1.2, 0.8, 1.0], ddof=1) / 2)
    assert g.u_type_b_mm == pytest.approx(0.0002)
    assert g.expanded_mm == pytest.approx(1.96 * np.hypot(g.u_type_a_mm, 0.0002))
    assert "k = 1.96" in g.sentence()


def test_form_size_flatness(rng):
    r = rng.uniform(-0.01, 0.01, 10_000)
    r[:3] = [0.5, -0.4, 0.3]  # 3 wild points out of 10 000 (0.03 %) are discarded by the 0.3 % rule
    assert probing_form_error(r) <= 0.02
    assert probing_form_error(r, exclude_fraction=0) == pytest.approx(0.9)
    assert flatness_error(np.linspace(-0.002, 0.003, 101), exclude_fraction=0) == pytest.approx(0.005)
    assert probing_size_error(50.86, 50.85) == pytest.approx(0.01)
    assert one_part_in(0.087, 2872.3) == pytest.approx(33015, rel=1e-4)


def test_seven_positions_span_the_volume():
    pos = seven_ballbar_positions([-500, -400, 2000], [500, 400, 3000], 1000.0)
    assert pos.shape == (7, 2, 3)
    np.testing.assert_allclose(np.linalg.norm(pos[:, 1] - pos[:, 0], axis=1), 1000.0)
    np.testing.assert_allclose(pos.mean(axis=1), [[0, 0, 2500]] * 7)
    d = pos[:, 1] - pos[:, 0]
    assert np.all(np.abs(d[:4]).min(axis=1) > 100)  # space diagonals
    # face diagonals (VDI/VDE 2634 part 2): in the x-y, x-z and y-z faces, along the box's half sizes
    np.testing.assert_allclose(d[4:] / np.linalg.norm(d[4:], axis=1, keepdims=True),
                               [[500 / 640.3124, 400 / 640.3124, 0], [500 / 707.1068, 0, 500 / 707.1068],
                                [0, 400 / 640.3124, 500 / 640.3124]], atol=1e-6)
    axes = seven_ballbar_positions([-500, -400, 2000], [500, 400, 3000], 1000.0, directions="axes")
    np.testing.assert_allclose(axes[:4], pos[:4])
    assert np.count_nonzero(np.abs(axes[4:, 1] - axes[4:, 0]) > 1e-9) == 3  # axis-parallel


def test_cli_json(thesis_dir):
    res = runner.invoke(app, ["verify", "ballbar", "--centres", str(thesis_dir / "ballbar_verification_table6-9.csv"),
                              "--reference-length-mm", "1015.650", "--volume-diagonal-mm", "2872.3", "--json"])
    assert res.exit_code == 0, res.output
    doc = json.loads(res.stdout)
    assert len(doc["positions"]) == 9
    assert doc["mean_length_mm"] == pytest.approx(1015.612, abs=0.0005)
    assert doc["max_abs_error_mm"] == pytest.approx(0.149, abs=0.0011)


def test_bad_ballbar_tables(tmp_path):
    p = tmp_path / "c.csv"
    p.write_text("measurement,scanner,sphere_id,x_mm,y_mm,z_mm\n1,s1,A,0,0,0\n1,s2,B,1000,0,0\n2,s1,A,0,0,0\n2,s2,C,1,1,1\n")
    with pytest.raises(TableError) as info:
        ballbar_lengths(read_table(p, SphereCentresTable), str(p))
    msg = str(info.value)
    assert "c.csv" in msg and "measurement '2' has no row(s) for sphere 'B'" in msg and "['C'] are not ball-bar spheres" in msg
    res = runner.invoke(app, ["verify", "ballbar", "--centres", str(p), "--reference-length-mm", "1000"])
    assert res.exit_code == 2 and "measurement '2'" in res.output


def test_position_tables_name_their_problems_by_position():
    rows = pd.DataFrame({"position": ["p1", "p1", "p2"], "scanner": ["s1", "s2", "s1"], "sphere_id": ["A", "B", "A"],
                         "x_mm": [0.0, 1000.0, 0.0], "y_mm": [0.0] * 3, "z_mm": [0.0] * 3})
    with pytest.raises(TableError) as info:
        ballbar_lengths(rows, "centres.csv")
    assert "position 'p2' has no row(s) for sphere 'B'" in str(info.value)
    lengths = ballbar_lengths(rows[rows.position == "p1"])
    assert lengths.measurement.tolist() == ["p1"] and lengths.length_mm[0] == pytest.approx(1000.0)


def _as_run_table(thesis_dir, path):
    """Thesis table 6-9 in the layout of a run's tables/ballbar_centres.csv (one row per
    position, scanner and sphere, named by position)."""
    table = pd.read_csv(thesis_dir / "ballbar_verification_table6-9.csv", dtype={"measurement": str})
    table.rename(columns={"measurement": "position"}).to_csv(path, index=False)
    return path


def test_either_centres_layout_is_read_and_neither_is_named(thesis_dir, tmp_path):
    from fringecal.schemas import BallbarCentresTable, read_any_table

    models = (SphereCentresTable, BallbarCentresTable)
    by_measurement = read_any_table(thesis_dir / "ballbar_verification_table6-9.csv", *models)
    by_position = read_any_table(_as_run_table(thesis_dir, tmp_path / "run.csv"), *models)
    assert "measurement" in by_measurement and "position" in by_position and len(by_position) == 18
    np.testing.assert_array_equal(ballbar_lengths(by_position).length_mm, ballbar_lengths(by_measurement).length_mm)
    (tmp_path / "neither.csv").write_text("scanner,sphere_id,x_mm,y_mm,z_mm\ns1,A,0,0,0\n")
    with pytest.raises(TableError) as info:
        read_any_table(tmp_path / "neither.csv", *models)
    assert "neither.csv" in str(info.value) and "['measurement'] for a SphereCentresTable or ['position'] for a " \
        "BallbarCentresTable" in str(info.value)


def test_verify_ballbar_takes_what_a_run_wrote(thesis_dir, tmp_path):
    """A run's tables/ballbar_centres.csv as --centres, and the run itself as --run (its
    centres and its bar's CMM length): the same lengths as thesis table 6-9's layout."""
    import shutil

    from fringecal.rundir import RunDir

    args = ["--reference-length-mm", "1015.650", "--json"]
    given = runner.invoke(app, ["verify", "ballbar", "--centres", str(thesis_dir / "ballbar_verification_table6-9.csv"),
                                *args])
    rd = RunDir(tmp_path / "run")
    rd.ballbar_centres.path.parent.mkdir(parents=True)
    _as_run_table(thesis_dir, rd.ballbar_centres.path)
    table = runner.invoke(app, ["verify", "ballbar", "--centres", str(rd.ballbar_centres.path), *args])
    shutil.copy(thesis_dir / "ballbar.csv", rd.ballbar.path)
    run = runner.invoke(app, ["verify", "ballbar", "--run", str(rd.root), "--json"])
    for res in (given, table, run):
        assert res.exit_code == 0, res.output
    lengths = [[p["length_mm"] for p in json.loads(r.stdout)["positions"]] for r in (given, table, run)]
    assert len(lengths[0]) == 9 and lengths[0] == lengths[1] == lengths[2]
    assert json.loads(run.stdout)["reference_length_mm"] == pytest.approx(1015.65)
    empty = runner.invoke(app, ["verify", "ballbar", "--run", str(tmp_path)])
    assert empty.exit_code == 2 and "no tables/ballbar_centres.csv" in empty.output
    neither = runner.invoke(app, ["verify", "ballbar", "-L", "1000"])
    assert neither.exit_code == 2 and "--centres CSV and --reference-length-mm L, or --run RUN_DIR" in neither.output
