"""RSS safe distance against Intel ad-rss-lib's published unit-test vectors."""

import jax
import numpy as np
import pytest

from jaxfalsify import rss_safe_distance

KMH = 1 / 3.6


@pytest.mark.parametrize("v, rho, a, b, expected", [
    (100 * KMH, 2.0, 3.5, 4.0, 213.74),
    (100 * KMH, 1.0, 3.5, 4.0, 151.81),
    (50 * KMH, 2.0, 2.0, 4.0, 71.77),
])
def test_ad_rss_lib_vectors(v, rho, a, b, expected):
    d = rss_safe_distance(v, 0.0, response_time=rho, accel_max=a, brake_min=b)
    assert float(d) == pytest.approx(expected, abs=0.01)


def test_stopping_distance_vector():
    # 100 km/h braking at 6 m/s^2 without response time stops after 64.3 m
    d = rss_safe_distance(100 * KMH, 0.0, response_time=0.0, accel_max=0.0, brake_min=6.0)
    assert float(d) == pytest.approx(64.30, abs=0.01)


def test_faster_leader_gives_zero():
    assert float(rss_safe_distance(10 * KMH, 100 * KMH)) == 0.0


def test_negative_speed_is_invalid():
    assert np.isnan(float(rss_safe_distance(-1.0)))
    assert np.isnan(float(rss_safe_distance(1.0, -1.0)))


def test_paper_defaults_closed_form_batched_and_jitted():
    v = np.linspace(0.0, 20.0, 41).astype(np.float32)
    expected = v * 1.0 + 3.5 / 2 + (v + 3.5) ** 2 / 8.0  # the original code's call
    got = jax.jit(jax.vmap(rss_safe_distance))(v, np.zeros_like(v))
    np.testing.assert_allclose(np.asarray(got), expected, rtol=1e-6)
    assert float(rss_safe_distance(0.0)) == pytest.approx(1.75 + 3.5**2 / 8)
