"""carla-tm's collision stage against an independent shapely implementation of CARLA's
polygons (pipeline-era ``CollisionStage.cpp``: ``GetBoundary``, ``GetGeodesicBoundary``,
``NegotiateCollision``), and the planner's no-hold behaviour."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxfalsify.suts.carla_tm import boundary_extension, carla_tm_act, carla_tm_hazard
from jaxfalsify.suts.registry import REGISTRY, Observation

shapely = pytest.importorskip("shapely")
from shapely.geometry import Polygon  # noqa: E402

P = REGISTRY["carla-tm"].default_params


def _extension(v):
    # CollisionStage.cpp (pipeline era), GetBoundingBoxExtention, speeds in m/s
    if v > 50 / 3.6:
        return 5.0 * v
    if v < 10 / 3.6:
        return 1.0
    return math.sqrt(7.5 * v) + 0.5 * v + 1.0


def _get_boundary(loc, heading, ext_x, ext_y):
    """GetBoundary's four corners: loc + X - Y, loc - X - Y, loc - X + Y, loc + X + Y."""
    h = np.asarray(heading, float)
    perp = np.array([-h[1], h[0]])
    X, Y = h * ext_x, perp * ext_y
    loc = np.asarray(loc, float)
    return [loc + X - Y, loc - X - Y, loc - X + Y, loc + X + Y]


def _oracle(c):
    """CARLA's decision for one configuration, with shapely polygons."""
    ego, h = np.array([c["ego_x"], c["ego_y"]]), np.array([1.0, 0.0])
    perp = np.array([-h[1], h[0]])
    L, W = c["ego_length"], c["ego_width"]
    ego_box = _get_boundary(ego, h, L / 2, W / 2)
    ext = _extension(c["ego_speed"])
    # geodesic boundary: from the first path point one vehicle length (2 extent.x) from the
    # vehicle's location to max(leading distance 2.0, ext) beyond it, as wide as the vehicle
    start = ego + h * L
    path = [start, start + h * max(2.0, ext)]
    left = [p + perp * (W / 2) for p in path]
    right = [p - perp * (W / 2) for p in path]
    ego_geo = Polygon(list(reversed(right)) + ego_box + left)
    ego_box = Polygon(ego_box)
    # the walker: its own box grown by 1.5 s x speed on every side; heading +y
    wh = np.array([0.0, 1.0])
    walker = np.array([c["ped_x"], c["ped_y"]])
    grow = 1.5 * abs(c["ped_speed"])
    w_poly = Polygon(_get_boundary(walker, wh, c["ped_width"] / 2 + grow,
                                   c["ped_length"] / 2 + grow))
    # pre-filter outside junctions (1.4 x the half-lengths; leading distance 2.0)
    diff = walker - ego
    d2 = float(diff @ diff)
    lim = 1.4 * (L / 2 + c["ped_width"] / 2)
    dot = float(h @ diff)
    if dot < 0 and d2 > (ext + lim) ** 2:
        return False, None
    if dot > 0 and d2 > max((ext + lim) ** 2, (2.0 + lim) ** 2):
        return False, None
    geo = ego_geo.distance(w_poly)
    bb = ego_box.distance(w_poly)
    r2o, o2r = ego_box.distance(w_poly), w_poly.distance(ego_geo)
    u = diff / math.sqrt(d2)
    dr, do = float(h @ u), float(wh @ -u)
    hazard = geo < 0.1 and ((bb > 0.1 and r2o > o2r) or (bb < 0.1 and dr > do))
    return hazard, (geo, bb, d2, ext, lim, dr - do)


def _configs(n, seed):
    rng = np.random.default_rng(seed)
    c = dict(ego_x=rng.uniform(-10, 10, n), ego_y=np.full(n, -1.5),
             ego_speed=np.where(rng.random(n) < 0.1, 0.0, rng.uniform(0, 18, n)),
             ego_length=rng.uniform(3.5, 5.5, n), ego_width=rng.uniform(1.6, 2.3, n),
             ped_length=rng.uniform(0.3, 0.8, n), ped_width=rng.uniform(0.3, 0.8, n),
             ped_speed=rng.uniform(0, 3, n))
    # walkers around the corridor: ahead, beside and behind the ego, near its lane
    c["ped_x"] = c["ego_x"] + rng.uniform(-8, 30, n)
    c["ped_y"] = -1.5 + rng.uniform(-9, 9, n)
    return c


