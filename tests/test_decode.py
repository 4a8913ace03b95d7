"""Decoder numerics against frames written by the test's own formula (not a simulator):
I = A + B cos(t * w + 2 pi k / N) for orientation x (w = tau_x) and y (w = tau_y)."""

import numpy as np
import pytest

from fringecal.fringe.decode import DecodeSettings, _atan2, decode, tau_noise_theory
from fringecal.fringe.sequence import FringeSequence


def fringe_frames(w_x, w_y, counts, n_steps, A=2000.0, B=1500.0, noise=0.0, rng=None, dtype=np.float64):
    """(2 * len(counts) * n_steps, *w.shape) frames, orientation x then y, counts, steps."""
    out = []
    for w in (w_x, w_y):
        for t in counts:
            for k in range(n_steps):
                img = A + B * np.cos(t * w + 2 * np.pi * k / n_steps)
                if noise:
                    img = img + rng.normal(0.0, noise, img.shape)
                out.append(img)
    frames = np.stack(out)
    if np.dtype(dtype).kind == "u":
        frames = np.clip(np.rint(frames), 0, np.iinfo(dtype).max)
    return frames.astype(dtype)


def wrap(a):
    return (a + np.pi) % (2 * np.pi) - np.pi


@pytest.mark.parametrize("n_steps", [3, 4, 7])
@pytest.mark.parametrize("counts", [(64, 63, 62, 60, 56, 48, 32), (16, 15, 14, 12), (100, 99, 98, 96, 92)])
def test_noise_free_frames_decode_to_the_known_phase(n_steps, counts, rng):
    w_x = rng.uniform(-np.pi, np.pi, (12, 40))
    w_y = rng.uniform(-np.pi, np.pi, (12, 40))
    seq = FringeSequence(counts, n_steps)
    res = decode(fringe_frames(w_x, w_y, counts, n_steps), seq)
    assert np.abs(wrap(res.tau["x"] - w_x)).max() < 2e-6
    assert np.abs(wrap(res.tau["y"] - w_y)).max() < 2e-6
    for o in "xy":
        np.testing.assert_allclose(res.modulation[o], 1500.0, rtol=1e-5)
        assert res.phase_error[o].max() < 1e-4
    np.testing.assert_allclose(res.texture, 2000.0, rtol=1e-6)
    assert res.valid.all() and not res.saturated.any()


def test_zero_unwrapping_errors_over_the_full_tau_range():
    """Every w in [-pi, pi] (endpoints included; +-pi are the same code), 12-bit frames."""
    w = np.linspace(-np.pi, np.pi, 200_001).reshape(1, -1)
    seq = FringeSequence()
    frames = fringe_frames(w, -w, seq.fringe_counts, 7, A=2000, B=1800, dtype=np.uint16)
    res = decode(frames, seq, full_scale=4095)
    for o, truth in (("x", w), ("y", -w)):
        err = np.abs(wrap(res.tau[o] - truth))
        # 12-bit quantisation alone: sigma_tau ~ 0.29 / 1800 * sqrt(2/7) / 148 ~ 6e-7 rad
        assert err.max() < 1e-5, (o, err.max())
        assert res.phase_error[o].max() < 5e-3
    assert res.valid.all()


def test_tau_stays_in_range_when_noise_wraps_the_first_beat():
    """Near the projector edge, phase noise on count 63 can push the first beat
    (phi_64 - phi_63 = w) past -pi; the chain then finds the twin w + 2 pi, which
    fits every integer count equally well. The decoder returns it in [-pi, pi]."""
    seq = FringeSequence()
    w = np.array([[-3.10, 3.10, 0.5]])
    shift = np.array([[0.1, -0.1, 0.1]])  # phase error on count 63 only
    frames = []
    for o in seq.orientations:
        for t in seq.fringe_counts:
            for k in range(seq.n_steps):
                frames.append(2000 + 1500 * np.cos(t * w + (shift if t == 63 else 0) + 2 * np.pi * k / 7))
    res = decode(np.stack(frames), seq)
    for o in "xy":
        assert np.all(np.abs(res.tau[o]) <= np.pi)
        # the one perturbed phase moves the least-squares slope by 63 * 0.1 / sum(t^2) = 2.9e-4 rad
        np.testing.assert_allclose(res.tau[o], w + 63 * shift / 21973, atol=1e-6)


