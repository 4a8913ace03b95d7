"""``fringecal artefact``: the commands write what the API computes; bad input exits 2 with one message."""

import json

import numpy as np
import pandas as pd
import pytest
from typer.testing import CliRunner

from fringecal.config import load_yaml_model
from fringecal.engineering import (
    ArtefactCorrections,
    SupportCondition,
    apply_corrections,
    compensate_temperature,
    fickian_fraction,
    gravity_sag_correction,
    load_materials,
)
from fringecal.flows.cli import app
from fringecal.schemas import TrussDisplacementsTable, TrussForcesTable, read_table

runner = CliRunner()


def run(*args):
    return runner.invoke(app, ["artefact", *map(str, args)])


def test_truss_writes_forces_and_displacements(tmp_path, thesis_dir):
    out = tmp_path / "forces.csv"
    r = run("truss", "--artefact", thesis_dir / "artefact_design.csv", "--rod-end-load-n", 3.825, "--out", out, "--json")
    assert r.exit_code == 0, r.output
    s = json.loads(r.output)
    assert s["max_tension_member"] == "1-3" and s["max_tension_n"] == pytest.approx(35.33, abs=0.01)
    assert s["max_compression_n"] == pytest.approx(-55.21, abs=0.01)
    assert s["magnet_safety_factor"] == pytest.approx(1.78, abs=0.01)
    f = read_table(out, TrussForcesTable)
    assert len(f) == 39 and list(f.columns[:6]) == ["rod_id", "sphere_a", "sphere_b", "length_mm", "force_n", "stress_mpa"]
    np.testing.assert_allclose(f.stress_mpa, f.force_n / load_materials().tube.area_mm2)
    d = read_table(tmp_path / "forces_displacements.csv", TrussDisplacementsTable)
    assert d.set_index("sphere_id").loc["5", ["dx_mm", "dy_mm", "dz_mm"]].abs().max() < 1e-15
    r = run("truss", "--out", tmp_path / "mass.csv")   # thesis defaults, mass loads, table output
    assert r.exit_code == 0 and "magnet safety factor 2.58" in " ".join(r.output.split())


@pytest.mark.parametrize("args, message", [
    (["--supports", "5:xyz,1:yz"], "needs at least 6"),
    (["--supports", "5:xyz,1:xyz"], "is a mechanism"),
    (["--supports", "5:xyz,1:yz,42:z"], "unknown node"),
    (["--supports", "5:xyq,1:yz,14:z"], "unknown axis 'q'"),
    (["--gravity", "0,0"], "--gravity"),
])
def test_truss_bad_input_exits_2_and_writes_nothing(tmp_path, args, message):
    out = tmp_path / "f.csv"
    r = run("truss", *args, "--out", out)
    assert r.exit_code == 2 and message in " ".join(r.output.split())
    assert not list(tmp_path.iterdir())


def test_truss_rod_naming_a_missing_sphere(tmp_path, thesis_dir):
    rods = pd.read_csv(thesis_dir / "rods.csv", dtype=str)
    rods.loc[0, "sphere_b"] = "16"
    rods.to_csv(tmp_path / "rods.csv", index=False)
    r = run("truss", "--rods", tmp_path / "rods.csv", "--out", tmp_path / "f.csv")
    assert r.exit_code == 2 and "line 2, column 'sphere_b': sphere '16' is not in artefact" in " ".join(r.output.split())


def test_rigidity_cte_cme_thermal(tmp_path, thesis_dir):
    s = json.loads(run("rigidity", "--json").output)
    assert s["minimally_rigid"] and s["rank"] == 39
    s = json.loads(run("cte", "--log", thesis_dir / "thermal_log_table3-5.csv", "--json").output)
    assert round(s["cte_per_c"], 7) == 1.9e-6
    s = json.loads(run("cme", "--mass-change-pct", 0.05, "--json").output)
    assert s["range_um"] == pytest.approx(0.4, abs=1e-6) and round(np.log10(s["cme_per_pct_from_range"])) == -5
    out = tmp_path / "a.csv"
    s = json.loads(run("thermal", "--temperature-c", 25, "--out", out, "--json").output)
    assert s["scale"] == pytest.approx(1 + 9.5e-6, rel=1e-12)
    from fringecal.artefact import load_artefact
    a = load_artefact(out)
    ref = compensate_temperature(load_artefact(thesis_dir / "artefact_cmm2.csv"), 25.0)
    np.testing.assert_allclose(a.centres, ref.centres, atol=1e-9)


