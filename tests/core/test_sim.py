"""The crossing simulator: calibration to the paper, kinematics, closed forms, API contracts."""

import dataclasses
import math

import jax.numpy as jnp
import numpy as np
import pytest
from conftest import random_scenarios

import jaxfalsify as jf
from jaxfalsify.core import sim
from jaxfalsify.suts.registry import REGISTRY, SUT, CruiseParams, cruise_command
from jaxfalsify.suts.sensor_aeb import sensor_capability

W = jf.WORLD


# ------------------------------------------------------------------ calibration (Table II)
def test_challenging_scenario_collides_with_high_risk_second_half(table_ii):
    _, traj, out = table_ii
    assert bool(out.collision[0])
    assert float(out.high_risk_share_second_half[0]) > 0.95
    assert float(out.min_distance[0]) == 0.0 and float(out.robustness[0]) < 0
    assert float(out.reward[0]) > 0.25  # collision bonus dominates


def test_non_challenging_scenario_stops_clear_then_resumes(table_ii):
    _, traj, out = table_ii
    assert not bool(out.collision[1])
    assert float(out.high_risk_share_second_half[1]) < 0.15
    valid = np.asarray(traj.valid[1])
    speed = np.asarray(traj.ego_speed[1])[valid]
    x = np.asarray(traj.ego_x[1])[valid]
    stopped = np.nonzero((speed == 0.0) & (np.arange(valid.sum()) > 0))[0]
    assert stopped.size > 0, "the ego never stopped for the pedestrian"
    # stopped short of the crosswalk with the pedestrian clear of the clash distance
    assert x[stopped[0]] + W.ego_length / 2 < W.crosswalk_x - W.ped_length / 2
    assert float(out.min_distance[1]) > W.epsilon
    # ... then resumed cruising: the episode ended by distance travelled, not at the horizon
    assert int(out.steps[1]) < W.horizon and x[-1] >= W.end_x
    assert speed[-1] > 5.0


def test_paper_collision_set_is_neither_empty_nor_most(paper_sweep):
    rate = paper_sweep["collision"].mean()
    assert 0.01 < rate < 0.5


def test_weather_is_a_distractor_for_carla_tm_but_not_for_sensor_aeb():
    sc = random_scenarios(64, seed=3)
    per_weather = []
    for w in (0, 6):
        sc["weather"] = np.full(64, float(w))
        per_weather.append((jf.evaluate(sc), jf.evaluate(sc, sut="sensor-aeb")))
    (tm0, aeb0), (tm6, aeb6) = per_weather
    np.testing.assert_array_equal(np.asarray(tm0.reward), np.asarray(tm6.reward))
    assert np.any(np.asarray(aeb0.steps) != np.asarray(aeb6.steps))


def test_sensor_aeb_degrades_in_rain_and_low_sun():
    p = REGISTRY["sensor-aeb"].default_params
    clear_r, clear_lat, clear_dec = map(float, sensor_capability(0, p))  # ClearNoon
    rain_r, rain_lat, rain_dec = map(float, sensor_capability(6, p))  # HardRainSunset
    sun_r, sun_lat, _ = map(float, sensor_capability(1, p))  # ClearSunset (glare, dusk)
    assert rain_r < clear_r and sun_r < clear_r and rain_lat > sun_lat > clear_lat
    assert rain_dec < clear_dec
    assert clear_dec == pytest.approx(p.mu_dry * 9.81)
    # closed form of the light model: E = sin(altitude) * (1 - 0.75 * cloud^3.4)
    e_cloudy_noon = math.sin(math.radians(75)) * (1 - 0.75 * 0.8**3.4)
    _, lat, _ = map(float, sensor_capability(2, p))  # CloudyNoon
    assert lat == pytest.approx(p.latency + p.dark_latency * (1 - e_cloudy_noon), abs=1e-5)