def test_tau_noise_matches_theory_and_the_beat_estimate_is_several_times_noisier():
    rng = np.random.default_rng(7)
    seq = FringeSequence()
    n = 60_000
    w_x = rng.uniform(-2.8, 2.8, (1, n))
    w_y = rng.uniform(-2.8, 2.8, (1, n))
    sigma_i, B = 20.0, 1000.0
    frames = fringe_frames(w_x, w_y, seq.fringe_counts, 7, A=2000, B=B, noise=sigma_i, rng=rng)
    res = decode(frames, seq, beat_estimate=True)
    theory = tau_noise_theory(seq, sigma_i, B)
    for o, truth in (("x", w_x), ("y", w_y)):
        ls = np.std(wrap(res.tau[o] - truth))
        beat = np.std(wrap(res.tau_beat[o] - truth))
        # the standard deviation of n samples is known to ~1/sqrt(2n) = 0.3 %; 4 % tolerance
        assert ls == pytest.approx(theory["least_squares"], rel=0.04)
        assert beat == pytest.approx(theory["beat"], rel=0.04)
        assert beat / ls == pytest.approx(6.55, rel=0.06)
        # the phase-error map estimates sigma_phi (K - 1 degrees of freedom)
        assert np.sqrt(np.mean(res.phase_error[o] ** 2)) == pytest.approx(theory["phase"], rel=0.03)
        assert np.abs(wrap(res.tau[o] - truth)).max() < 10 * theory["least_squares"]  # no unwrapping error


def test_validity_mask_thresholds():
    seq = FringeSequence(n_steps=4)
    w = np.linspace(-3, 3, 40).reshape(4, 10)
    frames = fringe_frames(w, w, seq.fringe_counts, 4, A=100, B=80, dtype=np.uint8)
    frames[:, 0, :5] = 100 + (frames[:, 0, :5].astype(int) - 100) // 20  # modulation ~4 DN < 2 % of 255
    frames[3, 1, 0] = 255  # one saturated sample
    rng = np.random.default_rng(1)
    frames[:, 2, 2] = rng.permutation(frames[:, 2, 2])  # scrambled frames: inconsistent phases
    res = decode(frames, seq, DecodeSettings(min_modulation=0.02, max_phase_error=0.3))
    assert res.full_scale == 255
    assert not res.valid[0, :5].any() and res.modulation["x"][0, :5].max() < 0.02 * 255
    assert res.saturated[1, 0] and not res.valid[1, 0] and res.saturated.sum() == 1
    assert res.phase_error["x"][2, 2] > 0.3 and not res.valid[2, 2]
    assert res.valid.sum() == 40 - 5 - 1 - 1
    loose = decode(frames, seq, DecodeSettings(min_modulation=0.0, max_phase_error=10.0))
    assert loose.valid.sum() == 40 - 1  # only the saturated pixel remains invalid


def test_single_orientation_and_float_frames_without_full_scale():
    seq = FringeSequence((8, 7, 6), 3, ("y",))
    w = np.linspace(-3.1, 3.1, 30).reshape(3, 10)
    frames = np.stack([0.5 + 0.4 * np.cos(t * w + 2 * np.pi * k / 3) for t in (8, 7, 6) for k in range(3)])
    res = decode(frames.astype(np.float32), seq)
    assert set(res.maps()) == {"tau_y", "modulation_y", "phase_error_y", "texture", "valid"}
    assert np.abs(res.tau["y"] - w).max() < 1e-5 and res.valid.all()


def test_wrong_frame_count_is_refused():
    with pytest.raises(ValueError, match=r"expected frames of shape \(98, H, W\)"):
        decode(np.zeros((97, 4, 4), np.uint16), FringeSequence())


def test_fast_atan2_matches_numpy():
    g = np.concatenate([np.linspace(-5, 5, 1001), [1e-300, -1e-300, 1e6, -1e6]])
    y, x = np.meshgrid(g, g)
    ours = np.vectorize(_atan2.py_func)(y.ravel(), x.ravel())
    ref = np.arctan2(y.ravel(), x.ravel())
    diff = np.abs(wrap(ours - ref))
    assert diff.max() < 1e-10
    assert _atan2.py_func(0.0, 0.0) == 0.0  # no modulation: a defined phase, never NaN
