"""Safety metrics of one crossing: RSS safe distance, box distance, time-to-collision, STL.

All functions are written for one scenario and one timestep (scalars); ``vmap`` them for batches.
"""

import jax.numpy as jnp
from jax.typing import ArrayLike

__all__ = ["rss_safe_distance", "box_gaps", "box_distance", "time_to_collision"]


def rss_safe_distance(v_rear: ArrayLike, v_front: ArrayLike = 0.0, *, response_time: float = 1.0,
                      accel_max: float = 3.5, brake_min: float = 4.0,
                      brake_max: float = 8.0) -> jnp.ndarray:
    """RSS minimum safe longitudinal distance, same direction (paper Eq. 4) [m].

    d_min = v_r*rho + a_max*rho^2/2 + (v_r + rho*a_max)^2 / (2*b_min) - v_f^2 / (2*b_max),
    floored at 0, as Intel's ad-rss-lib computes it (without its optional cap on the speed
    reached during the response time, which the paper's formula does not have).

    Args:
      v_rear: speed of the rear (ego) vehicle [m/s], >= 0.
      v_front: speed of the front object [m/s], >= 0; the original uses 0 for the pedestrian.
      response_time: rho [s]. accel_max: a_max,accel [m/s^2]. brake_min: b_min of the rear
        vehicle [m/s^2]. brake_max: b_max of the front object [m/s^2].
    Returns:
      d_min [m], broadcast shape of the speeds; NaN for negative speeds (invalid input).
    """
    v_r = jnp.asarray(v_rear, jnp.float32)
    v_f = jnp.asarray(v_front, jnp.float32)
    reach = v_r + response_time * accel_max
    d = (v_r * response_time + 0.5 * accel_max * response_time**2
         + reach**2 / (2.0 * brake_min) - v_f**2 / (2.0 * brake_max))
    d = jnp.maximum(d, 0.0)
    return jnp.where((v_r < 0) | (v_f < 0), jnp.nan, d)


def box_gaps(dx: ArrayLike, dy: ArrayLike, sx: ArrayLike, sy: ArrayLike):
    """Signed gaps between two axis-aligned boxes [m].

    Args:
      dx, dy: centre offset of box B from box A [m].
      sx, sy: half-length sums (A's half-extent + B's half-extent) along x and y [m].
    Returns:
      (gap_x, gap_y): separation along each axis, negative when the extents overlap.
    """
    return jnp.abs(dx) - sx, jnp.abs(dy) - sy


def box_distance(gap_x: ArrayLike, gap_y: ArrayLike) -> jnp.ndarray:
    """Euclidean distance between the closest points of two boxes, 0 when they overlap [m]."""
    gx = jnp.maximum(gap_x, 0.0)
    gy = jnp.maximum(gap_y, 0.0)
    # the order is part of the result on CPUs: XLA contracts the first product of a sum into a
    # fused multiply-add, and this order keeps the simulator's stored outcomes
    # (docs/performance.md, 'The centre distance's last bits')
    return jnp.sqrt(gy * gy + gx * gx)


def time_to_collision(gap_x: ArrayLike, gap_y: ArrayLike, closing_x: ArrayLike,
                      closing_y: ArrayLike, span_x: ArrayLike, span_y: ArrayLike) -> jnp.ndarray:
    """Constant-velocity time until two boxes overlap [s]; inf if they never do.

    Each axis closing (``closing > 0``) overlaps during [gap/closing, (gap + span)/closing]
    (from 0 while it already overlaps); an axis opening (``closing < 0``) that overlaps now does
    so until its gap reaches 0, at -gap/|closing|, and one that does not never will; a static
    axis overlaps forever or never. The boxes collide at the start of the intersection of the
    two intervals.

    Args:
      gap_x, gap_y: signed gaps (see :func:`box_gaps`) [m].
      closing_x, closing_y: rates at which the gaps shrink [m/s] (<= 0: opening or static).
      span_x, span_y: sum of the two boxes' full sizes along each axis [m].
    """
    inf = jnp.float32(jnp.inf)

    def interval(gap, closing, span):
        toward, away = closing > 1e-6, closing < -1e-6
        inv = 1.0 / jnp.where(toward | away, closing, 1.0)
        start = jnp.where(gap <= 0, 0.0, jnp.where(toward, gap * inv, inf))  # inf: never
        end = jnp.where(toward, jnp.where(gap + span <= 0, -inf, (gap + span) * inv),
                        jnp.where(gap > 0, -inf,  # apart and not closing: never
                                  jnp.where(away, gap * inv, inf)))  # until it opens
        return start, end

    s1, e1 = interval(gap_x, closing_x, span_x)
    s2, e2 = interval(gap_y, closing_y, span_y)
    start = jnp.maximum(s1, s2)
    return jnp.where(start <= jnp.minimum(e1, e2), start, inf)
