"""The smoke tier of ``benchmarks/``: every script runs at a tiny size (``--smoke``), so an
API change that breaks a benchmark fails the tests instead of the next measurement.

Each script is imported from its folder and its ``main`` called in this process (the
kernels, fringecal and its imports are loaded once per test worker), with ``--out``: the
JSON it writes must carry the conditions every benchmark records (``benchmarks/_common.py``:
commit, load average at start and end, numba's cache state) and what the script
measured, checked here against what a tiny case must give. The scripts that read a
finished run directory are smoke-tested on the run of ``tests/test_run_flow.py``;
the two that make whole runs themselves are in the slow tier.
"""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[1] / "benchmarks"
SCRIPTS = sorted(p.stem for p in BENCH.glob("*.py") if not p.stem.startswith("_"))

#: scripts smoke-tested on tests/test_run_flow.py's finished run (they read a run directory)
ON_A_RUN = ("artefact_refinement", "coverage_split", "extraction_accuracy", "measure_spheres", "parameter_coverage", "thesis_scale")
#: scripts that make whole runs themselves: the slow tier
WHOLE_RUNS = ("first_run", "length_coverage", "black_box_coverage")


def run_benchmark(name: str, args: list[str], out: Path) -> dict:
    """Import ``benchmarks/<name>.py`` and call its ``main`` with ``args`` and ``--out``;
    return the JSON it wrote (checked against what it returned)."""
    sys.path.insert(0, str(BENCH))
    spec = importlib.util.spec_from_file_location(f"benchmark_{name}", BENCH / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    returned = module.main([*args, "--out", str(out)])
    doc = json.loads(out.read_text())
    assert doc["benchmark"] == name and doc["smoke"] is ("--smoke" in args)
    c = doc["conditions"]
    assert c["commit"] and c["cores"] >= 1 and c["numba_cache"] in ("warm", "cold")
    assert len(c["load_average_start"]) == 3 and len(c["load_average_end"]) == 3
    assert returned["benchmark"] == name
    return doc


def _bundle(doc):
    for case in doc["cases"]:
        f = case["fringecal"]
        assert f["converged"], f["message"]
        # a minimum: at or below F at the true parameters (F = n * RMS^2)
        assert f["after"]["rms_f_mm"] <= case["truth"]["rms_f_mm"] * (1 + 1e-6)
        assert case["scipy"]["nfev"] > 0
    assert [c["case"] for c in doc["cases"]] == ["thesis", "ring4"]


def _ceres(doc):
    if "skipped" in doc:  # pyceres is an optional benchmark dependency (pip install -e ".[bench]")
        assert "pyceres" in doc["skipped"]
        return
    for case in doc["cases"]:
        assert abs(case["relative_cost_difference_ceres_minus_fringecal"]) < 1e-9  # the same minimum
        assert case["iterations_at_most_ceres"], case


def _decode(doc):
    for o, acc in doc["fringecal"]["accuracy"].items():
        assert acc["unwrapping_errors"] == 0, o
        assert acc["tau_rms_error_rad"] < 3 * acc["theory_sigma_tau_ls_rad"] + 1e-3, o
    assert {"png", "tif", "npy"} <= set(doc["read_frames_per_format"])


def _image_import(doc):
    first, second = doc["variants"].values()
    assert first["read_frames"]["m_px_per_s"] > 0 and second["read_frames_cold_cache"]["m_px_per_s"] > 0
    assert first["memory"]["stack_mb"] > 0 and "skipped" in second["memory"]


def _busy_neighbours(doc):
    b = doc["bundle_step"]
    assert len(b["idle"]) == len(b["busy"]) == 1 and b["idle"][0]["draws"] == 4
    assert b["busy_over_idle"]["bootstrap_s"] > 0 and "skipped" in doc["whole_run"]


def _cloud_speed(doc):
    m = doc["median"]
    assert m["views_labelled"] == 6 and m["bbB_error_mm"] < 0.1  # the second black box found where it is
    assert doc["ply_read_mb_s"] > 0 and doc["filesystem_read_mb_s"] > 0
    assert "pye57" in doc["e57"].get("skipped", "pye57") and (doc["e57"].get("e57_read_mb_s", 1) > 0)


def _black_box_row(doc):
    s = doc["summary"]
    assert doc["views_labelled"] == doc["views"] == 6 and not doc["joint"]["failures"]
    # 0.05 mm noise, 800 points a cap: every transform within a few um of the lengths with the true ones
    assert s["E_max_joint_um"] < 30 and s["E_max_true_um"] < 30 and doc["transform_errors"]["bbB"]["joint_mm"] < 0.1


CHECKS = {
    "acquire": lambda d: d["widths"]["64"]["store_mb"] > 0,
    "black_box_row": _black_box_row,
    "cloud_speed": _cloud_speed,
    "bundle": _bundle,
    "busy_neighbours": _busy_neighbours,
    "ceres": _ceres,
    # a 3 um lens error leaves a pattern the 14 parameters cannot take and the field can
    "correction_field": lambda d: d["sizes"][0]["z_max"]["brown14"] > 5 > d["sizes"][0]["z_max"]["field"],
    "convergence_basin": lambda d: d["rigs"]["thesis"]["scales"]["1"]["starts"] == 2,
    "decode": _decode,
    "image_import": _image_import,
    "labelling_rigs": lambda d: d["rigs"]["thesis"]["seeds"]["0"]["with_plan"]["wrong_labels"] == 0,
    "measure": lambda d: d["points"] > 0 and d["ply_bytes"] > 0 and d["observed_regions"]
    and 0 <= d["points_outside_observed_region"] < d["points"],
    # even at 96 px the 3-step gamma ripple is found and corrected, and noise alone is not
    "phase_ripple": lambda d: d["cases"][0]["orientations"]["x"]["applied"]
    and not d["cases"][2]["orientations"]["x"]["applied"],
    "noise_calibration": lambda d: d["measurements"][0]["n_pixels"] > 0 and d["unwrap"]["unwrap_errors"]["x"] == 0,
    # a 3 px term stands out of its u (4.0-4.7 u) even on control points every 60 px
    "prism_detectability": lambda d: len(d["sizes"]) == 1 and min(d["sizes"][0]["term_over_u"]) > 3
    and d["sizes"][0]["wald_p"] < 1e-6 and len(d["dense"]["wald"]["0.2"]) == 1
    and d["dense"]["with_dispersion"]["0.0"][0]["kappa"] > 0,
    "probing_size_bias": lambda d: d["far_positions"] == 1 and abs(d["noise_free_P_S_along_rays_mm"]) < 0.5,
    "pointcloud": lambda d: d["labelling"]["labelled_groups"] == d["labelling"]["groups"] == 24,
    "render": lambda d: d["render_64"]["wall_s"] > 0 and d["frames_bytes"] == 98 * 64 * 64 * 2,
}


def test_every_benchmark_has_a_smoke_test():
    assert set(SCRIPTS) == set(CHECKS) | set(ON_A_RUN) | set(WHOLE_RUNS)


@pytest.mark.parametrize("name", sorted(CHECKS))
def test_benchmark_smoke(name, tmp_path):
    doc = run_benchmark(name, ["--smoke"], tmp_path / f"{name}.json")
    assert CHECKS[name](doc) is not False


@pytest.mark.slow
def test_length_coverage_smoke(tmp_path):
    doc = run_benchmark("length_coverage", ["--smoke"], tmp_path / "coverage.json")
    assert doc["complete"] and doc["summary"]["seeds_ok"] == 1 and doc["summary"]["n_lengths"] == 1


@pytest.mark.slow
def test_black_box_coverage_smoke(tmp_path):
    doc = run_benchmark("black_box_coverage", ["--smoke"], tmp_path / "black_box_coverage.json")
    (seed,) = doc["seeds"]
    assert seed["ok"], seed.get("traceback")
    assert doc["n_lengths"] >= 1 and seed["e_max_true_mm"] > 0 and seed["black_box"][0]["scanner"] == "scanner2"


@pytest.mark.slow
def test_first_run_smoke(tmp_path):
    doc = run_benchmark("first_run", ["--smoke"], tmp_path / "first_run.json")
    (cold,) = doc["cold"]
    assert cold["flow_s"] > 0 and cold["compile_s"] == 0 and cold["threads"]["workers"] >= 1
    assert doc["install_s"] is None and doc["warm"] == [] and doc["cold_median_wall_s"] == cold["wall_s"]
