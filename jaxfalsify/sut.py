"""Systems under test: longitudinal controllers of the ego vehicle, black boxes to the search.

A SUT is a pair of pure functions over one scenario (the simulator vmaps them):

* ``init(key, params) -> state``
* ``act(obs, state, params, key) -> (accel_command, new_state)``: called every step with an
  :class:`Observation` (its ``dt`` is the world's step); the longitudinal acceleration command
  [m/s^2] (negative = braking) acts during the next step, within the vehicle's limits.

``params`` is a pytree (a :func:`jaxfalsify.pytree.dataclass` of floats) passed *traced*: a
calibration change does not recompile, and a sweep can vmap over calibrations. ``key`` is a
typed PRNG key (sensor noise); the built-ins are deterministic and ignore it.

Registry (gymnax / jumanji style): ``register(SUT(...))``, ``make(name, **params) -> (sut,
params)``; a user's SUT is named by import path, ``my_pkg.my_aeb:AEB`` or
``path/to/file.py:AEB`` (a :class:`SUT`, a function returning one, or a bare ``act``).

Built-ins:

* ``carla-tm`` (default): CARLA 0.9.9's Traffic Manager autopilot (pipeline era) with its
  ground-truth collision stage, the SUT of the paper. Weather does not change it (CARLA's
  weather is visual only).
* ``sensor-aeb``: a perception-based AEB on the same autopilot whose detection degrades with
  light, glare and rain, with staged braking on time-to-collision and friction-limited
  braking on wet roads.
* ``none``: the autopilot's speed keeping (CARLA's PID) without any emergency braking.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Any, Callable, Mapping, NamedTuple

import jax
import jax.numpy as jnp

from jaxfalsify import cache, metrics, pytree, weather
from jaxfalsify.worker import import_module

G = 9.81  # m/s^2


class Observation(NamedTuple):
    """What a SUT sees at one step (ground truth; a perception SUT filters it itself).

    Positions are box centres [m] in the road frame (x along the ego's lane, y to the left);
    speeds [m/s]; sizes are full box lengths [m]; ``dt`` the step [s]; ``weather`` the CARLA
    preset index.
    """

    t: jax.Array
    dt: jax.Array
    ego_x: jax.Array
    ego_y: jax.Array
    ego_speed: jax.Array
    ego_length: jax.Array
    ego_width: jax.Array
    ped_x: jax.Array
    ped_y: jax.Array
    ped_vx: jax.Array
    ped_vy: jax.Array
    ped_length: jax.Array
    ped_width: jax.Array
    road_right: jax.Array
    road_left: jax.Array
    weather: jax.Array


def _no_state(key, params):
    return jnp.bool_(False)


@dataclasses.dataclass(frozen=True)
class SUT:
    """A system under test (hashable: a static argument of compiled code).

    Attributes:
      name: registry name or import path.
      act: ``act(obs, state, params, key) -> (accel [m/s^2], state)``.
      init: ``init(key, params) -> state``.
      default_params: the parameter pytree with its defaults (``None``: no parameters). Not
        part of the hash: parameters are traced.
      stochastic: whether ``init``/``act`` use their key; False skips deriving per-scenario
        and per-step keys (the built-ins are deterministic).
    """

    name: str
    act: Callable[[Observation, Any, Any, jax.Array], tuple[jax.Array, Any]]
    init: Callable[[jax.Array, Any], Any] = _no_state
    default_params: Any = dataclasses.field(default=None, compare=False, hash=False)
    stochastic: bool = True


# ----------------------------------------------------------------------------- cruise
@pytree.dataclass
class CruiseParams:
    """A simple speed keeper (a clipped P controller), a helper for user SUTs; the built-ins
    use CARLA's PID (:class:`AutopilotParams`)."""

    cruise_speed: float = 30.0 / 3.6 * 0.7  # m/s
    gain: float = 1.0  # 1/s
    accel_max: float = 1.5  # m/s^2, comfortable launch
    decel_max: float = 3.0  # m/s^2, normal (non-emergency) braking

    RANGES = {"cruise_speed": "[0, inf)", "gain": "[0, inf)", "accel_max": "[0, inf)",
              "decel_max": "[0, inf)"}


def cruise_command(speed, p) -> jax.Array:
    """Speed-keeping acceleration command [m/s^2] (``p`` has the :class:`CruiseParams` fields)."""
    return jnp.clip(p.gain * (p.cruise_speed - speed), -p.decel_max, p.accel_max)


@pytree.dataclass
class AutopilotParams:
    """CARLA 0.9.9's Traffic Manager speed keeping (pipeline era: ``PIDController.cpp``,
    ``MotionPlannerStage.cpp``, ``TrafficManager.cpp``; see README 'Systems under test').

    Target speed = ``speed_limit * (1 - below_limit / 100)`` (TM's default: 30 % below the
    limit). PID on the normalised error ``e = (v - target) / target`` with CARLA's urban
    longitudinal gains and its fixed ``pid_dt = 1/20 s``; the integral clamped to +-5;
    ``expr < 0`` gives throttle ``min(-expr, 0.7)``, otherwise brake ``min(expr, 1)``.

    Not fixed by CARLA's code (assumptions, parameters): Town05's speed limit where the original
    spawns (40 km/h), and the accelerations that full throttle and a full brake
    pedal give the BMW Gran Tourer (``throttle_accel``, ``full_brake``; no drag, no gears).
    """

    speed_limit: float = 40.0  # km/h (assumption, calibrated; Town05 has 30-60 km/h roads)
    below_limit: float = 30.0  # %, CARLA's perc_difference_from_limit default
    kp: float = 2.0  # CARLA urban longitudinal gains {2.0, 0.05, 0.07}
    ki: float = 0.05
    kd: float = 0.07
    pid_dt: float = 0.05  # s, CARLA's PID assumes 20 FPS whatever the tick
    max_throttle: float = 0.7
    throttle_accel: float = 2.75  # m/s^2 at throttle 1.0 (assumption, calibrated)
    full_brake: float = 6.0  # m/s^2 at brake 1.0 (assumption, calibrated)

    # below_limit < 0: faster than the limit, as in CARLA
    RANGES = {"speed_limit": "(0, inf)", "below_limit": "(-inf, 100)", "kp": "[0, inf)",
              "ki": "[0, inf)", "kd": "[0, inf)", "pid_dt": "(0, inf)",
              "max_throttle": "[0, 1]", "throttle_accel": "(0, inf)", "full_brake": "(0, inf)"}


def target_speed(p) -> jax.Array:
    """The autopilot's target speed [m/s]."""
    return p.speed_limit / 3.6 * (1.0 - p.below_limit / 100.0)


def _pid_init(key, params):
    """PID state: (integral of the normalised error [s], previous normalised error)."""
    return (jnp.float32(0.0), jnp.float32(0.0))


def autopilot_command(speed, pid, p: AutopilotParams):
    """One PID step: ``(acceleration [m/s^2], new pid state)``."""
    integral, prev = pid
    target = jnp.maximum(target_speed(p), 1e-3)
    e = (speed - target) / target
    integral = jnp.clip(integral + e * p.pid_dt, -5.0, 5.0)
    expr = p.kp * e + p.ki * integral + p.kd * (e - prev) / p.pid_dt
    throttle = jnp.where(expr < 0, jnp.minimum(-expr, p.max_throttle), 0.0)
    brake = jnp.where(expr < 0, 0.0, jnp.minimum(expr, 1.0))
    return throttle * p.throttle_accel - brake * p.full_brake, (integral, e)


def none_act(obs: Observation, state, p: AutopilotParams, key):
    """The autopilot's speed keeping only: no emergency braking at all."""
    return autopilot_command(obs.ego_speed, state, p)


# ----------------------------------------------------------------------------- carla-tm
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


# ----------------------------------------------------------------------------- sensor-aeb
@pytree.dataclass
class SensorAEBParams(AutopilotParams):
    """A perception-based AEB (camera + radar class) on the autopilot, degraded by weather.

    Detection: the pedestrian's centre within ``range`` metres and ``fov`` degrees of the
    bumper's centre line; a braking demand must persist for a latency (confirmation +
    actuation) that grows as light fails and rain falls.
    Weather model (constants are parameters; sources in README 'Systems under test'):

    * light: relative illuminance ``E = sin(sun altitude) * (1 - 0.75 * (cloud/100)^3.4)``
      (clear-sky irradiance ~ sin(altitude); Kasten & Czeplak 1980 cloud factor); latency
      ``+ dark_latency * (1 - E)`` (camera detection degrades in low light: AAA 2019, IIHS);
    * glare: the sun below ``glare_altitude`` (low sun into the camera) cuts range by
      ``glare_range_loss`` scaled by the clear-sky share ``1 - cloud/100``;
    * rain: range ``* (1 - rain_range_loss * precipitation/100)``, latency
      ``+ rain_latency * precipitation/100`` (Zang et al. 2019, IEEE VT Magazine);
    * wet road: friction falls from ``mu_dry`` to ``mu_wet`` as deposits go 0 -> 100 %;
      the AEB's full stage brakes at ``mu * g`` (the tyres' limit; the autopilot's
      ``full_brake``, its pedal at brake 1.0, is not used by the AEB).

    Braking is staged on TTC: ``partial_brake`` below ``ttc_partial`` s, full below
    ``ttc_full`` s. The TTC is the constant-velocity one of :func:`metrics.time_to_collision`
    with an *in-path* target model: a pedestrian walking away from the ego's centre line is
    taken to stay where it is laterally (no prediction that it leaves the path), so the AEB
    keeps braking for a pedestrian inside its path until the car stops or the pedestrian is out.

    ``latency`` counts from the first step a demand is perceived: with ``dt`` 0.1 s a latency
    of 0.1 s brakes one step after that, 0 on the same step. The weather's terms add to it
    (at least ``dark_latency * (1 - 0.965)`` = 0.014 s, the brightest preset's illuminance
    being 0.965) and it is served in whole steps, so the default brakes two steps after.
    """

    range: float = 40.0  # m, clear day
    fov: float = 50.0  # deg, full angle
    latency: float = 0.1  # s, confirmation + actuation in full daylight
    dark_latency: float = 0.4  # s added at zero illuminance
    glare_altitude: float = 20.0  # deg
    glare_range_loss: float = 0.5  # fraction under a clear low sun
    rain_range_loss: float = 0.5  # fraction at 100 % precipitation
    rain_latency: float = 0.3  # s added at 100 % precipitation
    ttc_partial: float = 1.6  # s
    ttc_full: float = 0.9  # s
    partial_brake: float = 4.0  # m/s^2
    mu_dry: float = 0.9
    mu_wet: float = 0.55

    RANGES = {"range": "(0, inf)", "fov": "(0, 360]", "latency": "[0, inf)",
              "dark_latency": "[0, inf)", "glare_altitude": "[0, 90]",
              "glare_range_loss": "[0, 1]", "rain_range_loss": "[0, 1]",
              "rain_latency": "[0, inf)", "ttc_partial": "[0, inf)", "ttc_full": "[0, inf)",
              "partial_brake": "[0, inf)", "mu_dry": "(0, inf)", "mu_wet": "(0, inf)"}


def illuminance(weather_index) -> jax.Array:
    """Relative daylight illuminance in [0, 1] of a weather preset (see SensorAEBParams)."""
    row = jnp.asarray(weather.TABLE)[jnp.asarray(weather_index, jnp.int32)]
    cloud, sun = row[0] / 100.0, row[3]
    return jnp.sin(jnp.deg2rad(jnp.clip(sun, 0.0, 90.0))) * (1.0 - 0.75 * cloud**3.4)


def sensor_capability(weather_index, p: SensorAEBParams):
    """(range [m], latency [s], max deceleration [m/s^2]) under a weather preset."""
    row = jnp.asarray(weather.TABLE)[jnp.asarray(weather_index, jnp.int32)]
    cloud, rain, deposits, sun = row[0] / 100.0, row[1] / 100.0, row[2] / 100.0, row[3]
    glare = jnp.where(sun < p.glare_altitude, p.glare_range_loss * (1.0 - cloud), 0.0)
    rng = p.range * (1.0 - p.rain_range_loss * rain) * (1.0 - glare)
    latency = p.latency + p.dark_latency * (1.0 - illuminance(weather_index)) \
        + p.rain_latency * rain
    mu = p.mu_dry + (p.mu_wet - p.mu_dry) * deposits
    return rng, latency, mu * G


def sensor_aeb_act(obs: Observation, state, p: SensorAEBParams, key):
    """State: (consecutive steps a braking demand has been perceived (int32), PID state).

    A demand is a detected pedestrian with TTC below ``ttc_partial``; the brake acts once the
    demand has persisted for the weather's latency (perception confirmation + actuation)."""
    armed_for, pid = state
    rng, latency, decel = sensor_capability(obs.weather, p)
    front = obs.ego_x + obs.ego_length / 2
    dx = obs.ped_x - front
    dy = obs.ped_y - obs.ego_y
    in_fov = (dx > 0) & (jnp.abs(jnp.arctan2(dy, jnp.maximum(dx, 1e-6))) <= jnp.deg2rad(p.fov / 2))
    detected = in_fov & (dx * dx + dy * dy <= rng * rng)
    gap_x, gap_y = metrics.box_gaps(obs.ped_x - obs.ego_x, obs.ped_y - obs.ego_y,
                                    (obs.ego_length + obs.ped_length) / 2,
                                    (obs.ego_width + obs.ped_width) / 2)
    # in-path target model: a pedestrian walking away from the centre line is held in place
    closing_y = jnp.maximum(-jnp.sign(obs.ped_y - obs.ego_y) * obs.ped_vy, 0.0)
    ttc = metrics.time_to_collision(gap_x, gap_y, obs.ego_speed, closing_y,
                                    obs.ego_length + obs.ped_length,
                                    obs.ego_width + obs.ped_width)
    brake = jnp.where(ttc <= p.ttc_full, decel, jnp.where(ttc <= p.ttc_partial,
                                                          jnp.minimum(p.partial_brake, decel), 0.0))
    armed_for = jnp.where(detected & (brake > 0), armed_for + 1, 0)
    # the demand has persisted (armed_for - 1) steps since it was first perceived
    confirmed = (armed_for > 0) & ((armed_for - 1).astype(jnp.float32) * obs.dt
                                   >= latency - 1e-6)
    cruise, pid = autopilot_command(obs.ego_speed, pid, p)
    accel = jnp.where(confirmed, -brake, cruise)
    return accel, (armed_for, pid)


def _sensor_init(key, params):
    return (jnp.int32(0), _pid_init(key, params))


# ----------------------------------------------------------------------------- registry
REGISTRY: dict[str, SUT] = {}


def register(sut: SUT) -> SUT:
    """Add a SUT to the registry under ``sut.name`` (replacing one of the same name)."""
    if not isinstance(sut, SUT):
        raise ValueError(f"register() takes a SUT (got {type(sut).__name__})")
    REGISTRY[sut.name] = sut
    return sut


register(SUT("carla-tm", carla_tm_act, _pid_init, CarlaTMParams(), stochastic=False))
register(SUT("sensor-aeb", sensor_aeb_act, _sensor_init, SensorAEBParams(), stochastic=False))
register(SUT("none", none_act, _pid_init, AutopilotParams(), stochastic=False))


def error_line(e: BaseException) -> str:
    """``TypeName: first line of the message`` of a user's exception, for one-line errors."""
    text = str(e).strip()
    return f"{type(e).__name__}: {text.splitlines()[0] if text else ''}"


def load_attr(spec: str, what: str = "SUT"):
    """``module:attr`` or ``path/file.py:attr`` -> the attribute (one-line ValueError naming
    ``what`` it was to be: a SUT, a requirement)."""
    mod_name, _, attr = spec.rpartition(":")
    if not mod_name or not attr:
        known = f"a registry name ({', '.join(REGISTRY)}) or " if what == "SUT" else ""
        raise ValueError(f"{what} '{spec}': expected {known}an import path module:attr")
    try:
        if mod_name.endswith(".py") and not Path(mod_name).resolve().is_file():
            raise ValueError(f"{what} '{spec}': no such file {mod_name}")
        module = import_module(mod_name, "jaxfalsify_user_sut_")
    except ValueError:
        raise
    except (Exception, SystemExit) as e:  # noqa: BLE001 - a user module can raise anything
        # on import (sys.exit too)
        raise ValueError(f"{what} '{spec}': cannot import {mod_name} ({error_line(e)})") from None
    try:
        return getattr(module, attr)
    except AttributeError:
        raise ValueError(f"{what} '{spec}': {mod_name} has no attribute '{attr}'") from None
    except (Exception, SystemExit) as e:  # noqa: BLE001 - a module __getattr__ can raise
        raise ValueError(f"{what} '{spec}': looking up '{attr}' in {mod_name} raised "
                         f"{error_line(e)}") from None


def recorded_spec(spec: str, folder: Path | None = None) -> str:
    """The SUT name as a run records it: a file path ``path/file.py:attr`` made absolute (a
    relative one taken from ``folder``, default the working folder), so ``--resume`` and
    ``--config`` find the same file from any working folder; registry names and module import
    paths unchanged."""
    mod_name, _, attr = spec.rpartition(":")
    if spec in REGISTRY or not mod_name.endswith(".py") or Path(mod_name).is_absolute():
        return spec
    return f"{((folder or Path.cwd()) / mod_name).resolve()}:{attr}"


def folder_name(spec: str) -> str:
    """A SUT name usable in a folder name: ``file.py:AEB`` -> ``file-AEB``, ``pkg.mod:AEB``
    -> ``pkg.mod-AEB``, registry names unchanged."""
    mod, _, attr = spec.rpartition(":")
    if mod.endswith(".py"):
        mod = Path(mod).stem
    return (f"{mod}-{attr}" if mod else spec).replace("/", "_").replace("\\", "_")


def _example_observation() -> Observation:
    return Observation(*([jnp.float32(0.0)] * (len(Observation._fields) - 1)),
                       weather=jnp.int32(0))


def is_builtin(sut: SUT) -> bool:
    """Whether ``sut``'s code is jaxfalsify's own (trusted, cached by name)."""
    return all(getattr(f, "__module__", "").startswith("jaxfalsify.") for f in (sut.act, sut.init))


_TRACEABLE: set = set()  # SUTs that passed check_traceable


def check_traceable(sut: SUT, params: Any) -> None:
    """Return once ``sut``'s ``init(key, params)`` and ``act(obs, state, params, key)`` trace
    with ``params`` (its resolved parameters) and return ``(command, state)`` with a scalar
    command and the state's structure kept (abstract evaluation: nothing is computed or
    compiled); else a one-line ValueError naming the SUT. Run on every user SUT (not the
    built-ins) where a command or library call resolves its parameters, before any file is
    written; once per SUT and process."""
    if is_builtin(sut):
        return
    try:
        if sut in _TRACEABLE:
            return
    except TypeError:  # an unhashable act or init: checked every time
        pass

    def one_step(key):
        state = sut.init(key, params)
        out = sut.act(_example_observation(), state, params, key)
        if not (isinstance(out, tuple) and len(out) == 2):
            raise TypeError(f"act returned {type(out).__name__}, expected (command, state)")
        cmd, new_state = out
        if jnp.shape(cmd) != ():
            raise TypeError(f"act's command has shape {jnp.shape(cmd)}, expected a scalar "
                            "(m/s^2)")
        if jax.tree.structure(new_state) != jax.tree.structure(state):
            raise TypeError("act's new state differs in structure from init's")
        for a, b in zip(jax.tree.leaves(state), jax.tree.leaves(new_state)):
            ta, tb = jnp.result_type(a), jnp.result_type(b)
            sa, sb = jnp.shape(a), jnp.shape(b)
            if ta != tb or sa != sb:  # the rollout's scan carries the state unchanged in type
                raise TypeError(f"act changes the state from {ta}{list(sa)} to "
                                f"{tb}{list(sb)} (init's dtype and shape must be kept)")
        return cmd

    try:
        jax.eval_shape(one_step, jax.random.key(0))
    except Exception as e:  # noqa: BLE001 - a user's code can raise anything when traced
        hint = (" (a bare act function gets params=None; give the SUT default_params)"
                if params is None and "NoneType" in str(e) else "")
        raise ValueError(f"SUT '{sut.name}' fails on a step: {error_line(e)}{hint}") from None
    try:
        _TRACEABLE.add(sut)
    except TypeError:
        pass


def resolve(spec: str | SUT | Callable) -> SUT:
    """A :class:`SUT` from a registry name, an import path, a SUT, or a bare ``act`` function
    (stateless: ``act(obs, state, params, key)``). Raises ValueError listing the known names."""
    if isinstance(spec, SUT):
        return spec
    if isinstance(spec, str):
        if spec in REGISTRY:
            return REGISTRY[spec]
        if ":" not in spec:
            raise ValueError(f"unknown SUT '{spec}' (one of {', '.join(REGISTRY)}, or an "
                             "import path module:attr)")
        obj = load_attr(spec)
        if isinstance(obj, type) or (callable(obj) and not isinstance(obj, SUT)
                                     and getattr(obj, "__code__", None) is not None
                                     and obj.__code__.co_argcount == 0):
            try:
                obj = obj()  # a factory returning a SUT
            except Exception as e:  # noqa: BLE001 - a user's code can raise anything
                raise ValueError(f"SUT '{spec}' could not be built (called with no "
                                 f"arguments): {error_line(e)}") from None
        if isinstance(obj, SUT):
            return dataclasses.replace(obj, name=spec) if obj.name != spec else obj
        builtin = next((s for s in REGISTRY.values() if s.act is obj or s.init is obj), None)
        if builtin is not None:  # a built-in's own function needs its state and parameters
            raise ValueError(f"SUT '{spec}' is the '{builtin.name}' SUT's "
                             f"{'act' if builtin.act is obj else 'init'} function, which needs "
                             f"that SUT's state and parameters: name the SUT, --sut "
                             f"{builtin.name}")
        if callable(obj):
            return SUT(spec, obj, _no_state, None)
        raise ValueError(f"SUT '{spec}' is a {type(obj).__name__}, not a SUT or act function")
    if callable(spec):
        return SUT(getattr(spec, "__name__", "custom"), spec, _no_state, None)
    raise ValueError(f"sut must be a name, an import path, a SUT or a function "
                     f"(got {type(spec).__name__})")


def cache_key(sut: SUT) -> str | None:
    """What identifies a SUT's code across processes, for the per-user program cache: the
    built-ins by name, a module-level SUT by its functions' qualified names and the source of
    every loaded user module (:func:`jaxfalsify.cache.user_code_hash`: its own file and any
    helper it imports). None (never cached) for closures or functions without a source
    file."""

    fns = (sut.act, sut.init)
    if any(getattr(f, "__closure__", True) is not None for f in fns):
        return None
    if is_builtin(sut):
        return f"builtin:{sut.name}"
    code = cache.user_code_hash(*fns)
    return None if code is None else f"{sut.name}:{code}"


def param_names(sut: SUT) -> tuple[str, ...]:
    p = sut.default_params
    if p is None:
        return ()
    if dataclasses.is_dataclass(p):
        return pytree.field_names(p)
    if isinstance(p, Mapping):
        return tuple(p)
    return ()


def with_params(sut: SUT, params: Any = None, where: str = "sut_params") -> Any:
    """The SUT's parameters: its defaults, a full parameter pytree, or a mapping of overrides
    ``{name: number}`` applied to the defaults. One-line ValueError naming a bad name/value."""
    if params is None:
        return sut.default_params
    if not isinstance(params, Mapping):  # a full parameter pytree
        d = sut.default_params
        if dataclasses.is_dataclass(d) and not isinstance(params, type(d)):
            raise ValueError(f"{where}: SUT '{sut.name}' takes {type(d).__name__} (got "
                             f"{type(params).__name__})")
        if dataclasses.is_dataclass(params):  # its concrete scalar values, in their intervals
            values = {f: getattr(params, f) for f in pytree.field_names(params)}
            pytree.check_ranges(params, {f: x for f, v in values.items()
                                         if (x := pytree.real_number(v)) is not None},
                                f"{where}: SUT '{sut.name}'")
        return params
    if not params:
        return sut.default_params
    known = param_names(sut)
    params = dict(params)
    for name, value in params.items():
        if name not in known:
            raise ValueError(f"{where}: SUT '{sut.name}' has no parameter '{name}' "
                             f"(known: {', '.join(known) or 'none'})")
        number = pytree.real_number(value)
        if number is None:
            raise ValueError(f"{where}: {name}={value!r:.40} is not a number")
        if not math.isfinite(number):
            raise ValueError(f"{where}: {name}={value!r:.40} is not finite")
        if abs(number) > pytree.FLOAT32_MAX:
            raise ValueError(f"{where}: {name}={value!r:.40} is beyond float32's range (the "
                             "simulator computes in float32)")
        params[name] = number
    p = sut.default_params
    if dataclasses.is_dataclass(p):
        pytree.check_ranges(p, params, f"{where}: SUT '{sut.name}'")
        return dataclasses.replace(p, **{k: float(v) for k, v in params.items()})
    return {**p, **{k: float(v) for k, v in params.items()}}


def override(params: Any, values: dict) -> Any:
    """``params`` with the fields in ``values`` replaced (traced values welcome: a space's
    ``sut.NAME`` parameters, one value per scenario under ``vmap``)."""
    if dataclasses.is_dataclass(params):
        return dataclasses.replace(params, **values)
    if isinstance(params, dict):
        return {**params, **values}
    raise ValueError(f"cannot set {', '.join(values)} on SUT parameters of type "
                     f"{type(params).__name__}")


def make(spec: str | SUT | Callable = "carla-tm", **params) -> tuple[SUT, Any]:
    """``(sut, params)``: a SUT by name or import path, and its parameters with ``params``
    overriding the defaults (``make("sensor-aeb", ttc_full=0.8)``)."""
    sut = resolve(spec)
    p = with_params(sut, params)
    check_traceable(sut, p)
    return sut, p


def params_dict(params: Any) -> dict[str, float]:
    """``{name: value}`` of a flat parameter pytree (host-side; for config files and tables)."""
    if params is None:
        return {}
    if dataclasses.is_dataclass(params):
        return {f: float(getattr(params, f)) for f in pytree.field_names(params)}
    if isinstance(params, Mapping):
        return {k: float(v) for k, v in params.items()}
    return {}


def callback_error(e: BaseException) -> str | None:
    """The user's exception (``Type: message``, one line) when ``e`` is JAX's runtime error
    for a host callback (``jax.pure_callback`` / ``io_callback`` in a user's SUT) that raised;
    None for any other error."""
    if type(e).__name__ not in ("JaxRuntimeError", "XlaRuntimeError") or \
            "callback" not in str(e).lower():
        return None
    lines = [ln.strip() for ln in str(e).splitlines() if ln.strip()]
    found = next((ln for ln in reversed(lines) if ":" in ln and ln.split(":", 1)[0].isidentifier()
                  and ln.split(":", 1)[0][0].isupper()), None)
    return (found or lines[-1] if lines else type(e).__name__)[:300]
