"""The crossing world and its batched simulator (paper Fig. 1/2: a pedestrian crosses an urban
road).

One concern: the world's dynamics and their batched rollout; the SUTs
live in ``jaxfalsify.suts``, the metrics in ``jaxfalsify.scenario.metrics``.

Frame: x along the ego's lane (direction of travel), y to the left, origin at the ego's *base*
start (its box centre), SI units. The road is straight with ``lanes_right`` lanes right of
the centre line y = 0 (the ego drives in the innermost one) and ``lanes_left`` lanes left of
it; the pedestrian comes from the right. A marked crosswalk crosses it at ``x = crosswalk_x``.

One episode (written for one concrete scenario; ``vmap`` + ``jit`` are applied outside):

* The ego starts at rest ``ego_offset`` m behind its base, and its SUT drives it.
* The pedestrian starts ``ped_offset + 1`` m back (towards the kerb) from its base spawn
  point, which lies ``walker_base`` (4.5 m) inside the right kerb, on the road: with
  ``ped_offset`` 3 it starts 0.5 m inside the kerb (as the original spawns it),
  and walks straight across, starting when the ego starts moving (t = 0), with the original
  code's speed profile (:func:`ped_speed_profile`).
* Every 0.1 s step (one tick of the original's loop): the SUT observes, the ego integrates
  the SUT's command (exactly, for constant acceleration over the step, stopping at v = 0) and
  the pedestrian its profile speed, then the metrics are taken on the new state.
* The episode ends on collision (box overlap), after the step that starts beyond ``30 m +
  ego_offset`` travelled (x > 30 m), or at the 30 s horizon. ``lax.scan`` runs the fixed
  horizon with a done mask; metrics are reduced inside the carry.

Distances: collision, STL robustness, ``min_distance`` and the figures use the gap between
the two boxes; the paper reward (RSS comparison and distance term) uses the original's 3-D
distance between the actors' origins (``centre_distance``).

The geometry constants in :class:`World` were calibrated (``experiments/calibrate_world.py``;
README, 'The crossing world') so that the paper's mechanism appears with its SUT: a slow
pedestrian's grown box stays outside the Traffic Manager's narrow hazard corridor (the car's
own width) until the car can no longer stop clear of the crosswalk.
"""

from __future__ import annotations

import functools
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxfalsify.base import pytree
from jaxfalsify.base.config import check_memory, jsonable, number_text, plain
from jaxfalsify.io import cache
from jaxfalsify.scenario import metrics, reward
from jaxfalsify.scenario.space import (
    KNOWN_PARAMETERS,
    SUT_PREFIX,
    check_scenario_values,
    is_sut_parameter,
)
from jaxfalsify.suts import registry as sut_lib

__all__ = [
    "World", "WORLD", "Trajectory", "Outcome", "BLOCK", "STILL", "WINDOW",
    "ped_profile_constants", "ped_speed_profile", "start_positions", "ego_tick", "rollout",
    "batch_rollout", "LANES_PER", "lane_count", "as_float32", "seed_key_data", "seed_key",
    "simulate", "CPU_CHUNK", "default_chunk", "evaluate", "local_batch_sharding", "describe"
]

NON_NEGATIVE = ("lanes_left", "crosswalk_x", "end_x", "walker_base", "origin_dz")


@pytree.dataclass
class World:
    """World constants: a pytree whose numbers are traced (a geometry study vmaps over them);
    ``horizon`` is static (it fixes shapes). Check a hand-made world with :meth:`check`."""

    dt: float = 0.1  # s
    horizon: int = pytree.static(300)  # steps (30 s)
    lane_width: float = 3.0  # m (the original's notes: 'each lane is 3 meters wide')
    lanes_right: float = 3.0  # lanes right of the centre line; the ego uses the inner one
    lanes_left: float = 1.0  # lanes left of it (4 lanes; the ego in the third from the walker)
    crosswalk_x: float = 6.0  # m ahead of the ego's base start (box centre), calibrated
    walker_base: float = 4.5  # m from the right kerb to the walker's base spawn point (a
    # vehicle spawn point: here the second lane's centre, calibrated); the walker starts ped_offset
    # + 1 m behind it
    end_x: float = 30.0  # m: the ego has travelled 30 m + ego_offset
    ego_length: float = 4.6  # m, BMW Gran Tourer-class box incl. mirrors
    ego_width: float = 2.1  # m
    ped_length: float = 0.5  # m along x (shoulder width; Euro NCAP adult target)
    ped_width: float = 0.6  # m along y (walking direction)
    max_accel: float = 4.0  # m/s^2, vehicle limit on the SUT's command
    max_brake: float = 9.0  # m/s^2, vehicle limit on the SUT's command
    epsilon: float = 1.0  # m, the STL requirement's clash distance (paper Eq. 1)
    origin_dz: float = 0.9  # m, height of the walker's origin (capsule centre) above the
    # car's (on the ground): the z part of the original's 3-D centre distance (assumption)

    def check(self) -> "World":
        """Host-side validation; ValueError naming the bad field."""
        if isinstance(self.horizon, bool) or not isinstance(self.horizon, int) \
                or self.horizon < 2:
            raise ValueError(f"world.horizon must be an integer >= 2 steps (got {self.horizon!r})")
        for f in pytree.field_names(self):
            v = getattr(self, f)
            if f == "horizon" or isinstance(v, jax.core.Tracer):
                continue
            try:
                a = np.asarray(v, np.float64)
            except (TypeError, ValueError):
                raise ValueError(f"world.{f} must be a number (got {v!r})") from None
            low_ok = np.all(a >= 0) if f in NON_NEGATIVE else \
                np.all(a > 0)
            if isinstance(v, bool) or not np.all(np.isfinite(a)) or not low_ok:
                kind = "non-negative" if f in NON_NEGATIVE else "positive"
                raise ValueError(f"world.{f} must be a finite {kind} number (got {v!r})")
        return self

    @property
    def ego_y(self):
        return -self.lane_width / 2.0

    @property
    def road_right(self):
        return -self.lane_width * self.lanes_right

    @property
    def road_left(self):
        return self.lane_width * self.lanes_left


WORLD = World()


