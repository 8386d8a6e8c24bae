"""Filter design and the numpy reference transform, checked against independent formulas
(scipy's mirror convolution, numpy's linear interpolation).  No OpenCL here."""
from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.ndimage as ndi

from endowave_cl.wavelet import filters as F


@pytest.mark.parametrize("q,R", [(1, 4), (2, 6), (3, 6), (4, 7), (7, 7), (8, 8), (50, 8)])
def test_support_radius(q, R):
    assert F.support_radius(q) == R
    assert all(v.size == 2 * R + 1 for v in F.design_filters(q).values())


@pytest.mark.parametrize("q", [1, 2, 3, 5])
def test_filters_follow_the_paper_equations(q):
    a = (q + 1) / q
    s = 1 / a
    f = F.design_filters(q)
    R = F.support_radius(q)
    u = range(-R, R + 1)
    z0 = sum(math.exp(-0.5 * (v / s) ** 2) for v in u)
    z1 = sum(abs(-v * math.exp(-0.5 * (v / s) ** 2)) for v in u)
    zg = sum(abs(math.sin(math.pi * v / a) * math.exp(-0.5 * (v / (2 * s)) ** 2)) for v in u)
    for t in (-2, -1, 0, 1, 3):
        i = t + R
        assert f["h0"][i] == pytest.approx(math.exp(-0.5 * (t / s) ** 2) / z0, rel=1e-12, abs=1e-300)
        assert f["h1"][i] == pytest.approx(-t * math.exp(-0.5 * (t / s) ** 2) / z1, rel=1e-12, abs=1e-300)
        assert f["g"][i] == pytest.approx(
            math.sin(math.pi * t / a) * math.exp(-0.5 * (t / (2 * s)) ** 2) / zg, rel=1e-12, abs=1e-15)
    assert f["h0"].sum() == pytest.approx(1.0)
    assert np.abs(f["h1"]).sum() == pytest.approx(1.0)
    assert np.abs(f["g"]).sum() == pytest.approx(1.0)
    assert abs(f["h1"].sum()) < 1e-12 and abs(f["g"].sum()) < 1e-12        # zero mean (odd)
    np.testing.assert_allclose(f["h0"], f["h0"][::-1], atol=1e-15)
    # the truncated tail of the widest Gaussian is below 4 standard deviations
    assert f["h0"][0] < 1e-6 and abs(f["g"][0]) < 1e-3


@pytest.mark.parametrize("n", [7, 9, 30])
@pytest.mark.parametrize("flen", [1, 3, 9, 13])
def test_reference_conv_is_scipy_mirror_convolution(n, flen):
    rng = np.random.default_rng(n * 100 + flen)
    x = rng.standard_normal((4, n, 2))
    f = rng.standard_normal(flen)
    np.testing.assert_allclose(F.conv_axis(x, f, 1), ndi.convolve1d(x, f, axis=1, mode="mirror"), atol=1e-12)


def test_reference_conv_reflects_repeatedly_on_short_signals():
    # n = 3: the reflection has period 4, positions -4..6 -> 0 1 2 1 0 1 2 1 0 1 2
    assert list(F.reflect_index(np.arange(-4, 7), 3)) == [0, 1, 2, 1, 0, 1, 2, 1, 0, 1, 2]
    assert list(F.reflect_index(np.arange(-3, 4), 1)) == [0] * 7
    x = np.array([1.0, 10.0, 100.0])
    f = np.zeros(9)
    f[1] = 1.0  # the single tap t = -3: out[k] = x[reflect(k + 3)] = x[1], x[0], x[1]
    np.testing.assert_array_equal(F.conv_axis(x, f, 0), [10.0, 1.0, 10.0])
    f = np.zeros(9)
    f[6] = 1.0  # t = 2: out[k] = x[reflect(k - 2)] = x[2], x[1], x[0]
    np.testing.assert_array_equal(F.conv_axis(x, f, 0), [100.0, 10.0, 1.0])


@pytest.mark.parametrize("q", [1, 2, 3, 4])
@pytest.mark.parametrize("n", [1, 2, 5, 16, 17])
def test_reference_resampling_is_linear_interpolation(q, n):
    x = np.random.default_rng(n).standard_normal(n)
    y = F.resample_axis(x, q, 0)
    pos = np.arange(F.resampled_length(n, q)) * (q + 1) / q
    assert pos[-1] <= n - 1 < pos[-1] + (q + 1) / q
    np.testing.assert_allclose(y, np.interp(pos, np.arange(n), x), atol=1e-12)


def test_reference_dyadic_resampling_is_every_second_sample():
    x = np.random.default_rng(0).standard_normal((7, 9, 3))
    np.testing.assert_array_equal(F.resample_axis(F.resample_axis(x, 1, 0), 1, 1), x[::2, ::2])
    assert F.level_shapes(512, 640, 1, 2) == [(256, 320), (128, 160)]
    assert F.level_shapes(512, 640, 2, 2) == [(341, 427), (227, 285)]
