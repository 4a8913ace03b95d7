"""Unmodelled error sources of the simulation (``simulate.errors``), each measured
against an independent prediction: the artefact and ball-bar as built, sphere form,
projector gamma (N-step harmonic aliasing), camera response, phase field, drift in a
scan and over a session, a thin-prism lens term; the ideal profile renders exactly
what the renderer rendered before the switches existed; the realistic profile."""

import numpy as np
import pytest
import yaml
from numpy.polynomial import legendre

from fringecal.artefact import Artefact, load_artefact, load_rods
from fringecal.config import ConfigError
from fringecal.engineering.materials import load_materials
from fringecal.engineering.sag import SupportCondition, gravity_sag_correction
from fringecal.frames import Frame
from fringecal.fringe.decode import DecodeSettings, decode
from fringecal.fringe.sequence import FringeSequence
from fringecal.rig import scaled_scanner
from fringecal.run.config import load_run_config
from fringecal.simulate import (
    Material,
    RenderConfig,
    Scene,
    SceneObject,
    Sphere,
    artefact_scene,
    backdrop,
    render_measurement,
)
from fringecal.simulate import geometry as g
from fringecal.simulate.errors import REALISTIC, SimulationErrors, error_rng
from fringecal.simulate.measurement import measurement_rng
from fringecal.simulate.settings import SimulationConfig
from fringecal.simulate.unmodelled import RenderErrors, phase_field, thin_prism
from fringecal.simulate.world import (
    as_built_artefact,
    as_built_ballbar,
    drifted_scanner,
    form_rms,
    render_errors,
    session_displacement,
    sphere_form_terms,
)

SEQ = FringeSequence()  # the thesis's 7 counts x 7 steps: the aliasing tests need N = 7
#: Noise-free, one sample per pixel, 16 bits, a white backdrop: frames are the contract to 1e-5.
EXACT = RenderConfig(bit_depth=16, materials={"background": Material(albedo=1.0)}).ideal()


@pytest.fixture(scope="module")
def scanner(thesis_rig):
    return scaled_scanner(thesis_rig.scanner("scanner1"), 96)


@pytest.fixture(scope="module")
def scene(thesis_artefact, thesis_dir, pose1, scanner):
    rods = load_rods(thesis_dir / "rods.csv", thesis_artefact)
    return artefact_scene(thesis_artefact, rods, pose1, background=backdrop(scanner, 3500.0))


def render(scanner, scene, cfg, errors=None, seed=0, seq=SEQ):
    return render_measurement(scanner, scene, cfg, np.random.default_rng(seed), seq, errors)


def contract(truth, emitted, seq=SEQ):
    """Noise-free intensity (fraction of full scale) at the true centre tau for an
    emitted pattern ``emitted(psi)``: (n_frames, rows, cols)."""
    lit = np.isfinite(truth.tau_x_centre)
    out = []
    for o, t, k in seq.frames():
        w = np.where(lit, truth.tau_x_centre if o == "x" else truth.tau_y_centre, 0.0)
        out.append(truth.ambient_level + np.where(lit, truth.irradiance * emitted(t * w + 2 * np.pi * k / seq.n_steps),
                                                  0.0))
    return np.array(out)


def demodulated_phase_error(frames, truth, seq=SEQ):
    """Per fringe count of orientation x: angle(sum_k I_k exp(-i delta_k)) minus t tau, (n_t, rows, cols)."""
    out = []
    for t in seq.fringe_counts:
        first = seq.frame_index("x", t, 0)
        z = np.tensordot(np.exp(-1j * seq.step_phases()), frames[first:first + seq.n_steps].astype(float), axes=1)
        out.append(np.angle(z * np.exp(-1j * t * truth.tau_x_centre)))
    return np.array(out)


def well_lit(truth):
    """Lit pixels bright enough for a 16-bit phase to ~1e-5 rad and never saturated
    (irradiance 0.3..1; the glossy end caps reach 1.3)."""
    return np.isfinite(truth.tau_x_centre) & (truth.irradiance > 0.3) & (truth.irradiance < 1.0)


def slope_of(errors_per_count, seq=SEQ):
    """What the decoder's least-squares slope through the origin makes of per-count phase errors."""
    t = np.asarray(seq.fringe_counts, float)
    return np.tensordot(t, errors_per_count, axes=1) / np.sum(t * t)


# -- configuration ----------------------------------------------------------------------