@pytree.dataclass
class Trajectory:
    """Per-step record of one episode; each field ``(T,)`` (leading batch dims if batched).

    Steps after the episode ended have ``valid`` False and hold no meaning (their positions
    are the final state, their distances those of one more hypothetical tick): read only the
    valid steps.
    """

    t: jax.Array  # s
    ego_x: jax.Array  # m, box centre
    ego_y: jax.Array  # m
    ego_speed: jax.Array  # m/s
    ego_accel: jax.Array  # m/s^2, effective over the step that led to this record
    ped_x: jax.Array  # m
    ped_y: jax.Array  # m
    ped_speed: jax.Array  # m/s
    distance: jax.Array  # m, Euclidean distance between the two boxes (the gap)
    centre_distance: jax.Array  # m, 3-D distance between the actors' origins (the original's)
    rss_distance: jax.Array  # m, RSS minimum safe distance (paper Eq. 4)
    high_risk: jax.Array  # bool, rss_distance > centre_distance, pedestrian ahead of the ego
    braking: jax.Array  # bool, the SUT commands deceleration
    collided: jax.Array  # bool, boxes overlap at this step
    valid: jax.Array  # bool, step belongs to the episode
    ttc: jax.Array  # s, constant-velocity time-to-collision (inf: none)


@pytree.dataclass
class Outcome:
    """Per-scenario result; each field a scalar (leading batch dims if batched)."""

    reward: jax.Array  # paper reward = sum of the three terms (NaN if the rollout was non-finite)
    reward_rss: jax.Array
    reward_distance: jax.Array
    reward_collision: jax.Array
    collision: jax.Array  # bool
    collision_time: jax.Array  # s, NaN if no collision
    min_distance: jax.Array  # m, smallest box gap (0 on collision)
    final_distance: jax.Array  # m, centre distance before the last step (the reward's term)
    high_risk_steps: jax.Array  # int32
    high_risk_share: jax.Array  # over the episode's steps
    high_risk_share_second_half: jax.Array  # over its second half (paper Fig. 8)
    robustness: jax.Array  # m, STL robustness of always(not clash); < 0 iff violated
    steps: jax.Array  # int32, episode length in steps
    min_ttc: jax.Array  # s
    nonfinite: jax.Array  # bool, the rollout produced NaN/inf and was stopped
    min_rss_margin: jax.Array  # m, smallest centre distance - RSS safe distance while the
    # pedestrian is ahead (< 0 at the high-risk steps; inf if it never was ahead)


BLOCK = 32  # steps per block: one uint32 word of high-risk bits, early exit between blocks
STILL = 6  # the original profile is constant for steps 0..5 (pdf.py, starting_speed_upto + 1)
WINDOW = 6  # the original speed-change window covers steps T..T+5 (change_speed_timesteps + 1)


def _once(one, tree):
    """``tree``'s float arrays divided by ``one``, a traced 1.0: the same values (``x / 1 == x``
    exactly; booleans through float32; integers, whose division x86 does not vectorise, as they
    are), each computed once per step.

    XLA's CPU fusion copies chains of cheap element-wise operations into every kernel that
    consumes them, but never a division: left alone, each of the ~17 kernels that update the
    carry recomputed the SUT's command, the tick and the contact test (``lax.optimization_barrier``
    does not stop that on CPU). Routed through a division, each value is computed by one
    kernel, stored, and read by the others (docs/performance.md, 'Each value once per step').
    """
    def stored(x):
        x = jnp.asarray(x)
        if x.dtype == jnp.bool_:
            return x.astype(jnp.float32) / one != 0
        if not jnp.issubdtype(x.dtype, jnp.floating):
            return x
        return x / one.astype(x.dtype)

    return jax.tree.map(stored, tree)


def ped_profile_constants(ped_speed, ped_accel):
    """(start speed [m/s], number of growth steps) of the original code's profile."""
    start = ped_speed - 5.0 * ped_accel
    pos = ped_accel > 0
    # first n with start + n*accel > speed + 0.25, i.e. n > 0.25/accel + 5; 'exceeds' means by
    # more than 1e-4 of a step, so exact ties of 3-decimal inputs do not hang on float rounding
    n_grow = jnp.where(pos, jnp.floor(0.25 / jnp.where(pos, ped_accel, 1.0) + 5.0 + 1e-4) + 1.0,
                       0.0)
    return start, n_grow


def ped_speed_profile(k, ped_speed, ped_accel, ped_speed_change=0.0, ped_change_step=0.0):
    """Pedestrian speed during step k [m/s], the original code's profile (``pdf.py``).

    ``s = speed - 5*accel``; steps 0..5 walk at ``s``; from step 6, ``s`` grows by ``accel``
    per step (per step, not accel*dt, as the original) until it first exceeds speed + 0.25,
    then stays. The steps ``change_step .. change_step + 5`` (six) walk at the current
    ``s + change`` and the growth pauses during them, whatever the change (0 holds the speed;
    the default ``change_step`` 0 is the still phase). Never < 0 (the original does not
    guard; CARLA cannot walk backwards).
    """
    start, n_grow = ped_profile_constants(ped_speed, ped_accel)
    return _profile_at(k, start, n_grow, ped_accel, ped_speed_change, ped_change_step)


def _profile_at(k, start, n_grow, accel, change, change_step):
    # growth steps done by step k: steps 6..k outside the window [T, T+5] (the window is
    # open whatever the change, as in pdf.py: a change of 0 holds the speed; at T = 0 it is
    # the still phase)
    paused = jnp.clip(jnp.minimum(k, change_step + WINDOW - 1)
                      - jnp.maximum(float(STILL), change_step) + 1.0, 0.0, None)
    grown = jnp.clip(jnp.maximum(k - (STILL - 1.0), 0.0) - paused, 0.0, n_grow)
    v = start + grown * accel
    window = (k >= change_step) & (k < change_step + WINDOW)
    return jnp.maximum(jnp.where(window, v + change, v), 0.0)


class _Carry(NamedTuple):
    ego_x: jax.Array
    ego_v: jax.Array
    ped_y: jax.Array
    ped_v: jax.Array
    sut_state: object
    alive: jax.Array
    nonfinite: jax.Array
    n_valid: jax.Array
    hr_count: jax.Array
    hr_word: jax.Array
    min_dist: jax.Array
    last_centre: jax.Array
    collided: jax.Array
    coll_step: jax.Array
    min_ttc: jax.Array
    min_rss: jax.Array


def _scenario_scalars(scenario: dict) -> dict:
    return {k: jnp.asarray(scenario[k], jnp.float32) for k in KNOWN_PARAMETERS}


