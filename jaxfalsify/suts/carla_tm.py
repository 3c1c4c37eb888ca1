"""``carla-tm``: CARLA 0.9.9's Traffic Manager autopilot (pipeline era) with its ground-truth
collision stage, the SUT of the paper. Weather does not change it (CARLA's weather is visual
only)."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from jaxfalsify.base import pytree
from jaxfalsify.suts.autopilot import AutopilotParams, autopilot_command
from jaxfalsify.suts.interface import Observation

__all__ = ["CarlaTMParams", "boundary_extension", "tm_polygons", "carla_tm_hazard", "carla_tm_act"]


@pytree.dataclass
class CarlaTMParams(AutopilotParams):
    """CARLA 0.9.9-era Traffic Manager collision stage (``CollisionStage.cpp`` of the pipeline
    era, ``CollisionStageConstants``).

    Boundary extension ahead of the vehicle at speed v [m/s]: ``ext_min`` below ``crawl_speed``;
    ``sqrt(ext_square_point * v) + time_horizon * v + ext_min`` up to ``highway_speed``;
    ``highway_time * v`` above. The geodesic corridor reaches ``max(leading_distance, ext)``
    beyond a start one vehicle length ahead of the vehicle's location. A walker's box grows by
    ``walker_time * its speed`` on every side.
    """

    ext_min: float = 1.0  # m, BOUNDARY_EXTENSION_MINIMUM
    ext_square_point: float = 7.5  # m, EXTENSION_SQUARE_POINT
    time_horizon: float = 0.5  # s, TIME_HORIZON
    crawl_speed: float = 10.0 / 3.6  # m/s, CRAWL_SPEED
    highway_speed: float = 50.0 / 3.6  # m/s, HIGHWAY_SPEED
    highway_time: float = 5.0  # s, HIGHWAY_TIME_HORIZON
    leading_distance: float = 2.0  # m, Parameters.h distance_margin (the global default)
    walker_time: float = 1.5  # s, WALKER_TIME_EXTENSION
    bbox_multiplier: float = 1.4  # BBOX_EXTENT_MULTIPLIER of the pre-filter
    touch: float = 0.1  # m, the geodesic and box 'touching' threshold

    RANGES = {name: "[0, inf)" for name in (
        "ext_min", "ext_square_point", "time_horizon", "crawl_speed", "highway_speed",
        "highway_time", "leading_distance", "walker_time", "touch")}
    RANGES["bbox_multiplier"] = "(0, inf)"


def boundary_extension(speed, p: CarlaTMParams) -> jax.Array:
    """``GetBoundingBoxExtention``: how far the hazard corridor reaches [m] at speed [m/s]."""
    mid = jnp.sqrt(p.ext_square_point * jnp.maximum(speed, 0.0)) + p.time_horizon * speed \
        + p.ext_min
    return jnp.where(speed > p.highway_speed, p.highway_time * speed,
                     jnp.where(speed < p.crawl_speed, p.ext_min, mid))


def _rect_distance(ax0, ax1, ay0, ay1, bx0, bx1, by0, by1):
    """Distance between two axis-aligned rectangles [m] (0 when they overlap)."""
    gx = jnp.maximum(jnp.maximum(bx0 - ax1, ax0 - bx1), 0.0)
    gy = jnp.maximum(jnp.maximum(by0 - ay1, ay0 - by1), 0.0)
    return jnp.sqrt(gx * gx + gy * gy)


def tm_polygons(obs: Observation, p: CarlaTMParams):
    """The collision stage's polygons on the straight road, as axis-aligned rectangles
    ``(x0, x1, y0, y1)`` [m]: the ego's box, the ego's geodesic boundary (its box joined with
    the corridor along its lane from one vehicle length ahead of its location to
    ``max(leading_distance, ext)`` beyond), and the walker's box grown by
    ``walker_time * speed`` on every side (a walker's 'geodesic' polygon is that box)."""
    hl, hw = obs.ego_length / 2, obs.ego_width / 2
    ext = jnp.maximum(p.leading_distance, boundary_extension(obs.ego_speed, p))
    ego_box = (obs.ego_x - hl, obs.ego_x + hl, obs.ego_y - hw, obs.ego_y + hw)
    ego_geo = (obs.ego_x - hl, obs.ego_x + obs.ego_length + ext, obs.ego_y - hw,
               obs.ego_y + hw)
    grow = p.walker_time * jnp.sqrt(obs.ped_vx**2 + obs.ped_vy**2)
    px, py = obs.ped_length / 2 + grow, obs.ped_width / 2 + grow
    walker = (obs.ped_x - px, obs.ped_x + px, obs.ped_y - py, obs.ped_y + py)
    return ego_box, ego_geo, walker


def carla_tm_hazard(obs: Observation, p: CarlaTMParams) -> jax.Array:
    """The collision stage's hazard decision for the walker (bool).

    Pre-filter (outside junctions): with ``d`` the centre distance, ``ext`` the extension at
    the ego's speed and ``l = bbox_multiplier * (ego half-length + walker half-length)``, skip
    a walker behind (``dot < 0``) farther than ``ext + l``, and one ahead farther than
    ``max(ext + l, leading_distance + l)``. Negotiation: hazard when the geodesic polygons are
    within ``touch`` (0.1 m) and, with ``r2o`` = ego box to walker polygon, ``o2r`` = walker box
    to ego geodesic: boxes apart (> 0.1 m) and ``r2o > o2r``; or boxes touching and
    ``dot(ego heading, unit(walker - ego)) > dot(walker heading, unit(ego - walker))``.
    The walker walks along +y (its heading); the ego along +x.
    """
    ego_box, ego_geo, walker = tm_polygons(obs, p)
    geo = _rect_distance(*ego_geo, *walker)
    bb = _rect_distance(*ego_box, *walker)
    r2o, o2r = bb, geo  # a walker's box and its geodesic polygon are the same grown box
    dx, dy = obs.ped_x - obs.ego_x, obs.ped_y - obs.ego_y
    d2 = dx * dx + dy * dy
    ext = boundary_extension(obs.ego_speed, p)
    reach = p.bbox_multiplier * (obs.ego_length / 2 + obs.ped_width / 2)
    min2 = (ext + reach) ** 2
    skip = ((dx < 0) & (d2 > min2)) | \
        ((dx > 0) & (d2 > jnp.maximum(min2, (p.leading_distance + reach) ** 2)))
    # dot products with the unit centre offset: ego heading (1, 0), walker heading (0, 1)
    ego_dot, walker_dot = dx, -dy  # both scaled by 1/|d|, which does not change the order
    negotiate = (geo < p.touch) & (((bb > p.touch) & (r2o > o2r))
                                   | ((bb < p.touch) & (ego_dot > walker_dot)))
    return ~skip & negotiate


def carla_tm_act(obs: Observation, state, p: CarlaTMParams, key):
    """Traffic Manager step: on a hazard throttle 0, brake 1.0 (``-full_brake``) and the PID's
    integral reset; otherwise the PID. Re-checked every step, no hold (the pipeline-era
    planner has no collision lock). State: the PID's."""
    hazard = carla_tm_hazard(obs, p)
    accel, (integral, e) = autopilot_command(obs.ego_speed, state, p)
    return (jnp.where(hazard, -p.full_brake, accel),
            (jnp.where(hazard, 0.0, integral), e))