def test_sag_command_matches_the_api(tmp_path, thesis_dir):
    out, table = tmp_path / "a.csv", tmp_path / "sag.csv"
    r = run("sag", "--use-gravity", "0.2,0,-1", "--out", out, "--table", table, "--json")
    assert r.exit_code == 0, r.output
    from fringecal.artefact import load_artefact, load_rods
    art = load_artefact(thesis_dir / "artefact_cmm2.csv")
    api = gravity_sag_correction(art, load_rods(thesis_dir / "rods.csv", art), load_materials(),
                                 SupportCondition("5:xyz,1:yz,14:z", (0, 0, -1)),
                                 SupportCondition("5:xyz,1:yz,14:z", (0.2, 0, -1)))
    np.testing.assert_allclose(load_artefact(out).centres, api.artefact.centres, atol=1e-9)
    assert json.loads(r.output)["max_correction_um"] == pytest.approx(api.max_correction_mm * 1e3)


def test_moisture_command_on_a_synthetic_series(tmp_path):
    t = np.linspace(0, 3e7, 25)
    mass = 20.0 * (1 + 0.55 / 100 * fickian_fraction(t, 1.1e-7, 2.8))
    pd.DataFrame({"time_s": t, "mass_g": mass}).to_csv(tmp_path / "s.csv", index=False)
    r = run("moisture", "--series", tmp_path / "s.csv", "--thickness-mm", 2.8, "--json")
    assert r.exit_code == 0, r.output
    s = json.loads(r.output)
    assert s["full_fit"]["D_m2_s"] == pytest.approx(1.1e-13, rel=1e-6)
    assert s["full_fit"]["m_inf_pct"] == pytest.approx(0.55, rel=1e-6)
    assert s["early_time_fitted_m_inf"]["D_m2_s"] == pytest.approx(1.1e-13, rel=2e-3)
    pd.DataFrame({"time_s": [0, 1, 1], "mass_g": [1, 2, 3]}).to_csv(tmp_path / "bad.csv", index=False)
    r = run("moisture", "--series", tmp_path / "bad.csv", "--thickness-mm", 2.8)
    assert r.exit_code == 2 and "line 4, column 'time_s'" in " ".join(r.output.split())


def test_consistency_command(tmp_path):
    r = run("consistency", "--out", tmp_path / "c.csv", "--json")
    assert r.exit_code == 0, r.output
    s = json.loads(r.output)
    worst = {c["comparison"]: c["worst_spheres"] for c in s["comparisons"]}
    assert worst["assembled - single"] == "2-6"
    assert 0.02e3 < s["from_single_lengths"]["max_um"] < 0.08e3
    assert len(pd.read_csv(tmp_path / "c.csv")) == 39


def test_corrections_block_for_a_calibration_config(tmp_path, thesis_dir, thesis_artefact):
    cfg = tmp_path / "corr.yaml"
    cfg.write_text(f"sag:\n  rods: {thesis_dir / 'rods.csv'}\n  use_gravity: [0.1, 0, -1]\n"
                   "thermal:\n  cte_per_c: 2.0e-6\n")
    corr = load_yaml_model(cfg, ArtefactCorrections)
    out = apply_corrections(thesis_artefact, corr, temperature_c=22.0)
    from fringecal.artefact import load_rods
    sag = gravity_sag_correction(thesis_artefact, load_rods(thesis_dir / "rods.csv", thesis_artefact), load_materials(),
                                 SupportCondition("5:xyz,1:yz,14:z", (0, 0, -1)),
                                 SupportCondition("5:xyz,1:yz,14:z", (0.1, 0, -1))).artefact
    np.testing.assert_allclose(out.centres, compensate_temperature(sag, 22.0, 2.0e-6).centres, atol=1e-12)
    assert apply_corrections(thesis_artefact, None) is thesis_artefact
    cfg.write_text("sag:\n  rods: rods.csv\n  extra: 1\n")
    from fringecal.config import ConfigError
    with pytest.raises(ConfigError, match="sag.extra: unknown key"):
        load_yaml_model(cfg, ArtefactCorrections)


def test_supports_from_a_table(tmp_path):
    rows = [("5", 1, 0, 0), ("5", 0, 1, 0), ("5", 0, 0, 1), ("1", 0, 2, 0), ("1", 0, 0, 1), ("14", 0, 0, 1)]
    pd.DataFrame(rows, columns=["sphere_id", "nx", "ny", "nz"]).to_csv(tmp_path / "s.csv", index=False)
    a = json.loads(run("truss", "--supports", tmp_path / "s.csv", "--out", tmp_path / "a.csv", "--json").output)
    b = json.loads(run("truss", "--out", tmp_path / "b.csv", "--json").output)
    np.testing.assert_allclose([m["force_n"] for m in a["member_forces"]], [m["force_n"] for m in b["member_forces"]],
                               rtol=1e-12)
    (tmp_path / "bad.csv").write_text("sphere_id,nx,ny,nz\n5,1,0,0\n5,0,x,0\n")
    r = run("truss", "--supports", tmp_path / "bad.csv", "--out", tmp_path / "c.csv")
    assert r.exit_code == 2 and "line 3, column 'ny': value 'x' is not a number" in " ".join(r.output.split())