def test_sensor_aeb_sees_sun_and_clouds():
    """Every preset that differs in what CARLA changes (sun, cloud, rain, wetness) gives the
    SUT a different capability; only Default (the map's ClearNoon) equals ClearNoon."""
    p = REGISTRY["sensor-aeb"].default_params
    caps = {tuple(round(float(x), 6) for x in sensor_capability(i, p)) for i in range(15)}
    assert len(caps) == 14
    # and outcomes differ between presets of every old identical group {0-4}, {5-6},
    # {7-10}, {11-14} (one batch over all presets)
    sc = random_scenarios(256, seed=5)
    sc = {k: np.tile(v, 15) for k, v in sc.items()}
    sc["weather"] = np.repeat(np.arange(15.0), 256)
    rew = np.asarray(jf.evaluate(sc, sut="sensor-aeb").reward).reshape(15, 256)
    for a, b in ((0, 1), (0, 2), (2, 3), (5, 6), (7, 8), (8, 9), (9, 10), (7, 10), (11, 12),
                 (13, 14), (11, 13)):
        assert np.any(rew[a] != rew[b]), (a, b)


# ------------------------------------------------------------------ kinematics
@pytest.fixture(scope="module")
def random_traj():
    sc = random_scenarios(200, seed=1, extended=True)
    return sc, jf.simulate(sc), jf.evaluate(sc)


# positions, speeds, braking, collision, robustness, reward terms and evaluate == reduce(simulate)
# are property-based tests in test_properties.py


def _aeb_steps(latency, demand_steps=8, ped_vy=0.0, ped_y=-1.5):
    """sensor-aeb's commands over ``demand_steps`` steps with a pedestrian standing (or
    walking at ``ped_vy``) in the ego's lane 3 m ahead at 6 m/s (TTC 0.5 s: a full-brake
    demand from the first step), the weather's extra latencies off."""
    from jaxfalsify.suts.registry import Observation, SensorAEBParams
    from jaxfalsify.suts.sensor_aeb import sensor_aeb_act, sensor_init
    p = SensorAEBParams(latency=latency, dark_latency=0.0, rain_latency=0.0)
    f = lambda v: jnp.float32(v)  # noqa: E731
    obs = Observation(t=f(0), dt=f(0.1), ego_x=f(0), ego_y=f(-1.5), ego_speed=f(6.0),
                      ego_length=f(4.6), ego_width=f(2.1), ped_x=f(5.55), ped_y=f(ped_y),
                      ped_vx=f(0), ped_vy=f(ped_vy), ped_length=f(0.5), ped_width=f(0.6),
                      road_right=f(-9), road_left=f(3), weather=jnp.int32(0))
    state, out = sensor_init(None, p), []
    for _ in range(demand_steps):
        a, state = sensor_aeb_act(obs, state, p, None)
        out.append(float(a))
    return np.array(out)


@pytest.mark.parametrize("latency", [0.0, 0.1, 0.3])
def test_sensor_aeb_brakes_after_its_latency(latency):
    """A demand perceived from step 0 brakes from step latency / dt on (0 on the same
    step); latency 0 does not stop a car that sees no demand from driving."""
    accel = _aeb_steps(latency)
    first = round(latency / 0.1)
    assert np.all(accel[:first] >= 0) and np.all(accel[first:] < -8.0)
    no_demand = _aeb_steps(latency, ped_y=-8.0)  # on the kerb, out of the path
    assert np.all(no_demand > 0)


def test_sensor_aeb_holds_a_pedestrian_in_its_path():
    """The in-path target model: a pedestrian inside the lane walking away from its centre
    line still gets full braking (the metric's TTC says it clears the path first)."""
    from jaxfalsify.scenario import metrics
    gy = abs(-1.0 - -1.5) - (2.1 + 0.6) / 2  # inside the path, 0.85 m from its far edge
    assert not np.isfinite(float(metrics.time_to_collision(3.0, gy, 6.0, -2.0,
                                                           5.1, 2.7)))  # leaves after 0.43 s
    assert np.all(_aeb_steps(0.0, ped_vy=2.0, ped_y=-1.0) < -8.0)


def test_pedestrian_profile_matches_the_original_loop():
    """pdf.py: constant for steps 0..5, then +accel per step until above speed + 0.25; the
    change window (T..T+5, six steps) walks at the current s + change and pauses growth,
    whatever the change."""
    def original(speed, accel, change, T, n):
        out, s = [], round(speed - accel * 5, 3)
        for i in range(n):
            if T <= i <= T + 5:  # whatever the change: 0 holds the speed
                out.append(s + change)
            elif i <= 5 or s > speed + 0.25:
                out.append(s)
            else:
                s += accel
                out.append(s)
        return out

    # (no exact ties s == speed + 0.25, which the original resolves by float noise)
    for speed, accel, change, T in ((1.237, 0.007, 0.0, 0.0), (1.4, 0.03, -0.5, 8.0),
                                    (1.1, 0.045, 0.75, 20.0), (1.808, 0.076, 0.5, 6.0),
                                    (1.3, 0.03, 0.0, 10.0)):  # a change of 0 mid-ramp
        got = np.asarray(sim.ped_speed_profile(jnp.arange(120.0), speed, accel, change, T))
        np.testing.assert_allclose(got, original(speed, accel, change, T, 120), atol=1e-5)


