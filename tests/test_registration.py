import numpy as np
import pytest

from fringecal.frames import Frame
from fringecal.registration import DegenerateGeometryError, RigidRegistration, kabsch


def random_frame(rng):
    return Frame.from_params(np.r_[rng.uniform(-2000, 2000, 3), rng.uniform(-np.pi, np.pi),
                                   rng.uniform(-1.5, 1.5), rng.uniform(-np.pi, np.pi)])


def test_random_rigid_transforms_recovered(rng):
    worst_t = worst_R = 0.0
    for _ in range(200):
        n = rng.integers(3, 20)
        local = rng.normal(size=(n, 3)) * rng.uniform(10, 1000)
        T = random_frame(rng)
        reg = RigidRegistration.from_estimate(local, T.to_world(local), near=T.angles)
        worst_t = max(worst_t, np.abs(reg.frame.t - T.t).max())
        worst_R = max(worst_R, np.abs(reg.frame.R - T.R).max())
        np.testing.assert_allclose(reg.frame.angles, T.angles, atol=1e-9)
    assert worst_t < 1e-9
    assert worst_R < 1e-12


def test_never_returns_a_reflection(rng):
    # A mirrored target: the best proper rotation, never det = -1.
    local = rng.normal(size=(8, 3)) * 100
    mirrored = local * np.array([1, 1, -1])
    M, _ = kabsch(local, mirrored)
    assert np.linalg.det(M) == pytest.approx(1.0, abs=1e-12)
    # Planar points admit a reflection with zero residual; it must not be chosen.
    planar = np.c_[rng.normal(size=(6, 2)) * 100, np.zeros(6)]
    M, _ = kabsch(planar, planar @ np.diag([1, -1, 1]))
    assert np.linalg.det(M) == pytest.approx(1.0, abs=1e-12)


def test_degenerate_inputs_are_refused():
    with pytest.raises(DegenerateGeometryError, match="at least 3"):
        RigidRegistration.from_estimate(np.zeros((2, 3)), np.zeros((2, 3)))
    line = np.c_[np.arange(4.0) * 100, np.zeros(4), np.zeros(4)]
    with pytest.raises(DegenerateGeometryError, match="collinear"):
        RigidRegistration.from_estimate(line, line)


def test_residuals_and_rms(rng):
    local = rng.normal(size=(6, 3)) * 300
    T = random_frame(rng)
    noisy = T.to_world(local) + rng.normal(size=(6, 3)) * 0.01
    reg = RigidRegistration.from_estimate(local, noisy)
    r = reg.residuals(local, noisy)
    assert reg.rms == pytest.approx(np.sqrt(np.mean(r**2)))
    assert 0.001 < reg.rms < 0.02
