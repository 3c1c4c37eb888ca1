"""The crossing world and its batched simulator (paper Fig. 1/3: a pedestrian crosses an urban road).

Frame: x along the ego's lane (direction of travel), y to the left, origin at the ego's *base*
start (its box centre), SI units. The road is straight with ``lanes_right`` lanes in the ego's
direction (the ego drives in the innermost one, next to the centre line at y = 0) and
``lanes_left`` lanes the other way. A marked crosswalk crosses it at ``x = crosswalk_x``.

One episode (written for one concrete scenario; ``vmap`` + ``jit`` are applied outside):

* The ego starts at rest ``ego_offset`` m behind its base, and its SUT drives it.
* The pedestrian starts ``ped_offset + 1`` m behind the right kerb (as the original spawns it)
  and walks straight across, starting when the ego starts moving (t = 0), with the original
  code's speed profile (:func:`ped_speed_profile`).
* Every 0.1 s step: the SUT observes, metrics are taken, then the ego integrates the SUT's
  command (exactly, for constant acceleration over the step, stopping at v = 0) and the
  pedestrian its profile speed.
* The episode ends on collision (box overlap), when the ego has travelled ``30 m +
  ego_offset`` (reached x = 30 m), or at the 30 s horizon. ``lax.scan`` runs the fixed horizon
  with a done mask; metrics are reduced inside the carry.

The geometry constants in :class:`World` were chosen (see README, 'The crossing world') so
that the paper's mechanism appears with its SUT: a slow pedestrian stays outside the Traffic
Manager's narrow hazard corridor (the car's own width) until the car can no longer stop clear
of the crosswalk.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from jaxfalsify import metrics, reward
from jaxfalsify import sut as sut_lib
from jaxfalsify.space import KNOWN_PARAMETERS


@dataclasses.dataclass(frozen=True)
class World:
    """Static world constants (hashable; a static argument of the jitted functions)."""

    dt: float = 0.1  # s
    horizon: int = 300  # steps (30 s)
    lane_width: float = 3.5  # m
    lanes_right: int = 2  # lanes in the ego's direction; the ego uses the inner one
    lanes_left: int = 2  # lanes in the other direction
    crosswalk_x: float = 11.0  # m ahead of the ego's base start (box centre)
    end_x: float = 30.0  # m: the ego has travelled 30 m + ego_offset
    ego_length: float = 4.6  # m, BMW Gran Tourer-class box incl. mirrors
    ego_width: float = 2.1  # m
    ped_length: float = 0.5  # m along x (shoulder width; Euro NCAP adult target)
    ped_width: float = 0.6  # m along y (walking direction)
    max_accel: float = 4.0  # m/s^2, vehicle limit on the SUT's command
    max_brake: float = 9.0  # m/s^2, vehicle limit on the SUT's command
    epsilon: float = 1.0  # m, the STL requirement's clash distance (paper Eq. 1)

    def __post_init__(self):
        if not isinstance(self.horizon, int) or self.horizon < 2:
            raise ValueError(f"world.horizon must be an integer >= 2 steps (got {self.horizon!r})")
        for name in ("dt", "lane_width", "ego_length", "ego_width", "ped_length", "ped_width",
                     "max_accel", "max_brake", "epsilon"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and np.isfinite(v) and v > 0):
                raise ValueError(f"world.{name} must be a positive number (got {v!r})")
        if self.lanes_right < 1 or self.lanes_left < 0:
            raise ValueError("world needs lanes_right >= 1 and lanes_left >= 0")

    @property
    def ego_y(self) -> float:
        return -self.lane_width / 2.0

    @property
    def road_right(self) -> float:
        return -self.lane_width * self.lanes_right

    @property
    def road_left(self) -> float:
        return self.lane_width * self.lanes_left


WORLD = World()


@struct.dataclass
class Trajectory:
    """Per-step record of one episode; each field ``(T,)`` (leading batch dims if batched).

    Steps after the episode ended hold the final state with ``valid`` False.
    """

    t: jax.Array  # s
    ego_x: jax.Array  # m, box centre
    ego_y: jax.Array  # m
    ego_speed: jax.Array  # m/s
    ego_accel: jax.Array  # m/s^2, effective over the step that follows
    ped_x: jax.Array  # m
    ped_y: jax.Array  # m
    ped_speed: jax.Array  # m/s
    distance: jax.Array  # m, Euclidean distance between the two boxes
    rss_distance: jax.Array  # m, RSS minimum safe distance (paper Eq. 4)
    high_risk: jax.Array  # bool, rss_distance > distance, pedestrian ahead of the ego's front
    braking: jax.Array  # bool, the SUT commands deceleration
    collided: jax.Array  # bool, boxes overlap at this step
    valid: jax.Array  # bool, step belongs to the episode
    ttc: jax.Array  # s, constant-velocity time-to-collision (inf: none)


@struct.dataclass
class Outcome:
    """Per-scenario result; each field a scalar (leading batch dims if batched)."""

    reward: jax.Array  # paper reward = sum of the three terms (NaN if the rollout was non-finite)
    reward_rss: jax.Array
    reward_distance: jax.Array
    reward_collision: jax.Array
    collision: jax.Array  # bool
    collision_time: jax.Array  # s, NaN if no collision
    min_distance: jax.Array  # m
    final_distance: jax.Array  # m
    high_risk_steps: jax.Array  # int32
    high_risk_share: jax.Array  # over the episode's steps
    high_risk_share_second_half: jax.Array  # over its second half (paper Fig. 9)
    robustness: jax.Array  # m, STL robustness of always(not clash); < 0 iff violated
    steps: jax.Array  # int32, episode length in steps
    min_ttc: jax.Array  # s
    nonfinite: jax.Array  # bool, the rollout produced NaN/inf and was stopped


BLOCK = 32  # steps per block: one uint32 word of high-risk bits, early exit between blocks


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
    """Pedestrian speed at step k [m/s], the original code's profile.

    start = speed - 5*accel; constant for steps 0..4; from step 5 it grows by ``accel`` per step
    (per step, not accel*dt, as the original) until it first exceeds speed + 0.25, then stays.
    In the extended space, steps [change_step, change_step + 5) use start + change. Never < 0.
    """
    start, n_grow = ped_profile_constants(ped_speed, ped_accel)
    return _profile_at(k, start, n_grow, ped_accel, ped_speed_change, ped_change_step)


def _profile_at(k, start, n_grow, accel, change, change_step):
    v = start + jnp.clip(k - 4.0, 0.0, n_grow) * accel
    window = (k >= change_step) & (k < change_step + 5.0) & (change != 0)
    return jnp.maximum(jnp.where(window, start + change, v), 0.0)


class _Carry(NamedTuple):
    ego_x: jax.Array
    ego_v: jax.Array
    ped_y: jax.Array
    sut_state: object
    alive: jax.Array
    nonfinite: jax.Array
    n_valid: jax.Array
    hr_count: jax.Array
    hr_word: jax.Array
    min_dist: jax.Array
    last_dist: jax.Array
    collided: jax.Array
    coll_step: jax.Array
    min_ttc: jax.Array


def _scenario_scalars(scenario: dict) -> dict:
    return {k: jnp.asarray(scenario[k], jnp.float32) for k in KNOWN_PARAMETERS}


def rollout(scenario: dict, sut: sut_lib.SUT, world: World = WORLD, record: bool = False):
    """Simulate one concrete scenario (all values scalars).

    Returns ``(Outcome, Trajectory | None)``; the trajectory only if ``record``.
    """
    s = _scenario_scalars(scenario)
    w = world
    dt = jnp.float32(w.dt)
    half_x = (w.ego_length + w.ped_length) / 2
    half_y = (w.ego_width + w.ped_width) / 2
    start_x = -s["ego_offset"]
    ped_y0 = w.road_right - (s["ped_offset"] + 1.0)
    weather_idx = s["weather"].astype(jnp.int32)
    p_start, p_grow = ped_profile_constants(s["ped_speed"], s["ped_accel"])
    n_blocks = -(-w.horizon // BLOCK)

    def step(c: _Carry, k):
        kf = k.astype(jnp.float32)
        vp = _profile_at(kf, p_start, p_grow, s["ped_accel"], s["ped_speed_change"],
                         s["ped_change_step"])
        obs = sut_lib.Observation(
            t=kf * dt, ego_x=c.ego_x, ego_y=jnp.float32(w.ego_y), ego_speed=c.ego_v,
            ego_length=jnp.float32(w.ego_length), ego_width=jnp.float32(w.ego_width),
            ped_x=jnp.float32(w.crosswalk_x), ped_y=c.ped_y, ped_vx=jnp.float32(0.0), ped_vy=vp,
            ped_length=jnp.float32(w.ped_length), ped_width=jnp.float32(w.ped_width),
            road_right=jnp.float32(w.road_right), road_left=jnp.float32(w.road_left),
            weather=weather_idx)
        cmd, new_sut_state = sut.act(obs, c.sut_state, sut.params)
        cmd = jnp.asarray(cmd, jnp.float32)

        # --- metrics at this step (state before integration)
        gap_x, gap_y = metrics.box_gaps(w.crosswalk_x - c.ego_x, c.ped_y - w.ego_y, half_x, half_y)
        dist = metrics.box_distance(gap_x, gap_y)
        d_min = metrics.rss_safe_distance(c.ego_v)
        # the pedestrian is RSS's front object until the ego's front bumper has passed it
        ahead = w.crosswalk_x + w.ped_length / 2 > c.ego_x + w.ego_length / 2
        valid = c.alive & (k < w.horizon)
        hr = valid & ahead & (d_min > dist)
        overlap = (gap_x <= 0) & (gap_y <= 0)
        closing_y = jnp.where(c.ped_y < w.ego_y, vp, -vp)
        ttc = metrics.time_to_collision(gap_x, gap_y, jnp.where(w.crosswalk_x > c.ego_x, c.ego_v,
                                                                 -c.ego_v),
                                        closing_y, 2 * half_x, 2 * half_y)
        ttc = jnp.where(valid, ttc, jnp.inf)

        # --- integrate (exact for constant acceleration; stops at v = 0)
        a = jnp.clip(cmd, -w.max_brake, w.max_accel)
        v1 = c.ego_v + a * dt
        stops = v1 < 0
        dx = jnp.where(stops, c.ego_v**2 / (2.0 * jnp.maximum(-a, 1e-6)), (c.ego_v + v1) / 2 * dt)
        v1 = jnp.maximum(v1, 0.0)
        bad = ~(jnp.isfinite(cmd) & jnp.isfinite(dx) & jnp.isfinite(v1))
        nonfinite = c.nonfinite | (valid & bad)
        collided_now = valid & overlap & ~bad
        done = collided_now | (c.ego_x >= w.end_x) | bad
        alive = valid & ~done
        ego_x = jnp.where(alive, c.ego_x + dx, c.ego_x)
        ego_v = jnp.where(alive, v1, c.ego_v)
        ped_y = jnp.where(alive, c.ped_y + vp * dt, c.ped_y)
        sut_state = jax.tree.map(lambda n, o: jnp.where(alive, n, o), new_sut_state, c.sut_state)

        bit = jnp.left_shift(hr.astype(jnp.uint32), (k % BLOCK).astype(jnp.uint32))
        new = _Carry(
            ego_x=ego_x, ego_v=ego_v, ped_y=ped_y, sut_state=sut_state, alive=alive,
            nonfinite=nonfinite,
            n_valid=c.n_valid + valid.astype(jnp.int32),
            hr_count=c.hr_count + hr.astype(jnp.int32),
            hr_word=c.hr_word | bit,
            min_dist=jnp.where(valid, jnp.minimum(c.min_dist, dist), c.min_dist),
            last_dist=jnp.where(valid, dist, c.last_dist),
            collided=c.collided | collided_now,
            coll_step=jnp.where(collided_now, k, c.coll_step),
            min_ttc=jnp.minimum(c.min_ttc, ttc))
        rec = None
        if record:
            rec = Trajectory(
                t=kf * dt, ego_x=c.ego_x, ego_y=jnp.float32(w.ego_y), ego_speed=c.ego_v,
                ego_accel=jnp.where(valid & alive, (ego_v - c.ego_v) / dt, 0.0),
                ped_x=jnp.float32(w.crosswalk_x), ped_y=c.ped_y, ped_speed=jnp.where(valid, vp, 0.0),
                distance=dist, rss_distance=d_min, high_risk=hr, braking=valid & (cmd < 0),
                collided=collided_now, valid=valid, ttc=ttc)
        return new, rec

    init = _Carry(
        ego_x=start_x, ego_v=jnp.float32(0.0), ped_y=ped_y0, sut_state=sut.init(sut.params),
        alive=jnp.bool_(True), nonfinite=jnp.bool_(False), n_valid=jnp.int32(0),
        hr_count=jnp.int32(0), hr_word=jnp.uint32(0),
        min_dist=jnp.float32(jnp.inf), last_dist=jnp.float32(jnp.nan),
        collided=jnp.bool_(False), coll_step=jnp.int32(-1), min_ttc=jnp.float32(jnp.inf))

    def run_block(c: _Carry, b):
        """BLOCK steps from step b*BLOCK; returns the block's high-risk bits as one word."""
        c, rec = jax.lax.scan(step, c._replace(hr_word=jnp.uint32(0)),
                              b * BLOCK + jnp.arange(BLOCK, dtype=jnp.int32))
        return c, (c.hr_word, rec)

    if record:
        c, (words, rec) = jax.lax.scan(run_block, init, jnp.arange(n_blocks, dtype=jnp.int32))
        traj = jax.tree.map(lambda x: x.reshape((n_blocks * BLOCK,) + x.shape[2:])[:w.horizon],
                            rec)
        return _outcome(c, words, w), traj

    # Outcome only: the same blocks, stopped once the episode is over. Under vmap the loop runs
    # until every scenario of the batch is done (finished ones are masked), so results are
    # identical to the full fixed-horizon scan, only cheaper.
    def body(cb):
        c, b, words = cb
        c, (word, _) = run_block(c, b)
        return c, b + 1, jax.lax.dynamic_update_index_in_dim(words, word, b, 0)

    c, _, words = jax.lax.while_loop(lambda cb: cb[0].alive & (cb[1] < n_blocks), body,
                                     (init, jnp.int32(0), jnp.zeros(n_blocks, jnp.uint32)))
    return _outcome(c, words, w), None


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
    total, r_rss, r_dist, r_col = reward.paper_reward(c.hr_count, n, c.last_dist, collision)
    total = jnp.where(c.nonfinite, jnp.nan, total)
    return Outcome(
        reward=total, reward_rss=r_rss, reward_distance=r_dist, reward_collision=r_col,
        collision=collision,
        collision_time=jnp.where(collision, c.coll_step.astype(jnp.float32) * w.dt, jnp.nan),
        min_distance=c.min_dist, final_distance=c.last_dist,
        high_risk_steps=c.hr_count,
        high_risk_share=c.hr_count / jnp.maximum(n, 1),
        high_risk_share_second_half=hr2 / jnp.maximum(second, 1),
        robustness=c.min_dist - w.epsilon,
        steps=n, min_ttc=c.min_ttc, nonfinite=c.nonfinite)