def test_profiles_fill_override_and_name():
    off = SimulationErrors()
    assert off.is_ideal and off.profile_name == "ideal"
    real = SimulationErrors(profile="realistic")
    fields = set(SimulationErrors.model_fields) - {"profile", "seed"}
    assert set(REALISTIC) == fields  # the preset covers every switch
    assert all(real.switches()[k] == SimulationErrors(**{k: v}).switches()[k] for k, v in REALISTIC.items())
    assert real.profile_name == "realistic"
    assert SimulationErrors(profile="realistic", seed=9).profile_name == "realistic"
    mixed = SimulationErrors(profile="realistic", projector_gamma=1.0)
    assert mixed.projector_gamma == 1.0 and mixed.session_drift_mm == REALISTIC["session_drift_mm"]
    assert mixed.profile_name == "realistic+custom"
    assert SimulationErrors(scan_drift_rad=1e-4).profile_name == "custom"
    with pytest.raises(ValueError, match="gama"):
        SimulationErrors(profile="realistic", gama=2.0)


def test_realistic_run_config_is_the_thesis_run_plus_the_profile(tmp_path):
    from fringecal.run.config import default_run_config_path

    base = default_run_config_path()
    real = load_run_config(base.with_name("run_thesis_realistic.yaml"))
    ideal = load_run_config(base)
    assert real.simulate.errors.profile_name == "realistic" and ideal.simulate.errors.profile_name == "ideal"
    a, b = real.model_dump(mode="json"), ideal.model_dump(mode="json")
    assert a["simulate"].pop("errors") != b["simulate"].pop("errors")
    assert (a.pop("name"), b.pop("name")) == ("thesis-realistic", "thesis")
    assert a == b
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump({"simulate": {"errors": {"profile": "realistic", "gama": 2}}}))
    with pytest.raises(ConfigError, match=r"simulate\.errors\.gama: unknown key"):
        load_run_config(bad)


# -- the artefact and the ball-bar as built ---------------------------------------------

def test_as_built_centres_and_diameters_follow_the_cmm_uncertainty(thesis_artefact):
    sim = SimulationConfig()
    e = SimulationErrors(cmm_deviation=True, cmm_u_scale=2.0, sphere_diameter_sd_mm=0.003, seed=4)
    built = as_built_artefact(sim, e)
    # exactly the documented draws
    z = error_rng(4, "cmm-centres").standard_normal((len(thesis_artefact), 3))
    np.testing.assert_array_equal(built.centres, thesis_artefact.centres + 2.0 * thesis_artefact.u[:, None] * z)
    np.testing.assert_array_equal(built.diameters, thesis_artefact.diameters
                                  + 0.003 * error_rng(4, "diameters").standard_normal(len(thesis_artefact)))
    # and their spread: 60 seeds x 45 coordinates, chi-square of the normalised deviations
    z = np.concatenate([(as_built_artefact(sim, e.model_copy(update={"seed": s})).centres - thesis_artefact.centres)
                        .ravel() / (2.0 * 0.010) for s in range(60)])
    assert abs(np.mean(z * z) - 1) < 4 * np.sqrt(2 / z.size) and abs(z.mean()) < 4 / np.sqrt(z.size)
    # the run keeps the table
    np.testing.assert_array_equal(sim.artefact().centres, thesis_artefact.centres)


def test_temperature_scales_the_artefact_by_cte_times_dt(thesis_artefact):
    built = as_built_artefact(SimulationConfig(), SimulationErrors(artefact_temperature_c=25.5))
    ratio = built.distance_matrix()[np.triu_indices(15, 1)] / thesis_artefact.distance_matrix()[np.triu_indices(15, 1)]
    np.testing.assert_allclose(ratio - 1, 1.9e-6 * 5.5, rtol=0, atol=1e-13)
    np.testing.assert_allclose(built.centres.mean(0), thesis_artefact.centres.mean(0), atol=1e-9)
    # a run that corrects to a recorded 21 C still renders the artefact at its true 25.5 C
    corrected = SimulationConfig(artefact_corrections={"thermal": {}}, temperature_c=21.0)
    built = as_built_artefact(corrected, SimulationErrors(artefact_temperature_c=25.5))
    d = built.distance_matrix()[0, 1:] / corrected.artefact().distance_matrix()[0, 1:]
    np.testing.assert_allclose(d, (1 + 1.9e-6 * 5.5) / (1 + 1.9e-6 * 1.0), rtol=1e-13)