# ------------------------------------------------------------------ closed forms (sut=none)
P_CRUISE = SUT("p-cruise", lambda o, s, p, k: (cruise_command(o.ego_speed, p), s),
               default_params=CruiseParams(), stochastic=False)


def _none_closed_form(ego_offset, ped_speed, ped_offset):
    """Exact discrete-time positions of a P-controller cruise (clipped; no braking) and of a
    constant-speed pedestrian; returns the first collision time or None."""
    p = P_CRUISE.default_params
    dt, k = W.dt, np.arange(W.horizon, dtype=np.float64)
    k1 = np.ceil((p.cruise_speed - p.accel_max / p.gain) / (p.accel_max * dt) + 1e-12)
    r = 1 - p.gain * dt
    e1 = p.cruise_speed - p.accel_max * k1 * dt
    x1 = -ego_offset + p.accel_max * (k1 * dt) ** 2 / 2
    m = k - k1
    x_late = x1 + dt * (m * p.cruise_speed - e1 * (1 + r) * (1 - r**m) / (2 * (1 - r)))
    x = np.where(k <= k1, -ego_offset + p.accel_max * (k * dt) ** 2 / 2, x_late)
    y0 = W.road_right + W.walker_base - (ped_offset + 1)
    hx, hy = (W.ego_length + W.ped_length) / 2, (W.ego_width + W.ped_width) / 2
    # contact at any instant of the tick that reaches state k (from state k-1): the walker's
    # centre is in the band |y - ego_y| <= hy for t in [ta, tb] (linear); the ego's, moving at
    # the tick's constant acceleration (speeds recovered from x_k - x_{k-1} = (v_{k-1} + v_k)
    # dt / 2, v_0 = 0), is in |x - crosswalk_x| <= hx between the roots of its quadratic
    v = np.zeros_like(x)
    for i in range(1, x.size):
        v[i] = 2 * (x[i] - x[i - 1]) / dt - v[i - 1]
    overlap = np.zeros(x.size, bool)
    ta = (W.ego_y - hy - y0) / ped_speed - (k - 1) * dt  # into the tick reaching state k
    tb = (W.ego_y + hy - y0) / ped_speed - (k - 1) * dt
    for i in range(1, x.size):
        lo, hi = max(ta[i], 0.0), min(tb[i], dt)
        if lo > hi:
            continue
        a = (v[i] - v[i - 1]) / dt
        reach = np.roots([a / 2, v[i - 1], x[i - 1] - (W.crosswalk_x - hx)])
        t_in = 0.0 if x[i - 1] >= W.crosswalk_x - hx else min(
            [r.real for r in reach if abs(r.imag) < 1e-12 and r.real >= 0] or [np.inf])
        reach = np.roots([a / 2, v[i - 1], x[i - 1] - (W.crosswalk_x + hx)])
        t_out = -np.inf if x[i - 1] > W.crosswalk_x + hx else min(
            [r.real for r in reach if abs(r.imag) < 1e-12 and r.real >= 0] or [np.inf])
        overlap[i] = max(lo, t_in) <= min(hi, t_out)
    # state k is reached by step k-1, which runs unless a state before it was beyond the end
    ended = np.concatenate([[False, False], np.cumsum(x > W.end_x)[:-2] > 0])
    hits = np.nonzero(overlap & ~ended)[0]
    return None if hits.size == 0 else hits[0] * dt


