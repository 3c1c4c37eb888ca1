"""The paper's reward terms against a direct transcription of the original's arithmetic."""

import numpy as np
import pytest

from jaxfalsify.scenario import reward


def original_reward(high_risk, timesteps, final_distance, collision):
    """Python transcription of the original code's reward, float64
    (dkarunakaran/scenario_based_falsification)."""
    rss_x = round((high_risk - 1) / (timesteps - 1), 2)
    dist_x = round((final_distance - 1) / (10 - 1), 2)
    return (0.02 * rss_x - 0.01) + (0.02 * (1 - dist_x) - 0.01) + (0.25 if collision else 0.0)


def test_reward_matches_original_on_random_non_tie_inputs():
    rng = np.random.default_rng(0)
    hr, n, d, c = [], [], [], []
    while len(hr) < 500:
        T = int(rng.integers(2, 300))
        h = int(rng.integers(0, T + 1))
        dist = float(rng.uniform(0, 30))
        # skip exact .005 ties, where Python's float rounding and ours may legitimately differ
        if abs(((h - 1) / (T - 1) * 100) % 1 - 0.5) < 1e-6:
            continue
        if abs((((dist - 1) / 9) * 100) % 1 - 0.5) < 1e-3:
            continue
        hr.append(h), n.append(T), d.append(dist), c.append(bool(rng.integers(0, 2)))
    total, r_rss, r_dist, r_col = reward.paper_reward(np.array(hr), np.array(n),
                                                      np.array(d, np.float32), np.array(c))
    expected = [original_reward(*args) for args in zip(hr, n, d, c)]
    np.testing.assert_allclose(np.asarray(total), expected, atol=1e-6)
    np.testing.assert_allclose(np.asarray(total), np.asarray(r_rss + r_dist + r_col), atol=1e-7)


@pytest.mark.parametrize("d, expected", [(1.0, 0.01), (10.0, -0.01), (5.5, 0.0), (19.0, -0.03)])
def test_distance_term_endpoints_not_clipped(d, expected):
    assert float(reward.distance_term(d)) == pytest.approx(expected, abs=1e-7)


def test_rss_term_range_and_collision_bonus():
    assert float(reward.rss_term(1, 101)) == pytest.approx(-0.01)
    assert float(reward.rss_term(101, 101)) == pytest.approx(0.01)
    assert float(reward.rss_term(51, 101)) == pytest.approx(0.0, abs=1e-8)
    assert float(reward.collision_term(True)) == 0.25
    assert float(reward.collision_term(False)) == 0.0