def start_positions(ego_offset, ped_offset, world: World = WORLD):
    """``(ego x, pedestrian y)`` at t = 0 [m] (NumPy or JAX values): the ego ``ego_offset``
    behind its base start, the walker ``ped_offset + 1`` m beyond its base start on the kerb
    side (the ego's y is ``world.ego_y``, the walker's x ``world.crosswalk_x``)."""
    return -ego_offset, world.road_right + world.walker_base - (ped_offset + 1.0)


def ego_tick(v, cmd, world: World, dt):
    """One tick of the ego, exact for constant acceleration over the step and stopping at
    v = 0: ``(acceleration [m/s^2], the SUT's command clipped to the vehicle's limits; distance
    travelled [m]; speed after [m/s])`` from the speed before ``v`` [m/s] and the command."""
    a = jnp.clip(cmd, -world.max_brake, world.max_accel)
    v1 = v + a * dt
    stops = v1 < 0
    dx = jnp.where(stops, v**2 / (2.0 * jnp.maximum(-a, 1e-6)), (v + v1) / 2 * dt)
    return a, dx, jnp.maximum(v1, 0.0)


def rollout(scenario: dict, sut: sut_lib.SUT, params: Any, key: jax.Array,
            world: World = WORLD, record: bool = False):
    """Simulate one concrete scenario (all values scalars).

    Step k (one simulator tick, as one iteration of the original's loop): the SUT observes
    the state, the tick integrates both actors, then the metrics are taken on the new state
    (as the original measures its RSS comparison after ``world.tick()``); the paper reward's
    distance term uses the centre distance before the last tick (the original's
    ``eucld_dist``). The episode ends on a collision during the tick, or after the tick that
    started ``30 m + ego_offset`` past the ego's start (the original checks the distance
    travelled before the tick), or at the horizon.

    Args:
      scenario: ``{name: scalar}`` for every known parameter.
      sut: the system under test (static); ``params`` its parameter pytree (traced).
      key: typed PRNG key of this rollout (the SUT's ``init`` and per-step ``act`` keys are
        derived from it).
      world: world constants (traced, ``horizon`` static).
    Returns ``(Outcome, Trajectory | None)``; the trajectory (the state after each step) only
    if ``record``.
    """
    init, run_block, finish = _parts(scenario, sut, params, key, world, record)
    n_blocks = -(-world.horizon // BLOCK)
    if record:
        c, (words, rec) = jax.lax.scan(run_block, init, jnp.arange(n_blocks, dtype=jnp.int32))
        traj = jax.tree.map(lambda x: x.reshape((n_blocks * BLOCK,) + x.shape[2:])
                            [:world.horizon], rec)
        return finish(c, words), traj

    # Outcome only: the same blocks, stopped once the episode is over. Under vmap the loop runs
    # until every scenario of the batch is done (finished ones are masked), so results are
    # identical to the full fixed-horizon scan, only cheaper.
    def body(cb):
        c, b, words = cb
        c, (word, _) = run_block(c, b)
        return c, b + 1, jax.lax.dynamic_update_index_in_dim(words, word, b, 0)

    c, _, words = jax.lax.while_loop(lambda cb: cb[0].alive & (cb[1] < n_blocks), body,
                                     (init, jnp.int32(0), jnp.zeros(n_blocks, jnp.uint32)))
    return finish(c, words), None


def _parts(scenario: dict, sut: sut_lib.SUT, params: Any, key: jax.Array, world: World,
           record: bool):
    """One scenario's rollout in pieces: ``(init carry, run_block(carry, b) -> (carry, (word,
    records)), finish(carry, words) -> Outcome)``; ``run_block`` runs steps ``b * BLOCK`` ..
    ``b * BLOCK + BLOCK - 1`` and returns their high-risk bits as one uint32 word."""
    s = _scenario_scalars(scenario)
    w = world
    dt = jnp.asarray(w.dt, jnp.float32)
    f32 = lambda x: jnp.asarray(x, jnp.float32)  # noqa: E731
    k_init, k_act = jax.random.split(key) if sut.stochastic else (key, key)
    half_x = (w.ego_length + w.ped_length) / 2
    half_y = (w.ego_width + w.ped_width) / 2
    start_x, ped_y0 = start_positions(s["ego_offset"], s["ped_offset"], w)
    weather_idx = s["weather"].astype(jnp.int32)
    p_start, p_grow = ped_profile_constants(s["ped_speed"], s["ped_accel"])

    def box_gap(ego_x, ped_y):
        return metrics.box_gaps(w.crosswalk_x - ego_x, ped_y - w.ego_y, half_x, half_y)

    def swept_contact(x0, v0, a, y0, vp):
        """Do the boxes overlap at some instant of a tick ``[0, dt]`` that starts at ego
        centre ``x0`` [m], speed ``v0`` [m/s], constant acceleration ``a`` [m/s^2] (stopping
        at v = 0) and walker centre ``y0`` [m] at constant speed ``vp`` [m/s]? The walker's
        centre is inside the y-overlap band ``|y - ego_y| <= half_y`` for one interval of
        time ``[ta, tb]`` (it moves linearly); the ego's centre moves monotonically, so over
        that interval it spans ``[x(ta), x(tb)]``, which must meet ``|x - crosswalk_x| <=
        half_x``."""
        lo, hi = w.ego_y - half_y - y0, w.ego_y + half_y - y0  # walker displacement band
        moving = vp != 0
        inv = 1.0 / jnp.where(moving, vp, 1.0)
        t_lo, t_hi = lo * inv, hi * inv
        ta = jnp.where(moving, jnp.minimum(t_lo, t_hi), jnp.where(lo <= 0, 0.0, jnp.inf))
        tb = jnp.where(moving, jnp.maximum(t_lo, t_hi), jnp.where(hi >= 0, dt, -jnp.inf))
        ta, tb = jnp.maximum(ta, 0.0), jnp.minimum(tb, dt)
        t_stop = jnp.where(a < 0, v0 / jnp.maximum(-a, 1e-6), jnp.inf)

        def x_at(t):
            t = jnp.minimum(t, t_stop)
            return x0 + v0 * t + 0.5 * a * t * t

        inside = ta <= tb
        ta, tb = jnp.where(inside, ta, 0.0), jnp.where(inside, tb, 0.0)
        return inside & (x_at(ta) <= w.crosswalk_x + half_x) \
            & (x_at(tb) >= w.crosswalk_x - half_x)

    def centre(ego_x, ped_y):
        """3-D distance between the actors' origins (the original's ``loc.distance``)."""
        return jnp.sqrt((w.crosswalk_x - ego_x) ** 2 + (ped_y - w.ego_y) ** 2 + w.origin_dz ** 2)

    def step(c: _Carry, k):
        kf = k.astype(jnp.float32)
        vp = _profile_at(kf, p_start, p_grow, s["ped_accel"], s["ped_speed_change"],
                         s["ped_change_step"])
        obs = sut_lib.Observation(
            t=kf * dt, dt=dt, ego_x=c.ego_x, ego_y=f32(w.ego_y), ego_speed=c.ego_v,
            ego_length=f32(w.ego_length), ego_width=f32(w.ego_width),
            ped_x=f32(w.crosswalk_x), ped_y=c.ped_y, ped_vx=jnp.float32(0.0), ped_vy=c.ped_v,
            ped_length=f32(w.ped_length), ped_width=f32(w.ped_width),
            road_right=f32(w.road_right), road_left=f32(w.road_left), weather=weather_idx)
        k_step = jax.random.fold_in(k_act, k) if sut.stochastic else k_act
        cmd, new_sut_state = sut.act(obs, c.sut_state, params, k_step)
        # one: 1.0 that XLA cannot fold (it cannot prove k >= 0), for _once
        one = jnp.where(k >= 0, jnp.float32(1.0), jnp.float32(2.0))
        cmd, new_sut_state, vp = _once(one, (jnp.asarray(cmd, jnp.float32), new_sut_state, vp))

        a, dx, v1 = ego_tick(c.ego_v, cmd, w, dt)
        x1 = c.ego_x + dx
        y1 = c.ped_y + vp * dt
        valid = c.alive & (k < w.horizon)
        bad = ~(jnp.isfinite(cmd) & jnp.isfinite(dx) & jnp.isfinite(v1))
        move = valid & ~bad
        a, v1, x1, y1, valid, bad, move = _once(one, (a, v1, x1, y1, valid, bad, move))

        # --- metrics on the state after the tick
        gap_x, gap_y = box_gap(x1, y1)
        dist = metrics.box_distance(gap_x, gap_y)
        d_min = metrics.rss_safe_distance(v1)
        d_centre = centre(x1, y1)
        d_min, d_centre = _once(one, (d_min, d_centre))
        # the pedestrian is RSS's front object until the ego's front bumper has passed it
        ahead = w.crosswalk_x + w.ped_length / 2 > x1 + w.ego_length / 2
        hr = move & ahead & (d_min > d_centre)
        # contact at any instant of the tick, not only at its end: the walker can clip a
        # corner of the passing car between two samples
        overlap = ((gap_x <= 0) & (gap_y <= 0)) | swept_contact(c.ego_x, c.ego_v, a, c.ped_y, vp)
        overlap = _once(one, overlap)
        dist = jnp.where(overlap, 0.0, dist)
        closing_y = jnp.where(y1 < w.ego_y, vp, -vp)
        ttc = metrics.time_to_collision(gap_x, gap_y, jnp.where(w.crosswalk_x > x1, v1, -v1),
                                        closing_y, 2 * half_x, 2 * half_y)
        ttc = _once(one, jnp.where(move, jnp.where(overlap, 0.0, ttc), jnp.inf))

        nonfinite = c.nonfinite | (valid & bad)
        collided_now = move & overlap
        done = collided_now | (c.ego_x > w.end_x) | bad
        alive = valid & ~done
        sut_state = jax.tree.map(lambda n, o: jnp.where(move, n, o), new_sut_state, c.sut_state)

        bit = jnp.left_shift(hr.astype(jnp.uint32), (k % BLOCK).astype(jnp.uint32))
        new = _Carry(
            ego_x=jnp.where(move, x1, c.ego_x), ego_v=jnp.where(move, v1, c.ego_v),
            ped_y=jnp.where(move, y1, c.ped_y), ped_v=jnp.where(move, vp, c.ped_v),
            sut_state=sut_state, alive=alive, nonfinite=nonfinite,
            n_valid=c.n_valid + move.astype(jnp.int32),
            hr_count=c.hr_count + hr.astype(jnp.int32),
            hr_word=c.hr_word | bit,
            min_dist=jnp.where(move, jnp.minimum(c.min_dist, dist), c.min_dist),
            last_centre=jnp.where(move, centre(c.ego_x, c.ped_y), c.last_centre),
            collided=c.collided | collided_now,
            coll_step=jnp.where(collided_now, k + 1, c.coll_step),
            min_ttc=jnp.minimum(c.min_ttc, ttc),
            min_rss=jnp.where(move & ahead, jnp.minimum(c.min_rss, d_centre - d_min), c.min_rss))
        rec = None
        if record:
            rec = Trajectory(
                t=(kf + 1.0) * dt, ego_x=new.ego_x, ego_y=f32(w.ego_y), ego_speed=new.ego_v,
                ego_accel=jnp.where(move, (v1 - c.ego_v) / dt, 0.0),
                ped_x=f32(w.crosswalk_x), ped_y=new.ped_y, ped_speed=jnp.where(move, vp, 0.0),
                distance=dist,
                centre_distance=d_centre, rss_distance=d_min, high_risk=hr,
                braking=move & (cmd < 0), collided=collided_now, valid=move, ttc=ttc)
        return new, rec

    gx0, gy0 = box_gap(start_x, ped_y0)
    init = _Carry(
        ego_x=start_x, ego_v=jnp.float32(0.0), ped_y=f32(ped_y0), ped_v=jnp.float32(0.0),
        sut_state=sut.init(k_init, params),
        alive=jnp.bool_(True), nonfinite=jnp.bool_(False), n_valid=jnp.int32(0),
        hr_count=jnp.int32(0), hr_word=jnp.uint32(0),
        min_dist=metrics.box_distance(gx0, gy0), last_centre=jnp.float32(jnp.nan),
        collided=jnp.bool_(False), coll_step=jnp.int32(-1), min_ttc=jnp.float32(jnp.inf),
        min_rss=jnp.float32(jnp.inf))

    def run_block(c: _Carry, b):
        """BLOCK steps from step b*BLOCK; returns the block's high-risk bits as one word."""
        c, rec = jax.lax.scan(step, c._replace(hr_word=jnp.uint32(0)),
                              b * BLOCK + jnp.arange(BLOCK, dtype=jnp.int32))
        return c, (c.hr_word, rec)

    return init, run_block, lambda c, words: _outcome(c, words, w)


def _second_half_count(bits, n):
    """Number of set bits at positions [n // 2, n) of a ``(W,)`` uint32 bitmask."""
    base = jnp.arange(bits.shape[0], dtype=jnp.int32) * 32
    lo = jnp.clip(n // 2 - base, 0, 32)
    hi = jnp.clip(n - base, 0, 32)

    def low_mask(m):  # lowest m bits set, m in 0..32
        full = jnp.uint32(0xFFFFFFFF)
        return jnp.where(m >= 32, full,
                         jnp.left_shift(jnp.uint32(1), jnp.minimum(m, 31).astype(jnp.uint32))
                         - jnp.uint32(1))

    mask = low_mask(hi) & ~low_mask(lo)
    return jnp.sum(jax.lax.population_count(bits & mask).astype(jnp.int32))


def _outcome(c: _Carry, hr_bits, w: World) -> Outcome:
    n = c.n_valid
    second = n - n // 2
    hr2 = _second_half_count(hr_bits, n)
    collision = c.collided & ~c.nonfinite
    total, r_rss, r_dist, r_col = reward.paper_reward(c.hr_count, n, c.last_centre, collision)
    total = jnp.where(c.nonfinite, jnp.nan, total)
    return Outcome(
        reward=total, reward_rss=r_rss, reward_distance=r_dist, reward_collision=r_col,
        collision=collision,
        collision_time=jnp.where(collision, c.coll_step.astype(jnp.float32) * w.dt, jnp.nan),
        min_distance=c.min_dist, final_distance=c.last_centre,
        high_risk_steps=c.hr_count,
        high_risk_share=(c.hr_count / jnp.maximum(n, 1)).astype(jnp.float32),
        high_risk_share_second_half=(hr2 / jnp.maximum(second, 1)).astype(jnp.float32),
        robustness=c.min_dist - w.epsilon,
        steps=n, min_ttc=c.min_ttc, nonfinite=c.nonfinite, min_rss_margin=c.min_rss)


# ---------------------------------------------------------------------------- batched API
def split_sut_values(scenario: dict, sut_params, sut) -> tuple[dict, dict]:
    """A scenario's ``sut.NAME`` values (scalars, or arrays of one value) merged into the SUT
    parameter overrides: ``(scenario without them, sut_params)``; ValueError (one line) for
    a name the SUT does not have or values that differ across the batch."""
    if not isinstance(scenario, dict):
        raise ValueError("scenario must be a dict of parameter values (got "
                         f"{type(scenario).__name__})")
    keys = [k for k in scenario if isinstance(k, str) and is_sut_parameter(k)]
    if not keys:
        return scenario, sut_params
    s = sut_lib.resolve(sut)
    known = sut_lib.param_names(s)
    over = {}
    for k in keys:
        name = k[len(SUT_PREFIX):]
        if name not in known:
            raise ValueError(f"scenario parameter {k}: the SUT '{s.name}' has no parameter "
                             f"'{name}' (it has: {', '.join(known) or 'none'})")
        v = np.unique(np.asarray(scenario[k], np.float64))
        if v.size != 1 or not np.isfinite(v[0]):
            raise ValueError(f"scenario parameter {k}: one finite value per call (got "
                             f"{v.size} values); evaluate each calibration separately or "
                             "sweep them")
        over[name] = float(v[0])
    if sut_params is None:
        base = {}
    elif isinstance(sut_params, dict):
        base = dict(sut_params)
        twice = sorted(set(over) & set(base))
        if twice:
            raise ValueError(f"{SUT_PREFIX}{twice[0]} given twice (in the scenario and in "
                             "sut_params): give its value in one place")
    else:
        base = sut_lib.params_dict(sut_params)
    return {k: v for k, v in scenario.items() if k not in keys}, {**base, **over}


def _check_scenario(scenario: dict) -> dict:
    if not isinstance(scenario, dict):
        raise ValueError("scenario must be a dict of parameter values (got "
                         f"{type(scenario).__name__})")
    unknown = set(scenario) - set(KNOWN_PARAMETERS)
    if unknown:
        raise ValueError(f"unknown scenario parameter '{sorted(unknown)[0]}' "
                         f"(known: {', '.join(KNOWN_PARAMETERS)})")
    for k, v in scenario.items():  # "3" or True would convert silently below
        kind = np.asarray(v).dtype.kind if not isinstance(v, jax.core.Tracer) else "f"
        if kind not in "iuf":
            raise ValueError(f"scenario parameter {k}={v!r}: values must be numbers or "
                             "arrays of numbers")
    try:
        arrs = {k: np.asarray(v, np.float32) for k, v in scenario.items()}
    except (TypeError, ValueError):
        raise ValueError("scenario values must be numbers or arrays of numbers") from None
    for k, v in arrs.items():  # validated like a space's values
        spec = KNOWN_PARAMETERS[k]
        lo, hi = spec["domain"]
        if v.size and not np.all(np.isfinite(v)):
            raise ValueError(f"scenario parameter {k}: not finite")
        if v.size and (v.min() < lo or v.max() > hi):
            bad = v[(v < lo) | (v > hi)].flat[0]
            raise ValueError(f"scenario parameter {k}={number_text(bad)} outside the allowed "
                             f"[{lo:g}, {hi:g}] {spec['unit']}")
        if spec["integer"] and v.size and np.any(v != np.round(v)):
            raise ValueError(f"scenario parameter {k}: values must be integers "
                             f"(got {number_text(v[v != np.round(v)].flat[0])})")
    try:
        shape = np.broadcast_shapes(*(np.shape(v) for v in arrs.values())) if arrs else ()
    except ValueError:
        raise ValueError("scenario arrays have incompatible shapes: "
                         + ", ".join(f"{k}{tuple(np.shape(v))}" for k, v in arrs.items())) from None
    full = {k: np.broadcast_to(np.asarray(arrs.get(k, spec["default"]), np.float32), shape)
            for k, spec in KNOWN_PARAMETERS.items()}
    return full


def _flat(full: dict):
    shape = next(iter(full.values())).shape
    return {k: v.reshape(-1) for k, v in full.items()}, shape


def batch_rollout(flat: dict, offsets: jax.Array, key: jax.Array, sut: sut_lib.SUT,
                  params: Any, world: World = WORLD, record: bool = False,
                  lanes: int | None = None):
    """vmap of :func:`rollout` over a flat batch ``{name: (B,)}``; not jitted (jit at the edge).

    Rollout ``i`` draws from ``fold_in(key, offsets[i])``: pass scenario or evaluation numbers
    as ``offsets`` so a scenario's randomness does not depend on how batches are cut.
    ``lanes`` (static; outcomes only, ``record`` False): run the batch on that many lanes
    refilled as episodes end (:func:`lane_count`, :func:`_refilled`) instead of one lane per
    scenario; :func:`evaluate` does on one device, and its outcomes are the same bit for bit
    (checked on every scenario of the paper space and of ``paper-extended``). Sweeps and
    campaigns run one lane per scenario: compiled inside them, XLA fuses the refilled loop
    differently and distances can differ in the last bits. The failure-rate estimate's program
    runs refilled lanes (1.2-1.7x faster there; about 2 % of its robustness values differ from
    one lane per scenario's, by at most 4e-5 m, and no violation did in 1M draws).
    """
    over = {k[len(SUT_PREFIX):]: v for k, v in flat.items() if is_sut_parameter(k)}
    flat = {k: v for k, v in flat.items() if not is_sut_parameter(k)}

    def one(sc, ov, k):  # a space's sut.NAME values replace the SUT's parameters per scenario
        p = sut_lib.override(params, ov) if ov else params
        return rollout(sc, sut, p, k, world, record)

    n = next(iter(flat.values())).shape[0]
    if lanes is not None and not record and lanes < n:
        return _refilled(flat, over, offsets, key, sut, params, world, lanes), None
    if not sut.stochastic:  # the key is never used: no per-scenario keys to derive
        return jax.vmap(lambda sc, ov: one(sc, ov, key))(flat, over)
    keys = jax.vmap(lambda o: jax.random.fold_in(key, o))(offsets)
    return jax.vmap(one)(flat, over, keys)


PAD = 8  # run_batch pads a batch of host arrays to a multiple of this many scenarios
LANES_PER = 8  # a batch of n scenarios runs on n / LANES_PER lanes, refilled as episodes end
MIN_LANES = 4096  # but on no fewer lanes than this (a batch up to it: one scenario per lane)


def lane_count(n: int) -> int:
    """Lanes a batch of ``n`` scenarios runs on (static): ``n // LANES_PER``, at least
    ``MIN_LANES``, at most ``n``. On few lanes a block's fixed costs (each of the step's
    ~70 fused kernels is dispatched once per step whatever the lanes) outweigh what refilling
    saves: on 2 CPU cores 1,024 lanes ran the paper space 1.5-2x slower than 12,500."""
    return min(n, max(MIN_LANES, n // LANES_PER))


def _refilled(flat: dict, over: dict, offsets, key, sut: sut_lib.SUT, params, world: World,
              lanes: int) -> Outcome:
    """The batch's outcomes, run on ``lanes`` lanes that each take the next scenario as soon
    as their episode has ended (checked between blocks of BLOCK steps).

    A batch run one scenario per lane runs every lane until the batch's longest episode ends
    (a vmapped loop stops only when all lanes are done): the paper space's episodes last 60-90
    steps on average but some run the whole 300-step horizon. Refilled lanes run about the
    blocks the episodes need. Each scenario's steps are the same operations on the same values
    as in :func:`rollout`, so every outcome is bit-identical.
    """
    n = next(iter(flat.values())).shape[0]
    n_blocks = -(-world.horizon // BLOCK)
    lane = jnp.arange(lanes, dtype=jnp.int32)
    keys = None if not sut.stochastic else \
        jax.vmap(lambda o: jax.random.fold_in(key, o))(offsets)

    def pieces(i):
        """Scenario i's rollout pieces (i: a lane's scenario number, traced)."""
        sc = {k: v[i] for k, v in flat.items()}
        ov = {k: v[i] for k, v in over.items()}
        p = sut_lib.override(params, ov) if ov else params
        return _parts(sc, sut, p, key if keys is None else keys[i], world, False)

    def init(i):
        return pieces(i)[0]

    def block(i, c, b):
        c, (word, _) = pieces(i)[1](c, b)
        return c, word

    def finish(i, c, words):
        return pieces(i)[2](c, words)

    out0 = jax.eval_shape(lambda: finish(jnp.int32(0), init(jnp.int32(0)),
                                         jnp.zeros(n_blocks, jnp.uint32)))
    outs = jax.tree.map(lambda a: jnp.zeros((n,) + a.shape, a.dtype), out0)
    state = (lane, jnp.ones(lanes, bool), jax.vmap(init)(lane),
             jnp.zeros((lanes, n_blocks), jnp.uint32), jnp.zeros(lanes, jnp.int32),
             jnp.int32(lanes), outs)

    def body(st):
        idx, active, c, words, b, nxt, outs = st
        c, word = jax.vmap(block)(idx, c, b)
        words = words.at[lane, jnp.minimum(b, n_blocks - 1)].set(word)
        b = b + 1
        ended = active & (~c.alive | (b >= n_blocks))
        done = jax.vmap(finish)(idx, c, words)
        where = jnp.where(ended, idx, n)  # out of bounds: dropped
        outs = jax.tree.map(lambda o, d: o.at[where].set(d, mode="drop"), outs, done)
        new = nxt + jnp.cumsum(ended.astype(jnp.int32)) - 1  # the next scenarios, in order
        take = ended & (new < n)
        new = jnp.where(take, new, idx)
        fresh = jax.vmap(init)(new)
        keep = lambda f, o: jnp.where(  # noqa: E731
            take.reshape((lanes,) + (1,) * (o.ndim - 1)), f, o)
        c = jax.tree.map(keep, fresh, c)
        words = keep(jnp.zeros_like(words), words)
        b = jnp.where(take, 0, b)
        nxt = jnp.minimum(nxt + jnp.sum(ended.astype(jnp.int32)), n)
        return new, active & (~ended | take), c, words, b, nxt, outs

    st = jax.lax.while_loop(lambda st: jnp.any(st[1]), body, state)
    return st[-1]


def as_float32(tree):
    return jax.tree.map(lambda x: np.asarray(x, np.float32), tree)


@functools.lru_cache(maxsize=128)
def _batch_program(sut: sut_lib.SUT, record: bool, n: int, params_tree, params_avals: tuple,
                   world_tree):
    """The compiled batch rollout for ``n`` scenarios (cached in-process and per machine)."""

    def fn(flat, offsets, key_data, params_leaves, world_leaves):
        params = jax.tree.unflatten(params_tree, params_leaves)
        world = jax.tree.unflatten(world_tree, world_leaves)
        out, traj = batch_rollout(flat, offsets, jax.random.wrap_key_data(key_data), sut,
                                  params, world, record, lanes)
        return vars(out), (vars(traj) if record else None)

    # (on several devices a batch is split between them: lanes refilled from one queue would
    # gather across devices every block)
    lanes = None if record or jax.device_count() > 1 else lane_count(n)
    f32 = jax.ShapeDtypeStruct((n,), jnp.float32)
    key_args = ({k: f32 for k in KNOWN_PARAMETERS}, jax.ShapeDtypeStruct((n,), jnp.int32),
                list(params_avals))

    def example():
        zeros = np.zeros(n, np.float32)
        return ({k: zeros for k in KNOWN_PARAMETERS}, np.zeros(n, np.int32),
                np.zeros(2, np.uint32), [np.zeros(a.shape, a.dtype) for a in params_avals],
                [np.float32(0)] * world_tree.num_leaves)

    key = sut_lib.cache_key(sut)
    static = None if key is None else {"sut": key, "record": record, "params": str(params_tree),
                                       "world": str(world_tree), "lanes": lanes}
    return cache.exported_jit(fn, "rollout", static, key_args, example)


def run_batch(flat: dict, offsets, key_data, sut: sut_lib.SUT, params, world: World,
              record: bool = False):
    """:func:`batch_rollout` compiled: host arrays in, ``(Outcome, Trajectory | None)`` of
    NumPy arrays out.

    A batch of host arrays runs padded to a multiple of ``PAD`` scenarios (copies of its last,
    dropped from the results): on CPUs XLA's kernels ran 2-5x slower per scenario on an odd
    number of lanes than on an even one (docs/performance.md, 'Lanes')."""
    p_leaves, p_tree = jax.tree.flatten(as_float32(params))
    w_leaves, w_tree = jax.tree.flatten(as_float32(world))
    avals = tuple(jax.ShapeDtypeStruct(x.shape, x.dtype) for x in p_leaves)
    n = int(np.shape(offsets)[0])
    size = n
    if n % PAD and isinstance(offsets, np.ndarray):
        size = -(-n // PAD) * PAD
        edge = lambda v: np.pad(np.asarray(v), (0, size - n), mode="edge")  # noqa: E731
        flat, offsets = {k: edge(v) for k, v in flat.items()}, edge(offsets)
    prog = _batch_program(sut, record, size, p_tree, avals, w_tree)
    out, traj = prog(flat, offsets, key_data, p_leaves, w_leaves)
    host = lambda d: {k: np.asarray(v)[:n] for k, v in d.items()}  # noqa: E731
    return Outcome(**host(out)), (Trajectory(**host(traj)) if record else None)


def _resolve(sut, sut_params, world: World):
    s = sut_lib.resolve(sut)
    params = sut_lib.with_params(s, sut_params)
    sut_lib.check_traceable(s, params)
    if not isinstance(world, World):
        raise ValueError(f"world must be a jaxfalsify.World (got {type(world).__name__})")
    return s, params, world.check()


def seed_key_data(seed: int) -> np.ndarray:
    """Key data ``(2,)`` uint32 of a 64-bit seed for the default threefry keys: the seed's high
    and low words. (``jax.random.key`` keeps only the low 32 bits when 64-bit types are off,
    so seeds 0 and 2**32 would collide; computed with NumPy, it also compiles nothing.)"""
    seed = int(seed)
    if not 0 <= seed < 2**64:
        raise ValueError(f"seed must be in 0..2**64-1 (got {seed})")
    if jax.config.jax_default_prng_impl != "threefry2x32":
        return np.asarray(jax.random.key_data(jax.random.key(seed)))
    return np.array([seed >> 32, seed & 0xFFFFFFFF], np.uint32)


def seed_key(seed: int) -> jax.Array:
    """A typed PRNG key from a 64-bit seed (see :func:`seed_key_data`)."""
    return jax.random.wrap_key_data(seed_key_data(seed))


def _key_data(seed_or_key) -> np.ndarray:
    if isinstance(seed_or_key, jax.Array) and jax.dtypes.issubdtype(seed_or_key.dtype,
                                                                     jax.dtypes.prng_key):
        return np.asarray(jax.random.key_data(seed_or_key))
    if isinstance(seed_or_key, int) and not isinstance(seed_or_key, bool):
        return seed_key_data(seed_or_key)  # range-checked there (64 bits)
    arr = np.asarray(seed_or_key)
    if arr.shape == () and arr.dtype.kind in "iu":
        return seed_key_data(int(arr))
    raw = (f" of shape {arr.shape}; a raw uint32 key from jax.random.PRNGKey: wrap it with "
           "jax.random.wrap_key_data") if arr.ndim else ""
    raise ValueError(f"key must be a typed PRNG key (jax.random.key) or an integer seed (got "
                     f"{type(seed_or_key).__name__}{raw})")


def _offsets(offsets, shape: tuple, n: int) -> np.ndarray:
    """The scenarios' key offsets ``(n,)`` int32: ``0..n-1`` by default, else ``offsets``
    (broadcast to the batch ``shape``; whole numbers in int32's range)."""
    if offsets is None:
        return np.arange(n, dtype=np.int32)
    arr = np.asarray(offsets)
    if arr.dtype.kind not in "iu":
        raise ValueError(f"offsets must be whole numbers (got dtype {arr.dtype})")
    try:
        arr = np.broadcast_to(arr, shape)
    except ValueError:
        raise ValueError(f"offsets of shape {arr.shape} do not match the batch shape "
                         f"{shape}") from None
    if arr.size and (arr.min() < 0 or arr.max() > np.iinfo(np.int32).max):
        raise ValueError("offsets must lie in 0..2**31-1")
    return arr.reshape(-1).astype(np.int32)


def simulate(scenario: dict, *, sut="carla-tm", sut_params=None, world: World = WORLD,
             key=0, offsets=None) -> Trajectory:
    """Per-step trajectories of concrete scenarios.

    Args:
      scenario: parameter name -> scalar or array (shapes broadcast); undeclared parameters
        take their defaults (``space.KNOWN_PARAMETERS``).
      sut: a registry name, an import path ``module:attr``, a
        :class:`~jaxfalsify.suts.registry.SUT`,
        or an ``act`` function.
      sut_params: the SUT's parameter pytree, or ``{name: value}`` overrides of its defaults.
      world: world constants.
      key: a typed PRNG key or an integer seed (the SUT's randomness; scenario ``i`` of the
        flattened batch draws from ``fold_in(key, i)``).
      offsets: integers, the batch's shape (broadcast): scenario ``i`` draws from
        ``fold_in(key, offsets[i])`` instead. A campaign draws evaluation ``e`` (1-based)
        from ``fold_in(campaign.evaluation_key(seed), e - 1)``, so a stochastic SUT's
        evaluation is re-simulated with that key and offset ``e - 1``.
    Returns:
      :class:`Trajectory` with fields ``(*batch, T)``.
    """
    scenario, sut_params = split_sut_values(scenario, sut_params, sut)
    s, params, world = _resolve(sut, sut_params, world)
    full = _check_scenario(scenario)
    flat, shape = _flat(full)
    n = int(np.prod(shape, dtype=np.int64))

    check_memory(n * world.horizon * len(Trajectory.__dataclass_fields__) * 4 * 3,
                 f"trajectories of {n} scenarios", "simulate fewer at once (use evaluate for "
                 "outcomes only)")
    _, traj = run_batch(flat, _offsets(offsets, shape, n), _key_data(key), s, params, world,
                        record=True)
    return jax.tree.map(lambda x: x.reshape(shape + x.shape[1:]), traj)


CPU_CHUNK = 1 << 17  # scenarios per compiled call on CPUs
ACCELERATOR_CHUNK = 1 << 20  # on GPUs / TPUs: an H100 ran 2^17-scenario chunks 4.5x slower
# (5.3e9 against 2.4e10 scenario-steps/s)


def default_chunk() -> int:
    """Scenarios per compiled call by default on JAX's default backend."""
    return CPU_CHUNK if jax.default_backend() == "cpu" else ACCELERATOR_CHUNK


def evaluate(scenario: dict, *, sut="carla-tm", sut_params=None, world: World = WORLD,
             key=0, chunk_size: int | None = None, offsets=None) -> Outcome:
    """Per-scenario outcomes (metrics and the paper's reward) of concrete scenarios.

    Arguments as :func:`simulate`. Batches larger than ``chunk_size`` (default
    :func:`default_chunk`) are evaluated chunk by chunk (the last chunk padded to the same
    shape, so nothing recompiles) so memory stays flat; results do not depend on the chunking.
    """
    chunk_size = default_chunk() if chunk_size is None else chunk_size
    if isinstance(chunk_size, bool) or not isinstance(chunk_size, int) or chunk_size <= 0:
        raise ValueError(f"chunk_size must be a positive integer (got {chunk_size!r})")
    scenario, sut_params = split_sut_values(scenario, sut_params, sut)
    s, params, world = _resolve(sut, sut_params, world)
    full = _check_scenario(scenario)
    flat, shape = _flat(full)
    key = _key_data(key)
    n = int(np.prod(shape, dtype=np.int64))
    every = _offsets(offsets, shape, n)
    n_dev = jax.local_device_count()
    if n <= chunk_size and n_dev == 1:
        out, _ = run_batch(flat, every, key, s, params, world)
    else:
        # equal chunks (a multiple of the device count), the batch split over local devices
        size = min(chunk_size, n)
        size = -(-size // n_dev) * n_dev
        sharding = local_batch_sharding()
        parts = []
        for b in range(0, n, size):
            e = min(b + size, n)
            chunk = {k: v[b:e] for k, v in flat.items()}
            offsets = every[b:e]
            if e - b < size:
                chunk = {k: np.pad(v, (0, size - (e - b)), mode="edge")
                         for k, v in chunk.items()}
                offsets = np.pad(offsets, (0, size - (e - b)), mode="edge")
            if sharding is not None:
                chunk, offsets = jax.device_put((chunk, offsets), sharding)
            o, _ = run_batch(chunk, offsets, key, s, params, world)
            parts.append(jax.tree.map(lambda x, m=e - b: np.asarray(x[:m]), o))
        out = jax.tree.map(lambda *xs: np.concatenate(xs), *parts)
    return jax.tree.map(lambda x: x.reshape(shape), out)


def local_batch_sharding():
    """``NamedSharding`` splitting a batch axis over this process's devices (None for one).

    Every rollout is independent, so a sharded batch gives bit-identical results to an
    unsharded one; XLA partitions the jitted rollout along the batch axis.
    """
    from jax.sharding import Mesh, NamedSharding, PartitionSpec

    devices = jax.local_devices()
    if len(devices) == 1:
        return None
    return NamedSharding(Mesh(np.array(devices), ("batch",)), PartitionSpec("batch"))


def describe(scenario: dict, *, sut="carla-tm", sut_params=None, seed: int = 0) -> dict:
    """``jaxfalsify simulate``: one concrete scenario ``{name: value}`` (any known parameters;
    the others take their defaults) evaluated under ``sut`` (a registry name or import path)
    with ``sut_params`` ``{name: value}`` overrides; the SUT's randomness from ``seed``.
    Returns a JSON-ready dict: the resolved ``scenario`` with its ``units``, the
    ``defaults_used``, ``sut`` and every ``sut_params`` value, and the ``outcome`` (each
    :class:`Outcome` field as a Python number, ``None`` for NaN and infinity). One-line
    ValueError for an unknown parameter or a value outside its domain."""

    full = check_scenario_values(scenario)
    s, params = sut_lib.make(sut, **dict(sut_params or {}))
    out = evaluate(full, sut=s, sut_params=params, key=seed)
    return jsonable({
        "scenario": full, "units": {k: KNOWN_PARAMETERS[k]["unit"] for k in full},
        "defaults_used": sorted(set(full) - set(scenario)),
        "sut": sut, "sut_params": sut_lib.params_dict(params),
        "outcome": {k: plain(np.asarray(v)[()]) for k, v in vars(out).items()}})
