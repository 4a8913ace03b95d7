"""The decoder's phase-ripple step (fringecal.fringe.ripple): a gamma projector seen
through a 3-step sequence, against the ripple predicted from the emitted pattern's
harmonics and against the renderer's true tau; noise alone is left alone."""

import json

import numpy as np
import pandas as pd
import pytest
import xarray as xr

from fringecal.artefact import load_rods
from fringecal.frames import Frame
from fringecal.fringe.decode import DecodeSettings, decode
from fringecal.fringe.measurement import decode_to_store
from fringecal.fringe.ripple import Z_APPLY, ripple_frequencies, ripple_of, scanner_ripple
from fringecal.fringe.sequence import FringeSequence
from fringecal.rig import scaled_scanner
from fringecal.simulate import Material, RenderConfig, artefact_scene, backdrop, render_measurement
from fringecal.simulate.unmodelled import RenderErrors, emitted_harmonics

#: three steps alias harmonic 2 of a gamma projector onto the fundamental (0.25 rad at
#: gamma 2.2); low fringe counts keep the harmonics sharp at 192 px
SEQ3 = FringeSequence(fringe_counts=(16, 15, 14, 12, 8), n_steps=3)
GAMMA = 2.2
EXACT = RenderConfig(bit_depth=16, materials={"background": Material(albedo=1.0)}).ideal()
NOISY = RenderConfig()


@pytest.fixture(scope="module")
def scanner(thesis_rig):
    return scaled_scanner(thesis_rig.scanner("scanner1"), 192)


@pytest.fixture(scope="module")
def scene(thesis_artefact, thesis_dir, scanner):
    row = pd.read_csv(thesis_dir / "poses_scanner1_table6-1.csv").iloc[0]
    pose = Frame.from_params(row[["tx_mm", "ty_mm", "tz_mm", "omega_rad", "phi_rad", "kappa_rad"]].to_numpy(float))
    rods = load_rods(thesis_dir / "rods.csv", thesis_artefact)
    return artefact_scene(thesis_artefact, rods, pose, background=backdrop(scanner, 3500.0))


def render(scanner, scene, cfg, gamma, seed=0):
    return render_measurement(scanner, scene, cfg, np.random.default_rng(seed), SEQ3,
                              RenderErrors(projector_gamma=gamma))


def tau_error(decoded, truth, o, mask):
    e = decoded.tau[o][mask] - getattr(truth, f"tau_{o}_centre")[mask]
    return (e + np.pi) % (2 * np.pi) - np.pi


def lit(truth):
    return np.isfinite(truth.tau_x_centre) & (truth.irradiance > 0.3) & (truth.irradiance < 1.0)


def predicted_ripple(phase, cfg):
    """Phase error of the 3-step estimator for the emitted pattern, from its harmonics
    (independent of the decoder): arg of the sum of the harmonics h = +-1 (mod 3)."""
    b = emitted_harmonics(cfg.offset, cfg.amplitude, GAMMA)
    z = sum(b[h] * np.exp(1j * (h - 1) * phase) for h in range(1, len(b)) if h % 3 == 1) \
        + sum(b[h] * np.exp(-1j * (h + 1) * phase) for h in range(1, len(b)) if h % 3 == 2)
    return np.angle(z)


