"""The kinematic screen (core/screen.py) against independent oracles: the simulator's own speed
profile summed step by step, the simulator's car trajectory, a step-by-step NumPy search of the
two windows, and the `none` SUT's collisions."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxfalsify as jf
from jaxfalsify.core import screen, sim
from jaxfalsify.suts import registry as sut_lib

H = int(sim.WORLD.horizon)


def _profiles(speed, accel):
    """``(n, H + 1)`` float64 travel [m/s x steps] after k = 0 .. H steps: the simulator's
    profile speeds (``sim.ped_speed_profile``) summed step by step."""
    ks = jnp.arange(H, dtype=jnp.float32)
    v = np.asarray(jax.vmap(lambda s, a: sim.ped_speed_profile(ks, s, a))(
        jnp.float32(speed), jnp.float32(accel)), np.float64)
    return np.concatenate([np.zeros((len(speed), 1)), np.cumsum(v, axis=1)], axis=1)


def test_walker_arrival_is_the_first_step_of_the_summed_profile():
    """On 20,000 random profiles (start speeds below zero, zero speeds and accelerations, walkers
    that never get there included): the closed-form first step equals the first step at which
    the simulator's profile speeds, summed one by one, reach the travel; and the closed-form
    travel equals the sum."""
    rng = np.random.default_rng(0)
    n = 20_000
    speed = np.where(rng.random(n) < 0.1, 0.0, rng.uniform(0.0, 5.0, n))
    accel = np.where(rng.random(n) < 0.3, 0.0, rng.uniform(0.0, 1.0, n))
    travel = rng.uniform(-5.0, 600.0, n)
    summed = _profiles(speed, accel)
    assert np.mean(speed - 5 * accel < 0) > 0.2  # negative start speeds are exercised
    reached = summed >= travel[:, None]
    want = np.where(reached.any(axis=1), reached.argmax(axis=1), H + 1)
    got = np.asarray(jax.jit(lambda r, s, a: screen.walker_arrival(r, s, a, H))(
        jnp.float32(travel), jnp.float32(speed), jnp.float32(accel)))
    np.testing.assert_array_equal(got, want)
    assert np.mean(want == H + 1) > 0.01 and np.mean(want == 0) > 0.005
    ks = jnp.arange(H + 1, dtype=jnp.float32)
    closed = np.asarray(jax.vmap(lambda s, a: screen.walker_travel(ks, s, a))(
        jnp.float32(speed[:2000]), jnp.float32(accel[:2000])))
    np.testing.assert_allclose(closed, summed[:2000], rtol=1e-5, atol=1e-3)


@pytest.mark.parametrize("sut", ["none", "carla-tm", "sensor-aeb"])
def test_unbraked_drive_is_the_simulated_car_with_the_walker_standing_far_off(sut):
    """The drive is the simulator's car position (travelled from its start) in a scenario whose
    walker never moves from 20 m behind the kerb, for every step the episode runs."""
    s = sut_lib.resolve(sut)
    drive = np.asarray(jax.jit(lambda p: screen.unbraked_drive(s, p))(s.default_params))
    tr = jf.simulate({"ego_offset": 50.0, "ped_offset": 20.0, "ped_speed": 0.0}, sut=sut)
    valid = np.asarray(tr.valid)
    travelled = np.asarray(tr.ego_x)[valid] + 50.0
    assert valid.sum() > 100
    np.testing.assert_allclose(drive[1:1 + valid.sum()], travelled, atol=1e-4)
    assert drive[0] == 0.0 and np.all(np.diff(drive) >= 0)


def _np_gap(sc, drive, w=sim.WORLD):
    """The gap [s] by stepping: the windows' first and past-the-end steps found by scanning
    k = 0 .. H over the car's drive and the walker's summed profile."""
    half_x = (w.ego_length + w.ped_length) / 2
    half_y = (w.ego_width + w.ped_width) / 2
    car = -sc["ego_offset"][:, None] + drive[None, :].astype(np.float64)
    ped = (w.road_right + w.walker_base - (sc["ped_offset"] + 1.0))[:, None] \
        + w.dt * _profiles(sc["ped_speed"], sc["ped_accel"])

    def first(cond):
        return np.where(cond.any(axis=1), cond.argmax(axis=1), H + 1)

    car_in = first(car >= w.crosswalk_x - half_x)
    car_out = first(car > w.crosswalk_x + half_x)
    ped_in = first(ped >= w.ego_y - half_y)
    ped_out = first(ped > w.ego_y + half_y)
    gap = np.maximum(car_in - ped_out, ped_in - car_out) * w.dt
    return np.where((car_in > H) | (ped_in > H), np.inf, gap)


def _sample(n, seed):
    rng = np.random.default_rng(seed)
    return {"ego_offset": rng.uniform(0.0, 50.0, n).astype(np.float32),
            "ped_offset": rng.uniform(0.0, 20.0, n).astype(np.float32),
            "ped_speed": rng.uniform(0.0, 5.0, n).astype(np.float32),
            "ped_accel": np.where(rng.random(n) < 0.5, 0.0,
                                  rng.uniform(0.0, 0.3, n)).astype(np.float32)}


def test_conflict_gap_against_a_step_by_step_search_and_the_unbraked_collisions():
    """On 4,000 random scenarios: the gap equals a step-by-step NumPy search of the two
    windows (up to one step where a window's edge is a float32 tie); every collision of the
    `none` SUT (no braking) has a gap <= 0, and nearly every scenario with a gap of -0.2 s or
    less collides."""
    sut = sut_lib.resolve("none")
    sc = _sample(4000, 1)
    drive = np.asarray(screen.unbraked_drive(sut, sut.default_params))
    gap = np.asarray(jax.jit(lambda s: screen.conflict_gap(s, jnp.asarray(drive)))(
        {k: jnp.asarray(v) for k, v in sc.items()}))
    want = _np_gap({k: v.astype(np.float64) for k, v in sc.items()}, drive)
    np.testing.assert_array_equal(np.isinf(gap), np.isinf(want))
    assert 0 < np.mean(np.isinf(want)) < 0.5
    finite = np.isfinite(want)
    off = np.abs(gap[finite] - want[finite])
    assert np.all(off <= sim.WORLD.dt + 1e-5) and np.mean(off < 1e-5) > 0.995
    hit = np.asarray(jf.evaluate(sc, sut="none").collision)
    assert 50 < hit.sum() < len(hit) - 50
    assert np.all(gap[hit] <= 1e-6)
    deep = gap <= -0.2 + 1e-6
    assert deep.sum() > 30 and np.mean(hit[deep]) > 0.95


def test_the_screen_of_a_space_without_ego_offset_uses_its_default():
    """A space that does not declare ``ego_offset`` (nor ``ped_accel``): the per-value screen
    of its indices equals :func:`screen.conflict_gap` of the decoded scenarios, which take the
    parameters' defaults."""
    from jaxfalsify.scenario.space import space_from_dict
    space = space_from_dict({"parameters": {
        "ped_speed": {"distribution": "uniform", "low": 0.5, "high": 3.0, "samples": 30},
        "ped_offset": {"distribution": "uniform", "low": 0.0, "high": 8.0, "samples": 20}}})
    sut = sut_lib.resolve("carla-tm")
    every = np.asarray(space.unravel(np.arange(space.size)))
    drive = screen.unbraked_drive(sut, sut.default_params)
    want = np.asarray(screen.conflict_gap(
        {k: jnp.asarray(v) for k, v in space.scenario(every).items()}, drive))
    got = np.asarray(jax.jit(screen.for_space(space.layout, space.table_array, sut,
                                              sut.default_params))(jnp.asarray(every)))
    np.testing.assert_array_equal(got, want)
    assert 0 < np.mean(want <= 0) < 1


def test_an_actor_that_never_gets_there_is_no_conflict():
    """A walker that stands (speed 0) never enters the lane, and a car whose SUT commands no
    acceleration never reaches the crossing: the gap is infinite, not 0 (two windows that both
    never open do not overlap)."""
    sc = {"ego_offset": jnp.float32([5.0, 5.0]), "ped_offset": jnp.float32([3.0, 3.0]),
          "ped_speed": jnp.float32([0.0, 1.5]), "ped_accel": jnp.float32([0.0, 0.0])}
    moving = sut_lib.resolve("none")
    drive = screen.unbraked_drive(moving, moving.default_params)
    gap = np.asarray(screen.conflict_gap(sc, drive))
    assert gap[0] == np.inf and np.isfinite(gap[1])
    standing = jf.SUT("standing", lambda obs, state, params, key: (jnp.float32(0.0), state))
    still = np.asarray(screen.unbraked_drive(standing, None))
    assert np.all(still == 0.0)
    assert np.all(np.asarray(screen.conflict_gap(sc, jnp.asarray(still))) == np.inf)