def test_gravity_state_is_the_sag_correction_to_the_use_condition(thesis_artefact, thesis_dir):
    tilt = np.radians(10.0)
    use = (0.0, np.sin(tilt), -np.cos(tilt))
    built = as_built_artefact(SimulationConfig(), SimulationErrors(artefact_use_gravity=use))
    supports = "5:xyz,1:yz,14:z"
    expected = gravity_sag_correction(thesis_artefact, load_rods(thesis_dir / "rods.csv"), load_materials(None),
                                      SupportCondition(supports, (0, 0, -1)), SupportCondition(supports, use))
    np.testing.assert_allclose(built.centres, expected.artefact.centres, rtol=0, atol=1e-12)
    moved = np.linalg.norm(built.centres - thesis_artefact.centres, axis=1).max()
    assert 1e-4 < moved < 5e-3  # microns (docs/engineering.md: 1.3-1.8 um at 10 deg)


def test_ballbar_length_differs_from_its_certificate_by_its_uncertainty(thesis_dir):
    cert = load_artefact(thesis_dir / "ballbar.csv")
    length = float(np.linalg.norm(cert.centres[1] - cert.centres[0]))
    assert as_built_ballbar(cert, SimulationErrors()) is cert
    deltas = []
    for seed in range(400):
        bar = as_built_ballbar(cert, SimulationErrors(ballbar_deviation=True, seed=seed))
        deltas.append(np.linalg.norm(bar.centres[1] - bar.centres[0]) - length)
        if seed == 0:
            assert deltas[0] == pytest.approx(0.0004 * error_rng(0, "ballbar-length").standard_normal(), abs=1e-12)
            np.testing.assert_allclose(bar.centres.mean(0), cert.centres.mean(0), atol=1e-12)
    sd = np.std(deltas)
    assert abs(sd / 0.0004 - 1) < 4 * np.sqrt(1 / (2 * 400))