def test_constant_speed_crossing_collision_time_matches_closed_form():
    rng = np.random.default_rng(7)
    sc = dict(ego_offset=rng.uniform(1, 10, 300), ped_speed=rng.uniform(0.6, 2.5, 300),
              ped_offset=rng.uniform(3, 4.5, 300), ped_accel=np.zeros(300))
    out = jf.evaluate(sc, sut=P_CRUISE)
    expected = [_none_closed_form(*a) for a in zip(sc["ego_offset"], sc["ped_speed"],
                                                    sc["ped_offset"])]
    hit = np.array([e is not None for e in expected])
    assert 10 < hit.sum() < 290  # both outcomes are exercised
    np.testing.assert_array_equal(np.asarray(out.collision), hit)
    got = np.asarray(out.collision_time)[hit]
    np.testing.assert_allclose(got, [e for e in expected if e is not None], atol=1e-5)


def test_user_sut_constant_acceleration_closed_form():
    """A user-supplied SUT (a bare act function): x(t) = x0 + a t^2 / 2 exactly."""
    def constant_accel(obs, state, params, key):
        return jnp.float32(2.0), state

    sc = dict(ego_offset=4.0, ped_speed=1.3, ped_offset=3.5, ped_accel=0.0)
    tr = jf.simulate(sc, sut=constant_accel)
    n = int(np.asarray(tr.valid).sum())
    t = np.asarray(tr.t)[:n]
    np.testing.assert_allclose(np.asarray(tr.ego_x)[:n], -4.0 + t**2, atol=1e-4)


# ------------------------------------------------------------------ API contracts
def test_batched_equals_unbatched_and_shapes(table_ii):
    sc, traj, out = table_ii
    one = jf.evaluate({k: float(v[0]) for k, v in sc.items()})
    assert np.asarray(one.reward).shape == ()
    assert float(one.reward) == float(out.reward[0])
    assert traj.distance.shape == (2, W.horizon)
    grid = jf.evaluate({k: np.broadcast_to(v, (3, 2)) for k, v in sc.items()})
    assert grid.reward.shape == (3, 2)
    np.testing.assert_array_equal(np.asarray(grid.reward[2]), np.asarray(out.reward))


def test_chunked_evaluation_is_identical(random_traj):
    sc, _, out = random_traj
    chunked = jf.evaluate(sc, chunk_size=37)
    for f in dataclasses.fields(out):
        np.testing.assert_array_equal(np.asarray(getattr(chunked, f.name)),
                                      np.asarray(getattr(out, f.name)), err_msg=f.name)


def test_evaluate_compiles_once_for_new_values_and_calibrations(compile_events):
    """Other scenario values and SUT parameter values reuse the compiled program (counted
    through JAX's public compilation events)."""
    jf.evaluate(random_scenarios(50, seed=11), sut="sensor-aeb")
    with compile_events() as events:
        for seed, ttc in ((12, 0.5), (13, 1.2)):
            jf.evaluate(random_scenarios(50, seed=seed), sut="sensor-aeb",
                        sut_params={"ttc_full": ttc})
    assert events == []


def test_nan_command_is_flagged_not_a_collision():
    def nan_sut(obs, state, params, key):
        return jnp.where(obs.t > 1.0, jnp.nan, 1.0), state

    out = jf.evaluate(random_scenarios(8, seed=2), sut=nan_sut)
    assert np.all(np.asarray(out.nonfinite)) and not np.any(np.asarray(out.collision))
    assert np.all(np.isnan(np.asarray(out.reward)))


def test_bad_scenarios_raise_one_line_errors():
    with pytest.raises(ValueError, match="unknown scenario parameter 'ped_sped'"):
        jf.evaluate({"ped_sped": 1.0})
    with pytest.raises(ValueError, match="incompatible shapes"):
        jf.evaluate({"ped_speed": np.ones(3), "ego_offset": np.ones(4)})
    with pytest.raises(ValueError, match="unknown SUT 'tesla'"):
        jf.evaluate({"ped_speed": 1.0}, sut="tesla")
    with pytest.raises(ValueError, match="chunk_size"):
        jf.evaluate({"ped_speed": 1.0}, chunk_size=0)
    with pytest.raises(ValueError, match="horizon"):
        jf.evaluate({"ped_speed": 1.0}, world=dataclasses.replace(W, horizon=0))
    with pytest.raises(ValueError, match="scenario must be a dict .*got NoneType"):
        jf.evaluate(None)
    with pytest.raises(ValueError, match="world must be a jaxfalsify.World .*got int"):
        jf.simulate({"ped_speed": 1.0}, world=5)