# ---------------------------------------------------------------------------- batched API
def _check_scenario(scenario: dict) -> dict:
    if not isinstance(scenario, dict):
        raise ValueError(f"scenario must be a dict of parameter values (got {type(scenario).__name__})")
    unknown = set(scenario) - set(KNOWN_PARAMETERS)
    if unknown:
        raise ValueError(f"unknown scenario parameter '{sorted(unknown)[0]}' "
                         f"(known: {', '.join(KNOWN_PARAMETERS)})")
    arrs = {k: np.asarray(v, np.float32) if not isinstance(v, jax.Array) else v
            for k, v in scenario.items()}
    try:
        shape = np.broadcast_shapes(*(np.shape(v) for v in arrs.values())) if arrs else ()
    except ValueError:
        raise ValueError("scenario arrays have incompatible shapes: "
                         + ", ".join(f"{k}{tuple(np.shape(v))}" for k, v in arrs.items())) from None
    full = {k: jnp.broadcast_to(jnp.asarray(arrs.get(k, spec["default"]), jnp.float32), shape)
            for k, spec in KNOWN_PARAMETERS.items()}
    return full


def _flat(full: dict):
    shape = next(iter(full.values())).shape
    return {k: v.reshape(-1) for k, v in full.items()}, shape


def batch_rollout(flat: dict, sut: sut_lib.SUT, world: World = WORLD, record: bool = False):
    """vmap of :func:`rollout` over a flat batch ``{name: (B,)}``; not jitted (jit at the edge)."""
    return jax.vmap(lambda sc: rollout(sc, sut, world, record))(flat)