def test_a_gamma_projector_seen_in_three_steps_is_found_and_corrected(scanner, scene):
    m = render(scanner, scene, EXACT, GAMMA)
    off = decode(m.frames, SEQ3, DecodeSettings(phase_ripple="off"), full_scale=EXACT.max_dn)
    auto = decode(m.frames, SEQ3, full_scale=EXACT.max_dn)
    mask = lit(m.truth) & off.valid & auto.valid
    assert mask.sum() > 2000
    for o in SEQ3.orientations:
        r = auto.ripple[o]
        assert r.applied and r.z > 1e3 and r.frequencies == ripple_frequencies(3)
        # the fitted ripple, a function of the measured phase, against the prediction:
        # phi_measured = Phi + e(Phi), so the fit at Phi + e(Phi) must be e(Phi); the
        # inverse of so large a ripple has harmonics beyond 3N (4.5 % of it RMS here)
        true_phase = np.linspace(-np.pi, np.pi, 721)
        e = predicted_ripple(true_phase, EXACT)
        assert np.sqrt(np.mean(e ** 2)) > 0.15
        for j in range(len(SEQ3.fringe_counts)):
            fitted = ripple_of(r.coefficients[j:j + 1], (true_phase + e)[None], r.frequencies)[0]
            assert np.sqrt(np.mean((fitted - e) ** 2)) < 0.06 * np.sqrt(np.mean(e ** 2))
        before = np.sqrt(np.mean(tau_error(off, m.truth, o, mask) ** 2))
        after = np.sqrt(np.mean(tau_error(auto, m.truth, o, mask) ** 2))
        assert before > 3e-3 and after < 0.1 * before
        # the slope's residuals were the ripple: the phase-error map falls with it
        assert np.median(auto.phase_error[o][mask]) < 0.1 * np.median(off.phase_error[o][mask])


def test_with_camera_noise_the_correction_leaves_tau_nearer_the_truth(scanner, scene):
    m = render(scanner, scene, NOISY, GAMMA, seed=3)
    off = decode(m.frames, SEQ3, DecodeSettings(phase_ripple="off"), full_scale=NOISY.max_dn)
    auto = decode(m.frames, SEQ3, full_scale=NOISY.max_dn)
    mask = lit(m.truth) & off.valid & auto.valid
    for o in SEQ3.orientations:
        assert auto.ripple[o].applied and auto.ripple[o].z > 100
        before = np.sqrt(np.mean(tau_error(off, m.truth, o, mask) ** 2))
        after = np.sqrt(np.mean(tau_error(auto, m.truth, o, mask) ** 2))
        assert after < 0.8 * before


def test_a_stack_too_small_for_a_fit_takes_its_scanners_ripple(scanner, scene):
    """A window of a few hundred valid pixels (as a ball-bar's two spheres) gets no fit of
    its own; given the fits of the scanner's calibration stacks it is corrected with their
    inverse-variance mean, and only where most of them were corrected."""
    m = render(scanner, scene, EXACT, GAMMA)
    full = decode(m.frames, SEQ3, full_scale=EXACT.max_dn)
    records = [r.to_dict(SEQ3) for r in full.ripple.values()]
    mask = lit(m.truth) & full.valid
    rows, cols = np.nonzero(mask)
    r0, c0 = int(np.median(rows)), int(np.median(cols))
    win = (slice(r0 - 14, r0 + 14), slice(c0 - 14, c0 + 14))
    frames = np.ascontiguousarray(m.frames[:, win[0], win[1]])
    alone = decode(frames, SEQ3, full_scale=EXACT.max_dn)
    assert alone.ripple == {} and 300 < alone.valid.sum() < 1600  # 40 pixels for each of 40 coefficients
    helped = decode(frames, SEQ3, full_scale=EXACT.max_dn, scanner_fits=records + records)
    off = decode(frames, SEQ3, DecodeSettings(phase_ripple="off"), full_scale=EXACT.max_dn, scanner_fits=records)
    assert off.ripple == {}
    inside = mask[win] & helped.valid & alone.valid
    truth = m.truth.tau_x_centre[win][inside]
    r = helped.ripple["x"]
    assert r.source == "scanner" and r.applied and r.n_pixels == 2 * full.ripple["x"].n_pixels
    np.testing.assert_allclose(r.coefficients, full.ripple["x"].coefficients, atol=1e-12)  # the mean of equals
    np.testing.assert_allclose(np.diag(r.covariance), np.diag(full.ripple["x"].covariance) / 2, rtol=1e-9)
    before = np.sqrt(np.mean((alone.tau["x"][inside] - truth) ** 2))
    after = np.sqrt(np.mean((helped.tau["x"][inside] - truth) ** 2))
    assert before > 3e-3 and after < 0.25 * before
    # a scanner whose calibration stacks were mostly left alone lends nothing
    rest = [{**rec, "applied": False} for rec in records]
    assert scanner_ripple(records + rest + rest, SEQ3) == {}
    assert set(scanner_ripple(records + records + rest, SEQ3)) == {"x", "y"}
    # nor do fits of another sequence
    assert scanner_ripple(records, FringeSequence(fringe_counts=(16, 15, 14, 12, 8), n_steps=4)) == {}


