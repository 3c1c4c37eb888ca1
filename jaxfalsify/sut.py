"""Systems under test: longitudinal controllers of the ego vehicle, black boxes to the search.

A SUT is a pure function ``act(obs, state, params) -> (accel_command, new_state)`` plus an
initial state: it sees one :class:`Observation` per 0.1 s step and returns a longitudinal
acceleration command [m/s^2] (negative = braking), which the simulator applies during the next
step (one step of actuation latency) within the vehicle's limits. Written for one scenario;
the simulator vmaps it.

Built-ins (``SUTS``):

* ``carla-tm`` (default): CARLA's Traffic Manager autopilot with its ground-truth emergency
  stop, the SUT of the paper. Weather does not change it (CARLA's weather is visual only), so
  in the paper's experiment the weather parameter is a distractor the search must learn to
  ignore.
* ``sensor-aeb``: a perception-based AEB whose detection degrades with weather, with staged
  braking on time-to-collision and friction-limited braking on wet roads.
* ``none``: the autopilot's cruise control without any emergency braking.

Users can pass their own :class:`SUT` (or a bare ``act`` function, stateless) to
``simulate``/``evaluate``.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable, NamedTuple

import jax.numpy as jnp

from jaxfalsify import metrics, weather

G = 9.81  # m/s^2


class Observation(NamedTuple):
    """What a SUT sees at one step (ground truth; a perception SUT filters it itself).

    Positions are box centres [m] in the road frame (x along the ego's lane, y to the left);
    speeds [m/s]; sizes are full box lengths [m]. ``weather`` is the CARLA preset index.
    """

    t: jnp.ndarray
    ego_x: jnp.ndarray
    ego_y: jnp.ndarray
    ego_speed: jnp.ndarray
    ego_length: jnp.ndarray
    ego_width: jnp.ndarray
    ped_x: jnp.ndarray
    ped_y: jnp.ndarray
    ped_vx: jnp.ndarray
    ped_vy: jnp.ndarray
    ped_length: jnp.ndarray
    ped_width: jnp.ndarray
    road_right: jnp.ndarray
    road_left: jnp.ndarray
    weather: jnp.ndarray


@dataclasses.dataclass(frozen=True)
class SUT:
    """A system under test: ``act(obs, state, params) -> (accel, state)``; ``init(params)``.

    ``params`` must be hashable (a NamedTuple of floats) so a SUT can be a static argument.
    """

    name: str
    act: Callable[[Observation, Any, Any], tuple[jnp.ndarray, Any]]
    init: Callable[[Any], Any]
    params: Any = None


class CruiseParams(NamedTuple):
    """The autopilot's speed keeping (a P controller standing in for CARLA's PID).

    CARLA's Traffic Manager drives 30 % below the speed limit by default; Town05's urban
    limit is 30 km/h, so the cruise speed is 21 km/h.
    """

    cruise_speed: float = 30.0 / 3.6 * 0.7  # m/s
    gain: float = 1.0  # 1/s
    accel_max: float = 1.5  # m/s^2, comfortable launch
    decel_max: float = 3.0  # m/s^2, normal (non-emergency) braking


def cruise_command(speed, p: CruiseParams) -> jnp.ndarray:
    """Speed-keeping acceleration command [m/s^2]."""
    return jnp.clip(p.gain * (p.cruise_speed - speed), -p.decel_max, p.accel_max)


# ----------------------------------------------------------------------------- carla-tm
class CarlaTMParams(NamedTuple):
    """CARLA Traffic Manager collision stage (facts.md, 'CARLA Traffic Manager').

    The hazard boundary extends ahead of the vehicle's box by
    ``boundary_min + boundary_rate * speed``, as wide as the vehicle; a walker's box is extended
    ``walker_time * its speed`` along its heading. Overlap -> emergency stop (full brake).
    """

    cruise: CruiseParams = CruiseParams()
    boundary_min: float = 2.5  # m
    boundary_rate: float = 4.35  # s
    walker_time: float = 1.5  # s
    full_brake: float = 8.0  # m/s^2, full brake pedal on dry asphalt


def carla_tm_act(obs: Observation, state, p: CarlaTMParams):
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
    accel = jnp.where(hold, -p.full_brake, cruise_command(obs.ego_speed, p.cruise))
    return accel, hold


def _false(_params):
    return jnp.bool_(False)


# ----------------------------------------------------------------------------- none
def none_act(obs: Observation, state, p: CruiseParams):
    """Cruise control only: no emergency braking at all."""
    return cruise_command(obs.ego_speed, p), state


# ----------------------------------------------------------------------------- sensor-aeb
class SensorAEBParams(NamedTuple):
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

    cruise: CruiseParams = CruiseParams()
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


def sensor_aeb_act(obs: Observation, state, p: SensorAEBParams):
    """State: consecutive steps the pedestrian has been detected (int32)."""
    seen_for = state
    rng, latency, decel = sensor_capability(obs.weather, p)
    front = obs.ego_x + obs.ego_length / 2
    dx = obs.ped_x - front
    dy = obs.ped_y - obs.ego_y
    in_fov = (dx > 0) & (jnp.abs(jnp.arctan2(dy, jnp.maximum(dx, 1e-6))) <= jnp.deg2rad(p.fov / 2))
    detected = in_fov & (dx * dx + dy * dy <= rng * rng)
    seen_for = jnp.where(detected, seen_for + 1, 0)
    confirmed = seen_for.astype(jnp.float32) * 0.1 >= latency
    gap_x, gap_y = metrics.box_gaps(obs.ped_x - obs.ego_x, obs.ped_y - obs.ego_y,
                                    (obs.ego_length + obs.ped_length) / 2,
                                    (obs.ego_width + obs.ped_width) / 2)
    closing_y = -jnp.sign(obs.ped_y - obs.ego_y) * obs.ped_vy
    ttc = metrics.time_to_collision(gap_x, gap_y, obs.ego_speed, closing_y,
                                    obs.ego_length + obs.ped_length,
                                    obs.ego_width + obs.ped_width)
    brake = jnp.where(ttc <= p.ttc_full, decel, jnp.where(ttc <= p.ttc_partial,
                                                          jnp.minimum(p.partial_brake, decel), 0.0))
    accel = jnp.where(confirmed & (brake > 0), -brake, cruise_command(obs.ego_speed, p.cruise))
    return accel, seen_for


def _zero(_params):
    return jnp.int32(0)


SUTS: dict[str, SUT] = {
    "carla-tm": SUT("carla-tm", carla_tm_act, _false, CarlaTMParams()),
    "sensor-aeb": SUT("sensor-aeb", sensor_aeb_act, _zero, SensorAEBParams()),
    "none": SUT("none", none_act, _false, CruiseParams()),
}


def get(sut: str | SUT | Callable) -> SUT:
    """Resolve a SUT by registry name, or wrap a user function ``act(obs, state, params)``."""
    if isinstance(sut, SUT):
        return sut
    if isinstance(sut, str):
        if sut not in SUTS:
            raise ValueError(f"unknown SUT '{sut}' (one of {', '.join(SUTS)})")
        return SUTS[sut]
    if callable(sut):
        return SUT(getattr(sut, "__name__", "custom"), sut, _false, None)
    raise ValueError(f"sut must be a name, a SUT or a function (got {type(sut).__name__})")