def test_sphere_form_rms_and_rendered_surface(thesis_artefact, pose1, thesis_rig):
    terms = sphere_form_terms(3, "artefact", "5", 0.002)
    n = np.random.default_rng(1).standard_normal((200_000, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)

    def deviation(t, normals):
        return sum(a * legendre.legval(normals @ u, [0] * int(deg) + [1]) for *u, a, deg in t)

    assert form_rms(terms) == pytest.approx(0.002, rel=1e-12)
    assert np.sqrt(np.mean(deviation(terms, n) ** 2)) == pytest.approx(0.002, rel=0.01)  # Monte Carlo
    # rendered: bare spheres; each pixel-centre hit lies off the nominal sphere by the form error there
    bare = artefact_scene(thesis_artefact, None, pose1)
    scanner = scaled_scanner(thesis_rig.scanner("scanner1"), 256)
    e = SimulationErrors(sphere_form_rms_mm=0.002, seed=3)
    errs = render_errors(e, scanner, pose1, "artefact", bare.sphere_ids)
    cfg = RenderConfig().ideal()
    m, m0 = render(scanner, bare, cfg, errs), render(scanner, bare, cfg)
    on = m.truth.centre_object_index >= 0
    sid = np.array([m.truth.object_names[i].split(":")[1] for i in m.truth.centre_object_index[on]])
    p = m.truth.point[on]
    v = p - pose1.to_world(thesis_artefact.centres_of(sid))
    normal = v / np.linalg.norm(v, axis=1, keepdims=True)
    radial = np.linalg.norm(v, axis=1) - thesis_artefact.radii[thesis_artefact.index(sid)]
    predicted = np.empty(len(p))
    for s in np.unique(sid):
        k = sid == s  # the body-fixed terms see the normal in the artefact frame: R n
        predicted[k] = deviation(sphere_form_terms(3, "artefact", s, 0.002), normal[k] @ pose1.R.T)
    ray = (p - scanner.camera.pinhole) / np.linalg.norm(p - scanner.camera.pinhole, axis=1, keepdims=True)
    good = np.abs(np.einsum("ij,ij->i", ray, normal)) > 0.5
    assert good.sum() > 500 and np.abs(predicted[good]).max() > 0.002
    # first order: the second-order terms (the hit's normal moves by ~delta tan(i) / r) stay below 5e-6 mm
    np.testing.assert_allclose(radial[good], predicted[good], rtol=0, atol=5e-6)
    assert np.sqrt(np.mean((radial[good] - predicted[good]) ** 2)) < 1e-6
    # no spurious self-shadowing from the moved hits
    assert abs(int((m.truth.light == 1).sum()) - int((m0.truth.light == 1).sum())) <= 2


# -- projector and camera non-linearity ---------------------------------------------------

def emitted_pattern(A, B, gamma, orders=60):
    """The rescaled emitted pattern's harmonics b_0..b_orders by quadrature (independent of the renderer)."""
    psi = np.linspace(0, 2 * np.pi, 20001)[:-1]
    v = ((A + B * np.cos(psi)) / (A + B)) ** gamma
    c = np.array([2 * np.mean(v * np.cos(h * psi)) for h in range(orders + 1)])
    b = B * c / c[1]
    b[0] = A
    return b


GAMMA = 1.3  # with B / A = 0.975: b2 / b1 = 0.087, b6 / b1 = 7e-4, b8 / b1 = 1.9e-4


@pytest.fixture(scope="module")
def gamma_render(scanner, scene):
    cfg = EXACT.model_copy(update={"offset": 0.4, "amplitude": 0.39})
    return cfg, render(scanner, scene, cfg, RenderErrors(projector_gamma=GAMMA))


def test_gamma_frames_are_the_emitted_harmonic_pattern(gamma_render):
    cfg, m = gamma_render
    b = emitted_pattern(cfg.offset, cfg.amplitude, GAMMA)
    expected = contract(m.truth, lambda psi: b[0] + sum(b[h] * np.cos(h * psi) for h in range(1, len(b))))
    unsaturated = (expected < 1).all(axis=0)  # glossy end caps saturate
    assert unsaturated.mean() > 0.99
    # rounding (0.5 DN) plus the neglected tail of harmonics (< 1e-6 of full scale, 0.07 DN)
    assert np.abs(m.frames - expected * cfg.max_dn)[:, unsaturated].max() < 0.5 + 0.07


def test_gamma_phase_error_is_the_n_step_aliasing_of_harmonics_6_and_8(gamma_render):
    """N = 7 steps reject harmonics 2..5 (and 9..12); 6, 8 (13, 15, ...) alias onto the
    fundamental: phase error = arg(b1 + b6 exp(-7i phi) + b8 exp(7i phi) + ...)."""
    cfg, m = gamma_render
    b = emitted_pattern(cfg.offset, cfg.amplitude, GAMMA)
    n = SEQ.n_steps
    bright = well_lit(m.truth)
    assert bright.sum() > 3000
    measured = demodulated_phase_error(m.frames, m.truth)[:, bright]
    tau = m.truth.tau_x_centre[bright]
    predicted = []
    for t in SEQ.fringe_counts:
        z = sum(b[h] * np.exp(1j * (h - 1) * t * tau) for h in range(1, len(b)) if h % n == 1) \
            + sum(b[h] * np.exp(-1j * (h + 1) * t * tau) for h in range(1, len(b)) if h % n == n - 1)
        predicted.append(np.angle(z))
    predicted = np.array(predicted)
    assert np.sqrt(np.mean(predicted ** 2)) > 2e-4  # harmonic 2 alone would give ~0.09 rad were it not rejected
    assert np.sqrt(np.mean((measured - predicted) ** 2)) < 3e-5  # 16-bit quantisation: ~1.5e-5 rad
    # the decoder without its ripple step carries the slope of those per-count errors
    d = decode(m.frames, SEQ, DecodeSettings(phase_ripple="off"), full_scale=cfg.max_dn)
    ok = d.valid[bright]
    err = d.tau["x"][bright][ok] - tau[ok]
    np.testing.assert_allclose(err, slope_of(predicted)[ok], rtol=0, atol=3e-6)
    # with it (the default), noise-free frames show the ripple beyond doubt and it is gone
    fixed = decode(m.frames, SEQ, full_scale=cfg.max_dn)
    assert fixed.ripple["x"].applied and fixed.ripple["x"].z > 100
    left = fixed.tau["x"][bright][ok] - tau[ok]
    assert np.sqrt(np.mean(left ** 2)) < 0.1 * np.sqrt(np.mean(slope_of(predicted)[ok] ** 2))


def test_camera_response_is_applied_to_the_mean_signal_and_leaves_the_phase(scanner, scene):
    cfg, e = EXACT, 0.02
    m = render(scanner, scene, cfg, RenderErrors(camera_linearity_error=e))
    lin = render(scanner, scene, cfg)
    i = contract(m.truth, lambda psi: cfg.offset + cfg.amplitude * np.cos(psi))
    unsaturated = (i < 1).all(axis=0)
    assert unsaturated.mean() > 0.99
    assert np.abs(m.frames - (i + 4 * e * i * (1 - i)) * cfg.max_dn)[:, unsaturated].max() < 0.5 + 1e-6
    assert np.abs(m.frames.astype(int) - lin.frames).max() > 0.01 * cfg.max_dn  # visible in the frames
    # a quadratic response only adds harmonic 2, which the 7-step estimator rejects
    a, b = decode(m.frames, SEQ, full_scale=cfg.max_dn), decode(lin.frames, SEQ, full_scale=cfg.max_dn)
    ok = a.valid & b.valid & well_lit(m.truth)
    assert ok.sum() > 3000 and np.abs(a.tau["x"][ok] - b.tau["x"][ok]).max() < 2e-6


# -- phase field and drift in a scan --------------------------------------------------------

def test_phase_field_is_what_the_decoder_adds_to_the_truth(scanner, scene):
    cfg = EXACT
    errs = RenderErrors(phase_field_rms_rad=1e-3, phase_field_modes=4)
    rng = measurement_rng(2026, "3-scanner1")
    m = render_measurement(scanner, scene, cfg, rng, SEQ, errs)
    ref = render(scanner, scene, cfg)
    field = m.phase_field
    assert field.shape == (2, 96, 96) and np.sqrt(np.mean(field ** 2, axis=(1, 2))) == pytest.approx([1e-3, 1e-3])
    again = measurement_rng(2026, "3-scanner1")
    again.integers(0, 2**63, dtype=np.int64)  # the noise key comes first
    np.testing.assert_array_equal(phase_field(again, (96, 96), 1e-3, 4), field)
    other = measurement_rng(2026, "3-scanner2")
    other.integers(0, 2**63, dtype=np.int64)
    assert abs(np.corrcoef(phase_field(other, (96, 96), 1e-3, 4)[0].ravel(), field[0].ravel())[0, 1]) < 0.9
    np.testing.assert_array_equal(m.truth.tau_x, ref.truth.tau_x)  # the truth is the geometry, not the error
    d = decode(m.frames, SEQ, full_scale=cfg.max_dn)
    ok = d.valid & well_lit(m.truth)
    assert ok.sum() > 3000
    for i, o in enumerate("xy"):
        truth = m.truth.tau_x if o == "x" else m.truth.tau_y
        np.testing.assert_allclose(d.tau[o][ok] - truth[ok], field[i][ok], rtol=0, atol=3e-6)


def test_drift_during_a_scan_shifts_the_decoded_phase_as_predicted(scanner, scene):
    cfg, drift = EXACT, 0.01
    m = render(scanner, scene, cfg, RenderErrors(scan_drift_rad=drift))
    # prediction: frame f of count t is shifted by t psi_f, psi_f = drift f / (n_frames - 1)
    lit = np.isfinite(m.truth.tau_x_centre) & well_lit(m.truth)
    tau = {"x": m.truth.tau_x_centre[lit], "y": m.truth.tau_y_centre[lit]}
    d = decode(m.frames, SEQ, DecodeSettings(phase_ripple="off"), full_scale=cfg.max_dn)
    fixed = decode(m.frames, SEQ, full_scale=cfg.max_dn)
    ok = d.valid[lit]
    for o in "xy":
        per_count = []
        for t in SEQ.fringe_counts:
            f = SEQ.frame_index(o, t, 0) + np.arange(SEQ.n_steps)
            psi = drift * f / (SEQ.n_frames - 1)
            delta = SEQ.step_phases()
            z = np.exp(-1j * delta) @ np.cos(t * tau[o][None, :] + t * psi[:, None] + delta[:, None])
            per_count.append(np.angle(z * np.exp(-1j * t * tau[o])))
        predicted = slope_of(np.array(per_count))
        assert np.abs(predicted).mean() > 1e-3
        np.testing.assert_allclose(d.tau[o][lit][ok] - tau[o][ok], predicted[ok], rtol=0, atol=3e-6)
        # the ripple step sees the steps' errors (two periods per fringe) in the slope's
        # residuals and takes out what varies with the phase (1.9e-5 -> 1.1e-7 rad RMS);
        # the shift common to all phases lies along t itself, no residual shows it, it stays
        left = fixed.tau[o][lit][ok] - tau[o][ok]
        assert fixed.ripple[o].applied
        assert np.std(left) < 0.05 * np.std(predicted[ok])
        assert np.mean(left) == pytest.approx(np.mean(predicted[ok]), rel=1e-3)


# -- drift over the session ---------------------------------------------------------------

def test_session_drift_is_a_random_walk_of_the_documented_size():
    e = SimulationErrors(session_drift_mm=0.003, session_drift_mrad=0.001, seed=5)
    poses = ["1", "2", "3", "4"]
    walk = session_displacement(e, "scanner1", poses)
    steps = sum(error_rng(5, "session", "scanner1", p).standard_normal(6) for p in poses[1:])
    np.testing.assert_allclose(walk, steps * np.array([0.003] * 3 + [1e-6] * 3), rtol=1e-15)
    assert not session_displacement(e, "scanner1", poses[:1]).any()  # zero at the first pose
    one_step = np.array([session_displacement(e, f"s{i}", ["1", "2"]) for i in range(600)])
    sd = one_step.std(axis=0) / np.array([0.003] * 3 + [1e-6] * 3)
    assert np.all(np.abs(sd - 1) < 4 * np.sqrt(1 / (2 * 600)))


def test_drifted_scanner_renders_the_moved_world_it_sees(scanner, thesis_artefact, pose1):
    displacement = np.array([0.8, -0.5, 0.3, 2e-4, -1e-4, 3e-4])
    moved = drifted_scanner(scanner, displacement)
    mid = (scanner.camera.pinhole + scanner.projector.pinhole) / 2
    angle = np.linalg.norm(displacement[3:])
    k = displacement[3:] / angle
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    Rd = np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K

    def motion(x):
        return (np.asarray(x) - mid) @ Rd.T + mid + displacement[:3]

    X = np.random.default_rng(2).uniform(-500, 500, (50, 3)) + pose1.t
    for a, b in ((scanner.camera, moved.camera), (scanner.projector, moved.projector)):
        np.testing.assert_allclose(b.pinhole, motion(a.pinhole), atol=1e-9)
        np.testing.assert_allclose(b.project(motion(X)), a.project(X), atol=1e-9)
    # rendered: the drifted scanner looking at the world moved with it sees the same
    # projector coordinates, at truth points moved by the drift
    T_moved = Frame.from_matrix(pose1.R @ Rd.T, motion(pose1.t))
    cfg = RenderConfig().ideal()
    a = render(scanner, artefact_scene(thesis_artefact, None, pose1, background=backdrop(scanner, 3500.0)), cfg)
    b = render(moved, artefact_scene(thesis_artefact, None, T_moved, background=backdrop(moved, 3500.0)), cfg)
    same = a.truth.centre_object_index == b.truth.centre_object_index
    spheres = np.isin(a.truth.centre_object_index, a.truth.objects_of_kind("sphere"))
    assert same.mean() > 0.999 and (same & spheres).sum() > 150
    np.testing.assert_allclose(b.truth.point[same], motion(a.truth.point[same]), atol=1e-6)
    lit = same & np.isfinite(a.truth.tau_x) & np.isfinite(b.truth.tau_x)
    assert lit.mean() > 0.9
    np.testing.assert_allclose(b.truth.tau_x[lit], a.truth.tau_x[lit], atol=1e-9)
    np.testing.assert_allclose(b.truth.tau_y[lit], a.truth.tau_y[lit], atol=1e-9)
    shift = np.linalg.norm(b.truth.point[same] - a.truth.point[same], axis=1)
    assert shift.min() > 0.3  # the points did move (0.99 mm and 0.39 mrad about the scanner)


# -- lens behaviour outside the 14-parameter model ----------------------------------------

def test_thin_prism_moves_the_projection_by_the_corner_displacement(thesis_rig):
    cam = thesis_rig.scanner("scanner1").camera  # the native 2048 px format
    s1, s2 = thin_prism(cam.format, 0.2, 0.7)
    pitch = cam.format.width_mm / (cam.format.width_px - 1)
    pack = g.sensor_pack(cam, (s1, s2))
    corner = cam.format.pixel_to_mm(np.array([[0.0, 0.0], [2047.0, 2047.0], [2047.0, 0.0], [600.0, 1300.0]]))
    origins, dirs = cam.rays(corner)
    X = origins + 2500 * dirs
    for x in X:
        xi, eta, _ = g.project_point(x[0], x[1], x[2], pack)
        model = cam.project(x[None])[0]
        ideal = -cam.c * cam.to_sensor(x[None])[0, :2] / cam.to_sensor(x[None])[0, 2]
        r2 = float(ideal @ ideal)
        np.testing.assert_allclose([xi, eta] - model, [s1 * r2, s2 * r2], rtol=0, atol=1e-12)
        # the renderer's ray through its own projection returns to the point
        dx, dy, dz, ok, _, _ = g.image_ray(xi, eta, pack, 0.0, 0.0)
        v = x - cam.pinhole
        assert ok and np.linalg.norm(np.cross(v / np.linalg.norm(v), [dx, dy, dz])) < 1e-11
    xi, eta, _ = g.project_point(*X[0], pack)
    shift_px = np.hypot(*([xi, eta] - cam.project(X[:1])[0])) / pitch
    r_corner2 = (cam.format.width_mm ** 2 + cam.format.height_mm ** 2) / 4
    ideal = -cam.c * cam.to_sensor(X[:1])[0, :2] / cam.to_sensor(X[:1])[0, 2]
    assert shift_px == pytest.approx(0.2 * (ideal @ ideal) / r_corner2, rel=1e-9)
    assert shift_px == pytest.approx(0.2, rel=0.05)  # the corner's ideal radius is within 5 % of the format's


def test_rendered_projector_coordinates_include_the_thin_prism(scanner, scene):
    e = SimulationErrors(thin_prism_corner_px=0.5, seed=2)
    errs = render_errors(e, scanner)
    m = render(scanner, scene, RenderConfig().ideal(), errs)
    lit = m.truth.light == 1
    prj = scanner.projector
    pack = g.sensor_pack(prj, errs.projector_prism)
    rendered = np.stack([m.truth.tau_x_centre[lit], m.truth.tau_y_centre[lit]], 1)
    prism = prj.measured(np.array([g.project_point(*p, pack)[:2] for p in m.truth.point[lit]]))
    model = prj.measured(prj.project(m.truth.point[lit]))
    np.testing.assert_allclose(rendered, prism, atol=1e-6)
    # against the 14-parameter model: 0.5 SLM pixels x (r / r_corner)^2 (r: ideal radius)
    shift_px = np.linalg.norm(prj.image_mm(rendered) - prj.image_mm(model), axis=1) \
        / (prj.format.width_mm / (prj.format.width_px - 1))
    xs = prj.to_sensor(m.truth.point[lit])
    r2 = np.sum((prj.c * xs[:, :2] / xs[:, 2:]) ** 2, axis=1)
    np.testing.assert_allclose(shift_px, 0.5 * r2 / ((prj.format.width_mm ** 2 + prj.format.height_mm ** 2) / 4),
                               rtol=1e-6)
    assert shift_px.max() > 0.3


# -- the ideal profile is the renderer without errors ---------------------------------------

def test_ideal_profile_renders_bit_for_bit_as_without_errors(scanner, scene, pose1):
    """With every switch off no error reaches the renderer, and explicitly trivial
    errors change nothing either (noise included). The frames were also compared with
    the renderer as it was before the switches existed: identical."""
    assert render_errors(SimulationErrors(), scanner, pose1, "artefact", scene.sphere_ids) is None
    cfg = RenderConfig()
    a = render(scanner, scene, cfg, seed=3)
    b = render(scanner, scene, cfg, RenderErrors(), seed=3)
    np.testing.assert_array_equal(a.frames, b.frames)
    np.testing.assert_array_equal(a.truth.tau_x, b.truth.tau_x)
    assert b.phase_field is None
    sim = SimulationConfig()
    assert as_built_artefact(sim, SimulationErrors()).centres.tolist() == sim.artefact().centres.tolist()
    bar = Artefact(("A", "B"), [[0, 0, 0], [1000, 0, 0]], [50, 50], [4e-4, 4e-4])
    assert as_built_ballbar(bar, SimulationErrors(profile="realistic", ballbar_deviation=False)) is bar


def test_sphere_scene_without_spheres_in_the_form_table_is_unchanged(scanner):
    s = Scene((SceneObject("sphere:Q", "sphere", "sphere", (Sphere(scanner.camera.pinhole + 2500
                                                                       * scanner.camera.R[2], 60.0),), "Q"),))
    cfg = RenderConfig().ideal()
    form = {"Z": sphere_form_terms(1, "artefact", "Z", 0.002)}
    np.testing.assert_array_equal(render(scanner, s, cfg, RenderErrors(sphere_form=form)).frames,
                                  render(scanner, s, cfg).frames)


# -- both doors, keys ------------------------------------------------------------------------

@pytest.fixture(scope="module")
def realistic_config(tmp_path_factory):
    from conftest import write_small_config

    d = tmp_path_factory.mktemp("realistic")
    path = write_small_config(d)
    cfg = yaml.safe_load(path.read_text())
    cfg["simulate"]["acquisition"].update({"camera_width_px": 48, "store_frames": True})
    cfg["simulate"]["verification"]["camera_width_px"] = 48
    cfg["simulate"]["errors"] = {"profile": "realistic"}
    path.write_text(yaml.safe_dump(cfg))
    return path


@pytest.fixture(scope="module")
def realistic_run(realistic_config, tmp_path_factory):
    """The small realistic rig through both doors: `fringecal simulate` (data set and
    truth folder) and the simulated run's source steps (run directory)."""
    from fringecal.rundir import RunDir
    from fringecal.simulate.export import write_dataset
    from fringecal.steps import run_pipeline

    cfg = load_run_config(realistic_config)
    d = tmp_path_factory.mktemp("doors")
    write_dataset(cfg, d / "data", d / "data-truth", "png")
    rd = RunDir(d / "run").create()
    run_pipeline(rd, cfg, until="simulate-ballbar")
    return rd, d / "data", d / "data-truth"


@pytest.mark.slow
def test_both_doors_render_the_as_built_world(realistic_run):
    """`fringecal simulate` and the simulated run's steps render the same frames with
    every error on; each keeps the CMM table and the certificate for the pipeline and
    the as-built artefact and bar as truth."""
    from fringecal.fringe.importer import read_frames
    from fringecal.store import open_store

    rd, out, truth = realistic_run
    table = load_artefact(out / "artefact.csv")
    built = load_artefact(truth / "artefact.csv")
    np.testing.assert_allclose(rd.artefact.load().centres, table.centres, atol=1e-9)
    np.testing.assert_allclose(rd.truth.artefact.load().centres, built.centres, atol=1e-9)
    assert 0.005 < np.abs(built.centres - table.centres).max() < 0.06
    cert, bar = load_artefact(out / "verification" / "ballbar.csv"), load_artefact(truth / "ballbar.csv")
    np.testing.assert_allclose(rd.ballbar.load().centres, cert.centres, atol=1e-9)
    np.testing.assert_allclose(rd.truth.ballbar.load().centres, bar.centres, atol=1e-9)
    length = [float(np.linalg.norm(np.diff(x.centres, axis=0))) for x in (bar, cert)]
    assert 0 < abs(length[0] - length[1]) < 0.003
    assert "simulation profile realistic" in (out / "dataset.yaml").read_text()
    for folder, m in ((out / "measurements" / "9" / "scanner2", "9-scanner2"),
                      (out / "measurements" / "1" / "scanner1", "1-scanner1"),
                      (out / "verification" / "bb04" / "scanner1", "bb04-scanner1")):
        np.testing.assert_array_equal(read_frames(folder).frames, open_store(rd.store(m).path)["frames"].values)


@pytest.mark.slow
def test_each_switch_keys_exactly_the_steps_it_affects(realistic_run, realistic_config, tmp_path):
    """A switch keys the steps that read it: artefact switches the prepare step (whose
    as-built tables then key the renders by content), render switches every rendered
    store, the session drift the calibration stores only."""
    from fringecal.steps import SIMULATED_SOURCE, run_pipeline
    from fringecal.steps.keys import step_key

    rd = realistic_run[0]
    base = yaml.safe_load(realistic_config.read_text())

    def config(**errors):
        doc = {**base, "simulate": {**base["simulate"], "errors": {"profile": "realistic", **errors}}}
        path = tmp_path / "run.yaml"
        path.write_text(yaml.safe_dump(doc))
        return load_run_config(path)

    def keys(cfg):
        return {(s.name, item): step_key(s, rd, s.view(cfg), item) for s in SIMULATED_SOURCE
                for item in s.items(rd, s.view(cfg))}

    before = keys(config())
    for change, expected in (
            ({"session_drift_mm": 0.01}, {"simulate-render"}),
            ({"projector_gamma": 1.8}, {"simulate-render", "simulate-ballbar"}),
            ({"thin_prism_corner_px": 0.3}, {"simulate-render", "simulate-ballbar"}),
            ({"lens_field_rms_um": 1.0}, {"simulate-render", "simulate-ballbar"}),
            ({"phase_field_modes": 6}, {"simulate-render", "simulate-ballbar"}),
            ({"sphere_diameter_sd_mm": 0.005}, {"simulate-prepare"}),
            ({"ballbar_deviation": False}, {"simulate-prepare"}),
            ({"profile": "realistic", "seed": 1, "cmm_u_scale": 1.0}, set())):  # the same values, said explicitly
        after = keys(config(**change))
        assert {name for name, item in after if after[name, item] != before[name, item]} == expected, change
    # end to end: the drift reruns the calibration stores, nothing else
    records = run_pipeline(rd, config(session_drift_mm=0.01), until="simulate-ballbar")
    assert {name for name, items in records.items() if any(not r["reused"] for r in items.values())} \
        == {"simulate-render"}