def test_measure_decodes_raw_frames_with_the_scanners_ripple(scanner, scene, tmp_path):
    """fringecal measure's frame folders: a small stack takes the ripple of the
    calibration stacks of the run directory the calibration file lies in."""
    from fringecal.fringe.importer import write_frames
    from fringecal.measure.sources import open_entry

    m = render(scanner, scene, EXACT, GAMMA)
    records = [r.to_dict(SEQ3) for r in decode(m.frames, SEQ3, full_scale=EXACT.max_dn).ripple.values()]
    rows, cols = np.nonzero(lit(m.truth))
    r0, c0 = int(np.median(rows)), int(np.median(cols))
    small = m.frames[:, r0 - 14:r0 + 14, c0 - 14:c0 + 14]
    write_frames(tmp_path / "scanner1", small, SEQ3, 16, fmt="npy", scanner="scanner1")
    alone = open_entry(tmp_path / "scanner1", "frames")
    assert alone.attrs["decoder"]["phase_ripple_fit"] == {}
    helped = open_entry(tmp_path / "scanner1", "frames", None, records)
    fit = helped.attrs["decoder"]["phase_ripple_fit"]
    assert {o: (r["source"], r["applied"]) for o, r in fit.items()} == {"x": ("scanner", True), "y": ("scanner", True)}
    assert not np.array_equal(helped["tau_x"].values, alone["tau_x"].values)


def test_noise_alone_shows_no_ripple_and_tau_is_left_as_it_was(scanner, scene):
    m = render(scanner, scene, NOISY, 1.0, seed=5)
    off = decode(m.frames, SEQ3, DecodeSettings(phase_ripple="off"), full_scale=NOISY.max_dn)
    auto = decode(m.frames, SEQ3, full_scale=NOISY.max_dn)
    assert off.ripple == {}
    for o in SEQ3.orientations:
        r = auto.ripple[o]
        assert not r.applied and abs(r.z) < Z_APPLY
        np.testing.assert_array_equal(auto.tau[o], off.tau[o])
    np.testing.assert_array_equal(auto.valid, off.valid)
    # "always" corrects the fitted noise: tau moves, but by far less than its noise
    always = decode(m.frames, SEQ3, DecodeSettings(phase_ripple="always"), full_scale=NOISY.max_dn)
    mask = lit(m.truth) & off.valid
    for o in SEQ3.orientations:
        assert always.ripple[o].applied
        moved = np.sqrt(np.mean((always.tau[o][mask] - off.tau[o][mask]) ** 2))
        noise = np.sqrt(np.mean(tau_error(off, m.truth, o, mask) ** 2))
        assert 0 < moved < 0.2 * noise


def test_the_store_records_the_ripple_and_its_evidence(scanner, scene, tmp_path):
    m = render(scanner, scene, EXACT, GAMMA)
    decode_to_store(m.frames, SEQ3, tmp_path / "m.zarr", full_scale=EXACT.max_dn)
    attrs = xr.open_zarr(tmp_path / "m.zarr").attrs
    assert attrs["decoder"]["phase_ripple"] == "auto"  # the setting; the fit beside it
    rec = attrs["decoder"]["phase_ripple_fit"]["x"]
    assert rec["applied"] and rec["z"] > 1e3 and rec["z_apply"] == Z_APPLY
    assert rec["frequencies_per_fringe"] == [2, 3, 6, 9]
    f3 = rec["counts"]["16"]["f3"]
    assert np.hypot(f3["cos_rad"], f3["sin_rad"]) == pytest.approx(0.25, abs=0.02)
    assert 0 < f3["u_cos_rad"] < 1e-3
    assert attrs["decoder"]["method"].endswith("phase ripple corrected")
    assert attrs["summary"]["phase_ripple"]["y"]["applied"]


