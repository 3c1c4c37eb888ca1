"""A kinematic screen of concrete scenarios: does the walker cross the car's path while the car,
driving as if no walker were there, passes the crosswalk?

A scenario can end in a collision only where the two actors meet. Without any braking, they meet
when the two time windows overlap: the steps during which the car's box spans the walker's line
(``|crosswalk_x - ego_x| <= half_x``, the box half-lengths summed) and the steps during which the
walker spans the car's lane (``|ped_y - ego_y| <= half_y``). An AEB brakes, so its car passes
later; it collides where the unbraked car would have, or just after. :func:`conflict_gap` gives
the time between the windows, at most 0 where they overlap: ``reinforce/default`` draws part of
its first batch where it is small (:mod:`jaxfalsify.search.batched`, docs/search.md).

Two approximations: the car's unbraked drive is the SUT's own command with the walker out of
reach (:func:`unbraked_drive`, one drive for every scenario, with the run's SUT parameters: a
space's ``sut.NAME`` values are not used, so where they change the car's speed keeping the
screen prefers the conflicts of the run's drive; the built-in spaces vary only the AEB's
thresholds), and the walker follows the original's speed profile (exactly, in closed form)
without the extended space's speed-change window. On
``aeb-9e6`` (a million scenarios) the scenarios with a gap of at most 0 s are 9.7 % of the space:
every collision of the car without AEB (``none``, 9.3 %) and a few more whose windows touch
within a step; the 9 ``sensor-aeb`` collisions have gaps of -0.9 to 0 s.
"""

from __future__ import annotations

from typing import Any, Callable

import jax
import jax.numpy as jnp

from jaxfalsify.core import sim
from jaxfalsify.scenario.space import KNOWN_PARAMETERS, Layout
from jaxfalsify.suts import registry as sut_lib

__all__ = [
    "unbraked_drive", "walker_travel", "walker_arrival", "car_window", "walker_window", "gap_of",
    "conflict_gap", "for_space"
]

OUT_OF_REACH = 1000.0  # m beyond the kerb: where the walker is put for the unbraked drive


def unbraked_drive(sut: sut_lib.SUT, params: Any, world: sim.World = sim.WORLD) -> jax.Array:
    """``(horizon + 1,)`` float32 metres the car has travelled after ``k`` steps (``k = 0 ..
    horizon``), driven by ``sut`` from rest with the walker standing ``OUT_OF_REACH`` m beyond
    the right kerb (the simulator's tick, :func:`jaxfalsify.core.sim.ego_tick`). One drive for
    every scenario: it starts at x = 0 in weather preset 0, so a SUT whose command depends on
    where the car is or on the weather drives differently in a scenario (the built-ins' speed
    keeping does not). A stochastic SUT draws from a fixed key. Not jitted."""
    w = world
    dt = jnp.asarray(w.dt, jnp.float32)
    f32 = lambda x: jnp.asarray(x, jnp.float32)  # noqa: E731
    key = jax.random.key(0)
    k_init, k_act = jax.random.split(key)

    def step(c, k):
        x, v, state = c
        obs = sut_lib.Observation(
            t=k.astype(jnp.float32) * dt, dt=dt, ego_x=x, ego_y=f32(w.ego_y), ego_speed=v,
            ego_length=f32(w.ego_length), ego_width=f32(w.ego_width),
            ped_x=f32(w.crosswalk_x), ped_y=f32(w.road_right - OUT_OF_REACH),
            ped_vx=jnp.float32(0.0), ped_vy=jnp.float32(0.0), ped_length=f32(w.ped_length),
            ped_width=f32(w.ped_width), road_right=f32(w.road_right),
            road_left=f32(w.road_left), weather=jnp.int32(0))
        k_step = jax.random.fold_in(k_act, k) if sut.stochastic else k_act
        cmd, state = sut.act(obs, state, params, k_step)
        _, dx, v1 = sim.ego_tick(v, jnp.asarray(cmd, jnp.float32), w, dt)
        x1 = x + jnp.where(jnp.isfinite(dx), dx, 0.0)
        v1 = jnp.where(jnp.isfinite(v1), v1, 0.0)
        return (x1, v1, state), x1

    init = (jnp.float32(0.0), jnp.float32(0.0), sut.init(k_init, params))
    _, xs = jax.lax.scan(step, init, jnp.arange(w.horizon, dtype=jnp.int32))
    return jnp.concatenate([jnp.zeros(1, jnp.float32), xs])