_jit_batch = jax.jit(batch_rollout, static_argnames=("sut", "world", "record"))


def simulate(scenario: dict, *, sut="carla-tm", world: World = WORLD) -> Trajectory:
    """Per-step trajectories of concrete scenarios.

    Args:
      scenario: parameter name -> scalar or array (shapes broadcast); undeclared parameters
        take their defaults (``space.KNOWN_PARAMETERS``).
      sut: a registry name, a :class:`~jaxfalsify.sut.SUT`, or an ``act`` function.
    Returns:
      :class:`Trajectory` with fields ``(*batch, T)``.
    """
    full = _check_scenario(scenario)
    flat, shape = _flat(full)
    _, traj = _jit_batch(flat, sut_lib.get(sut), world, True)
    return jax.tree.map(lambda x: x.reshape(shape + x.shape[1:]), traj)


def evaluate(scenario: dict, *, sut="carla-tm", world: World = WORLD,
             chunk_size: int = 1 << 17) -> Outcome:
    """Per-scenario outcomes (metrics and the paper's reward) of concrete scenarios.

    Batches larger than ``chunk_size`` are evaluated chunk by chunk (the last chunk padded to
    the same shape, so nothing recompiles) so memory stays flat.
    """
    if isinstance(chunk_size, bool) or not isinstance(chunk_size, int) or chunk_size <= 0:
        raise ValueError(f"chunk_size must be a positive integer (got {chunk_size!r})")
    full = _check_scenario(scenario)
    flat, shape = _flat(full)
    s = sut_lib.get(sut)
    n = int(np.prod(shape, dtype=np.int64))
    n_dev = jax.local_device_count()
    if n <= chunk_size and n_dev == 1:
        out, _ = _jit_batch(flat, s, world, False)
    else:
        # equal chunks (a multiple of the device count), the batch split over local devices
        size = min(chunk_size, n)
        size = -(-size // n_dev) * n_dev
        sharding = local_batch_sharding()
        parts = []
        for b in range(0, n, size):
            e = min(b + size, n)
            chunk = {k: v[b:e] for k, v in flat.items()}
            if e - b < size:
                chunk = {k: jnp.pad(v, (0, size - (e - b)), mode="edge")
                         for k, v in chunk.items()}
            if sharding is not None:
                chunk = jax.device_put(chunk, sharding)
            o, _ = _jit_batch(chunk, s, world, False)
            parts.append(jax.tree.map(lambda x, m=e - b: np.asarray(x[:m]), o))
        out = jax.tree.map(lambda *xs: jnp.asarray(np.concatenate(xs)), *parts)
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
