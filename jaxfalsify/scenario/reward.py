"""The paper's episode reward (Section III-A 'Reward function', Eq. 5-6), as the original code
computes it.

Three terms, summed:

* RSS term: x = round((high_risk - 1) / (timesteps - 1), 2), mapped to [-0.01, 0.01] by Eq. 5
  (new_x = (b - a) * x + a, a = -0.01, b = 0.01).
* Distance term: x = round((d_final - 1) / (10 - 1), 2), inverted (1 - x), mapped the same way.
  Not clipped: a final distance beyond 10 m gives less than -0.01, below 1 m more than 0.01.
* Collision term: +0.25 on collision.

Where the paper's text and the original code differ we follow the code: the text normalises the
high-risk count by ``x / timesteps`` and does not say the final distance is normalised over
[1, 10] m or inverted; the code subtracts 1 in the RSS fraction, rounds both fractions to 2
decimals and does not clip. The RSS fraction is rounded half-up with exact integer arithmetic
(the original used Python's ``round`` on a float, which differs only at exact .005 ties).
"""

import jax.numpy as jnp
from jax.typing import ArrayLike

__all__ = ["rss_term", "distance_term", "collision_term", "paper_reward"]

LOW, HIGH = -0.01, 0.01
COLLISION_BONUS = 0.25
DIST_MIN, DIST_MAX = 1.0, 10.0


def _to_range(x):
    """Eq. 5 with min = 0, max = 1: [0, 1] -> [LOW, HIGH] (not clipped)."""
    return (HIGH - LOW) * x + LOW


def rss_term(high_risk_steps: ArrayLike, timesteps: ArrayLike) -> jnp.ndarray:
    """RSS high-risk term; counts are integers, timesteps >= 2 (clamped)."""
    hr = jnp.asarray(high_risk_steps, jnp.int32) - 1
    den = jnp.maximum(jnp.asarray(timesteps, jnp.int32) - 1, 1)
    # round half-up of 100 * hr / den, exactly: floor((200*hr + den) / (2*den))
    hundredths = jnp.floor_divide(200 * hr + den, 2 * den)
    return _to_range(hundredths.astype(jnp.float32) / 100.0)


def distance_term(final_distance: ArrayLike) -> jnp.ndarray:
    """Final Euclidean distance term [m] -> reward."""
    x = (jnp.asarray(final_distance, jnp.float32) - DIST_MIN) / (DIST_MAX - DIST_MIN)
    x = jnp.round(x * 100.0) / 100.0
    return _to_range(1.0 - x)


def collision_term(collision: ArrayLike) -> jnp.ndarray:
    return jnp.where(jnp.asarray(collision), COLLISION_BONUS, 0.0).astype(jnp.float32)


def paper_reward(high_risk_steps, timesteps, final_distance, collision):
    """Returns ``(reward, rss_term, distance_term, collision_term)``, all float32."""
    r_rss = rss_term(high_risk_steps, timesteps)
    r_dist = distance_term(final_distance)
    r_col = collision_term(collision)
    return r_rss + r_dist + r_col, r_rss, r_dist, r_col
