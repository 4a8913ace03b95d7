"""Camera noise with a counter-based random generator (numba).

Each pixel draws the noise of all its frames, in frame order, from its own stream
``splitmix64(key, pixel)``, so the result depends only on the key (drawn from the
caller's ``numpy.random.Generator``) and never on how threads split the image.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_M1 = np.uint64(0xBF58476D1CE4E5B9)
_M2 = np.uint64(0x94D049BB133111EB)
_S30, _S27, _S31, _S11 = np.uint64(30), np.uint64(27), np.uint64(31), np.uint64(11)
_TWO_M53 = 2.0 ** -53
#: Below this mean (electrons) shot noise is drawn exactly (Knuth), above by its normal limit.
POISSON_EXACT_BELOW = 30.0


@njit(cache=True, error_model="numpy")
def _mix(z):
    z = (z ^ (z >> _S30)) * _M1
    z = (z ^ (z >> _S27)) * _M2
    return z ^ (z >> _S31)


@njit(cache=True)
def stream(key, counter):
    """Start of the random stream of one (frame, pixel)."""
    return _mix(key ^ _mix(np.uint64(counter) * _GOLDEN + _GOLDEN))


@njit(cache=True, error_model="numpy")
def uniform(state):
    """(next state, uniform in (0, 1))."""
    state = state + _GOLDEN
    return state, (float(_mix(state) >> _S11) + 0.5) * _TWO_M53


# Acklam's rational approximation of the normal quantile (relative error < 1.2e-9).
_QA = (-3.969683028665376e+01, 2.209460984245205e+02, -2.759285104469687e+02,
       1.383577518672690e+02, -3.066479806614716e+01, 2.506628277459239e+00)
_QB = (-5.447609879822406e+01, 1.615858368580409e+02, -1.556989798598866e+02,
       6.680131188771972e+01, -1.328068155288572e+01)
_QC = (-7.784894002430293e-03, -3.223964580411365e-01, -2.400758277161838e+00,
       -2.549732539343734e+00, 4.374664141464968e+00, 2.938163982698783e+00)
_QD = (7.784695709041462e-03, 3.224671290700398e-01, 2.445134137142996e+00, 3.754408661907416e+00)
_P_LOW = 0.02425


@njit(cache=True)
def _tail(p):
    q = math.sqrt(-2.0 * math.log(p))
    return (((((_QC[0] * q + _QC[1]) * q + _QC[2]) * q + _QC[3]) * q + _QC[4]) * q + _QC[5]) / \
        ((((_QD[0] * q + _QD[1]) * q + _QD[2]) * q + _QD[3]) * q + 1.0)


@njit(cache=True, error_model="numpy")
def quantile(p):
    """Standard normal quantile of ``p`` in (0, 1) (Acklam)."""
    if p < _P_LOW:
        return _tail(p)
    if p > 1.0 - _P_LOW:
        return -_tail(1.0 - p)
    return _central(p)


@njit(cache=True, error_model="numpy")
def _central(p):
    q = p - 0.5
    r = q * q
    return (((((_QA[0] * r + _QA[1]) * r + _QA[2]) * r + _QA[3]) * r + _QA[4]) * r + _QA[5]) * q / \
        (((((_QB[0] * r + _QB[1]) * r + _QB[2]) * r + _QB[3]) * r + _QB[4]) * r + 1.0)


@njit(cache=True)
def normal(state):
    """(next state, standard normal) by inverting the normal CDF at a uniform draw."""
    state, p = uniform(state)
    return state, quantile(p)


@njit(cache=True)
def record(mean_e, state, shot, sigma_e, inv_gain, max_dn):
    """Digital number recorded for ``mean_e`` expected electrons: (next state, dn).

    Poisson shot noise (if ``shot``; exact below ``POISSON_EXACT_BELOW`` electrons,
    else its normal limit), Gaussian noise of ``sigma_e`` electrons (read plus
    excess), gain ``1 / inv_gain`` e-/DN, rounding, clipping to [0, max_dn].
    """
    mean_e = max(mean_e, 0.0)
    if shot and mean_e < POISSON_EXACT_BELOW:
        limit = math.exp(-mean_e)
        k = 0
        state, prod = uniform(state)
        while prod > limit:
            k += 1
            state, u = uniform(state)
            prod *= u
        state, z = normal(state)
        e = k + sigma_e * z
    else:
        state, z = normal(state)
        e = mean_e + math.sqrt(mean_e + sigma_e * sigma_e if shot else sigma_e * sigma_e) * z
    return state, quantise(e * inv_gain, max_dn)


@njit(cache=True, error_model="numpy")
def record_pixels(mean_e, states, shot, sigma_e, inv_gain, max_dn, out, scratch):
    """:func:`record` for many pixels, each with its own stream: the same draws and the
    same numbers, in passes the compiler can vectorise.

    Called pixel by pixel, :func:`record`'s branches and numba's division check keep
    the arithmetic scalar (camera noise was ~60 % of a render). Here only the uniform
    draws, the rare exact-Poisson pixels and the normal tails (5 % of draws) stay
    scalar; the central quantile, the noise scaling and the quantisation run over all
    pixels (``error_model="numpy"``: no ZeroDivisionError branch). Pixels that see
    nothing (mean exactly 0, common around an artefact) join the vector path. Shapes:
    ``mean_e``, ``states``, ``out`` (n,) (``mean_e`` is overwritten); ``scratch`` (3, n).
    """
    n = mean_e.shape[0]
    u, z, exact_dn = scratch[0], scratch[1], scratch[2]
    var_read = sigma_e * sigma_e
    for c in range(n):
        m = max(mean_e[c], 0.0)
        mean_e[c] = m
        if shot and m < POISSON_EXACT_BELOW and m > 0.0:
            states[c], dn = record(m, states[c], shot, sigma_e, inv_gain, max_dn)
            exact_dn[c] = dn
            u[c] = -1.0  # no uniform of (0, 1): this pixel is done
        else:
            if shot and m == 0.0:
                # Knuth's loop at mean 0 takes one draw and ends at k = 0, whatever it is
                # (exp(-0) = 1 > u); the normal below then gives k + sigma_e z exactly,
                # since sqrt(0 + sigma_e^2) == sigma_e in binary floating point.
                states[c] = states[c] + _GOLDEN
            states[c], u[c] = uniform(states[c])
    for c in range(n):
        z[c] = _central(u[c])
    for c in range(n):
        if (u[c] < _P_LOW or u[c] > 1.0 - _P_LOW) and u[c] > 0.0:
            z[c] = quantile(u[c])
    if shot:
        for c in range(n):
            out[c] = quantise((mean_e[c] + math.sqrt(mean_e[c] + var_read) * z[c]) * inv_gain, max_dn)
    else:
        for c in range(n):
            out[c] = quantise((mean_e[c] + math.sqrt(var_read) * z[c]) * inv_gain, max_dn)
    for c in range(n):
        if u[c] < 0.0:
            out[c] = np.uint16(exact_dn[c])


@njit(cache=True, error_model="numpy")
def quantise(x, max_dn):
    """Round to the nearest count and clip to [0, max_dn]."""
    dn = math.floor(x + 0.5)
    if dn < 0:
        return np.uint16(0)
    if dn > max_dn:
        return np.uint16(max_dn)
    return np.uint16(dn)