def _walker_phases(ped_speed, ped_accel):
    """The original's speed profile as three phases: ``L`` still steps at ``s_still``, then
    ``n_g`` growth steps at ``s_g + a``, ``s_g + 2 a``, ..., then steady at ``s_g + a n_g``
    [m/s]. A profile whose start speed ``ped_speed - 5 ped_accel`` is negative (the walker
    stands, :func:`jaxfalsify.core.sim.ped_speed_profile` never walks backwards) is still at 0
    until its speed turns non-negative."""
    start, n = sim.ped_profile_constants(ped_speed, ped_accel)
    a = ped_accel
    still = float(sim.STILL)
    # growth steps until the speed start + a q is non-negative (a hair below an exact tie, so
    # a speed that rounds to -1e-9 counts as the 0 it is)
    q = jnp.where(start < 0, jnp.ceil(-start / jnp.where(a > 0, a, 1.0) - 1e-4), 0.0)
    negative = start < 0
    L = jnp.where(negative, still - 1.0 + q, still)
    s_still = jnp.where(negative, 0.0, start)
    s_g = jnp.where(negative, start + a * q - a, start)
    n_g = jnp.where(negative, jnp.maximum(n - q + 1.0, 0.0), n)
    return L, s_still, s_g, n_g


def walker_travel(k, ped_speed, ped_accel):
    """The sum of the walker's profile speeds over its first ``k`` steps [m/s x steps]
    (``k`` float, any shape; times ``dt``: metres walked) under the original's speed profile
    (:func:`jaxfalsify.core.sim.ped_speed_profile` without a speed change), in closed form."""
    L, s_still, s_g, n_g = _walker_phases(ped_speed, ped_accel)
    a = ped_accel
    m = jnp.maximum(k - L, 0.0)  # steps after the still ones
    grown = jnp.where(m <= n_g, s_g * m + a * m * (m + 1.0) / 2.0,
                      s_g * n_g + a * n_g * (n_g + 1.0) / 2.0 + (m - n_g) * (s_g + a * n_g))
    return s_still * jnp.minimum(k, L) + grown


def walker_arrival(travel, ped_speed, ped_accel, horizon: int) -> jax.Array:
    """The first step ``k`` (float32, ``0 .. horizon``; ``horizon + 1`` where never) after
    which :func:`walker_travel` reaches ``travel`` [m/s x steps: metres over ``dt``], in closed
    form: the travel is a non-decreasing piecewise quadratic in ``k`` (still, growing, steady),
    so the answer is the ceiling of the real root in the piece where it is reached."""
    L, s_still, s_g, n_g = _walker_phases(ped_speed, ped_accel)
    a = ped_accel
    R = travel
    r1 = s_still * L  # travel after the still steps
    r2 = r1 + s_g * n_g + a * n_g * (n_g + 1.0) / 2.0  # ... and after the growth steps
    k1 = R / jnp.where(s_still > 0, s_still, 1.0)
    # growing: s_g m + a m (m + 1) / 2 = R - r1, the stable form of the positive root
    b = s_g + a / 2.0
    disc = jnp.sqrt(jnp.maximum(b * b + 2.0 * a * (R - r1), 0.0))
    k2 = L + 2.0 * (R - r1) / jnp.where(b + disc > 0, b + disc, 1.0)
    v = s_g + a * n_g  # steady
    k3 = L + n_g + (R - r2) / jnp.where(v > 0, v, 1.0)
    k = jnp.where(R <= r1, k1, jnp.where(R <= r2, k2, k3))
    never = jnp.where(R <= r1, s_still <= 0, jnp.where(R <= r2, b + disc <= 0, v <= 0))
    k = jnp.where(R <= 0, 0.0, jnp.where(never, jnp.inf, jnp.ceil(k)))
    return jnp.where(k > horizon, horizon + 1.0, k)


