"""Weighting functions (8)-(11) against their closed forms."""
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from hdrmerge_cli.core.crf import CRF
from hdrmerge_cli.core.weights import (
    NOISE_MODEL_WEIGHTS, WEIGHTING_FUNCTIONS, weights_debevec1997_triangle, weights_mann1995_slope,
)

CLASSICAL = sorted(set(WEIGHTING_FUNCTIONS) - set(NOISE_MODEL_WEIGHTS))

V = np.linspace(-0.1, 1.1, 1201)  # includes codes below black and above white


@pytest.mark.parametrize("name", CLASSICAL)
@pytest.mark.parametrize("crf", [CRF("linear"), CRF("srgb"), CRF("gamma", 2.2)])
def test_weights_are_tables_in_unit_interval_zero_at_clipping(name, crf):
    w = WEIGHTING_FUNCTIONS[name](V, crf.inverse(np.clip(V, 0, 1)))
    assert w.shape == V.shape and np.all(np.isfinite(w))
    assert w.min() >= 0 and w.max() == pytest.approx(1.0)
    assert np.all(w[(V <= 0) | (V >= 1)] == 0)


def test_triangle_is_eq8():
    z = np.arange(256.0)
    w = weights_debevec1997_triangle(z / 255, z / 255)
    expected = np.where(z <= 127.5, z, 255 - z)
    expected[255] = 0
    np.testing.assert_allclose(w, expected / expected.max(), atol=1e-12)


@settings(max_examples=25, deadline=None)
@given(st.floats(1.2, 3.0))
def test_mann_is_inverse_slope_of_g_for_gamma_crfs(gamma):
    """Eq. (9): w = dz / d log q; for gamma^-1(v) = v^G, g'(v) = G / v, so w ∝ v."""
    v = np.linspace(0, 1, 4097)
    w = weights_mann1995_slope(v, v**gamma)
    inner = (v > 0.01) & (v < 0.99)
    np.testing.assert_allclose(w[inner], v[inner] / v[inner].max() * (v[inner].max() / v[v < 1].max()), rtol=2e-3)


def test_mann_matches_numerical_derivative_for_srgb():
    v = np.linspace(0, 1, 256)
    lin = CRF("srgb").inverse(v)
    w = weights_mann1995_slope(v, lin)
    # independent: the sRGB EOTF's derivative in closed form
    a = 0.055
    dlin = np.where(v <= 0.04045, 1 / 12.92, 2.4 / (1 + a) * ((v + a) / (1 + a)) ** 1.4)
    ref = lin / dlin
    ref[[0, -1]] = 0
    np.testing.assert_allclose(w, ref / ref.max(), atol=5e-3)