def test_an_unknown_ripple_mode_is_refused_by_name():
    with pytest.raises(ValueError, match="phase_ripple"):
        DecodeSettings(phase_ripple="sometimes")


def test_fringecal_decode_reports_and_switches_the_correction(scanner, scene, tmp_path):
    from typer.testing import CliRunner

    from fringecal.flows.cli import app
    from fringecal.fringe.importer import write_frames

    m = render(scanner, scene, NOISY, GAMMA, seed=3)
    write_frames(tmp_path / "m", m.frames, SEQ3, NOISY.bit_depth, fmt="npy", scanner="s1", measurement="m1")
    runner = CliRunner()
    res = runner.invoke(app, ["decode", "--frames", str(tmp_path / "m"), "--out", str(tmp_path / "m.zarr")])
    assert res.exit_code == 0, res.output
    assert "corrected" in res.output and "phase ripple" in res.output
    res = runner.invoke(app, ["decode", "--frames", str(tmp_path / "m"), "--out", str(tmp_path / "off.zarr"),
                              "--phase-ripple", "off", "--json"])
    assert res.exit_code == 0, res.output
    assert "phase_ripple" not in json.loads(res.output)["stores"][0]
    res = runner.invoke(app, ["decode", "--frames", str(tmp_path / "m"), "--out", str(tmp_path / "x.zarr"),
                              "--phase-ripple", "sometimes"])
    assert res.exit_code != 0 and "--phase-ripple" in res.output


def test_the_run_summary_states_per_scanner_what_was_corrected(scanner, scene, tmp_path):
    from fringecal.fringe.measurement import decoding_summary
    from fringecal.rundir import RunDir

    rd = RunDir(tmp_path / "run").create()
    rows = [{"measurement": "1-s1", "kind": "artefact", "pose": "1", "scanner": "s1"},
            {"measurement": "2-s1", "kind": "artefact", "pose": "2", "scanner": "s1"},
            {"measurement": "3-s1", "kind": "artefact", "pose": "3", "scanner": "s1"}]  # never decoded
    acq = pd.DataFrame(rows)
    acq["store"] = [rd.store(m).rel for m in acq.measurement]
    acq["source"] = "simulated"
    rd.acquisition.save(acq)
    for name, gamma in (("1-s1", GAMMA), ("2-s1", 1.0)):
        m = render(scanner, scene, NOISY, gamma, seed=3)
        decode_to_store(m.frames, SEQ3, rd.store(name).path, full_scale=NOISY.max_dn)
    (d,) = decoding_summary(rd.store_summaries())
    assert d["scanner"] == "s1" and d["stacks"] == 2
    r = d["phase_ripple"]
    assert r["fits"] == 4 and r["corrected"] == ["1-s1 x", "1-s1 y"] and r["largest_z"] > 100
    assert 0.12 < r["largest_corrected_rms_rad"] < 0.2  # the 3-step gamma-2.2 ripple, 0.16 rad RMS
    assert 0.05 < d["phase_noise_median_rad"]["x"] < 0.3 and 0 < d["valid_fraction_median"] < 1
    # what the run's small stacks (and fringecal measure -r RUN on raw frames) are corrected with
    fits = rd.phase_ripple_fits("s1")
    assert [(f["orientation"], f["applied"]) for f in fits] == [("x", True), ("y", True), ("x", False), ("y", False)]
    assert rd.phase_ripple_fits("s2") == []
