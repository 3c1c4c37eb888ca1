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

* ``carla-tm`` (default): CARLA's Traffic Manager autopilot with its ground-truth emergency
  stop, the SUT of the paper. Weather does not change it (CARLA's weather is visual only).
* ``sensor-aeb``: a perception-based AEB whose detection degrades with weather, with staged
  braking on time-to-collision and friction-limited braking on wet roads.
* ``none``: the autopilot's cruise control without any emergency braking.
"""

from __future__ import annotations

import dataclasses
import importlib
import importlib.util
import math
import sys
from pathlib import Path
from typing import Any, Callable, Mapping, NamedTuple

import jax
import jax.numpy as jnp

from jaxfalsify import metrics, pytree, weather

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
    """The autopilot's speed keeping (a P controller standing in for CARLA's PID).

    CARLA's Traffic Manager drives 30 % below the speed limit by default; Town05's urban
    limit is 30 km/h, so the cruise speed is 21 km/h.
    """

    cruise_speed: float = 30.0 / 3.6 * 0.7  # m/s
    gain: float = 1.0  # 1/s
    accel_max: float = 1.5  # m/s^2, comfortable launch
    decel_max: float = 3.0  # m/s^2, normal (non-emergency) braking


def cruise_command(speed, p) -> jax.Array:
    """Speed-keeping acceleration command [m/s^2] (``p`` has the :class:`CruiseParams` fields)."""
    return jnp.clip(p.gain * (p.cruise_speed - speed), -p.decel_max, p.accel_max)


def none_act(obs: Observation, state, p: CruiseParams, key):
    """Cruise control only: no emergency braking at all."""
    return cruise_command(obs.ego_speed, p), state


# ----------------------------------------------------------------------------- carla-tm
@pytree.dataclass
class CarlaTMParams(CruiseParams):
    """CARLA Traffic Manager collision stage (facts.md, 'CARLA Traffic Manager').

    The hazard boundary extends ahead of the vehicle's box by
    ``boundary_min + boundary_rate * speed``, as wide as the vehicle; a walker's box is extended
    ``walker_time * its speed`` along its heading. Overlap -> emergency stop (full brake).
    """

    boundary_min: float = 2.5  # m
    boundary_rate: float = 4.35  # s
    walker_time: float = 1.5  # s
    full_brake: float = 8.0  # m/s^2, full brake pedal on dry asphalt


def carla_tm_act(obs: Observation, state, p: CarlaTMParams, key):
    """Traffic Manager step. State: ``hold`` (bool), set by an emergency stop for a walker.

    A stateless check would chatter (stop, boundary shrinks to 2.5 m, walker no longer inside,
    go, boundary grows, stop...). CARLA's collision lock keeps tracking the hazard instead; we
    model that as a hold which is released once the walker has left the carriageway on the far
    side (it has crossed) or is behind the ego, after which the autopilot resumes cruising.
    """
    hold = state
    speed_ext = p.walker_time * jnp.sqrt(obs.ped_vx**2 + obs.ped_vy**2)
    heading_up = obs.ped_vy >= 0
    w_lo = obs.ped_y - obs.ped_width / 2 - jnp.where(heading_up, 0.0, speed_ext)
    w_hi = obs.ped_y + obs.ped_width / 2 + jnp.where(heading_up, speed_ext, 0.0)
    lat = (w_hi > obs.ego_y - obs.ego_width / 2) & (w_lo < obs.ego_y + obs.ego_width / 2)
    front = obs.ego_x + obs.ego_length / 2
    reach = front + p.boundary_min + p.boundary_rate * obs.ego_speed
    lon = (obs.ped_x + obs.ped_length / 2 > front) & (obs.ped_x - obs.ped_length / 2 < reach)
    hazard = lat & lon
    behind = obs.ped_x + obs.ped_length / 2 < obs.ego_x - obs.ego_length / 2
    crossed = jnp.where(heading_up, obs.ped_y - obs.ped_width / 2 > obs.road_left,
                        obs.ped_y + obs.ped_width / 2 < obs.road_right)
    hold = hazard | (hold & ~crossed & ~behind)
    accel = jnp.where(hold, -p.full_brake, cruise_command(obs.ego_speed, p))
    return accel, hold


# ----------------------------------------------------------------------------- sensor-aeb
@pytree.dataclass
class SensorAEBParams(CruiseParams):
    """A perception-based AEB (camera + radar class), degraded by weather.

    Detection: the pedestrian's centre within ``range`` metres and ``fov`` degrees of the
    bumper's centre line, confirmed for ``latency`` seconds (tracker confirmation + actuation).
    Weather model (see README 'Systems under test'): rain shortens range by up to
    ``rain_range_loss`` at 100 % precipitation and adds up to ``rain_latency`` seconds; low sun
    (altitude < 20 deg, glare) cuts range by ``glare_range_loss``; heavy cloud
    (> 70 %) cuts range by ``cloud_range_loss`` (low contrast). Braking is staged on TTC:
    ``partial_brake`` below ``ttc_partial`` s, full below ``ttc_full`` s, the full brake being
    limited by tyre-road friction mu*g, with mu falling from ``mu_dry`` to ``mu_wet`` as
    water deposits go from 0 to 100 %.
    """

    range: float = 40.0  # m, clear day
    fov: float = 50.0  # deg, full angle
    latency: float = 0.2  # s, clear day
    rain_range_loss: float = 0.5  # fraction at 100 % precipitation
    rain_latency: float = 0.3  # s added at 100 % precipitation
    glare_range_loss: float = 0.3  # fraction, sun altitude < 20 deg
    cloud_range_loss: float = 0.1  # fraction, cloudiness > 70 %
    ttc_partial: float = 1.6  # s
    ttc_full: float = 0.9  # s
    partial_brake: float = 4.0  # m/s^2
    mu_dry: float = 0.9
    mu_wet: float = 0.55


def sensor_capability(weather_index, p: SensorAEBParams):
    """(range [m], latency [s], max deceleration [m/s^2]) under a weather preset."""
    row = jnp.asarray(weather.TABLE)[jnp.asarray(weather_index, jnp.int32)]
    cloud, rain, deposits, sun = row[0], row[1], row[2], row[3]
    rng = (p.range * (1.0 - p.rain_range_loss * rain / 100.0)
           * jnp.where(sun < 20.0, 1.0 - p.glare_range_loss, 1.0)
           * jnp.where(cloud > 70.0, 1.0 - p.cloud_range_loss, 1.0))
    latency = p.latency + p.rain_latency * rain / 100.0
    mu = p.mu_dry + (p.mu_wet - p.mu_dry) * deposits / 100.0
    return rng, latency, mu * G


def sensor_aeb_act(obs: Observation, state, p: SensorAEBParams, key):
    """State: consecutive steps the pedestrian has been detected (int32)."""
    seen_for = state
    rng, latency, decel = sensor_capability(obs.weather, p)
    front = obs.ego_x + obs.ego_length / 2
    dx = obs.ped_x - front
    dy = obs.ped_y - obs.ego_y
    in_fov = (dx > 0) & (jnp.abs(jnp.arctan2(dy, jnp.maximum(dx, 1e-6))) <= jnp.deg2rad(p.fov / 2))
    detected = in_fov & (dx * dx + dy * dy <= rng * rng)
    seen_for = jnp.where(detected, seen_for + 1, 0)
    confirmed = seen_for.astype(jnp.float32) * obs.dt >= latency - 1e-6
    gap_x, gap_y = metrics.box_gaps(obs.ped_x - obs.ego_x, obs.ped_y - obs.ego_y,
                                    (obs.ego_length + obs.ped_length) / 2,
                                    (obs.ego_width + obs.ped_width) / 2)
    closing_y = -jnp.sign(obs.ped_y - obs.ego_y) * obs.ped_vy
    ttc = metrics.time_to_collision(gap_x, gap_y, obs.ego_speed, closing_y,
                                    obs.ego_length + obs.ped_length,
                                    obs.ego_width + obs.ped_width)
    brake = jnp.where(ttc <= p.ttc_full, decel, jnp.where(ttc <= p.ttc_partial,
                                                          jnp.minimum(p.partial_brake, decel), 0.0))
    accel = jnp.where(confirmed & (brake > 0), -brake, cruise_command(obs.ego_speed, p))
    return accel, seen_for


def _zero_steps(key, params):
    return jnp.int32(0)


# ----------------------------------------------------------------------------- registry
REGISTRY: dict[str, SUT] = {}


def register(sut: SUT) -> SUT:
    """Add a SUT to the registry under ``sut.name`` (replacing one of the same name)."""
    if not isinstance(sut, SUT):
        raise ValueError(f"register() takes a SUT (got {type(sut).__name__})")
    REGISTRY[sut.name] = sut
    return sut


register(SUT("carla-tm", carla_tm_act, _no_state, CarlaTMParams(), stochastic=False))
register(SUT("sensor-aeb", sensor_aeb_act, _zero_steps, SensorAEBParams(), stochastic=False))
register(SUT("none", none_act, _no_state, CruiseParams(), stochastic=False))


def _load_attr(spec: str):
    """``module:attr`` or ``path/file.py:attr`` -> the attribute (one-line ValueError)."""
    mod_name, _, attr = spec.rpartition(":")
    if not mod_name or not attr:
        raise ValueError(f"SUT '{spec}': expected a registry name ({', '.join(REGISTRY)}) or "
                         "an import path module:attr")
    try:
        if mod_name.endswith(".py"):
            path = Path(mod_name).resolve()
            if not path.is_file():
                raise ValueError(f"SUT '{spec}': no such file {mod_name}")
            import hashlib

            name = "jaxfalsify_user_sut_" + hashlib.sha256(str(path).encode()).hexdigest()[:12]
            module = sys.modules.get(name)
            if module is None:
                loader = importlib.util.spec_from_file_location(name, path)
                module = importlib.util.module_from_spec(loader)
                sys.modules[name] = module
                try:
                    loader.loader.exec_module(module)
                except BaseException:
                    del sys.modules[name]
                    raise
        else:
            if "" not in sys.path and str(Path.cwd()) not in sys.path:
                sys.path.insert(0, str(Path.cwd()))  # like `python -m`: the working folder
            module = importlib.import_module(mod_name)
    except ValueError:
        raise
    except Exception as e:  # noqa: BLE001 - a user module can raise anything on import
        raise ValueError(f"SUT '{spec}': cannot import {mod_name} "
                         f"({type(e).__name__}: {e})".splitlines()[0]) from None
    try:
        return getattr(module, attr)
    except AttributeError:
        raise ValueError(f"SUT '{spec}': {mod_name} has no attribute '{attr}'") from None


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
        obj = _load_attr(spec)
        if isinstance(obj, type) or (callable(obj) and not isinstance(obj, SUT)
                                     and getattr(obj, "__code__", None) is not None
                                     and obj.__code__.co_argcount == 0):
            obj = obj()  # a factory returning a SUT
        if isinstance(obj, SUT):
            return dataclasses.replace(obj, name=spec) if obj.name != spec else obj
        if callable(obj):
            return SUT(spec, obj, _no_state, None)
        raise ValueError(f"SUT '{spec}' is a {type(obj).__name__}, not a SUT or act function")
    if callable(spec):
        return SUT(getattr(spec, "__name__", "custom"), spec, _no_state, None)
    raise ValueError(f"sut must be a name, an import path, a SUT or a function "
                     f"(got {type(spec).__name__})")


def cache_key(sut: SUT) -> str | None:
    """What identifies a SUT's code across processes, for the per-user program cache: the
    built-ins by name, a module-level SUT by its functions' qualified names and its source
    file's hash. None (never cached) for closures or functions without a source file."""
    from jaxfalsify import cache

    fns = (sut.act, sut.init)
    if any(getattr(f, "__closure__", True) is not None for f in fns):
        return None
    if all(getattr(f, "__module__", "").startswith("jaxfalsify.") for f in fns):
        return f"builtin:{sut.name}"
    hashes = [cache.source_hash(f) for f in fns]
    if None in hashes:
        return None
    return ":".join([sut.name] + [f"{f.__module__}.{f.__qualname__}" for f in fns] + hashes)


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
    if not isinstance(params, Mapping):
        return params
    if not params:
        return sut.default_params
    known = param_names(sut)
    for name, value in params.items():
        if name not in known:
            raise ValueError(f"{where}: SUT '{sut.name}' has no parameter '{name}' "
                             f"(known: {', '.join(known) or 'none'})")
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ValueError(f"{where}: {name}={value!r} is not a number")
        if not math.isfinite(value):
            raise ValueError(f"{where}: {name}={value!r} is not finite")
    p = sut.default_params
    if dataclasses.is_dataclass(p):
        return dataclasses.replace(p, **{k: float(v) for k, v in params.items()})
    return {**p, **{k: float(v) for k, v in params.items()}}


def make(spec: str | SUT | Callable = "carla-tm", **params) -> tuple[SUT, Any]:
    """``(sut, params)``: a SUT by name or import path, and its parameters with ``params``
    overriding the defaults (``make("sensor-aeb", ttc_full=0.8)``)."""
    sut = resolve(spec)
    return sut, with_params(sut, params, where=f"SUT '{sut.name}'")


def params_dict(params: Any) -> dict[str, float]:
    """``{name: value}`` of a flat parameter pytree (host-side; for config files and tables)."""
    if params is None:
        return {}
    if dataclasses.is_dataclass(params):
        return {f: float(getattr(params, f)) for f in pytree.field_names(params)}
    if isinstance(params, Mapping):
        return {k: float(v) for k, v in params.items()}
    return {}