def test_hazard_matches_shapely_on_10000_configurations():
    n = 12_000
    c = _configs(n, seed=0)
    obs = Observation(
        t=jnp.zeros(n), dt=jnp.full(n, 0.1), ego_x=c["ego_x"], ego_y=c["ego_y"],
        ego_speed=c["ego_speed"], ego_length=c["ego_length"], ego_width=c["ego_width"],
        ped_x=c["ped_x"], ped_y=c["ped_y"], ped_vx=jnp.zeros(n), ped_vy=c["ped_speed"],
        ped_length=c["ped_length"], ped_width=c["ped_width"], road_right=jnp.full(n, -9.0),
        road_left=jnp.full(n, 3.0), weather=jnp.zeros(n, jnp.int32))
    obs = jax.tree.map(lambda a: jnp.asarray(a, jnp.int32 if np.asarray(a).dtype.kind == "i"
                                             else jnp.float32), obs)
    got = np.asarray(jax.jit(jax.vmap(carla_tm_hazard, in_axes=(0, None)))(obs, P))
    want, near = np.zeros(n, bool), np.zeros(n, bool)
    for i in range(n):
        h, m = _oracle({k: float(v[i]) for k, v in c.items()})
        want[i] = h
        if m is not None:
            geo, bb, d2, ext, lim, dd = m
            # the tolerance: within 1e-4 m of the 0.1 m threshold (and float32 ties
            # of the pre-filter and the angular rule, equally thin)
            near[i] = (abs(geo - 0.1) < 1e-4 or abs(bb - 0.1) < 1e-4
                       or abs(math.sqrt(d2) - (ext + lim)) < 1e-4 or abs(dd) < 1e-6)
    keep = ~near
    assert keep.sum() >= 10_000
    np.testing.assert_array_equal(got[keep], want[keep])
    # both outcomes and both branches of the priority rule are exercised
    assert 0.05 < want.mean() < 0.95
    bb_touch = np.array([_oracle({k: float(v[i]) for k, v in c.items()})[1][1] < 0.1
                         for i in np.nonzero(want)[0][:400]])
    assert 0 < bb_touch.sum() < bb_touch.size


@pytest.mark.parametrize("kmh, want", [(5.0, 1.0), (21.0, 10.53), (40.0, 15.68), (60.0, 83.33)])
def test_boundary_extension_piecewise(kmh, want):
    v = kmh / 3.6
    assert float(boundary_extension(jnp.float32(v), P)) == pytest.approx(want, abs=0.01)
    assert _extension(v) == pytest.approx(want, abs=0.01)


def test_hazard_brakes_fully_and_is_rechecked_every_tick():
    """Pipeline-era planner: a hazard gives brake 1.0 (-full_brake); no hold once it clears."""
    def obs(ped_y):
        f = jnp.float32
        return Observation(t=f(0), dt=f(0.1), ego_x=f(0), ego_y=f(-1.5), ego_speed=f(5.0),
                           ego_length=f(4.6), ego_width=f(2.1), ped_x=f(8.0), ped_y=f(ped_y),
                           ped_vx=f(0), ped_vy=f(1.2), ped_length=f(0.5), ped_width=f(0.6),
                           road_right=f(-9), road_left=f(3), weather=jnp.int32(0))

    state = REGISTRY["carla-tm"].init(None, P)
    a1, state = carla_tm_act(obs(-1.5), state, P, None)  # walker in the lane ahead
    a2, _ = carla_tm_act(obs(-9.0), state, P, None)  # walker far to the right, outside
    assert float(a1) == -P.full_brake
    assert float(a2) > -P.full_brake  # back to the PID at once