def car_window(ego_offset, drive: jax.Array, world: sim.World = sim.WORLD):
    """``(first step inside, first step beyond)`` float32 of the unbraked car's window at the
    crossing: its box centre within ``half_x`` of the crosswalk (``drive``: :func:`unbraked_drive`,
    non-decreasing, so a search of it); ``horizon + 1`` where never."""
    w = world
    half_x = (w.ego_length + w.ped_length) / 2
    start_x, _ = sim.start_positions(ego_offset, 0.0, w)
    enter = jnp.searchsorted(drive, w.crosswalk_x - half_x - start_x, side="left")
    leave = jnp.searchsorted(drive, w.crosswalk_x + half_x - start_x, side="right")
    return enter.astype(jnp.float32), leave.astype(jnp.float32)


def walker_window(ped_offset, ped_speed, ped_accel, world: sim.World = sim.WORLD):
    """``(first step inside, first step beyond)`` float32 of the walker's window: its centre
    within ``half_y`` of the lane's centre line; ``horizon + 1`` where never."""
    w = world
    half_y = (w.ego_width + w.ped_width) / 2
    _, ped_y0 = sim.start_positions(0.0, ped_offset, w)
    H = int(w.horizon)
    enter = walker_arrival((w.ego_y - half_y - ped_y0) / w.dt, ped_speed, ped_accel, H)
    # beyond: more than the far edge's travel (the next float up: reaching it is not beyond)
    far = (w.ego_y + half_y - ped_y0) / w.dt
    leave = walker_arrival(jnp.nextafter(jnp.float32(far), jnp.float32(jnp.inf)), ped_speed,
                           ped_accel, H)
    return enter, leave


def gap_of(car, walker, world: sim.World = sim.WORLD) -> jax.Array:
    """Seconds between two windows ``(enter, leave)``: ``<= 0`` where they overlap, otherwise
    how long the later opens after the earlier closes; ``inf`` where either never opens
    (``enter`` past the horizon: that actor never gets there)."""
    H = float(world.horizon)
    gap = jnp.maximum(car[0] - walker[1], walker[0] - car[1]) * jnp.asarray(world.dt,
                                                                           jnp.float32)
    return jnp.where((car[0] > H) | (walker[0] > H), jnp.inf, gap)


def conflict_gap(scenario: dict, drive: jax.Array, world: sim.World = sim.WORLD) -> jax.Array:
    """Seconds between the unbraked car's and the walker's windows at the crossing, per
    scenario (``scenario``: ``{name: (...)}`` float32 with ``ego_offset``, ``ped_offset``,
    ``ped_speed`` and ``ped_accel``; ``drive``: :func:`unbraked_drive`): :func:`gap_of` of
    :func:`car_window` and :func:`walker_window`. ``<= 0`` where the unbraked car would hit the
    walker (to a step)."""
    return gap_of(car_window(scenario["ego_offset"], drive, world),
                  walker_window(scenario["ped_offset"], scenario["ped_speed"],
                                scenario["ped_accel"], world), world)


def for_space(layout: Layout, table, sut: sut_lib.SUT, params: Any,
              world: sim.World = sim.WORLD) -> Callable[[jax.Array], jax.Array]:
    """The screen of a space's scenarios: ``indices (N, P)`` int32 -> ``(N,)`` float32
    :func:`conflict_gap` (``table``: the space's ``(P, max_n)`` value table; a parameter the
    space does not declare takes its default). Computed per value where a window depends on
    one parameter (the car's on ``ego_offset``), per scenario otherwise; the car's drive
    (:func:`unbraked_drive`) inside, so a caller that never calls it never computes it."""
    names = layout.names

    def column(name, indices, per_value=None):
        if name not in names:
            v = jnp.float32(KNOWN_PARAMETERS[name]["default"])
            return per_value(v) if per_value else v
        p = names.index(name)
        values = jnp.asarray(table, jnp.float32)[p]
        if per_value is None:
            return values[indices[:, p]]
        return tuple(x[indices[:, p]] for x in per_value(values))

    def screen(indices):
        drive = unbraked_drive(sut, params, world)
        car = column("ego_offset", indices, lambda v: car_window(v, drive, world))
        walker = walker_window(column("ped_offset", indices), column("ped_speed", indices),
                               column("ped_accel", indices), world)
        return jnp.broadcast_to(gap_of(car, walker, world), indices.shape[:1])

    return screen
